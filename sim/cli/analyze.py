"""`bess-ded analyze LOG`: metrics, trajectory, anomalies and plot from any recorded log.

LOG is a candump-format log of a fleet (``candump -L``, ``bess-ded record``, the
run.log of ``bess-ded up``, a HIL rig's capture; any format python-can's LogReader
reads by its suffix: .log, .asc, .blf, .csv, ...). The scenario says what the fleet
was meant to do; a run made with ``--time-scale F`` is analysed with the same F.
The result is what ``bess-ded up`` writes for its own runs, through the same code:
DIR/metrics.json (verdict and anomalies included), DIR/trajectory.csv, DIR/bus_run.png.
Exit codes as ``bess-ded up``'s: 0 converged without anomalies, 1 not converged,
3 converged with anomalies, 2 bad input.

LOG may be the directory `up` wrote (or its run.log): everything `up` knew is then read
back from it (DIR/keys, DIR/logs/*.counters.json, DIR/logs/run_facts.json: exit codes,
deaths, --insecure, the boot floors, --time-scale and --tolerance; DIR/scenario.toml
when neither --case nor --scenario is given), so the same run gets the same verdict
from `analyze` as from `up`. A log without keys whose frames verify with the public
demo keys is an --insecure run (insecure_keys).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from firmware_py.cliargs import positive_float, time_scale

    from ._common import (
        add_case_option,
        add_no_plot_argument,
        add_transmit_argument,
        one_line_errors,
    )

    p = one_line_errors(sub.add_parser(
        "analyze", help="metrics, anomalies and plots from a recorded CAN log",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter))
    p.add_argument("log", type=Path, metavar="LOG",
                   help="candump-format log of the fleet, or the directory `up` wrote")
    add_case_option(p, required=False)
    p.add_argument("--variant", metavar="LABEL", help="the variant that ran (cases 2, 3, 6)")
    add_transmit_argument(p)
    p.add_argument("--time-scale", type=time_scale, metavar="F",
                   help="the --time-scale the run used (default: the run's, else 1)")
    p.add_argument("--tolerance", type=positive_float(), metavar="CU",
                   help="converged only if every dispatching agent's final λ is within CU "
                   "cu/kWh of ρ (default: the run's --tolerance, else 1e-3)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="output directory (default: LOG's directory/<LOG stem>-analysis)")
    p.add_argument("--counters", type=Path, metavar="DIR",
                   help="a directory with the plant's and router's counters JSON "
                   "(plant.counters.json, router.counters.json; default: LOG's "
                   "directory/logs when they are there, as `up` leaves them)")
    p.add_argument("--keys", type=Path, metavar="DIR",
                   help="the run's key set (default: LOG's directory's keys/ if there, as "
                        "`up` writes it): secured frames whose MAC does not verify are left "
                        "out and reported (auth_failed)")
    add_no_plot_argument(p, "bus_run.png")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from sim.run.analysis import prepare_analysis
    from sim.run.runreport import summary_lines

    analysis = prepare_analysis(args.log, args.case, args.variant, args.time_scale,
                                args.tolerance, args.out, args.counters, args.keys,
                                transmit=args.transmit)
    print(analysis.describe())
    rec = analysis.run(plot=not args.no_plot)
    for line in summary_lines(rec.metrics, rec.verdict, analysis.time_scale):
        print(line)
    print(f"  wrote {', '.join(map(str, rec.written))}")
    return rec.verdict.exit_code
