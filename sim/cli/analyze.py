"""`bess-ded analyze LOG`: metrics, trajectory, anomalies and plot from any recorded log.

LOG is a candump-format log of a fleet (``candump -L``, ``bess-ded record``, the
run.log of ``bess-ded up``, a HIL rig's capture; any format python-can's LogReader
reads by its suffix: .log, .asc, .blf, .csv, ...). The scenario says what the fleet
was meant to do; a run made with ``--time-scale F`` is analysed with the same F.
The result is what ``bess-ded up`` writes for its own runs, through the same code:
DIR/metrics.json (verdict and anomalies included), DIR/trajectory.csv, DIR/bus_run.png.
Exit codes as ``bess-ded up``'s: 0 converged without anomalies, 1 not converged,
3 converged with anomalies, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from firmware_py.errors import ConfigError


def register(sub: argparse._SubParsersAction) -> None:
    from firmware_py.cliargs import positive_float

    from ._common import add_case_option, add_no_plot_argument, one_line_errors

    p = one_line_errors(sub.add_parser(
        "analyze", help="metrics, anomalies and plots from a recorded CAN log",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter))
    p.add_argument("log", type=Path, metavar="LOG", help="candump-format log of the fleet")
    add_case_option(p)
    p.add_argument("--variant", metavar="LABEL", help="the variant that ran (cases 2, 3, 6)")
    p.add_argument("--time-scale", type=positive_float(), default=1.0, metavar="F",
                   help="the --time-scale the run used (default: 1)")
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
    from ..runreport import report, summary_lines
    from ..scenario import scaled
    from ..verdict import RunFacts
    from ._common import resolve_scenario
    from .keys import load_key_set
    from .up import pick_variant

    if not args.log.is_file():
        raise ConfigError(str(args.log), "LOG", "expected a readable log file, but there is "
                          "no such file")
    sc, chosen = pick_variant(resolve_scenario(args.case), args.variant, "analyze")
    sc = scaled(sc, args.time_scale)
    out = args.out or args.log.parent / f"{args.log.stem}-analysis"
    counters_dir = args.counters or args.log.parent / "logs"
    counters = {}
    for role in ("plant", "router"):
        path = counters_dir / f"{role}.counters.json"
        if path.is_file():
            counters[role] = json.loads(path.read_text())
    if args.counters is not None and not counters:
        raise ConfigError(str(args.counters), "--counters", "expected plant.counters.json "
                          "and/or router.counters.json in it, but found neither")
    keys_dir = args.keys or args.log.parent / "keys"
    if args.keys is not None and not keys_dir.is_dir():
        raise ConfigError(str(keys_dir), "--keys", "expected a key set directory "
                          "(bess-ded keys --fleet --out DIR)")
    keys = load_key_set(keys_dir) if keys_dir.is_dir() else None
    print(f"bess-ded analyze: {args.log} as {sc.title or sc.name}{chosen} ({sc.n} agents)"
          + (f"; node counters from {counters_dir}" if counters else "")
          + (f"; frames verified with the keys in {keys_dir}" if keys else
             "; no keys: secured frames are taken as they are"))
    try:
        rec = report(sc, args.log, out, RunFacts(node_counters=counters or None),
                     plot=not args.no_plot, time_scale=args.time_scale, keys=keys)
    except (ValueError, EOFError) as e:  # python-can's readers on a file of another format
        raise ConfigError(str(args.log), "LOG", f"expected a CAN log python-can reads, but "
                          f"got: {e}") from None
    for line in summary_lines(rec.metrics, rec.verdict, args.time_scale):
        print(line)
    print(f"  wrote {', '.join(map(str, rec.written))}")
    return rec.verdict.exit_code
