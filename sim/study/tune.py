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
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from sim.model import graph
from sim.model.metrics import SETTLING_BAND
from sim.model.scenario import Scenario

PEAK_RATIO = 1.2   # the bound: reset-PI's peak |u| ≤ 1.2 × PC's
MARGIN = 0.95      # the predicted peak must fit 95 % of the budget
_H_STEPS = 60      # geometric h grid, from Theorem 1's bound to 400× it
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
    t = np.arange(0.0, sc.prices[1].t if len(sc.prices) > 1 else sc.duration, sc.ts)
    tt = t[:, None]
    if kind == "pc":
        em = c * np.exp(-k * eta * tt)
        um = -k * eta * em
    else:
        sigma = k * eta / 2
        omega = np.sqrt(np.maximum(h * eta - sigma ** 2, 1e-300))
        t1 = np.arctan2(omega, sigma) / omega
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
    hm = sc.h
    lsb = 2.0 ** -sc.controller.q
    floor = 16 * float(np.max(np.count_nonzero(hm, axis=1) - 1 + (np.diag(hm) > 0) * 0)) * lsb
    floor = max(floor, 16 * lsb)
    eta_min = float(np.linalg.eigvalsh(hm)[0])
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
