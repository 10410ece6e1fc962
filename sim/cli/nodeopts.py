"""Options and serving shared by the node subcommands ``plant`` and ``router`` (not a
subcommand itself)."""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path
from typing import Any

from firmware_py.cliargs import (
    MAX_PERIOD_S,
    duration_s,
    float_in,
    int_in,
    probability,
    time_scale,
)
from firmware_py.nodeargs import (
    add_bus_arguments,
    add_fd_argument,
    add_filter_argument,
    add_key_arguments,
    add_rt_argument,
)


def add_node_arguments(p: argparse.ArgumentParser) -> None:
    """--case N | --scenario FILE, the bus flags, --duration, --period."""
    from ._common import add_case_option

    add_case_option(p)
    add_key_arguments(p)
    add_bus_arguments(p)
    add_fd_argument(p)
    add_filter_argument(p)
    add_rt_argument(p)
    p.add_argument("--duration", type=duration_s(), metavar="S",
                   help="stop after S seconds (default: run until SIGINT/SIGTERM)")
    p.add_argument("--time-scale", type=time_scale, default=1.0, metavar="F",
                   help="run the scenario stretched by F (Ts·F, k/F, h/F², every cycle and "
                   "timeout ×F), as `bess-ded up --time-scale F` runs it; give the agents "
                   "the configuration files such a run writes (default: 1)")
    p.add_argument("--period", type=float_in(0.0, MAX_PERIOD_S, lo_open=True), default=None,
                   metavar="S",
                   help="tick period of the node (default: the scenario's Ts, after the "
                   "time scale)")
    p.add_argument("--counters-json", metavar="FILE",
                   help="at exit, write the node's ticks and counters (deadline misses, "
                        "rejected frames by cause) to FILE as JSON: unlike the agents, the "
                        "plant and router have no diagnostics frame on the bus")
    t = p.add_argument_group("fault injection on received frames (`bess-ded up --loss`)")
    t.add_argument("--inject-rx-loss", type=probability, default=0.0, metavar="P",
                   help="drop each frame received with probability P (the echo of the "
                   "node's own frames passes)")
    t.add_argument("--inject-seed", type=int_in(0), default=0, metavar="N",
                   help="seed of the injected loss")


def load_node_scenario(args: argparse.Namespace) -> Any:
    """The scenario the flags name, stretched by --time-scale; sets the default --period
    to its Ts."""
    from firmware_py.config import agent_configs_from_scenario
    from sim.bench.fleetload import check_bus_load
    from sim.model.scenario import scaled
    from sim.model.scenario_select import resolve_scenario, with_fd

    sc = resolve_scenario(args.case)
    agent_configs_from_scenario(sc)  # a fleet larger than the DBC's frames: refused, named
    sc = with_fd(sc, args.fd, args.no_lambda_tags)  # --fd, or the scenario's [bus] fd
    if args.time_scale != 1.0:
        sc = scaled(sc, args.time_scale)
    check_bus_load(sc)  # and one the bus cannot carry
    if args.period is None:
        args.period = sc.ts
    return sc


def serve(node: Any, args: argparse.Namespace) -> int:
    """Run ``node`` on the bus the flags name until --duration or SIGINT/SIGTERM; always
    shut the bus down and print the node's summary to stderr."""
    from firmware_py.faultinject import FaultyBus, RxFaults, every_frame
    from firmware_py.node import (
        RxTxBus,
        StopFlag,
        behind_filter,
        bus_kwargs,
        freeze_startup_objects,
        open_bus,
        run_node,
        with_acceptance_filter,
    )
    from firmware_py.nodeargs import set_realtime

    if args.rt_priority:
        set_realtime(args.rt_priority)
    stop = StopFlag()
    kw = with_acceptance_filter(bus_kwargs(args.interface, args.channel, args.bus_config),
                                node.io.accepted_ids(), args.acceptance_filter)
    bus = open_bus(**kw)
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        stop.install_signal_handlers()
        node_bus: RxTxBus = behind_filter(bus, kw)
        if args.inject_rx_loss > 0:
            node_bus = injector = FaultyBus(node_bus, RxFaults(
                args.inject_rx_loss, seed=args.inject_seed, match=every_frame,
                spare_own=True))
        freeze_startup_objects()
        run_node(node, node_bus, duration=args.duration, stop=stop)
    finally:
        try:
            for s, h in previous.items():  # in-process callers (tests) get theirs back
                signal.signal(s, h)
        finally:
            bus.shutdown()
            print(node.summary(), file=sys.stderr, flush=True)
            doc: dict[str, Any] = {"ticks": node.ticks,
                                   "counters": dict(sorted(node.counters.items()))}
            if args.inject_rx_loss > 0:
                print(injector.summary(args.command), file=sys.stderr, flush=True)
                doc["injected"] = {"dropped": injector.dropped, "received": injector.matched}
            if args.counters_json:
                Path(args.counters_json).write_text(json.dumps(doc))
    return 0
