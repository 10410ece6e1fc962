"""`bess-ded compare N|PATH`: every controller on one scenario, side by side.

Runs reset-PI, PC, PI (no reset), finite-time and reset-PI with a dwell Δ = 1 s on
the scenario's graph, batteries, prices and gains (its [controller] table; its
variants are ignored), prints a table and writes into DIR (default
runs/compare-<scenario name>):
  compare.json   {"scenario", "title", "arithmetic", "controllers": {label: metrics}}
  compare.png    one column per controller: λ_i (ρ dashed, reset ticks) over u_i
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from sim.model.scenario import Scenario
from sim.model.scenario_select import resolve_scenario, with_transmit
from sim.report.textfmt import (
    describe,
    fmt_pct,
    fmt_resets,
    fmt_sci,
    fmt_time,
    slug,
    table,
    write_json,
)
from sim.run.lockstep_case import simulate

from ._common import (
    add_arithmetic_arguments,
    add_scenario_argument,
    add_transmit_argument,
    one_line_errors,
    scenario_spec,
)

# (label, controller overrides): the paper's method first, then its baselines
CONTROLLERS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("reset-PI", {"kind": "reset"}),
    ("PC", {"kind": "pc"}),
    ("PI", {"kind": "pi"}),
    ("finite-time", {"kind": "ft"}),
    ("dwell Δ=1 s", {"kind": "dwell", "dwell": 1.0}),
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="run every controller on one case and compare them",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scenario_argument(p)
    add_arithmetic_arguments(p)
    add_transmit_argument(p)
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="output directory (default: runs/compare-<scenario name>)")
    one_line_errors(p)
    p.set_defaults(func=run)


def plan(sc: Scenario) -> list[tuple[str, Scenario]]:
    """(label, scenario) for every controller of CONTROLLERS, on ``sc``."""
    return [(label, sc.with_controller(**over)) for label, over in CONTROLLERS]


def run(args: argparse.Namespace) -> int:
    from sim.report import plots

    t0 = time.perf_counter()
    sc = with_transmit(resolve_scenario(scenario_spec(args)), args.transmit)
    runs = plan(sc)
    out: Path = args.out or Path("runs") / f"compare-{slug(sc.name)}"
    out.mkdir(parents=True, exist_ok=True)
    results = simulate(runs, args.fixed)

    write_json(out / "compare.json", {
        "scenario": sc.name, "title": sc.title, "source": sc.source,
        "arithmetic": "fixed" if args.fixed else "float",
        "controllers": {label: m for label, _, _, m in results}})
    c = sc.controller
    title = (f"Controllers compared on {sc.name}: {sc.n} agents, k = {c.k:g}, h = {c.h:g}, "
             f"Ts = {sc.ts * 1e3:g} ms" + ("" if args.fixed else ", float"))
    png = plots.compare_figure([(label, tr) for label, _, tr, _ in results],
                               out / "compare.png", title)

    print(f"bess-ded compare: {sc.title or sc.name}")
    print(f"  {describe(sc, args.fixed)}, k = {c.k:g}, h = {c.h:g}")
    reset_pi, pc = (dict(runs)[name] for name in ("reset-PI", "PC"))
    for line in reset_pi.analysis().describe()[1:]:
        print(f"  reset-PI, PI: {line}")
    print(f"  PC, finite-time: {pc.analysis().describe()[2]}")
    print()
    print(compare_table([(label, m) for label, _, _, m in results]))
    print()
    print(f"wrote ({time.perf_counter() - t0:.1f} s):")
    print(f"  {out / 'compare.json'}")
    print(f"  {png}")
    return 0


def compare_table(rows: list[tuple[str, dict[str, Any]]]) -> str:
    """The comparison table: one row per controller's metrics."""
    headers = ["controller", "settling [s]", "overshoot", "TV(u)", "peak |u|", "resets/agent",
               "final error"]
    body = [[label, "/".join(fmt_time(x) for x in m["settling_times_s"]),
             fmt_pct(m["overshoot"]), f"{m.get('control_total_variation', float('nan')):.2f}",
             f"{m.get('peak_control', float('nan')):.2f}", fmt_resets(m["resets"]),
             fmt_sci(m["final_error"])] for label, m in rows]
    return table(headers, body, align="lrrrrlr")
