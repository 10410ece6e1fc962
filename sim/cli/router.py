"""`bess-ded router`: the energy-router node: price ρ(t), commands, grid and cost ledger.

Broadcasts ER_Price every 50 ms (t = 0 of the schedule is its first tick), sends
the scenario's ISOLATE/RECONNECT commands at their times, and ER_Balance every
100 ms (sim/nodes/router.py). Prints the cost ledger and counters to stderr at exit.
"""

from __future__ import annotations

import argparse

from ._common import one_line_errors
from .nodeopts import add_node_arguments


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run the energy-router node (price, commands, balance)",
                       description=__doc__)
    add_node_arguments(p)
    p.add_argument("--silent", action="append", default=[], metavar="T0:T1",
                   help="send nothing from T0 to T1 s after start (fault test; repeatable)")
    one_line_errors(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from firmware_py.nodeargs import keyring_from_args
    from sim.nodes.router import RouterNode, SilentWindow

    from .nodeopts import load_node_scenario, serve

    sc = load_node_scenario(args)
    silent = [SilentWindow.parse(w) for w in args.silent]
    return serve(RouterNode(sc, period=args.period, silent=silent,
                            keys=keyring_from_args(args, "router")), args)
