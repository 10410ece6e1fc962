"""Performance metrics of a run, as written to metrics.json (definitions in docs/metrics.md)."""

from __future__ import annotations

from typing import Any

import numpy as np

from sim.model.cost import expenditure, kkt_optimum
from sim.model.scenario import Scenario
from sim.model.trajectory import Trajectory

SETTLING_BAND = 0.02  # 2 % of the initial worst error


def worst_error(tr: Trajectory) -> np.ndarray:
    """max_i |λ_i − ρ| over the agents meant to be dispatching, per sample: on a bus, an
    agent stuck in SAFE or INIT still counts (its λ is what it would dispatch by)."""
    e = np.abs(tr.lam - tr.rho[:, None])
    return np.where(tr.judged, e, 0.0).max(axis=1)


def settling_times(tr: Trajectory) -> list[float | None]:
    """Per price segment: time from the segment start after which the error stays in band."""
    err = worst_error(tr)
    out: list[float | None] = []
    for seg in np.unique(tr.segment):
        idx = np.flatnonzero(tr.segment == seg)
        e = err[idx]
        band = SETTLING_BAND * e[0]
        outside = np.flatnonzero(e > band)
        if outside.size == 0:
            out.append(0.0)
        elif outside[-1] == idx.size - 1:
            out.append(None)  # never settled within the segment
        else:
            out.append(float(tr.t[idx[outside[-1] + 1]] - tr.t[idx[0]]))
    return out


def overshoot(tr: Trajectory) -> float:
    """Largest excursion past ρ opposite to each agent's initial error (first segment)."""
    idx = tr.segment == tr.segment[0]
    e = tr.lam[idx] - tr.rho[idx][:, None]
    e0 = e[0]
    scale = np.abs(e0).max()
    if scale == 0:
        return 0.0
    past = np.where(tr.judged[idx], -np.sign(e0)[None, :] * e, 0.0)
    return float(max(past.max(), 0.0) / scale)


def compute(sc: Scenario, tr: Trajectory) -> dict[str, Any]:
    """The metrics of trajectory ``tr`` of ``sc``: settling times, overshoot,
    resets, cost against the KKT optimum, final error and the graph's analysis."""
    rep = sc.analysis()
    st = settling_times(tr)
    final_p = tr.p[-1]
    rho_end = float(tr.rho[-1])
    _, optimal = kkt_optimum(sc.batteries, rho_end, sc.load_kw)
    m: dict[str, Any] = {
        "scenario": sc.name,
        "controller": sc.controller.kind,
        "label": tr.label,
        "settling_time_s": st[0],
        "settling_times_s": st,
        "overshoot": overshoot(tr),
        "final_error": float(worst_error(tr)[-1]),
        "resets": [len(r) for r in tr.resets],
        "eta_max": rep.eta_max,
        "regular": rep.regular,
        "discrete_stable": rep.discrete_stable,
        "cost": expenditure(sc.batteries, final_p, rho_end, sc.load_kw),
        "optimal_cost": optimal,
        "saturations": tr.saturations,
    }
    if tr.u is not None:
        u = np.where(tr.judged, tr.u, 0.0)
        m["control_total_variation"] = float(np.abs(np.diff(u, axis=0)).sum())
        m["peak_control"] = float(np.abs(u).max())
    return m
