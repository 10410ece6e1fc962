"""The continuous-time hybrid reference (sim/model/reference.py): checked against closed forms
and an ODE solver, then used to measure the discrete firmware's error.

Measured at Ts = 10 ms (fixed-point firmware vs reference, max over the run of max_i
|Δλ_i|): 5.74e-3 for cases 1, 4 and 5, all reached at t ≈ 0.35 s in the first transient;
after the transients the gap shrinks to < 7e-6 (case 1), 2.5e-5 (case 4) and 3.2e-6
(case 5) at the end. Halving Ts halves it (5.74e-3 → 2.85e-3 → 1.41e-3 at 10, 5, 2.5 ms):
forward Euler's global error, O(Ts), with a constant of ≈ 0.57 cu/kWh per second of Ts.
"""

from __future__ import annotations

import math
from dataclasses import replace
from functools import cache

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from sim.model.lockstep import run_lockstep
from sim.model.metrics import compute
from sim.model.reference import base_system, run_reference
from sim.model.scenario import Scenario, load_case, parse_scenario
from sim.model.trajectory import Trajectory

# Euler error bound used below: 1.0·Ts cu/kWh at Ts = 10 ms (measured 0.57·Ts).
EULER_TOL = 1e-2


@cache
def ref(case: int, label: str | None = None, ts: float | None = None) -> Trajectory:
    return run_reference(scenario(case, label, ts))


@cache
def disc(case: int, label: str | None = None, ts: float | None = None,
         fixed: bool = True) -> Trajectory:
    return run_lockstep(scenario(case, label, ts), fixed=fixed)


def scenario(case: int, label: str | None = None, ts: float | None = None) -> Scenario:
    sc = load_case(case)
    sc = sc.variant(label) if label else sc
    if ts is not None:
        sc = replace(sc, ts=ts, controller=replace(sc.controller, ts=ts))
    return sc


def single_agent(k: float = 1.0, h: float = 2.0, kind: str = "reset", band: float = 1e-4,
                 lam0: float = 0.3, rho: float = 0.8, duration: float = 5.0) -> Scenario:
    bat = {"alpha": 0.004, "beta": 0.2, "m": 0.1, "p_min": -100.0, "p_max": 100.0,
           "lambda0": lam0}
    return parse_scenario({
        "ts": 0.01, "duration": duration, "load_kw": 100.0,
        "controller": {"kind": kind, "k": k, "h": h, "band": band},
        "graph": {"agents": 1, "edges": [], "pinned": [1]},
        "price": [{"t": 0.0, "rho": rho}], "battery": [bat]}, "single-agent")


# --------------------------------------------------------------------------- the reference itself


def test_single_agent_clegg_reset_by_closed_form() -> None:
    """One pinned agent: e = λ − ρ obeys ë + k ė + h e = 0 with e(0) = e0, ė(0) = −k e0,
    so e = e^{−kt/2}(e0 cos ωt − k e0/(2ω) sin ωt), ω = √(h − k²/4). It first crosses
    zero at t1 = atan(2ω/k)/ω; resetting ν there leaves e = ν = 0, so λ stays at ρ."""
    k, h = 1.0, 2.0
    omega = math.sqrt(h - k * k / 4)
    t1 = math.atan(2 * omega / k) / omega
    tr = run_reference(single_agent(k, h))
    assert tr.resets[0][0] == pytest.approx(t1, abs=1e-9)
    assert len(tr.resets[0]) == 1                  # nothing left to cross (band 1e-4)
    before = tr.t < t1
    e = np.exp(-k * tr.t / 2) * (-0.5) * (np.cos(omega * tr.t)
                                          - k / (2 * omega) * np.sin(omega * tr.t))
    assert tr.lam[before, 0] - 0.8 == pytest.approx(e[before], abs=1e-12)
    assert np.abs(tr.lam[~before, 0] - 0.8).max() < 1e-12
    assert np.abs(tr.nu[~before, 0]).max() < 1e-12


@pytest.mark.parametrize("kind", ["pc", "pi"])
def test_flow_matches_an_ode_solver(kind: str) -> None:
    """Without resets the reference is the linear flow; an independent RK45/DOP853 solve
    at rtol 1e-12 agrees to 1e-9 (case 5: three price segments)."""
    sc = load_case(5).with_controller(kind=kind)
    tr = run_reference(sc)
    n, k, h = sc.n, sc.controller.k, sc.controller.h
    hm, b = sc.h, np.array([1.0 if i + 1 in sc.pinned else 0.0 for i in range(n)])

    def rhs(t: float, x: np.ndarray) -> np.ndarray:
        xi = hm @ x[:n] - sc.price_at(t)[0] * b
        dnu = xi if kind == "pi" else 0 * xi
        return np.concatenate([-k * xi - (h * x[n:] if kind == "pi" else 0), dnu])

    x = np.concatenate([sc.lambda0, np.zeros(n)])
    bounds = [0.0, 15.0, 35.0, sc.duration]
    for t0, t1 in zip(bounds, bounds[1:], strict=False):
        idx = np.flatnonzero((tr.t >= t0 - 1e-9) & (tr.t <= t1 + 1e-9))
        sol = solve_ivp(rhs, (t0, t1), x, method="DOP853", rtol=1e-12, atol=1e-14,
                        t_eval=tr.t[idx], first_step=1e-3, max_step=0.05)
        assert np.abs(sol.y[:n].T - tr.lam[idx]).max() < 1e-9
        x = sol.y[:, -1]


def _state_before(sc: Scenario, tr: Trajectory, t_r: float):
    """Exact z(t_r⁻), re-flowed from the last sample and the resets in between."""
    k = math.floor(t_r / sc.ts + 1e-12)
    sysm = base_system(sc, tr.active[k], tr.rho[k])
    z = np.concatenate([tr.lam[k], tr.nu[k], [1.0]])
    t = k * sc.ts
    between = sorted((r, i) for i, rs in enumerate(tr.resets) for r in rs if t < r < t_r)
    for r, i in between:
        z = sysm.flow(r - t) @ z
        z[sc.n + i] = 0.0
        t = r
    return sysm, sysm.flow(t_r - t) @ z


@pytest.mark.parametrize("case", [1, 4, 5])
def test_reset_instants_are_zero_crossings_to_1e9_s(case: int) -> None:
    """At every located reset t_r, ξ_i changes sign on [t_r − 1e-9, t_r + 1e-9] (the
    flow without that reset), and |ξ_i(t_r)| ≤ 1e-9 s × |ξ̇_i|: the instant is a zero
    crossing to 1e-9 s. (Crossings caused by a jump at an event instant are excluded.)"""
    sc, tr = scenario(case), ref(case)
    events = {0.0} | {e.t for e in sc.events} | {p.t for p in sc.prices}
    checked = 0
    for i, rs in enumerate(tr.resets):
        for t_r in rs:
            if min(abs(t_r - e) for e in events) < 1e-12:
                continue
            sysm, z = _state_before(sc, tr, t_r)
            lo = sysm.c[i] @ (sysm.flow(-1e-9) @ z)
            hi = sysm.c[i] @ (sysm.flow(1e-9) @ z)
            assert lo * hi <= 0, (i, t_r, lo, hi)
            assert abs(sysm.c[i] @ z) <= 1e-9 * abs(sysm.cd[i] @ z) + 1e-15
            checked += 1
    assert checked >= 20


def test_dwell_reference_spaces_resets() -> None:
    sc = scenario(6, "dwell=1.5")
    tr = run_reference(sc)
    for rs in tr.resets:
        assert (np.diff([0.0, *rs]) >= 1.5 - 1e-12).all()
    assert [len(rs) for rs in tr.resets] == [2, 2, 2, 2]


def test_isolated_agent_is_held_at_its_idle_mc() -> None:
    sc, tr = scenario(4), ref(4)
    off = (tr.t >= 10 - 1e-9) & (tr.t < 20 - 1e-9)
    assert np.array_equal(tr.active, disc(4).active)
    assert (tr.lam[off, 1] == sc.batteries[1].idle_lambda).all()
    assert (tr.nu[off, 1] == 0).all() and (tr.u[off, 1] == 0).all()


def test_finite_time_is_not_supported() -> None:
    with pytest.raises(NotImplementedError, match="finite-time"):
        run_reference(load_case(2).variant("finite-time"))


# --------------------------------------------------------------------------- firmware vs reference


@pytest.mark.parametrize("case", [1, 4, 5])
def test_discrete_firmware_tracks_the_reference(case: int) -> None:
    """Tolerance 1e-2 on λ at Ts = 10 ms: forward Euler's global error is O(Ts)
    (measured 0.57·Ts = 5.74e-3, in the first transient); see the module docstring.
    At the end both sit on ρ, so they agree to 1e-4 (the firmware's Q24 wire λ and
    its last resets)."""
    r, d = ref(case), disc(case)
    assert np.array_equal(r.t, d.t) and np.array_equal(r.rho, d.rho)
    gap = np.abs(r.lam - d.lam).max(axis=1)
    assert gap.max() <= EULER_TOL
    assert gap[-1] <= 1e-4
    mr, md = compute(scenario(case), r), compute(scenario(case), d)
    for a, b in zip(mr["settling_times_s"], md["settling_times_s"], strict=True):
        assert abs(a - b) <= 0.05                   # measured ≤ 0.02 s


def test_discretisation_error_is_first_order() -> None:
    """Float twin (no quantisation) at Ts = 10 and 5 ms against the reference on the same
    grid: the error halves (measured 5.74e-3 → 2.85e-3, ratio 0.497)."""
    e10 = np.abs(ref(1) .lam - disc(1, fixed=False).lam).max()
    e5 = np.abs(ref(1, ts=0.005).lam - disc(1, ts=0.005, fixed=False).lam).max()
    assert 0.4 <= e5 / e10 <= 0.6
    assert e10 <= EULER_TOL


@pytest.mark.parametrize("case", [1, 4, 5])
def test_reset_instants_match_within_a_few_samples(case: int) -> None:
    """In the 1.5 s after every excitation (start, plug event, price step) each reference
    reset has a firmware reset within 3 Ts and vice versa (measured ≤ 2.4 Ts: the firmware
    sees a crossing at the next sample, plus the O(Ts) trajectory error). Later crossings,
    where ξ is small and slow, drift further (≤ ~15 Ts), and the firmware adds "echo"
    resets one or two samples after a late-detected crossing; the continuous system has
    none (measured: case 1, 27 firmware resets vs 23)."""
    sc, r, d = scenario(case), ref(case), disc(case)
    starts = sorted({0.0} | {e.t for e in sc.events} | {p.t for p in sc.prices})
    in_window = lambda t: any(s <= t < s + 1.5 for s in starts)  # noqa: E731
    tol = 3 * sc.ts
    pairs = 0
    for rr, dd in zip(r.resets, d.resets, strict=True):
        rr, dd = np.array(rr), np.array(dd)
        for t in rr[[in_window(t) for t in rr]]:
            assert np.abs(dd - t).min() <= tol, t
            pairs += 1
        for t in dd[[in_window(t) for t in dd]]:
            assert np.abs(rr - t).min() <= tol, t
    assert pairs >= 8
    assert len(sum(r.resets, [])) <= len(sum(d.resets, []))
