"""The paper's seven cases, run on the discrete fixed-point firmware (run_lockstep) and judged
with sim.model.metrics.compute: every case behaves as the paper says, and the fixed-point
core agrees with its float twin."""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from firmware_py.controllers import DEFAULT_BAND
from sim.model.graph import unpinned_components
from sim.model.lockstep import run_lockstep
from sim.model.metrics import compute
from sim.model.scenario import Scenario, load_case
from sim.model.trajectory import Trajectory


@cache
def scenario(case: int, label: str | None = None, **overrides: object) -> Scenario:
    sc = load_case(case)
    sc = sc.variant(label) if label else sc
    return sc.with_controller(**overrides) if overrides else sc


@cache
def run(case: int, label: str | None = None, fixed: bool = True,
        **overrides: object) -> tuple[Trajectory, dict]:
    sc = scenario(case, label, **overrides)
    tr = run_lockstep(sc, fixed=fixed)
    return tr, compute(sc, tr)


def metrics(case: int, label: str | None = None, **overrides: object) -> dict:
    return run(case, label, **overrides)[1]


# --------------------------------------------------------------------------- case 1


def test_case1_validation() -> None:
    m = metrics(1)
    assert m["final_error"] < 1e-3
    assert m["regular"] and m["discrete_stable"]
    assert m["resets"] == [8, 5, 5, 5]       # default band (bit-exact lockstep run)
    assert m["saturations"] == 0
    assert m["cost"] == pytest.approx(m["optimal_cost"], rel=1e-4)


def test_case1_band_costs_no_settling_time() -> None:
    """The reset band cuts the chattering resets of a plain discrete Clegg reset
    (band 0: 48, 39, 37, 38 resets; the band: 8, 5, 5, 5) without settling more than
    10 % slower."""
    band, clegg = metrics(1), metrics(1, band=0.0)
    assert scenario(1).controller.band == DEFAULT_BAND == 1e-4  # what case 1 runs with
    assert band["settling_time_s"] <= 1.1 * clegg["settling_time_s"]
    assert (band["resets"], clegg["resets"]) == ([8, 5, 5, 5], [48, 39, 37, 38])


# --------------------------------------------------------------------------- case 2


def test_case2_reset_pi_against_pc_and_finite_time() -> None:
    rpi, pc, ft = metrics(2, "reset-PI"), metrics(2, "PC"), metrics(2, "finite-time")
    # measured: settling 2.54 s (reset-PI), 3.44 s (PC), 1.37 s (FT);
    #           control TV 5.2 (reset-PI), 4.6 (PC), 266 (FT)
    assert rpi["settling_time_s"] <= 0.8 * pc["settling_time_s"]
    assert rpi["control_total_variation"] <= 2 * pc["control_total_variation"]
    assert ft["control_total_variation"] >= 10 * rpi["control_total_variation"]
    for m in (rpi, pc, ft):
        assert m["final_error"] < 1e-3


def test_reset_pi_beats_pi_without_reset() -> None:
    assert metrics(1)["settling_time_s"] < 0.5 * metrics(1, kind="pi")["settling_time_s"]


# --------------------------------------------------------------------------- case 3


@pytest.mark.parametrize(("label", "regular"), [
    ("k=1,h=2", True), ("k=5,h=2", False), ("k=10,h=2", False),
    ("k=1,h=6", True), ("k=1,h=10", True),
])
def test_case3_gain_sweep_regularity(label: str, regular: bool) -> None:
    m = metrics(3, label)
    assert m["regular"] is regular
    assert m["eta_max"] == pytest.approx(4.7913, abs=1e-4)
    # at Ts = 10 ms every gain pair is still Euler-stable and converges
    assert m["discrete_stable"]
    assert m["final_error"] < 1e-3


# --------------------------------------------------------------------------- case 4


def test_case4_plug_and_play() -> None:
    tr, m = run(4)
    sc = scenario(4)
    off = (tr.t >= 10 - 1e-9) & (tr.t < 20 - 1e-9)
    assert not tr.active[off, 1].any()
    assert tr.active[~off, 1].all() and tr.active[:, [0, 2, 3]].all()
    idle = sc.batteries[1].idle_lambda
    assert np.abs(tr.lam[off, 1] - idle).max() < 1e-7          # held at its idle MC
    assert (tr.p[off, 1] == 0).all()
    # the three left re-converge while agent 2 is away, then all four at the end
    before = np.flatnonzero(tr.t < 20 - 1e-9)[-1]
    assert np.abs(tr.lam[before, [0, 2, 3]] - 0.8).max() < 1e-3
    assert np.abs(tr.lam[-1] - 0.8).max() < 1e-3
    assert m["final_error"] < 1e-3


# --------------------------------------------------------------------------- case 5


def test_case5_time_phased_price() -> None:
    tr, m = run(5)
    st = m["settling_times_s"]
    assert len(st) == 3 and all(s is not None for s in st)   # measured 2.54, 2.36, 2.36 s
    for seg, rho in enumerate((0.8, 1.0, 0.6)):
        last = np.flatnonzero(tr.segment == seg)[-1]
        assert tr.rho[last] == rho
        assert np.abs(tr.lam[last] - rho).max() < 1e-3
    assert m["final_error"] < 1e-4


# --------------------------------------------------------------------------- case 6


@pytest.mark.parametrize("label", ["dwell=1", "dwell=1.5"])
def test_case6_dwell_converges_and_spaces_resets(label: str) -> None:
    tr, m = run(6, label)
    dwell = scenario(6, label).controller.dwell
    assert m["final_error"] < 1e-3
    for r in tr.resets:
        times = np.array([0.0, *r])          # the start counts as a reset
        assert (np.diff(times) >= dwell - 1e-9).all(), (label, r)


def test_case6_dwell_trades_speed_for_fewer_resets() -> None:
    """Measured: Δ = 1 → 5.93 s, 18 resets; Δ = 1.5 → 3.21 s, 13 resets; both between
    reset-PI without dwell (2.54 s) and PI without reset (7.11 s)."""
    d1, d15 = metrics(6, "dwell=1"), metrics(6, "dwell=1.5")
    fastest, slowest = metrics(1)["settling_time_s"], metrics(1, kind="pi")["settling_time_s"]
    for m in (d1, d15):
        assert fastest <= m["settling_time_s"] <= slowest
    assert sum(d15["resets"]) <= sum(d1["resets"]) <= sum(metrics(1)["resets"])


def test_case6_settling_is_not_monotone_in_dwell() -> None:
    """A longer dwell does not always settle slower: with these parameters Δ = 1.5 s
    settles in 3.21 s and Δ = 1 s in 5.93 s. The continuous reference agrees (3.22 s vs
    5.90 s), so it is the hybrid dynamics, not the discretisation. Measured over Δ:
    0.5 → 4.44 s, 1.0 → 5.93 s, 1.2 → 3.21 s, 2.0 → 3.17 s."""
    assert metrics(6, "dwell=1.5")["settling_time_s"] < metrics(6, "dwell=1")["settling_time_s"]


# --------------------------------------------------------------------------- case 7


def test_case7_scale() -> None:
    rpi, pc = metrics(7), metrics(7, kind="pc")
    assert rpi["regular"] and rpi["discrete_stable"]
    # measured: 5.78 s (reset-PI) vs 11.76 s (PC)
    assert rpi["settling_time_s"] <= 0.5 * pc["settling_time_s"]
    assert rpi["final_error"] < 1e-3


# --------------------------------------------------------------------------- fixed vs float

RUNS = [(case, label if load_case(case).variants else None)
        for case in range(1, 8) for label, _ in load_case(case).runs()]
TS_SWEEP = (0.001, 0.0025, 0.005, 0.01, 0.05)
FIDELITY = 1e-5   # max |λ_fixed − λ_float| over time and agents (issue 10, deliverable 2)

# Forward Euler is unstable there (k·η_max·Ts = 2.4 > 2): both twins diverge, not judged
EULER_UNSTABLE = {(3, "k=10,h=2", 0.05)}

# Runs whose twins differ by more than FIDELITY somewhere, with the measured maximum
# (tools/fidelity.py prints them all):
FINITE_TIME_CYCLE = {
    # FT never settles at these Ts: both twins end on the same discrete limit cycle
    # (peak to peak 1.74e-5 at 2.5 ms, 6.96e-5 at 5 ms, 2.78e-4 at 10 ms, equal within
    # 9e-8 in both; their means agree within 6e-7) but out of phase: √ξ has infinite slope
    # at 0, so an LSB difference in ξ shifts the phase (at 2.5 ms the phases drift apart
    # while the cycle forms, then lock again: tail within 3.3e-8)
    (2, "finite-time", 0.0025): 1.36e-5, (2, "finite-time", 0.005): 7.98e-5,
    (2, "finite-time", 0.01): 2.98e-4,
}
RESET_TIMING = {
    # ξ within a few LSB of 0 at t = 0.938 s: the twins reset one sample apart and the
    # transients differ by up to 2.03e-5; the last 5 s agree within 4.8e-7
    (7, None, 0.0025): 2.03e-5,
}

SWEEP = [(case, label, ts) for case, label in RUNS for ts in TS_SWEEP
         if (case, label, ts) not in EULER_UNSTABLE]


def _tail(tr: Trajectory, seconds: float = 5.0) -> np.ndarray:
    return tr.t >= tr.t[-1] - seconds - 1e-9


@pytest.mark.parametrize(("case", "label", "ts"), SWEEP,
                         ids=[f"case{c}-{lab}-{ts * 1e3:g}ms" for c, lab, ts in SWEEP])
def test_fixed_and_float_twins_agree(case: int, label: str | None, ts: float) -> None:
    """Fixed point (Q24 on the wire, Q54 state, Q1.30 constants) against its float twin,
    closed loop, every paper case and variant at Ts = 1, 2.5, 5, 10, 50 ms: λ within
    1e-5 over the whole run (measured ≤ 9.2e-6, typically ≤ 1e-6; before the guard bits,
    with a Q24 state, up to 5.3e-4: docs/performance.md). The products are exact and k·Ts
    is quantised at 2**-30, so what is left is the Q24 rounding of the λ on the wire and
    in ξ (½ LSB) and of ν in h·Ts·ν, attenuated by the stable loop, and the odd reset
    decided a sample apart (a sign test on ξ) while ξ is within a few LSB of zero."""
    sc = scenario(case, label)
    if ts == sc.ts:
        fx_tr, fl_tr = run(case, label, True)[0], run(case, label, False)[0]
    else:
        sc = replace(sc, ts=ts, controller=replace(sc.controller, ts=ts))
        fx_tr, fl_tr = run_lockstep(sc, fixed=True), run_lockstep(sc, fixed=False)
    assert sc.analysis().discrete_stable
    assert fx_tr.saturations == 0
    diff = np.abs(fx_tr.lam - fl_tr.lam)
    tail = _tail(fx_tr)
    if (case, label, ts) in FINITE_TIME_CYCLE:
        cyc = fl_tr.lam[tail].max(axis=0) - fl_tr.lam[tail].min(axis=0)
        cyc_fx = fx_tr.lam[tail].max(axis=0) - fx_tr.lam[tail].min(axis=0)
        assert np.abs(cyc - cyc_fx).max() <= 1e-7                      # the same cycle
        assert np.abs(fx_tr.lam[tail].mean(axis=0) - fl_tr.lam[tail].mean(axis=0)).max() \
            <= 1e-6                                                    # around the same λ
        assert diff.max() <= 1.1 * FINITE_TIME_CYCLE[case, label, ts]
    elif (case, label, ts) in RESET_TIMING:
        assert diff.max() <= 1.1 * RESET_TIMING[case, label, ts]
        assert diff[tail].max() <= 1e-6
    else:
        assert diff.max() <= FIDELITY


def test_fidelity_tool_runs_and_builds_connected_regular_graphs(
        tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    """tools/fidelity.py (the full study, docs/performance.md): one case, one graph."""
    import random
    import runpy
    from pathlib import Path

    tool = runpy.run_path(str(Path(__file__).resolve().parent.parent / "tools" / "fidelity.py"))
    for n in (4, 8, 31, 32):
        degree = 4 if n % 2 else 3
        edges = tool["random_regular_edges"](n, degree, random.Random(n))
        deg = np.bincount(np.array(edges).ravel(), minlength=n + 1)[1:]
        assert (deg == degree).all() and len(set(edges)) == len(edges)
        assert unpinned_components(n, edges, [1]) == []          # connected
    out = tmp_path / "f.json"
    assert tool["main"](["--cases", "1", "--ts", "0.01", "--graphs", "4", "--graph-ts",
                         "0.01", "-q", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "case1" in text and "regular4" in text
    import json
    res = {r["name"]: r for r in json.loads(out.read_text())["results"]}
    assert res["case1"]["max"] <= 1e-5 and res["regular4"]["max"] <= 1e-4
