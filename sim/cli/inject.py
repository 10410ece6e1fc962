"""`bess-ded inject KIND`: put crafted bad frames on the bus (fault-injection tests)."""

from __future__ import annotations

import argparse

from firmware_py.__main__ import add_bus_arguments


def register(sub: argparse._SubParsersAction) -> None:
    from ..inject import KINDS

    p = sub.add_parser("inject", help="send crafted bad frames to test the firmware's rejection",
                       description=__doc__ + "\n\nkinds:\n" + "\n".join(
                           f"  {k:12} {v}" for k, v in KINDS.items()),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("kind", choices=sorted(KINDS))
    p.add_argument("--count", type=int, default=100)
    p.add_argument("--target", type=int, default=1, help="agent impersonated")
    p.add_argument("--rate", type=float, default=1000.0, help="frames per second")
    p.add_argument("--seed", type=int, default=0)
    add_bus_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from firmware_py.node import bus_kwargs, open_bus

    from ..inject import send

    bus = open_bus(**bus_kwargs(args.interface, args.channel, args.bus_config))
    try:
        n = send(bus, args.kind, args.count, args.target, args.rate, args.seed)
    finally:
        bus.shutdown()
    print(f"bess-ded inject: sent {n} {args.kind} frames")
    return 0
