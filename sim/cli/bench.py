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

from firmware_py.cliargs import float_in, int_in

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
                   "--quick: ~25 s): rates, deadline misses, silences, settling; and the "
                   "fleet capacity (~8 min; --quick: ~2 min): the agents' missed ticks by "
                   "fleet size and agents per process, each run --repeats times (median "
                   "and worst)")
    f = p.add_argument_group("fleet capacity (with --realtime)")
    f.add_argument("--fleet-sizes", type=int_list, default=(16, 32), metavar="N,...",
                   help="agents per fleet (default: 16,32)")
    f.add_argument("--agents-per-process", type=int_list, default=(1, 16), metavar="K,...",
                   help="Python agents per process, each fleet run with each (default: 1,16)")
    f.add_argument("--repeats", type=int_in(1), default=3, metavar="R",
                   help="runs per fleet and K (default: 3)")
    f.add_argument("--fleet-seconds", type=float_in(4.0, 3600.0), default=14.0, metavar="S",
                   help="price time per run (default: 14: 12 s of steady state)")
    f.add_argument("--fleet-impl", choices=("py", "c"), default="py",
                   help="firmware_py agents on udp_multicast (default), or firmware_c's node "
                   "program, a process per agent, on SocketCAN --channel")
    f.add_argument("--channel", default="vcan0", help="SocketCAN channel of --fleet-impl c")
    f.add_argument("--capacity-only", action="store_true",
                   help="the fleet capacity alone: no micro-benchmarks, no cases")
    one_line_errors(p)
    p.set_defaults(func=run)


def int_list(text: str) -> tuple[int, ...]:
    """"16,32" → (16, 32): positive integers."""
    try:
        out = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        out = ()
    if not out or min(out) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers like 16,32, but got "
                                         f"{text!r}")
    return out


def run(args: argparse.Namespace) -> int:
    from sim.bench.micro import machine_info, run_benches
    from sim.bench.realtime import CapacityPlan
    from sim.report.textfmt import table, write_json

    t0 = time.perf_counter()
    info = machine_info()
    print(f"bess-ded bench{' --quick' if args.quick else ''}"
          f"{' --realtime' if args.realtime else ''}"
          f"{' --capacity-only' if args.capacity_only else ''}")
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

    plan = CapacityPlan(args.fleet_sizes, args.agents_per_process, args.repeats,
                        args.fleet_seconds, args.fleet_impl, args.channel)
    tables = run_benches(args.quick, args.realtime, on_table=show, capacity=plan,
                         only_capacity=args.capacity_only)
    print()
    print(f"bench took {time.perf_counter() - t0:.1f} s")
    if args.json:
        write_json(args.json, {"machine": info, "quick": args.quick, "tables": [
            {"title": t.title, "headers": t.headers, "rows": t.rows, "data": t.data}
            for t in tables]})
        print(f"wrote {args.json}")
    return 0
