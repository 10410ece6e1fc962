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
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from firmware_py.cliargs import nonnegative_float, positive_float
from firmware_py.controllers import KINDS
from firmware_py.errors import ParameterError

from ..graph import GraphReport
from ..metrics import SETTLING_BAND
from ..scenario import Scenario
from ..trajectory import Trajectory
from ._common import (
    Progress,
    add_arithmetic_arguments,
    add_no_plot_argument,
    add_scenario_argument,
    controller_desc,
    describe,
    fmt_pct,
    fmt_resets,
    fmt_sci,
    fmt_settling,
    fmt_times,
    one_line_errors,
    resolve_scenario,
    scenario_spec,
    slug,
    table,
    write_json,
)

DEFAULT_DWELL_S = 1.0  # Δ for `--controller dwell` on a scenario that sets none (paper case 6)


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
    add_arithmetic_arguments(p)
    p.add_argument("--impl", choices=("py", "c"), default="py",
                   help="the controller implementation the agents step: firmware_py "
                   "(default) or firmware_c's C core (fixed point; the same trajectory bit "
                   "for bit)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="output directory (default: runs/<scenario name>, e.g. runs/case1)")
    add_no_plot_argument(p, "the PNG figures")
    one_line_errors(p)
    p.set_defaults(func=run)


Run = tuple[str, Scenario, Trajectory, dict[str, Any]]


def plan(sc: Scenario, controller: str | None = None, band: float | None = None,
         dwell: float | None = None) -> list[tuple[str, Scenario]]:
    """(label, scenario) for each run: the scenario's variants, or one run of
    ``controller``; ``band``/``dwell`` override every run's controller."""
    over: dict[str, Any] = {}
    if band is not None:
        over["band"] = band
    if dwell is not None:
        over["dwell"] = dwell
    if controller is not None:
        if controller == "dwell" and dwell is None and sc.controller.dwell < sc.ts:
            over["dwell"] = DEFAULT_DWELL_S
        return [(controller, sc.with_controller(kind=controller, **over))]
    return [(label, s.with_controller(**over) if over else s) for label, s in sc.runs()]


def simulate(runs: list[tuple[str, Scenario]], fixed: bool, impl: str = "py") -> list[Run]:
    """Run each (label, scenario) in lockstep: (label, scenario, trajectory, metrics)."""
    from ..lockstep import run_lockstep
    from ..metrics import compute

    out: list[Run] = []
    for label, s in runs:
        progress = Progress(label)
        try:
            tr = run_lockstep(s, fixed=fixed, progress=progress, impl=impl)
        finally:
            progress.done()
        tr.label = label
        m = compute(s, tr)
        m["arithmetic"] = "fixed" if fixed else "float"
        m["implementation"] = "firmware_c" if impl == "c" else "firmware_py"
        out.append((label, s, tr, m))
    return out


def run(args: argparse.Namespace) -> int:
    from .. import plots

    t0 = time.perf_counter()
    sc = resolve_scenario(scenario_spec(args))
    runs = plan(sc, args.controller, args.band, args.dwell)
    if args.impl == "c":
        check_c_core(args.fixed)
    out: Path = args.out or Path("runs") / slug(sc.name)
    out.mkdir(parents=True, exist_ok=True)
    results = simulate(runs, args.fixed, args.impl)

    first = results[0][3]
    top: dict[str, Any] = {**first, "title": sc.title, "source": sc.source}
    written = []
    if len(results) > 1:
        top["runs"] = {label: m for label, _, _, m in results}
    write_json(out / "metrics.json", top)
    written.append(out / "metrics.json")
    results[0][2].write_csv(out / "trajectory.csv")
    written.append(out / "trajectory.csv")
    if len(results) > 1:
        for label, _, tr, _ in results:
            path = out / f"trajectory_{slug(label)}.csv"
            tr.write_csv(path)
            written.append(path)

    if not args.no_plot:
        title = sc.title or sc.name
        if args.controller:
            title += f" — {args.controller}"
        if not args.fixed:
            title += " (float)"
        trs = [(label, tr) for label, _, tr, _ in results]
        written.append(plots.consensus_figure(trs, out / "lambda_u_xi.png", title))
        written.append(plots.gain_figure(trs, out / "nu_r.png", title))
        written.append(plots.power_figure(trs, out / "power.png", title, load_kw=sc.load_kw,
                                          batteries=sc.batteries))

    print(f"bess-ded case: {sc.title or sc.name}")
    print(f"  {describe(runs[0][1], args.fixed)}; controllers: "
          f"{'firmware_c (the C core)' if args.impl == 'c' else 'firmware_py'}")
    if len(runs) == 1:
        print(f"  controller {controller_desc(runs[0][1].controller)}")
        for line in runs[0][1].analysis().describe()[1:]:
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
    print(f"wrote ({time.perf_counter() - t0:.1f} s):")
    for path in written:
        print(f"  {path}")
    return 0


def check_c_core(fixed: bool) -> None:
    """--impl c: fixed point, and the C core builds (else a one-line error, exit 2)."""
    from ..cimpl import CBuildError, load

    if not fixed:
        raise ParameterError("--impl c", "--fixed (the C core is fixed point only)", "--float")
    try:
        load()
    except (CBuildError, OSError) as e:
        last = (str(e).strip().splitlines() or [type(e).__name__])[-1]
        raise ParameterError("--impl c", "firmware_c to build (make and a C compiler: "
                             "tools/install-c-deps)", last) from None


def summary_table(rows: list[tuple[str, dict[str, Any]]],
                  reports: Sequence[GraphReport] | None = None) -> str:
    """The summary; with ``reports`` (one per row) the regular column says 'n/a' for the
    controllers Theorem 1 is not about, and '; unstable at Ts' when the Euler step is."""
    headers = ["run", "settling [s]", "overshoot", "final error", "resets/agent", "TV(u)",
               "regular", "cost [cu/h]", "vs optimal"]
    body = []
    for r, (label, m) in enumerate(rows):
        tv = m.get("control_total_variation")
        body.append([
            label, fmt_times(m["settling_times_s"]), fmt_pct(m["overshoot"]),
            fmt_sci(m["final_error"]), fmt_resets(m["resets"]),
            "-" if tv is None else f"{tv:.2f}",
            reports[r].verdict() if reports else (
                ("yes" if m["regular"] else "no")
                + ("" if m["discrete_stable"] else "; unstable at Ts")),
            f"{m['cost']:.4f}", f"{m['cost'] - m['optimal_cost']:+.1e}"])
    return table(headers, body, align="lrrrlrlrr")
