"""`bess-ded bench [--quick]`: how fast the control core and the simulator run.

Not a test (nothing passes or fails): numbers for docs/performance.md, with the
machine they were measured on. The benchmarks are the library's: sim/bench/micro.py.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from ._common import one_line_errors

if TYPE_CHECKING:
    from sim.bench.micro import Table


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="micro-benchmarks: µs per agent step, simulator speed",
                       description=__doc__)
    p.add_argument("--quick", action="store_true",
                   help="fewer samples and repetitions: the whole bench in a few seconds")
    p.add_argument("--json", type=Path, metavar="FILE", help="also write the results as JSON")
    p.add_argument("--realtime", action="store_true",
                   help="also run cases 1 and 7 as node processes on the bus (~1 min; "
                   "--quick: ~25 s): rates, deadline misses, silences, settling")
    one_line_errors(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from sim.bench.micro import machine_info, run_benches
    from sim.report.textfmt import table, write_json

    t0 = time.perf_counter()
    info = machine_info()
    print(f"bess-ded bench{' --quick' if args.quick else ''}"
          f"{' --realtime' if args.realtime else ''}")
    print(f"  python {info['python']}, {info['platform']}")
    print(f"  CPU {info['cpu']} ({info['logical_cpus']} logical), numpy {info['numpy']}, "
          f"load average {info['load_average_1min']} at start")

    def show(tab: Table) -> None:
        print()
        print(tab.title)
        print(table(tab.headers, tab.rows))
        if tab.note:
            print(f"  ({tab.note})")
        sys.stdout.flush()

    tables = run_benches(args.quick, args.realtime, on_table=show)
    print()
    print(f"bench took {time.perf_counter() - t0:.1f} s")
    if args.json:
        write_json(args.json, {"machine": info, "quick": args.quick, "tables": [
            {"title": t.title, "headers": t.headers, "rows": t.rows, "data": t.data}
            for t in tables]})
        print(f"wrote {args.json}")
    return 0
