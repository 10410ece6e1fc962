"""Options and output shared by the fleet-run subcommands ``up`` and ``restbus`` (not a
subcommand itself): the options, the plan (sim.run.fleet_plan) and the report."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_py.nodeargs import add_bus_arguments, add_fd_argument
from sim.run.fleet_plan import GUEST_TIME_SCALE

if TYPE_CHECKING:
    from sim.run.fleet_plan import RunPlan
    from sim.run.runreport import Recording


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    """The options of a fleet run on a bus (`up`, `restbus`): scenario, bus, duration,
    output, time scale, keys."""
    from firmware_py.cliargs import duration_s, time_scale

    from ._common import add_case_option, add_no_plot_argument, add_transmit_argument

    add_case_option(p)
    add_transmit_argument(p)
    p.add_argument("--variant", metavar="LABEL",
                   help="for a scenario with variants (cases 2, 3, 6): which one to run "
                   "(default: the first)")
    add_bus_arguments(p)
    add_fd_argument(p)
    p.add_argument("--duration", type=duration_s(), metavar="S",
                   help="seconds of price time (default: the scenario's duration)")
    p.add_argument("--out", type=Path, help="output directory (default: runs/<command>-"
                   "<scenario>)")
    p.add_argument("--time-scale", type=time_scale, metavar="F",
                   help="stretch the time axis by F (Ts·F, k/F, h/F²: the same discrete "
                   "system) for hosts too slow for Ts = 10 ms, e.g. an emulated guest "
                   f"(default: 1, or {GUEST_TIME_SCALE:g} under tools/vcan-run)")
    add_no_plot_argument(p, "bus_run.png")
    add_tolerance_argument(p)
    k = p.add_mutually_exclusive_group()
    k.add_argument("--keys", type=Path, metavar="DIR",
                   help="sign with this key set from `bess-ded keys --fleet` (its boot "
                        "counters advance); default: a fresh key set for this run in "
                        "OUT/keys")
    k.add_argument("--insecure", action="store_true",
                   help="demo mode: every node signs with the public all-zero key and warns "
                        "(docs/security.md)")


def add_tolerance_argument(p: argparse.ArgumentParser) -> None:
    """--tolerance CU: the final max|λ−ρ| a converged run must be within."""
    from firmware_py.cliargs import positive_float
    from sim.run.verdict import TOLERANCE

    p.add_argument("--tolerance", type=positive_float(), default=TOLERANCE, metavar="CU",
                   help="converged only if every dispatching agent's final λ is within CU "
                   f"cu/kWh of ρ (default: {TOLERANCE:g}); a λ this far off the others' "
                   "is a lambda_outlier")


def plan_run(args: argparse.Namespace, command: str, nodes: str) -> RunPlan:
    """Check the options of a fleet run and print its banner (``nodes``: what runs)."""
    from sim.bench.fleetload import check_bus_load
    from sim.run import busrun
    from sim.run.fleet_plan import plan_fleet_run

    return plan_fleet_run(args.case, variant=args.variant,
                          bus=busrun.BusOptions(args.interface, args.channel, args.bus_config),
                          duration=args.duration, out=args.out, time_scale=args.time_scale,
                          keys=args.keys, insecure=args.insecure, command=command, nodes=nodes,
                          transmit=args.transmit, fd=args.fd,
                          no_lambda_tags=args.no_lambda_tags,
                          check=check_bus_load)  # a fleet the bus cannot carry: refused


def print_report(plan: RunPlan, rec: Recording) -> int:
    """The summary, the files written; the exit code of the verdict."""
    from sim.run.runreport import summary_lines

    for line in summary_lines(rec.metrics, rec.verdict, plan.scale):
        print(line)
    print(f"  wrote {', '.join(map(str, [plan.out / 'run.log', *rec.written]))}")
    return rec.verdict.exit_code
