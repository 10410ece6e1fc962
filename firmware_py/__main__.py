"""Run one agent node: ``python -m firmware_py --config agent_2.toml`` (or ``bess-ded agent``).

Kept free of numpy/matplotlib imports so a node starts fast on a small SBC.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from .cliargs import RT_PRIORITY, duration_s, float_in, int_in, probability
from .config import load_agent_config
from .errors import BessDedError
from .faultinject import FaultyBus, RxFaults, neighbour_mc
from .node import (
    BusConfigError,
    RxTxBus,
    StopFlag,
    behind_filter,
    bus_kwargs,
    open_bus,
    run_node,
    with_acceptance_filter,
)
from .secoc import KeyFileError, Keyring


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="agent TOML file (firmware_py/config.py)")
    add_key_arguments(p)
    add_bus_arguments(p)
    add_filter_argument(p)
    p.add_argument("--duration", type=duration_s(), default=None, metavar="S",
                   help="stop after S seconds")
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


def add_bus_arguments(p: argparse.ArgumentParser) -> None:
    """The bus flags every node shares; unset flags fall back to CAN_* variables."""
    p.add_argument("--interface", help="python-can interface (default: $CAN_INTERFACE or "
                   "udp_multicast)")
    p.add_argument("--channel", help="channel, e.g. vcan0 (default: $CAN_CHANNEL)")
    p.add_argument("--bus-config", help='extra python-can arguments as JSON, e.g. '
                   '\'{"port": 43200}\' (default: $CAN_CONFIG)')


def add_key_arguments(p: argparse.ArgumentParser) -> None:
    """--key FILE | --insecure, one of them required (docs/security.md)."""
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--key", metavar="FILE",
                   help="this node's key file from `bess-ded keys --fleet` (owner-only: "
                        "0600); its boot counter is advanced at every start")
    g.add_argument("--insecure", action="store_true",
                   help="demo mode: sign with the public all-zero key (anyone on the bus can "
                        "forge frames); prints a warning")


def keyring_from_args(args: argparse.Namespace, node: str) -> Keyring:
    """The keyring of ``node`` (e.g. "agent_3") from --key FILE, or the public insecure
    one with a warning on stderr. A key file of another node is refused."""
    if args.insecure:
        print(f"bess-ded: warning: {node} runs --insecure: its frames are signed with the "
              "public demo key and anyone on the bus can forge them (docs/security.md)",
              file=sys.stderr, flush=True)
        return Keyring.insecure_for(node)
    ring = Keyring.from_file(args.key)
    if ring.node != node:
        raise KeyFileError(f"--key {args.key}: expected the key file of {node}, but got "
                           f"the one of {ring.node}")
    return ring


def add_rt_argument(p: argparse.ArgumentParser) -> None:
    """--rt-priority for the nodes (agent, plant, router)."""
    p.add_argument("--rt-priority", type=RT_PRIORITY, default=0, metavar="N",
                   help="run under SCHED_FIFO priority N (1..99) so ticks keep their deadlines "
                   "on a loaded host; needs root or CAP_SYS_NICE (default: 0 = off)")


def add_filter_argument(p: argparse.ArgumentParser) -> None:
    """--[no-]acceptance-filter for the nodes (agent, plant, router)."""
    p.add_argument("--acceptance-filter", action=argparse.BooleanOptionalAction, default=None,
                   help="pass only the frames this node uses or sends, in the kernel "
                   "(default: on for socketcan, as an MCU's CAN controller would; off "
                   "elsewhere). --no-acceptance-filter lets every frame through, so the "
                   "node counts foreign IDs too, at more CPU on a busy bus")


def set_realtime(priority: int) -> None:
    """SCHED_FIFO for this process: the tick preempts ordinary work (logging, other
    programs). The loop sleeps in select between ticks, so it cannot starve the host."""
    if not 1 <= priority <= 99:
        raise BusConfigError(f"--rt-priority: expected 1..99, but got {priority}")
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, AttributeError, OSError) as e:
        logging.getLogger(__name__).warning("--rt-priority %d not applied (%s): running with "
                                            "normal priority", priority, e)


def run_agent(args: argparse.Namespace) -> int:
    from .runtime import AgentRuntime

    cfg = load_agent_config(args.config)
    agent = AgentRuntime(cfg, keys=keyring_from_args(args, f"agent_{cfg.id}"))
    if args.rt_priority:
        set_realtime(args.rt_priority)
    stop = StopFlag()
    stop.install_signal_handlers()
    kw = with_acceptance_filter(bus_kwargs(args.interface, args.channel, args.bus_config),
                                agent.io.accepted_ids(), args.acceptance_filter)
    bus = open_bus(**kw)
    faults = RxFaults(args.inject_rx_loss, args.inject_rx_delay, args.inject_rx_jitter,
                      args.inject_seed, match=neighbour_mc(cfg.id))
    node_bus: RxTxBus = behind_filter(bus, kw)
    if faults.active:
        node_bus = FaultyBus(node_bus, faults)
    try:
        run_node(agent, node_bus, duration=args.duration, stop=stop)
    finally:
        bus.shutdown()
        print(agent.summary(), file=sys.stderr, flush=True)
        if isinstance(node_bus, FaultyBus):
            print(f"agent {cfg.id}: injected {node_bus.dropped} losses, {node_bus.delayed} "
                  "delays", file=sys.stderr, flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
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
