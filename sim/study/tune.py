"""Gains for the reset-PI from the graph's spectrum and a bound on peak |u| (`bess-ded tune`).

The rule (docs/tuning.md):

* The error e = λ − ρ obeys, in the eigenbasis of H = L + B, one second-order system per
  eigenvalue η: ë + kη ė + hη e = 0 (the PI base system), e(0) = e₀, ė(0) = −kη e₀.
  Theorem 1's 4h > η k² makes every mode underdamped: e = e₀ e^{−σt}(cos ω t − σ/ω sin ω t)
  with σ = kη/2, ω = √(hη − σ²). A Clegg reset at the mode's first zero of ξ = ηe puts it at
  rest there, at t₁(η) = atan2(ω, σ)/ω: each mode is dead-beat, and for h ≫ k²η the slowest
  mode (η_min) arrives after about π/(2√(h η_min)). PC's modes decay as e^{−kηt} instead.
* The *modal reset model* sums those modes back over the agents and predicts the settling
  time (the metrics' 2 % band on max_i |λ_i − ρ|) and the peak |u| = max_i |λ̇_i| of a gain
  pair; the same sum with e^{−kηt} predicts PC's.
* Peak |u| is at t = 0 for PC: k·max_i|ξ_i(0)|. The budget is ``peak_ratio`` × PC's peak at
  the scenario's own k (the reference gain). Raising h shortens t₁ but the integral's push at
  the reset instant, ≈ √(hη)·|e₀|·e^{−σt₁} per mode, grows with √h; raising k spends the
  budget at t = 0. The tuner takes, over a grid of k ≤ peak_ratio·k_ref and h on Theorem 1's
  side with Ts-stability, the pair of shortest predicted settling whose predicted peak fits
  the budget with a safety ``margin`` (resets are per agent, not per mode, so the model is
  an estimate: the simulation verifies it).
* If the simulation of that pair exceeds the peak budget, h is lowered in steps of 10 %
  until it fits (``steps_down`` reports how many; 0 when the prediction alone held).
* The reset band: above the quantisation floor of ξ (each of the deg_i + b_i differences
  in ξ_i is rounded to one LSB of Q``q``) and far below the settled band: 1 % of the
  |ξ| that the 2 % settling band allows, η_min · 2 % · max|e₀|, and never below
  16 · max(deg_i + b_i) LSBs.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from sim.model import graph
from sim.model.metrics import SETTLING_BAND
from sim.model.scenario import Scenario

PEAK_RATIO = 1.2   # the bound: reset-PI's peak |u| ≤ 1.2 × PC's
MARGIN = 0.95      # the predicted peak must fit 95 % of the budget
_H_STEPS = 60      # geometric h grid, from Theorem 1's bound to 400× it
_T_POINTS = 4000   # the model's time grid
_K_STEPS = 9       # k grid, from 0.5·k_ref to peak_ratio·k_ref


@dataclass(frozen=True)
class Prediction:
    """The modal model's settling time (None: not within the run) and peak |u|."""

    settling_s: float | None
    peak_u: float


def _error0(sc: Scenario) -> np.ndarray:
    rho, _ = sc.price_at(0.0)
    return np.asarray(sc.lambda0, dtype=float) - rho


def _settling(t: np.ndarray, err: np.ndarray) -> float | None:
    """As sim.model.metrics.settling_times, for one segment."""
    outside = np.flatnonzero(err > SETTLING_BAND * err[0])
    if outside.size == 0:
        return 0.0
    if outside[-1] == t.size - 1:
        return None
    return float(t[outside[-1] + 1])


def predict(sc: Scenario, kind: str, k: float, h: float) -> Prediction:
    """The modal model's settling and peak |u| of ``kind`` ("pc" or "reset") with gains
    k, h on ``sc``'s graph, from λ(0) to the first price (module docstring)."""
    eta, vecs = np.linalg.eigh(sc.h)
    c = vecs.T @ _error0(sc)
    horizon = sc.prices[1].t if len(sc.prices) > 1 else sc.duration
    sigma = k * eta / 2
    omega = np.sqrt(np.maximum(h * eta - sigma ** 2, 1e-300))
    t1 = np.arctan2(omega, sigma) / omega
    if kind != "pc":  # every mode is at rest after its t₁
        horizon = min(horizon, float(t1.max()) + 2 * sc.ts)
    # at most _T_POINTS samples, a whole number of Ts apart
    dt = sc.ts * max(1, math.ceil(horizon / sc.ts / _T_POINTS))
    t = np.arange(0.0, horizon, dt)
    tt = t[:, None]
    if kind == "pc":
        em = c * np.exp(-k * eta * tt)
        um = -k * eta * em
    else:
        env = np.exp(-sigma * tt)
        cos, sin = np.cos(omega * tt), np.sin(omega * tt)
        live = tt < t1
        em = np.where(live, c * env * (cos - sigma / omega * sin), 0.0)
        um = np.where(live, c * env * (-2 * sigma * cos - (omega ** 2 - sigma ** 2) / omega
                                       * sin), 0.0)
    e = em @ vecs.T
    u = um @ vecs.T
    return Prediction(_settling(t, np.abs(e).max(axis=1)), float(np.abs(u).max()))


def reset_band(sc: Scenario) -> float:
    """The reset re-arm band on |ξ| (module docstring)."""
    terms = np.count_nonzero(sc.adjacency, axis=1)
    for i in sc.pinned:
        terms[i - 1] += 1
    floor = 16 * max(int(terms.max()), 1) * 2.0 ** -sc.controller.q
    eta_min = float(np.linalg.eigvalsh(sc.h)[0])
    settled = eta_min * SETTLING_BAND * float(np.abs(_error0(sc)).max())
    return max(0.01 * settled, floor)


@dataclass(frozen=True)
class Choice:
    """The tuner's pick before simulation."""

    k: float
    h: float
    band: float
    predicted: Prediction
    pc_predicted: Prediction
    budget: float


def choose(sc: Scenario, peak_ratio: float = PEAK_RATIO, margin: float = MARGIN) -> Choice:
    """Gains of shortest predicted settling within the peak budget (module docstring)."""
    k_ref = sc.controller.k
    ts = sc.ts
    pc = predict(sc, "pc", k_ref, 0.0)
    budget = peak_ratio * pc.peak_u
    eta_max = float(np.linalg.eigvalsh(sc.h)[-1])
    best: tuple[float, float, float, Prediction] | None = None
    for k in np.linspace(0.5 * k_ref, peak_ratio * k_ref, _K_STEPS):
        h_lo = 1.05 * eta_max * k * k / 4  # Theorem 1 with 5 % margin
        for h in h_lo * np.geomspace(1.0, 400.0, _H_STEPS):
            rep = graph.analyse(sc.h, float(k), float(h), ts, "reset")
            if not (rep.regular and rep.discrete_stable and rep.spectral_radius < 1 - 1e-9):
                continue
            p = predict(sc, "reset", float(k), float(h))
            if p.settling_s is None or p.peak_u > margin * budget:
                continue
            if best is None or p.settling_s < best[0]:
                best = (p.settling_s, float(k), float(h), p)
    if best is None:  # nothing fits: the reference gains, h at Theorem 1's bound
        k, h = k_ref, 1.05 * eta_max * k_ref * k_ref / 4
        best = (math.inf, k, h, predict(sc, "reset", k, h))
    _, k, h, p = best
    return Choice(round(k, 6), round(h, 6), reset_band(sc), p, pc, budget)


def simulate(sc: Scenario, kind: str, k: float, h: float,
             band: float | None = None) -> dict[str, Any]:
    """The lockstep's metrics of one run (settling, peak |u|, resets)."""
    from sim.model.lockstep import run_lockstep
    from sim.model.metrics import compute

    over: dict[str, Any] = {"kind": kind, "k": k, "h": h}
    if band is not None:
        over["band"] = band
    s = sc.with_controller(**over)
    m = compute(s, run_lockstep(s))
    return {"settling_s": m["settling_time_s"], "peak_u": m["peak_control"],
            "resets": int(sum(m["resets"]))}


@dataclass(frozen=True)
class TuneResult:
    """Everything `bess-ded tune` prints and writes to tune.json."""

    scenario: str
    agents: int
    eta_min: float
    eta_max: float
    ts: float
    peak_ratio: float
    k: float
    h: float
    band: float
    k_ref: float          # PC's reference gain: the scenario's k
    peak_budget: float    # peak_ratio × PC's simulated peak |u| at k_ref
    steps_down: int       # 10 % steps of h below the prediction's pick (0: none needed)
    spectral_radius: float  # max|1 + Ts·μ| of the chosen gains (discrete-time margin)
    predicted: dict[str, Any]  # the modal model: reset-PI and PC settling, peak |u|
    simulated: dict[str, Any]  # the lockstep: reset, pc (at k_ref), pc_same_peak
    ratios: dict[str, float | None]
    target_met: bool

    def to_json(self) -> dict[str, Any]:
        """The result as the JSON object tune.json holds."""
        return asdict(self)


def long_enough(sc: Scenario, limit_s: float = 1200.0) -> Scenario:
    """``sc`` with its duration doubled until PC at the scenario's k is predicted to
    settle within 2/3 of it (a single-price scenario only; up to ``limit_s``): else
    there is no PC settling to compare with."""
    if len(sc.prices) > 1:
        return sc
    while sc.duration < limit_s:
        p = predict(sc, "pc", sc.controller.k, 0.0)
        if p.settling_s is not None and p.settling_s < sc.duration * 2 / 3:
            break
        sc = replace(sc, duration=min(2 * sc.duration, limit_s))
    return sc


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b == 0 else a / b


def tune(sc: Scenario, peak_ratio: float = PEAK_RATIO, margin: float = MARGIN,
         max_steps_down: int = 20) -> TuneResult:
    """Pick k, h and the band for ``sc`` (``choose``), then verify in the lockstep against PC
    at the scenario's k and against PC with the same peak |u|; lower h by 10 % steps while
    the simulated peak exceeds the budget (module docstring)."""
    sc = long_enough(sc)
    c = choose(sc, peak_ratio, margin)
    k_ref = sc.controller.k
    pc = simulate(sc, "pc", k_ref, 0.0)
    budget = peak_ratio * pc["peak_u"]
    h = c.h
    steps = 0
    reset = simulate(sc, "reset", c.k, h, c.band)
    while reset["peak_u"] > budget and steps < max_steps_down:
        steps += 1
        h_next = round(h * 0.9, 6)
        if not graph.analyse(sc.h, c.k, h_next, sc.ts).regular:
            break
        h = h_next
        reset = simulate(sc, "reset", c.k, h, c.band)
    # PC whose (t = 0) peak k·max|ξ(0)| equals the reset-PI's simulated peak
    k_same = k_ref * reset["peak_u"] / pc["peak_u"]
    pc_same = simulate(sc, "pc", k_same, 0.0)
    pc_same["k"] = k_same
    rep = graph.analyse(sc.h, c.k, h, sc.ts)
    pred = predict(sc, "reset", c.k, h)
    ratios = {"settling_vs_pc": _ratio(reset["settling_s"], pc["settling_s"]),
              "settling_vs_pc_same_peak": _ratio(reset["settling_s"], pc_same["settling_s"]),
              "peak_vs_pc": _ratio(reset["peak_u"], pc["peak_u"]),
              "predicted_settling_vs_pc": _ratio(pred.settling_s, c.pc_predicted.settling_s)}
    s_ratio, p_ratio = ratios["settling_vs_pc"], ratios["peak_vs_pc"]
    met = (s_ratio is not None and s_ratio <= 0.5 and p_ratio is not None
           and p_ratio <= peak_ratio)
    return TuneResult(
        scenario=sc.name, agents=sc.n, eta_min=rep.eta_min, eta_max=rep.eta_max, ts=sc.ts,
        peak_ratio=peak_ratio, k=c.k, h=h, band=c.band, k_ref=k_ref, peak_budget=budget,
        steps_down=steps, spectral_radius=rep.spectral_radius,
        predicted={"reset": asdict(pred), "pc": asdict(c.pc_predicted)},
        simulated={"reset": reset, "pc": pc, "pc_same_peak": pc_same},
        ratios=ratios, target_met=bool(met))
