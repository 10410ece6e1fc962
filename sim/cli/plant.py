"""`bess-ded plant`: the plant simulator node, one battery + DC-DC chopper per BESS.

Follows AGENT_<i>_Setpoint frames and publishes PLANT_<i>_Status at the DBC's cycle
(50 ms at Ts = 10 ms, stretched with the scenario's Ts; model and constants:
sim/nodes/plant.py). Prints its counters to stderr at exit.
"""

from __future__ import annotations

import argparse

from ._common import one_line_errors
from .nodeopts import add_node_arguments


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plant", help="run the plant simulator node (battery + chopper per BESS)",
                       description=__doc__)
    add_node_arguments(p)
    p.add_argument("--fault", action="append", default=[], metavar="AGENT:KIND:T0:T1",
                   help="force a fault flag on BESS AGENT from T0 to T1 s after start; KIND is "
                   "overcurrent, voltage, soc or power_limit (repeatable)")
    p.add_argument("--ramp-full-s", type=float, default=None, metavar="S",
                   help="setpoint ramp limit: the time from 0 to p_max (default 0.25 s at "
                   "Ts = 10 ms, stretched with Ts; 0: no limit; docs/safety-model.md)")
    p.add_argument("--obey-inconsistent", action="store_true",
                   help="follow a setpoint that is not its agent's dispatch rule at the λ it "
                   "publishes (counted either way); default: hold the last consistent one")
    one_line_errors(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from firmware_py.nodeargs import keyring_from_args
    from sim.nodes.plant import PlantFault, PlantNode

    from .nodeopts import load_node_scenario, serve

    sc = load_node_scenario(args)
    faults = [PlantFault.parse(f).check(sc.n) for f in args.fault]
    return serve(PlantNode(sc, period=args.period, faults=faults,
                           ramp_full_s=args.ramp_full_s,
                           obey_inconsistent=args.obey_inconsistent,
                           keys=keyring_from_args(args, "plant")), args)
