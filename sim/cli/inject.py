"""`bess-ded inject KIND`: put crafted bad frames on the bus (fault-injection tests)."""

from __future__ import annotations

import argparse

from firmware_py.cliargs import float_in, int_in, positive_int
from firmware_py.nodeargs import add_bus_arguments, add_fd_argument, lambda_tags_of
from sim.model.scenario import MAX_AGENTS

from ._common import one_line_errors


def register(sub: argparse._SubParsersAction) -> None:
    from sim.nodes.inject import KINDS

    p = sub.add_parser("inject", help="send crafted bad frames to test the firmware's rejection",
                       description=__doc__ + "\n\nkinds:\n" + "\n".join(
                           f"  {k:12} {v}" for k, v in KINDS.items()),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("kind", choices=sorted(KINDS))
    p.add_argument("--count", type=positive_int(), default=100, metavar="N",
                   help="frames to send (default: 100)")
    p.add_argument("--target", type=int_in(1, MAX_AGENTS, what="an agent number"), default=1,
                   metavar="AGENT", help="agent impersonated (default: 1)")
    p.add_argument("--rate", type=float_in(0.0, 1e6, lo_open=True), default=1000.0, metavar="HZ",
                   help="frames per second (default: 1000)")
    p.add_argument("--seed", type=int_in(0), default=0, metavar="N")
    add_bus_arguments(p)
    add_fd_argument(p)
    one_line_errors(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dbc import dbc_path
    from firmware_py.frames import FrameCodec
    from firmware_py.node import bus_kwargs, open_bus
    from sim.nodes.inject import send

    bus = open_bus(**bus_kwargs(args.interface, args.channel, args.bus_config))
    try:
        n = send(bus, args.kind, args.count, args.target, args.rate, args.seed,
                 FrameCodec(dbc_path(args.fd, lambda_tags_of(args))))
    finally:
        bus.shutdown()
    print(f"bess-ded inject: sent {n} {args.kind} frames")
    return 0
