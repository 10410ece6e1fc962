"""`bess-ded up`: run a case with every node a separate process on a CAN bus.

The router, the plant and one firmware process per agent start on one bus; this
process records every frame to DIR/run.log, shows progress, stops the nodes at the
end (or on Ctrl-C / SIGTERM) and judges the run from the recording alone
(docs/runs.md). It writes DIR/metrics.json (with the verdict and the anomalies),
DIR/trajectory.csv and DIR/bus_run.png, and exits with:

  0    converged, no anomaly
  1    not converged (an agent SAFE/INIT/ISOLATED at the end, a node died, the last
       price segment never settled, a final λ more than --tolerance from ρ, ...): the
       reasons and the most likely cause are printed
  2    bad input (nothing was run)
  3    converged, but with anomalies (listed); --insecure runs exit 3 at best
  130  interrupted: the outputs cover what was recorded until then

On udp_multicast, a run without a port of its own (--bus-config '{"port": N}' or
CAN_CONFIG) gets a private one, so concurrent runs never hear each other.
"""

from __future__ import annotations

import argparse

from firmware_py.errors import ParameterError

from .fleetopts import add_run_arguments, plan_run, print_report


def register(sub: argparse._SubParsersAction) -> None:
    from firmware_py.cliargs import int_in

    from ._common import one_line_errors

    p = one_line_errors(sub.add_parser(
        "up", help="run router, plant and every agent as processes on a bus",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter))
    add_run_arguments(p)
    c = p.add_mutually_exclusive_group()
    c.add_argument("--agent-impl", choices=("py", "c"), default="py",
                   help="the agents' firmware: firmware_py (default) or firmware_c's node "
                   "program (on udp_multicast, the default bus, or --interface socketcan "
                   "--channel vcan0)")
    c.add_argument("--c-agents", metavar="I,J,...",
                   help="run these agents on firmware_c, the others on firmware_py "
                   "(udp_multicast or socketcan)")
    p.add_argument("--agents-per-process", type=int_in(1), default=1, metavar="K",
                   help="run the Python agents K to a process, on one loop and one bus "
                   "socket each (firmware_py.host): more agents than cores in real time "
                   "(default: 1, a process per agent; takes no --loss)")
    p.add_argument("--obey-inconsistent", action="store_true",
                   help="the plant follows a setpoint that is not its agent's dispatch rule "
                   "at the λ it publishes (still reported: setpoint_inconsistent); default: "
                   "it holds the last consistent one (docs/security.md)")
    add_loss_arguments(p)
    p.set_defaults(func=run)


def add_loss_arguments(p: argparse.ArgumentParser) -> None:
    """--loss P, --loss-seed N: the random-loss fault mode (docs/faults.md)."""
    from firmware_py.cliargs import float_in, int_in

    g = p.add_argument_group("fault mode: random frame loss (docs/faults.md)")
    g.add_argument("--loss", type=float_in(0.0, 0.99, what="a probability"),
                   default=0.0, metavar="P",
                   help="every node drops each frame it receives (but its own echo) with "
                   "probability P; the drops are counted and reported apart from the "
                   "anomalies (default: 0)")
    g.add_argument("--loss-seed", type=int_in(0), default=0, metavar="N",
                   help="seed of the loss: each node draws from its own generator seeded "
                   "from N and its name (default: 0)")


def run(args: argparse.Namespace) -> int:
    import json

    from sim.run import busrun
    from sim.run.busopts import C_BUS_EXPECTED, c_node_bus_argv
    from sim.run.fleet_plan import c_node_program

    c_flag, c_ids = c_agent_choice(args)
    if c_flag:
        bus = busrun.BusOptions(args.interface, args.channel, args.bus_config)
        if c_node_bus_argv(bus) is None:
            kw = bus.resolved()
            raise ParameterError(c_flag, C_BUS_EXPECTED,
                                 " ".join(str(kw.pop(k)) for k in ("interface", "channel")
                                          if k in kw)
                                 + (f" {json.dumps(kw)}" if kw else ""))
    plan = plan_run(args, "up", "{n} agents + plant + router")
    c_agents: frozenset[int] = frozenset()
    c_node = None
    if c_flag:
        c_agents = frozenset(range(1, plan.sc.n + 1)) if c_ids is None else c_ids
        if max(c_agents) > plan.sc.n:
            raise ParameterError("--c-agents", f"agents of this run (1..{plan.sc.n})",
                                 args.c_agents)
        c_node = c_node_program(c_flag)
        print(f"  agents in C: {', '.join(map(str, sorted(c_agents)))} ({c_node.name})")
    rec = busrun.record(plan.sc, plan.out, plan.bus, duration=plan.duration,
                        plot=not args.no_plot, time_scale=plan.scale, keys=args.keys,
                        insecure=args.insecure, c_agents=c_agents, c_node=c_node,
                        tolerance=args.tolerance, loss=args.loss, loss_seed=args.loss_seed,
                        agents_per_process=args.agents_per_process,
                        extra={"plant": ["--obey-inconsistent"]} if args.obey_inconsistent
                        else None)
    return print_report(plan, rec)


def c_agent_choice(args: argparse.Namespace) -> tuple[str | None, frozenset[int] | None]:
    """Which flag asks for C agents (None: none), and which agents (None: every one)."""
    if args.c_agents is not None:
        try:
            ids = frozenset(int(x) for x in args.c_agents.split(","))
        except ValueError:
            ids = frozenset()
        if not ids or min(ids) < 1:
            raise ParameterError("--c-agents", "agent ids like 3,5", args.c_agents)
        return "--c-agents", ids
    return ("--agent-impl c", None) if args.agent_impl == "c" else (None, None)
