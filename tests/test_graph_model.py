"""Graph analysis (H = L + B, Theorem 1, Euler stability) and the BESS cost model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from sim.model import graph
from sim.model.cost import Battery, expenditure, kkt_optimum
from sim.model.scenario import load_case

STAR = [(1, 2), (1, 3), (1, 4)]


def star_h() -> np.ndarray:
    return graph.h_matrix(graph.adjacency(4, STAR), graph.pinning(4, [1]))


def test_star_spectrum_is_the_papers() -> None:
    eta = graph.eigenvalues(star_h())
    # the characteristic polynomial of H factors as (η − 1)²(η² − 5η + 1): η = (5 ± √21)/2
    assert eta == pytest.approx([(5 - 21**0.5) / 2, 1, 1, (5 + 21**0.5) / 2], abs=1e-12)
    assert eta == pytest.approx([0.2087, 1, 1, 4.7913], abs=1e-4)
    assert graph.analyse(star_h(), 1, 2, 0.01).eta_max == pytest.approx(4.7913, abs=1e-4)


def test_h_is_laplacian_plus_pinning() -> None:
    h = star_h()
    assert np.array_equal(h, [[4, -1, -1, -1], [-1, 1, 0, 0], [-1, 0, 1, 0], [-1, 0, 0, 1]])
    assert np.array_equal(h, load_case(1).h)


@pytest.mark.parametrize(("k", "hgain", "regular"), [
    (1, 2, True), (5, 2, False), (10, 2, False), (1, 6, True), (1, 10, True),
    (0.5, 0.3, True), (0.5, 0.29, False),   # 4h > 4.7913·k² ⇔ h > 0.2995 at k = 0.5
])
def test_regularity_theorem_1(k: float, hgain: float, regular: bool) -> None:
    rep = graph.analyse(star_h(), k, hgain, 0.01)
    assert rep.regular is regular
    # regular ⇔ every base-system eigenvalue complex (Theorem 1)
    mus = graph.base_eigenvalues(star_h(), k, hgain)
    assert bool(np.all(np.abs(mus.imag) > 0)) is regular


def test_base_eigenvalues_are_those_of_the_pi_base_system() -> None:
    """μ(η) from the closed form equal the eigenvalues of [[−kH, −hI], [H, 0]]."""
    h, k, hg = star_h(), 1.0, 2.0
    a = np.block([[-k * h, -hg * np.eye(4)], [h, np.zeros((4, 4))]])
    key = lambda z: (round(z.real, 6), round(z.imag, 6))  # noqa: E731  (η = 1 is double)
    direct = sorted(np.linalg.eigvals(a), key=key)
    assert sorted(graph.base_eigenvalues(h, k, hg), key=key) == pytest.approx(direct, abs=1e-9)


def test_discrete_stability_at_ts() -> None:
    h = star_h()
    for k, hg in ((1, 2), (5, 2), (10, 2), (1, 6), (1, 10)):
        rep = graph.analyse(h, k, hg, 0.01)
        assert rep.discrete_stable, (k, hg)
        # the radius is that of the Euler matrix I + Ts·A itself
        a = np.block([[-k * h, -hg * np.eye(4)], [h, np.zeros((4, 4))]])
        euler = np.max(np.abs(np.linalg.eigvals(np.eye(8) + 0.01 * a)))
        assert rep.spectral_radius == pytest.approx(euler, abs=1e-12)
    # PC: |1 − Ts·k·η| < 1 ⇔ Ts < 2/(k·η_max) = 0.4174 s at k = 1
    assert graph.analyse(h, 1, 0, 0.41, kind="pc").discrete_stable
    assert not graph.analyse(h, 1, 0, 0.42, kind="pc").discrete_stable
    # PI at Ts = 0.5 s: the fast pair leaves the unit circle
    assert not graph.analyse(h, 1, 2, 0.5).discrete_stable


def test_ring_of_case_7_is_regular() -> None:
    rep = load_case(7).analysis()
    assert rep.eta_min == pytest.approx(0.1088, abs=1e-4)
    assert rep.eta_max == pytest.approx(4.2784, abs=1e-4)
    assert rep.regular and rep.discrete_stable


def test_describe_says_why() -> None:
    ok = graph.analyse(star_h(), 1, 2, 0.01).describe()
    assert ok[1] == "regular (Theorem 1): yes, 4h = 8 > η_max·k² = 4.79"
    assert ok[2] == "discrete-time stable at Ts = 10 ms: yes, max|1 + Ts·μ| = 0.9990"
    bad = graph.analyse(star_h(), 5, 2, 0.01).describe()
    assert bad[1] == ("regular (Theorem 1): no: 4h = 8 ≤ η_max·k² = 119.8 "
                      "(Theorem 1 needs 4h > η_max·k²)")
    unstable = graph.analyse(star_h(), 1, 2, 0.5)
    assert unstable.stability_line().startswith("discrete-time stable at Ts = 500 ms: no: "
                                                "max|1 + Ts·μ| = ")
    assert unstable.stability_line().endswith("≥ 1: lower Ts or the gains")
    assert unstable.verdict() == "yes; unstable at Ts"
    assert graph.analyse(star_h(), 1, 2, 0.6).stability_line() == (
        "discrete-time stable at Ts = 600 ms: no: max|1 + Ts·μ| = 1.2550 ≥ 1: lower Ts or the "
        "gains")
    assert graph._radius(0.99999) == "0.99999" and graph._radius(1.0000012) == "1.000001"
    pc = graph.analyse(star_h(), 1, 0, 0.42, kind="pc")
    assert "n/a" in pc.regular_line() and "max|1 − Ts·k·η|" in pc.stability_line()
    assert graph.describe(star_h(), 1, 2, 0.01) == ok


def test_unpinned_components() -> None:
    assert graph.unpinned_components(4, STAR, [1]) == []
    assert graph.unpinned_components(5, [(1, 2), (3, 4)], [1]) == [[3, 4], [5]]
    assert graph.unpinned_components(4, [(1, 2), (3, 4)], [2, 4]) == []


# --------------------------------------------------------------------------- cost model

BATS = load_case(1).batteries


@pytest.mark.parametrize("b", BATS)
def test_lambda_power_round_trip_and_clipping(b: Battery) -> None:
    p = np.linspace(b.p_min, b.p_max, 9)
    assert b.power(b.marginal_cost(p)) == pytest.approx(p, abs=1e-9)
    lam = np.linspace(0.0, 2.0, 7)
    assert b.marginal_cost(b.power(lam)) == pytest.approx(
        np.clip(lam, b.marginal_cost(b.p_min), b.marginal_cost(b.p_max)), abs=1e-12)
    assert b.power(100.0) == b.p_max
    assert b.power(-100.0) == b.p_min
    assert b.power(b.idle_lambda) == pytest.approx(0.0, abs=1e-12)
    assert isinstance(b.power(0.8), float)


def test_marginal_cost_is_the_derivative_of_the_cost() -> None:
    b, p, dp = BATS[0], 37.0, 1e-4
    numeric = (b.cost_rate(p + dp) - b.cost_rate(p - dp)) / (2 * dp)
    assert float(b.marginal_cost(p)) == pytest.approx(numeric, rel=1e-8)


@pytest.mark.parametrize("rho", [0.8, 1.0, 0.6, 0.1, 3.0, -1.0])
def test_kkt_optimum_matches_a_numerical_minimisation(rho: float) -> None:
    """F_c(P) = Σ(1+m)(αP²+βP) + ρ(D − ΣP) minimised over the box of power limits.
    ρ = 3.0 and −1.0 push batteries onto their discharge and charge limits."""
    load = 300.0
    p_star, cost = kkt_optimum(BATS, rho, load)
    bounds = [(b.p_min, b.p_max) for b in BATS]
    res = minimize(lambda p: expenditure(BATS, p, rho, load), x0=np.zeros(len(BATS)),
                   bounds=bounds, method="L-BFGS-B", options={"ftol": 1e-15, "gtol": 1e-12})
    assert res.success
    assert p_star == pytest.approx(res.x, abs=1e-3)
    assert cost == pytest.approx(res.fun, abs=1e-6)
    assert cost <= res.fun + 1e-9
    for b, p in zip(BATS, p_star, strict=True):
        if b.p_min < p < b.p_max:        # interior: every MC at the price
            assert float(b.marginal_cost(p)) == pytest.approx(rho, abs=1e-12)
        else:                            # on a limit: the MC points out of the box
            assert (p == b.p_max and b.marginal_cost(p) <= rho) or \
                   (p == b.p_min and b.marginal_cost(p) >= rho)
    if rho in (3.0, -1.0):
        assert any(p in (b.p_min, b.p_max) for b, p in zip(BATS, p_star, strict=True))


def test_case_1_dispatch_as_documented() -> None:
    """The scenario comment says ρ = 0.8 dispatches ≈ 66, 56, 41 and 57 kW."""
    p, cost = kkt_optimum(BATS, 0.8, 300.0)
    assert p == pytest.approx([66, 56, 41, 57], abs=1)
    assert cost == pytest.approx(expenditure(BATS, p, 0.8, 300.0))
