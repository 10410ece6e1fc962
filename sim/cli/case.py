"""`bess-ded case N|PATH`: run a scenario in the lockstep simulator, every variant.

Writes into DIR (default runs/<scenario name>, e.g. runs/case1):
  metrics.json              the first run's metrics; with variants also "runs": {label: metrics}
  trajectory.csv            the first run, one row per sample
  trajectory_<label>.csv    every variant (scenarios with variants only)
  lambda_u_xi.png           λ_i with ρ(t) dashed and reset ticks, u_i, ξ_i; a column per variant
  nu_r.png                  ν_i and the dynamic gain r_i = ν_i/ξ_i
  power.png                 BESS powers P_i and the grid exchange P_e

Metric definitions: docs/metrics.md. Scenario files: docs/scenarios.md.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

from firmware_py.cliargs import int_in, nonnegative_float, positive_float
from firmware_py.config import RESILIENT_F_MAX
from firmware_py.controllers import KINDS
from sim.run.lockstep_case import DEFAULT_DWELL_S

from ._common import (
    add_arithmetic_arguments,
    add_no_plot_argument,
    add_scenario_argument,
    add_transmit_argument,
    one_line_errors,
    scenario_spec,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("case", help="run a case (or a scenario .toml) in the lockstep "
                       "simulator: metrics, trajectories, figures",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scenario_argument(p)
    p.add_argument("--controller", choices=KINDS,
                   help="run only this controller kind, replacing the scenario's variants "
                   "(a single run)")
    p.add_argument("--band", type=nonnegative_float(), metavar="XI",
                   help="reset re-arm band on |ξ| in cu/kWh, for every run (default: the "
                   "scenario's, else 1e-4)")
    p.add_argument("--dwell", type=positive_float(), metavar="S",
                   help=f"dwell Δ in s for the dwell controller (default: the scenario's, else "
                   f"{DEFAULT_DWELL_S:g})")
    p.add_argument("--resilient", type=int_in(0, RESILIENT_F_MAX, what="a number of liars F"),
                   metavar="F",
                   help="the resilient (W-MSR) update: each agent drops up to F neighbour λ "
                   "above its own and F below before ξ; prints whether the graph meets its "
                   "condition (default: the scenario's resilient_f, else 0: off)")
    add_arithmetic_arguments(p)
    add_transmit_argument(p)
    p.add_argument("--impl", choices=("py", "c"), default="py",
                   help="the controller implementation the agents step: firmware_py "
                   "(default) or firmware_c's C core (fixed point; the same trajectory bit "
                   "for bit)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="output directory (default: runs/<scenario name>, e.g. runs/case1)")
    add_no_plot_argument(p, "the PNG figures")
    one_line_errors(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from sim.model.metrics import SETTLING_BAND
    from sim.model.scenario_select import resolve_scenario, with_transmit
    from sim.report.textfmt import controller_desc, describe, fmt_settling
    from sim.run.lockstep_case import run_case, summary_table

    t0 = time.perf_counter()
    sc = with_transmit(resolve_scenario(scenario_spec(args)), args.transmit)
    if args.resilient is not None:
        sc = replace(sc, resilient_f=args.resilient)
    result = run_case(sc, controller=args.controller, band=args.band, dwell=args.dwell,
                      fixed=args.fixed, impl=args.impl, out=args.out, plot=not args.no_plot)
    results = result.runs
    runs = [(r.label, r.scenario) for r in results]
    written = result.written

    print(f"bess-ded case: {sc.title or sc.name}")
    print(f"  {describe(runs[0][1], args.fixed)}; controllers: "
          f"{'firmware_c (the C core)' if args.impl == 'c' else 'firmware_py'}")
    if len(runs) == 1:
        print(f"  controller {controller_desc(runs[0][1].controller)}")
        for line in runs[0][1].analysis().describe()[1:]:
            print(f"  {line}")
    if sc.resilient_f:
        from sim.model.robust import resilience

        for line in resilience(sc.n, sc.edges, sc.pinned, sc.resilient_f).describe():
            print(f"  {line}")
    print()
    print(summary_table([(label, m) for label, _, _, m in results],
                        [s.analysis() for _, s, _, _ in results]))
    print()
    if len(runs) > 1:
        width = max(len(label) for label, _ in runs)
        print("graph and gains:")
        for label, s in runs:
            lines = s.analysis().describe()[1:]
            print(f"  {label:<{width}}  {lines[0]}")
            for line in lines[1:]:
                print(f"  {'':<{width}}  {line}")
        print()
    if len(sc.prices) > 1:  # the table's a/b/c is terse; say which price each one is
        width = max(len(label) for label, _ in runs)
        print(f"settling time ({SETTLING_BAND:.0%} band), per price segment:")
        for label, s, _, m in results:
            print(f"  {label:<{width}}  {fmt_settling(s, m['settling_times_s'])}")
        print()
    if sc.transmit.event:
        tx = sc.transmit
        print(f"event-triggered λ (threshold {tx.threshold:g} cu/kWh, heartbeat "
              f"{tx.heartbeat} ticks), MC frames sent of one per agent and tick:")
        width = max(len(label) for label, _ in runs)
        for label, _, _, m in results:
            print(f"  {label:<{width}}  {m['mc_frames']} of {m['mc_frames_periodic']} "
                  f"({1 - m['mc_frames'] / m['mc_frames_periodic']:.1%} fewer)")
        print()
    print(f"wrote ({time.perf_counter() - t0:.1f} s):")
    for path in written:
        print(f"  {path}")
    return 0
