"""`bess-ded sweep SPEC.toml`: many lockstep runs over graphs, gains and seeds, one table.

The spec (docs/sweeps.md) names the axes and a grid or a random sample; every point's
metrics are appended to OUT/results.csv as it finishes, a rerun skips the points already
there, and OUT/sweep.png plots settling time over the swept axes and the failures.
Local processes by default (--jobs); a Ray cluster with --ray ADDRESS.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from firmware_py.cliargs import positive_int

from ._common import add_no_plot_argument, one_line_errors


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sweep", help="many lockstep runs over graphs, gains, seeds: one table",
                       description=__doc__)
    p.add_argument("spec", metavar="SPEC", help="the sweep spec: a TOML file, or the name "
                   "of one that ships with bess-ded (reset-vs-pc)")
    p.add_argument("--limit", type=positive_int("a number of points"), default=None,
                   metavar="N", help="run only the sweep's first N points (a rerun adds "
                   "the rest)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="where results.csv and sweep.png go (default: runs/sweep-NAME)")
    p.add_argument("--jobs", type=positive_int("a number of processes"),
                   default=os.cpu_count() or 1, metavar="N",
                   help="local worker processes (default: one per CPU)")
    p.add_argument("--ray", metavar="ADDRESS", default=None,
                   help="run the points on a Ray cluster ('auto', 'ray://host:10001', or "
                   "'local' for Ray's own local mode); needs pip install 'bess-ded[ray]'")
    p.add_argument("--parquet", action="store_true",
                   help="also write results.parquet (needs pip install 'bess-ded[parquet]')")
    add_no_plot_argument(p, "sweep.png")
    one_line_errors(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from sim.report.sweep_plots import plot_sweep, varying
    from sim.study.sweep import load_spec, read_results, run_sweep, summarise

    spec = load_spec(args.spec)
    out = args.out or Path("runs") / f"sweep-{spec.name}"
    if args.ray is not None and args.jobs != (os.cpu_count() or 1):
        print("bess-ded sweep: --jobs is ignored with --ray (the cluster schedules)",
              file=sys.stderr)
    executor = None
    if args.ray is not None:
        from sim.study.rayrun import ray_executor

        executor = ray_executor(args.ray)
    t0 = time.perf_counter()
    tty = sys.stderr.isatty()
    cr = "\r" if tty else ""
    last = [0.0]

    def progress(done: int, total: int, failed: int) -> None:
        now = time.perf_counter() - t0
        if done == total or now - last[0] >= (0.2 if tty else 5.0):
            last[0] = now
            eta = now / done * (total - done)
            print(f"{cr}sweep: {done}/{total} points, {failed} failed, "
                  f"{now:.0f} s, ~{eta:.0f} s to go", end="" if tty and done < total else "\n",
                  file=sys.stderr, flush=True)

    res = run_sweep(spec, out, jobs=args.jobs, limit=args.limit, progress=progress,
                    executor=executor)
    rows = read_results(res.results)
    print(f"sweep {spec.name}: {res.run} points run, {res.skipped} done before, "
          f"{res.failed} of the new not converged or invalid, {res.wall_s:.1f} s")
    numeric, categorical = varying(rows, spec.columns)
    for line in summarise(rows, categorical[0] if categorical else None):
        print(f"  {line}")
    print(f"results: {res.results}")
    if args.parquet:
        from sim.study.rayrun import write_parquet

        print(f"parquet: {write_parquet(res.results)}")
    if not args.no_plot and rows:
        plot_sweep(rows, spec.columns, out / "sweep.png", f"sweep {spec.name}")
        print(f"plot: {out / 'sweep.png'}")
    return 0
