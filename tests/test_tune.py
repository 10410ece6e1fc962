"""`bess-ded tune` and sim.study.tune: the gains it picks and what it writes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sim.cli import main
from sim.model import graph
from sim.model.scenario import load_case
from sim.study.tune import MARGIN, PEAK_RATIO, choose, predict, reset_band, simulate


@pytest.fixture(scope="module")
def case1_json(tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("tune")
    assert main(["tune", "1", "--out", str(out)]) == 0
    data: dict = json.loads((out / "tune.json").read_text())
    return data


def test_chosen_gains_are_regular_and_stable_at_ts() -> None:
    for n in (1, 7):
        sc = load_case(n)
        c = choose(sc)
        rep = graph.analyse(sc.h, c.k, c.h, sc.ts)
        assert rep.regular and 4 * c.h > rep.eta_max * c.k ** 2
        assert rep.discrete_stable and rep.spectral_radius < 1
        assert 0 < c.k <= PEAK_RATIO * sc.controller.k
        assert c.predicted.peak_u <= MARGIN * c.budget


def test_band_sits_between_the_quantisation_floor_and_the_settled_band() -> None:
    sc = load_case(1)
    band = reset_band(sc)
    assert band >= 16 * 2.0 ** -sc.controller.q
    eta_min = graph.analyse(sc.h, 1, 2, sc.ts).eta_min
    assert band < eta_min * 0.02 * 0.5  # well inside the 2 % band's |ξ|


def test_pc_prediction_matches_the_lockstep_on_case_1() -> None:
    sc = load_case(1)
    p = predict(sc, "pc", 1.0, 0.0)
    s = simulate(sc, "pc", 1.0, 0.0)
    assert p.settling_s is not None and s["settling_s"] is not None
    assert abs(p.settling_s - s["settling_s"]) <= 0.05 * s["settling_s"]
    assert p.peak_u == pytest.approx(s["peak_u"], rel=1e-3)


def test_case_1_meets_the_target_and_json_has_its_keys(case1_json: dict) -> None:
    d = case1_json
    for key in ("scenario", "k", "h", "band", "k_ref", "peak_ratio", "peak_budget",
                "predicted", "simulated", "ratios", "target_met", "eta_max", "eta_min"):
        assert key in d
    assert set(d["simulated"]) == {"reset", "pc", "pc_same_peak"}
    assert set(d["predicted"]) == {"reset", "pc"}
    assert d["ratios"]["settling_vs_pc"] <= 0.5
    assert d["ratios"]["peak_vs_pc"] <= 1.2
    assert d["target_met"] is True
    assert 4 * d["h"] > d["eta_max"] * d["k"] ** 2


def test_bad_random_spec_is_a_one_line_error(capsys: pytest.CaptureFixture[str],
                                              tmp_path: Path) -> None:
    assert main(["tune", "random:x", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: error:") and "random:N" in err
