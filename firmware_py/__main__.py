"""Run one agent node: ``python -m firmware_py --config agent_2.toml`` (or ``bess-ded agent``),
or several on one loop and one bus socket: ``--config a1.toml --key a1.key --config a2.toml
--key a2.key ...`` (firmware_py.host: a host of agents, for more agents than cores).

Kept free of numpy/matplotlib imports so a node starts fast on a small SBC.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from typing import TYPE_CHECKING

from .cliargs import duration_s, float_in, int_in, probability
from .config import load_agent_config
from .errors import BessDedError, ParameterError
from .faultinject import FaultyBus, RxFaults, every_frame, neighbour_mc
from .host import AcceptedOnly, Routes, host_bus
from .node import (
    Node,
    RxTxBus,
    StopFlag,
    behind_filter,
    bus_kwargs,
    freeze_startup_objects,
    open_bus,
    run_nodes,
    spread_phases,
)
from .nodeargs import (
    add_bus_arguments,
    add_fd_argument,
    add_filter_argument,
    add_key_arguments,
    add_rt_argument,
    keyring_from_args,
    lambda_tags_of,
    set_realtime,
)

if TYPE_CHECKING:
    from .runtime import AgentRuntime


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The agent program's flags: --config, the key, bus and filter flags,
    --duration, --rt-priority and the fault-injection flags."""
    p.add_argument("--config", required=True, action="append",
                   help="agent TOML file (firmware_py/config.py); repeated: several agents "
                   "of one Ts in this process, on one loop and one bus socket, each with "
                   "its --key in the same order")
    add_key_arguments(p, repeat=True)
    add_bus_arguments(p)
    add_fd_argument(p)
    add_filter_argument(p)
    p.add_argument("--duration", type=duration_s(), default=None, metavar="S",
                   help="stop after S seconds")
    p.add_argument("--counters-dir", default=None, metavar="DIR",
                   help="at exit, write each agent's signed-price counters (signed_price: "
                   "unsigned_price, bad_signature, sig_malformed; no Diag slot), its "
                   "deadline misses and ticks to DIR/agent_<id>.counters.json, for the run's "
                   "verdict")
    add_rt_argument(p)
    t = p.add_argument_group("fault injection on received MC frames (tests and HIL rigs)")
    t.add_argument("--inject-rx-loss", type=probability, default=0.0, metavar="P",
                   help="drop each neighbour MC frame with probability P")
    t.add_argument("--inject-rx-delay", type=float_in(0.0, 60.0), default=0.0, metavar="S",
                   help="delay neighbour MC frames by S seconds")
    t.add_argument("--inject-rx-jitter", type=float_in(0.0, 60.0), default=0.0, metavar="S",
                   help="extra uniform random delay in [0, S] seconds")
    t.add_argument("--inject-seed", type=int_in(0), default=0, metavar="N",
                   help="seed of the injected faults")
    t.add_argument("--inject-rx-all", action="store_true",
                   help="apply them to every frame received (price, status, commands, "
                   "syncs, every MC), not only neighbour MC frames; the echo of the "
                   "node's own frames passes (`bess-ded up --loss`)")


def run_agent(args: argparse.Namespace) -> int:
    """Run the agents of --config (one, or a host of several) from parsed flags until
    --duration or SIGINT/SIGTERM; prints each one's summary (and injected faults) to
    stderr at exit. Returns the exit code."""
    from dbc import dbc_path

    from .frames import FrameCodec
    from .runtime import AgentRuntime

    # the bus's frame format (--fd: CAN FD, λ tagged unless --no-lambda-tags)
    codec = FrameCodec(dbc_path(args.fd, lambda_tags_of(args)))
    configs = [load_agent_config(path) for path in args.config]
    ids = [cfg.id for cfg in configs]
    if len(set(ids)) != len(ids):  # one identity twice: each would call the other forged
        raise ParameterError("--config", "the files of distinct agents", ids)
    if args.key is not None and len(args.key) != len(configs):
        raise ParameterError("--key", f"one key file per --config ({len(configs)})",
                             len(args.key))
    agents = [AgentRuntime(cfg, codec, keys=keyring_from_args(
        args, f"agent_{cfg.id}", None if args.key is None else args.key[i]))
        for i, cfg in enumerate(configs)]
    faults = RxFaults(args.inject_rx_loss, args.inject_rx_delay, args.inject_rx_jitter,
                      args.inject_seed,
                      match=every_frame if args.inject_rx_all else neighbour_mc(configs[0].id),
                      spare_own=args.inject_rx_all)
    if len(agents) > 1 and faults.active:
        raise ParameterError("--inject-*", "one --config (faults are injected per agent, "
                             "on its own socket)", f"{len(agents)} agents")
    if args.rt_priority:
        set_realtime(args.rt_priority)
    stop = StopFlag()
    stop.install_signal_handlers()
    kw, own_filters = host_bus(bus_kwargs(args.interface, args.channel, args.bus_config),
                               [a.io.accepted_ids() for a in agents], args.acceptance_filter)
    bus = open_bus(**kw)
    node_bus: RxTxBus = behind_filter(bus, kw) if len(agents) == 1 else bus
    if faults.active:
        node_bus = FaultyBus(node_bus, faults)
    nodes: list[Node] = [AcceptedOnly(a, a.io.accepted_ids()) if own_filters else a
                         for a in agents]
    freeze_startup_objects()
    wall, cpu = time.monotonic(), time.process_time()
    try:
        run_nodes(nodes, node_bus, duration=args.duration, stop=stop,
                  route=Routes(nodes, [a.io for a in agents]) if len(agents) > 1 else None,
                  phases=spread_phases(len(nodes), agents[0].io.sync_s))
    finally:
        bus.shutdown()
        for agent in agents:
            print(agent.summary(), file=sys.stderr, flush=True)
        if args.counters_dir is not None:
            _write_counters(agents, args.counters_dir)
        if len(agents) > 1:  # what a host costs, for sizing K (docs/performance.md)
            wall, cpu = time.monotonic() - wall, time.process_time() - cpu
            print(f"host of agents {', '.join(str(c.id) for c in configs)}: {cpu:.1f} s of "
                  f"CPU in {wall:.1f} s ({100 * cpu / max(wall, 1e-9):.0f} % of a core)",
                  file=sys.stderr, flush=True)
        if isinstance(node_bus, FaultyBus):
            print(node_bus.summary(f"agent {configs[0].id}"), file=sys.stderr, flush=True)
    return 0


def _write_counters(agents: list[AgentRuntime], directory: str) -> None:
    """The counters the verdict cannot read from AGENT_<i>_Diag (the signed price's) and
    the deadline misses, with the ticks, as DIR/agent_<id>.counters.json."""
    import json
    from pathlib import Path

    for agent in agents:
        Path(directory, f"agent_{agent.cfg.id}.counters.json").write_text(
            json.dumps(agent.verdict_counters()) + "\n")


def main(argv: list[str] | None = None) -> int:
    """``python -m firmware_py``: parse ``argv`` and run the agent; the exit code
    (2 on a usage, configuration, key or bus error, reported on one line)."""
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    p = argparse.ArgumentParser(prog="python -m firmware_py", description=__doc__)
    add_arguments(p)
    try:
        args = p.parse_args(argv)
    except SystemExit as e:  # a usage error (2, already printed) or --help (0)
        return e.code if isinstance(e.code, int) else 2
    try:
        return run_agent(args)
    except BessDedError as e:
        print(f"bess-ded agent: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a key file it cannot rewrite (its boot counter), a bus it cannot open
        print(f"bess-ded agent: error: {e.strerror or e}" + (f": {e.filename}" if e.filename
                                                            else ""), file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
