"""`bess-ded bench`'s options beyond the sections themselves: the fleet capacity's plan
(with --realtime, or --capacity-only) and which sections run."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from firmware_py.cliargs import float_in, int_in
from firmware_py.errors import ParameterError

if TYPE_CHECKING:
    from sim.bench.micro import Bench
    from sim.bench.realtime import CapacityPlan


def add_capacity_arguments(p: argparse.ArgumentParser) -> None:
    """The fleet capacity's options (sim.bench.realtime.CapacityPlan)."""
    f = p.add_argument_group("fleet capacity (with --realtime)")
    f.add_argument("--fleet-sizes", type=int_list, default=(16, 32), metavar="N,...",
                   help="agents per fleet (default: 16,32)")
    f.add_argument("--agents-per-process", type=int_list, default=(1, 16), metavar="K,...",
                   help="Python agents per process, each fleet run with each (default: 1,16)")
    f.add_argument("--repeats", type=int_in(1), default=3, metavar="R",
                   help="runs per fleet and K (default: 3)")
    f.add_argument("--fleet-seconds", type=float_in(4.0, 3600.0), default=14.0, metavar="S",
                   help="price time per run (default: 14: 12 s of steady state)")
    f.add_argument("--fleet-transmit", type=transmit_list, default=("periodic", "event"),
                   metavar="MODE,...",
                   help="the MC frames' transmission, each fleet run with each: periodic, "
                   "event (default: periodic,event); a fleet runs on classic CAN where its "
                   "load fits, else on CAN FD")
    f.add_argument("--fleet-impl", choices=("py", "c"), default="py",
                   help="firmware_py agents (default), or firmware_c's node program, a "
                   "process per agent")
    f.add_argument("--channel", default=None,
                   help="run the fleets on this SocketCAN channel (e.g. vcan0) instead of a "
                   "private udp_multicast port")
    f.add_argument("--capacity-only", action="store_true",
                   help="the fleet capacity alone: no micro-benchmarks, no cases")


def transmit_list(text: str) -> tuple[str, ...]:
    """"periodic,event" → ("periodic", "event"): the MC frames' transmission modes."""
    out = tuple(x.strip() for x in text.split(",") if x.strip())
    if not out or not set(out) <= {"periodic", "event"}:
        raise argparse.ArgumentTypeError(f"expected periodic, event or periodic,event, but "
                                         f"got {text!r}")
    return out


def int_list(text: str) -> tuple[int, ...]:
    """"16,32" → (16, 32): positive integers."""
    try:
        out = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        out = ()
    if not out or min(out) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers like 16,32, but got "
                                         f"{text!r}")
    return out


def selected(args: argparse.Namespace) -> tuple[list[Bench] | None, CapacityPlan]:
    """(the sections to run, None: the default set; the capacity plan) from the options:
    --auth and --capacity-only each run one section alone."""
    from sim.bench.micro import (
        auth_schemes,
        fleet_capacity,
        fleet_load,
        measured_load,
        scenario_loads,
    )
    from sim.bench.realtime import CapacityPlan  # noqa: F811 (the type above is for mypy)

    alone = [o for o, on in (("--fleet-load", args.fleet_load), ("--auth", args.auth),
                             ("--capacity-only", args.capacity_only),
                             ("--realtime", args.realtime)) if on]
    if len(alone) > 1 and alone[0] != "--realtime":
        raise ParameterError(alone[0], f"no {alone[1]} with it ({alone[0]} runs its section "
                             "alone)", " ".join(alone))
    plan = CapacityPlan(args.fleet_sizes, args.agents_per_process, args.repeats,
                        args.fleet_seconds, args.fleet_impl, args.channel,
                        args.fleet_transmit)
    if args.auth:
        return [auth_schemes], plan
    if args.fleet_load:
        return [fleet_load, *([scenario_loads(args.case)] if args.case else []),
                *([measured_load(args.measured)] if args.measured else [])], plan
    for flag, given in (("--measured", args.measured), ("--case", args.case)):
        if given:
            raise ParameterError(flag, "--fleet-load with it", f"{flag} alone")
    if args.capacity_only:
        return [fleet_capacity(plan)], plan
    return None, plan
