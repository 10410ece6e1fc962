"""`bess-ded bench [--quick] [--auth | --fleet-load | --capacity-only]`: how fast the
control core and the simulator run.

Not a test (nothing passes or fails): numbers for docs/performance.md, with the
machine they were measured on. The benchmarks are the library's: sim/bench/micro.py.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_py.errors import ParameterError

from ._common import one_line_errors
from .benchopts import add_capacity_arguments, selected

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
                   "--quick: ~25 s): rates, deadline misses, silences, settling; and the "
                   "fleet capacity (~16 min; --quick: ~3 min): the agents' missed ticks by "
                   "fleet size, agents per process and transmit mode, each run --repeats "
                   "times (median and worst), beside the machine's own stalls")
    p.add_argument("--auth", action="store_true",
                   help="only the authentication schemes (issue 25): sign/verify µs, bus "
                   "load of cases 1, 7 and a 32-agent ring at Ts = 10 ms, latency, what "
                   "an insider still forges (a few seconds)")
    p.add_argument("--fleet-load", action="store_true",
                   help="only the bus load per fleet size (issue 23): 4..64 agents at Ts = "
                   "10 ms, classic and CAN FD, periodic and event-triggered λ, computed "
                   "from the DBC, the largest N at ≤ 60 %% (~15 s; --quick: ~10 s)")
    p.add_argument("--measured", type=Path, action="append", default=[], metavar="DIR",
                   help="with --fleet-load: also the bus load of this `bess-ded up` run "
                   "measured from its recording (DIR/run.log, DIR/scenario.toml) against the "
                   "computed figure (repeatable)")
    p.add_argument("--case", "--scenario", dest="case", action="append", default=[],
                   metavar="CASE",
                   help="with --fleet-load: also the computed bus load of this scenario's "
                   "fleet at its Ts, classic and FD (event-triggered: the lockstep's ratio "
                   "over its run); a case number or a scenario .toml (repeatable)")
    p.add_argument("--png", type=Path, metavar="FILE",
                   help="also draw the schemes' bus load as a bar chart (PNG); with "
                   "--fleet-load: the load against N, one line per configuration")
    add_capacity_arguments(p)
    one_line_errors(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from sim.bench.micro import machine_info, run_benches
    from sim.report.textfmt import table, write_json

    t0 = time.perf_counter()
    only, plan = selected(args)
    info = machine_info()
    print(f"bess-ded bench{' --quick' if args.quick else ''}"
          f"{' --realtime' if args.realtime else ''}{' --auth' if args.auth else ''}"
          f"{' --fleet-load' if args.fleet_load else ''}"
          f"{' --capacity-only' if args.capacity_only else ''}")
    print(f"  python {info['python']}, {info['platform']}")
    print(f"  CPU {info['cpu']} ({info['logical_cpus']} logical), numpy {info['numpy']}, "
          f"load average {info['load_average_1min']} at start")

    def show(tab: Table) -> None:
        print()
        print(tab.title)
        print(table(tab.headers, tab.rows, tab.align))
        if tab.note:
            print(f"  ({tab.note})")
        sys.stdout.flush()

    tables = run_benches(args.quick, args.realtime, on_table=show, only=only,
                         capacity=plan)
    print()
    print(f"bench took {time.perf_counter() - t0:.1f} s")
    if args.json:
        write_json(args.json, {"machine": info, "quick": args.quick, "tables": [
            {"title": t.title, "headers": t.headers, "rows": t.rows, "data": t.data}
            for t in tables]})
        print(f"wrote {args.json}")
    if args.png and args.fleet_load:
        from sim.bench.fleetload import plot as plot_fleet

        plot_fleet(tables[0].data, args.png)
        print(f"wrote {args.png}")
    elif args.png:
        from sim.bench.auth import plot

        schemes = [t for t in tables if t.title.startswith("Authentication schemes")]
        if not schemes:
            raise ParameterError("--png", "--png with a run that has the authentication "
                                 "schemes (plain bench or --auth)", "--png without them")
        plot(schemes[0].data, args.png)
        print(f"wrote {args.png}")
    return 0
