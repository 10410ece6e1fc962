"""`bess-ded tune CASE|PATH|random:N[:DEGREE[:SEED]]`: reset-PI gains from the graph's spectrum.

Picks k, h and the reset band from H = L + B (η_min, η_max, Theorem 1 and the Ts-stability
margin), the initial errors and a bound on peak |u| (--peak-ratio × PC's peak at the
scenario's own k); predicts the settling and the peak with the modal reset model, then
runs the lockstep with those gains, with PC at the scenario's k and with PC at the same
peak |u|, and writes everything to DIR/tune.json. The rule: docs/tuning.md.

SCENARIO is a paper case number, a scenario .toml, or random:N[:DEGREE[:SEED]] (a random
DEGREE-regular fleet of N agents; degree 3, seed 0 by default).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_py.cliargs import float_in
from firmware_py.errors import ParameterError

from ._common import add_scenario_argument, one_line_errors, scenario_spec

if TYPE_CHECKING:
    from sim.model.scenario import Scenario


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("tune", help="reset-PI gains (k, h, band) from the graph's spectrum "
                       "and a peak-|u| bound; verified against PC",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scenario_argument(p)
    p.add_argument("--peak-ratio", type=float_in(1.0, 10.0, what="a ratio"), default=1.2,
                   metavar="R", help="bound on the reset-PI's peak |u| as a multiple of PC's "
                   "at the scenario's k (default: 1.2)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="where tune.json goes (default: runs/tune-<scenario name>)")
    one_line_errors(p)
    p.set_defaults(func=run)


def _scenario(spec: str) -> Scenario:
    if not spec.startswith("random:"):
        from sim.model.scenario_select import resolve_scenario

        return resolve_scenario(spec)
    from sim.model.generate import random_scenario

    parts = spec.split(":")[1:]
    try:
        nums = [int(x) for x in parts]
    except ValueError:
        nums = []
    if not 1 <= len(nums) <= 3:
        raise ParameterError("SCENARIO", "random:N[:DEGREE[:SEED]] with integers", spec)
    return random_scenario(*nums)


def _s(x: float | None) -> str:
    return "not settled" if x is None else f"{x:.2f} s"


def _r(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}×"


def run(args: argparse.Namespace) -> int:
    from sim.study.tune import tune

    t0 = time.perf_counter()
    sc = _scenario(scenario_spec(args))
    res = tune(sc, peak_ratio=args.peak_ratio)
    pred, sim = res.predicted, res.simulated
    print(f"bess-ded tune: {sc.title or sc.name}")
    print(f"  {res.agents} agents, η_min(H) = {res.eta_min:.4f}, η_max(H) = {res.eta_max:.4f}, "
          f"Ts = {res.ts * 1e3:g} ms")
    print(f"  gains: k = {res.k:g}, h = {res.h:g}, band = {res.band:.3g}  (4h = "
          f"{4 * res.h:.4g} > η_max·k² = {res.eta_max * res.k ** 2:.4g}; stable at Ts: "
          f"1 − max|1 + Ts·μ| = {1 - res.spectral_radius:.2g})")
    print(f"  peak |u| budget: {res.peak_ratio:g} × PC's {sim['pc']['peak_u']:.4g} at "
          f"k = {res.k_ref:g} = {res.peak_budget:.4g}"
          + (f"; h lowered {res.steps_down} × 10 % after simulation" if res.steps_down else ""))
    print()
    print(f"  {'':<22}{'settling':>13}{'peak |u|':>10}")
    print(f"  {'reset-PI predicted':<22}{_s(pred['reset']['settling_s']):>13}"
          f"{pred['reset']['peak_u']:>10.4g}")
    print(f"  {'PC predicted':<22}{_s(pred['pc']['settling_s']):>13}"
          f"{pred['pc']['peak_u']:>10.4g}")
    print(f"  {'reset-PI simulated':<22}{_s(sim['reset']['settling_s']):>13}"
          f"{sim['reset']['peak_u']:>10.4g}")
    print(f"  {'PC simulated':<22}{_s(sim['pc']['settling_s']):>13}"
          f"{sim['pc']['peak_u']:>10.4g}")
    print(f"  {'PC, same peak':<22}{_s(sim['pc_same_peak']['settling_s']):>13}"
          f"{sim['pc_same_peak']['peak_u']:>10.4g}  (k = {sim['pc_same_peak']['k']:.4g})")
    print()
    r = res.ratios
    print(f"  settling vs PC: {_r(r['settling_vs_pc'])} (predicted "
          f"{_r(r['predicted_settling_vs_pc'])}), vs PC at the same peak: "
          f"{_r(r['settling_vs_pc_same_peak'])}; peak vs PC: {_r(r['peak_vs_pc'])}")
    print(f"  target (≤ 0.5× PC's settling at ≤ {res.peak_ratio:g}× its peak): "
          f"{'met' if res.target_met else 'NOT met'}")
    out = args.out or Path("runs") / f"tune-{sc.name}"
    out.mkdir(parents=True, exist_ok=True)
    path = out / "tune.json"
    path.write_text(json.dumps(res.to_json(), indent=2) + "\n")
    print(f"wrote ({time.perf_counter() - t0:.1f} s): {path}")
    return 0
