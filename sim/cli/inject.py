"""`bess-ded inject KIND`: put crafted bad frames on the bus (fault-injection tests).

`bess-ded inject insider --key-file FILE --case N` is a key holder's attack (issue 25):
for the scenario's fleet, every secured message of another node, forged with the best
key FILE holds (the genuine key where it holds it: the residual risk; else its own key of
the same kind), for --duration seconds after --start seconds of listening. It prints its
plan first: which messages the file can forge (docs/security.md)."""

from __future__ import annotations

import argparse
import logging

from firmware_py.cliargs import duration_s, float_in, int_in, positive_int, time_scale
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
    i = p.add_argument_group("insider (a stolen key file's forgeries)")
    i.add_argument("--key-file", metavar="FILE",
                   help="the node key file the insider holds (from `bess-ded keys --fleet`)")
    i.add_argument("--case", "--scenario", dest="case", metavar="CASE",
                   help="the fleet under attack: a case number or a scenario TOML")
    i.add_argument("--duration", type=duration_s(), default=10.0, metavar="S",
                   help="seconds of forging (default: 10)")
    i.add_argument("--start", type=float_in(0.0, 3600.0), default=1.0, metavar="S",
                   help="seconds of listening first (default: 1): the genuine senders' "
                   "freshness, for the keys the file holds")
    i.add_argument("--skip-residual", action="store_true",
                   help="leave out what the file can really forge (the residual risk the "
                   "plan names): a test that everything else is refused")
    i.add_argument("--time-scale", type=time_scale, default=1.0, metavar="F",
                   help="the fleet's --time-scale (default: 1)")
    add_bus_arguments(p)
    add_fd_argument(p)
    one_line_errors(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dbc import dbc_path
    from firmware_py.frames import FrameCodec
    from firmware_py.node import bus_kwargs, open_bus
    from sim.nodes.inject import send

    if args.kind == "insider":
        return run_insider(args)
    bus = open_bus(**bus_kwargs(args.interface, args.channel, args.bus_config))
    try:
        n = send(bus, args.kind, args.count, args.target, args.rate, args.seed,
                 FrameCodec(dbc_path(args.fd, lambda_tags_of(args))))
    finally:
        bus.shutdown()
    print(f"bess-ded inject: sent {n} {args.kind} frames")
    return 0


def run_insider(args: argparse.Namespace) -> int:
    """`inject insider`: the plan, the forgeries, what was sent."""
    from dbc import dbc_path
    from firmware_py import contract
    from firmware_py.config import agent_configs_from_scenario
    from firmware_py.errors import ParameterError
    from firmware_py.frames import FrameCodec
    from firmware_py.node import bus_kwargs, open_bus
    from firmware_py.secoc import load_node_key
    from sim.model.scenario import scaled
    from sim.model.scenario_select import resolve_scenario, with_fd
    from sim.nodes import insider

    if not args.key_file or not args.case:
        raise ParameterError("inject insider", "--key-file FILE and --case N (or --scenario "
                             "FILE)", f"--key-file {args.key_file} --case {args.case}")
    sc = with_fd(resolve_scenario(args.case), args.fd, args.no_lambda_tags)
    if args.time_scale != 1.0:
        sc = scaled(sc, args.time_scale)
    key = load_node_key(args.key_file)
    codec = FrameCodec(dbc_path(sc.fd, sc.lambda_tags))
    receivers = {c.id: contract.lambda_receivers([n.id for n in c.neighbours])
                 for c in agent_configs_from_scenario(sc)}
    plan = insider.plan(sc, key, codec, receivers)
    if args.skip_residual:
        plan = insider.without_residual(plan)
    # what the listener rejects (it is not the node it claims to be) is not the output
    logging.getLogger("firmware_py.nodeio").setLevel(logging.ERROR)
    print("\n".join(insider.describe(plan)), flush=True)
    bus = open_bus(**bus_kwargs(args.interface, args.channel, args.bus_config))
    try:
        sent = insider.run(bus, plan, args.duration, args.start)
    finally:
        bus.shutdown()
    total = sum(v["sent"] for v in sent.values())
    held = [n for n, v in sent.items() if v["genuine"] and not v["sent"]]
    print(f"bess-ded inject: insider ({key.node}) sent {total} frames of "
          f"{len(sent)} forgeries" + (f"; never heard the genuine sender of {', '.join(held)}"
                                     if held else ""))
    return 0
