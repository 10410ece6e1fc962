"""The control core, pure: hand-computed steps, parameter validation, saturation,
and two properties (no wrap-around; fixed vs float twin inside a derived bound).

Constants used by the hand computations (k = 1, h = 2, Ts = 10 ms; Q1.30 constants,
Q24 words, Q54 state: G = 2**30 guard bits, LSB of a word 2**-24):
    k·Ts = round(0.01·2**30) = round(10737418.24) = 10737418   (KTS)
    h·Ts = round(0.02·2**30) = round(21474836.48) = 21474836   (HTS)
    Ts   = 10737418                                             (TSQ)
    band = round(1e-4·2**24) = round(1677.72) = 1678            (Q24)
    every controller product is a Q30 constant times a Q24 word: exact, Q54
    wire(λ) = (λ + 2**29) >> 30   (round to nearest, ties toward +∞)
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_py import fixedpoint as fx
from firmware_py.controllers import (
    ControllerConfig,
    ControllerState,
    consensus_error,
    make_controller,
)
from firmware_py.errors import ParameterError

KTS, HTS, TSQ, BAND = 10737418, 21474836, 10737418, 1678
ONE = 1 << 24
G = 1 << 30


def ctrl(kind: str = "reset", fixed: bool = True, **kw: float):
    return make_controller(ControllerConfig(kind=kind, **kw), fixed)


def run(c, s: ControllerState, xis: list[int]):
    outs = []
    for x in xis:
        s, o = c.step(s, x)
        outs.append((s, o))
    return outs


def test_constants_are_what_the_hand_computations_assume() -> None:
    c = ctrl()
    assert (c.kts, c.hts, c.ts_q, c.band) == (KTS, HTS, TSQ, BAND)


def test_q30_rounds_to_nearest_even_and_refuses_what_does_not_fit() -> None:
    assert fx.to_q30(0.01) == 10737418
    assert fx.to_q30(2.5 * 2.0 ** -30) == 2 and fx.to_q30(3.5 * 2.0 ** -30) == 4  # ties: even
    assert fx.to_q30(2 - 2.0 ** -30) == fx.INT32_MAX  # (2**31 − 1)·2**-30
    for bad in (2.0, 2 - 2.0 ** -32, -0.01, 2.0 ** -31, math.inf, math.nan):
        with pytest.raises(ParameterError):
            fx.to_q30(bad, "k·ts")


def test_wire_lambda_rounds_the_state_to_nearest_ties_up() -> None:
    assert [fx.narrow(v) for v in (G // 2, -G // 2, 3 * G // 2, -3 * G // 2, G // 2 - 1)] == \
        [1, 0, 2, -1, 0]
    assert fx.narrow(fx.STATE_MAX) == fx.INT32_MAX and fx.narrow(fx.STATE_MIN) == fx.INT32_MIN
    c = ctrl()
    s = c.initial_state(0.3)
    assert s.lam == fx.to_fixed(0.3) * G and c.wire_lambda(s) == fx.to_fixed(0.3)


# --------------------------------------------------------------------------- hand-computed


def test_pc_steps_by_hand() -> None:
    c = ctrl("pc")
    s = c.initial_state(1.0)
    assert s.lam == ONE * G and c.wire_lambda(s) == ONE
    # ξ = 0.5 = 2**23: Δλ = −KTS·2**23 exactly (83886.078 Q24 LSB); wire: ONE − 83886
    s, o = c.step(s, 1 << 23)
    assert (o.dlam, s.lam, s.nu, o.reset) == (-KTS << 23, ONE * G - (KTS << 23), 0, False)
    assert c.wire_lambda(s) == 16693330
    # ξ = −2**21: Δλ = +KTS·2**21 (20971.52 LSB); λ = ONE − 62914.56 LSB → wire ONE − 62915
    s, o = c.step(s, -(1 << 21))
    assert (o.dlam, s.lam) == (KTS << 21, ONE * G - (KTS << 23) + (KTS << 21))
    assert c.wire_lambda(s) == 16714301


def test_pi_steps_by_hand() -> None:
    """Three PI steps; the third crosses zero but PI never resets."""
    c = ctrl("pi")
    s = c.initial_state(1.0)
    (s1, o1), (s2, o2), (s3, o3) = run(c, s, [1 << 23, 1 << 22, -(1 << 21)])
    # step 0, ξ = 0.5: Δλ = −(KTS·ξ + HTS·0); ν = 0 + TSQ·ξ (Q54, 83886.078 Q24 LSB)
    assert (o1.dlam, s1.nu) == (-KTS << 23, TSQ << 23)
    assert c.wire_lambda(s1) == 16693330
    # step 1, ξ = 0.25: ν enters h·Ts·ν rounded to Q24: (TSQ·2**23 + 2**29) >> 30 = 83886
    assert fx.narrow(s1.nu) == 83886
    assert (o2.dlam, s2.nu) == (-((KTS << 22) + HTS * 83886), (TSQ << 23) + (TSQ << 22))
    assert c.wire_lambda(s2) == 16649709
    # step 2, ξ = −0.125: ν rounds to 125829 (125829.117)
    assert fx.narrow(s2.nu) == 125829
    assert (o3.dlam, s3.nu, o3.reset) == (-(-(KTS << 21) + HTS * 125829),
                                          (TSQ << 23) + (TSQ << 22) - (TSQ << 21), False)
    assert s3.lam == s2.lam + o3.dlam and s3.resets == 0
    # the Q24 core sent 16668163 here: the guard bits keep the 0.52 LSB it dropped
    assert c.wire_lambda(s3) == 16668164


def test_reset_step_by_hand() -> None:
    """Same inputs as the PI test; at the crossing ν is zeroed before it is used."""
    c = ctrl("reset")
    (_, _), (s2, _), (s3, o3) = run(c, c.initial_state(1.0), [1 << 23, 1 << 22, -(1 << 21)])
    assert s2.nu == (TSQ << 23) + (TSQ << 22)
    # ξ went 0.25 → −0.125 (> 0 to ≤ 0) and the agent is armed: ν := 0, so
    #   Δλ = −(KTS·(−2**21) + HTS·0) ; ν = 0 + TSQ·(−2**21)
    assert (o3.reset, o3.dlam, s3.nu, s3.resets) == (True, KTS << 21, -(TSQ << 21), 1)
    assert s3.lam == s2.lam + (KTS << 21) and c.wire_lambda(s3) == 16670681
    # disarmed at the reset sample whatever |ξ| is there: only a later |ξ| > band re-arms
    assert not s3.armed and s3.since_reset == 1
    s4, o4 = c.step(s3, 1 << 21)          # a crossing right after: blocked, but re-arms
    assert not o4.reset and s4.armed


def test_first_sample_is_never_a_crossing() -> None:
    c = ctrl("reset")
    s, o = c.step(c.initial_state(0.0), -(1 << 20))   # ξ_prev = 0 at the start
    assert not o.reset


def test_exact_zero_counts_as_a_crossing_once() -> None:
    c = ctrl("reset", band=0.0)
    outs = run(c, c.initial_state(0.0), [5000, 0, -5000, 5000])
    # 5000 → 0 crosses (> 0 to ≤ 0); 0 → −5000 does not (ξ_prev = 0); −5000 → 5000 does
    assert [o.reset for _, o in outs] == [False, True, False, True]


def test_band_rearm_by_hand() -> None:
    """After a reset the next crossing resets only once |ξ| has exceeded the band (1678)."""
    c = ctrl("reset")
    xis = [1000, -500, 600, 5000, -100]
    outs = run(c, c.initial_state(0.0), xis)
    resets = [o.reset for _, o in outs]
    armed = [s.armed for s, _ in outs]
    # 1000: no crossing (start).  −500: crossing, armed → reset; |−500| ≤ 1678 → disarmed.
    # 600: crossing but disarmed → no reset, still disarmed.  5000: > band → re-armed.
    # −100: crossing, armed → reset.
    assert resets == [False, True, False, False, True]
    assert armed == [True, False, False, True, False]
    # the blocked crossing did not zero ν: ν after it = TSQ·(−500) + TSQ·600, exact
    assert outs[2][0].nu == TSQ * -500 + TSQ * 600 == TSQ * 100


def test_dwell_blocks_resets_by_hand() -> None:
    """Δ = 30 ms = 3 samples. The start counts as a reset at t = 0, so crossings at
    t = 10 and 20 ms are blocked, the one at 30 ms resets; after it, 40 and 50 ms are
    blocked and 60 ms resets. Every crossing here is armed (|ξ| = 2**20 ≫ band)."""
    c = ctrl("dwell", dwell=0.03)
    assert c.dwell_samples == 3
    x = 1 << 20
    outs = run(c, c.initial_state(0.0), [x, -x, x, -x, x, -x, x])
    assert [o.reset for _, o in outs] == [False, False, False, True, False, False, True]
    # blocked crossings keep integrating: ν at the sample-3 reset had summed ξ·Ts since 0
    assert outs[2][0].nu == TSQ * x * 2 + TSQ * -x
    assert outs[3][0].nu == TSQ * -x  # zeroed, then this sample's ξ·Ts


def test_dwell_equal_to_ts_is_plain_reset() -> None:
    c, r = ctrl("dwell", dwell=0.01), ctrl("reset")
    xis = [1 << 20, -(1 << 20), 1 << 20, -(1 << 20)]
    a, b = run(c, c.initial_state(0.3), xis), run(r, r.initial_state(0.3), xis)
    assert [s for s, _ in a] == [s for s, _ in b]


def test_finite_time_exponent_half_by_hand() -> None:
    c = ctrl("ft", ft_exponent=0.5)
    s = c.initial_state(1.0)
    # ξ = 0.25 = 2**22: √ = isqrt(2**22 << 24) = isqrt(2**46) = 2**23 (0.5);
    #   Δλ = −KTS·2**23 (ξ > 0)
    s, o = c.step(s, 1 << 22)
    assert (o.dlam, c.wire_lambda(s)) == (-KTS << 23, 16693330)
    # ξ = −0.0625 = −2**20: √|ξ| = isqrt(2**44) = 2**22 (0.25); Δλ = +KTS·2**22
    s, o = c.step(s, -(1 << 20))
    assert (o.dlam, c.wire_lambda(s)) == (KTS << 22, 16735273)
    # ξ = 0.3 → round(0.3·2**24) = 5033165; isqrt(5033165 << 24) = 9189259 (0.547722518,
    #   floor of √0.3·2**24 = 9189259.66); Δλ = −KTS·9189259
    assert c.ar.frac_pow(5033165) == 9189259
    s, o = c.step(s, 5033165)
    assert o.dlam == -KTS * 9189259
    s, o = c.step(s, 0)
    assert o.dlam == 0


def test_finite_time_exponent_three_quarters_by_hand() -> None:
    c = ctrl("ft", ft_exponent=0.75)
    # ξ = 0.0625 = 2**20: two square roots give 0.0625**(1/4) = 0.5 = 2**23, then
    #   two products 0.5·0.5·0.5 = 0.125 = 2**21 (0.0625**0.75 = 0.125 exactly);
    #   Δλ = −KTS·2**21 = −20971.52 Q24 LSB: the wire λ rounds to −20972
    assert c.ar.frac_pow(1 << 20) == 1 << 21
    s, o = c.step(c.initial_state(0.0), 1 << 20)
    assert (o.dlam, c.wire_lambda(s)) == (-KTS << 21, -20972)
    # ξ = −1.0: 1**0.75 = 1 → Δλ = +KTS·ONE
    s, o = c.step(s, -ONE)
    assert o.dlam == KTS * ONE


def test_consensus_error_by_hand() -> None:
    ar = ctrl().ar
    # ξ = 1·(0.5 − 0.25) + 2·(0.5 − 1.0) + 1·(0.5 − 0.75) = 0.25 − 1 − 0.25 = −1
    xi, sat = consensus_error(ar, 1 << 23, [(ONE, 1 << 22), (2 * ONE, ONE)], ONE, 3 << 22)
    assert (xi, sat) == (-ONE, False)
    assert consensus_error(ar, 1 << 23, [], 0, 0) == (0, False)   # unpinned, no neighbours


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize(("overrides", "name"), [
    ({"k": 0.0}, "k"), ({"k": -1.0}, "k"), ({"k": math.nan}, "k"), ({"k": 2e4}, "k"),
    ({"k": True}, "k"),
    ({"kind": "pi", "h": 0.0}, "h"), ({"kind": "reset", "h": -2.0}, "h"),
    ({"kind": "pc", "h": -1.0}, "h"), ({"h": math.inf}, "h"),
    ({"ts": 0.0}, "ts"), ({"ts": -0.01}, "ts"), ({"ts": 11.0}, "ts"), ({"ts": 1.5}, "ts"),
    ({"ts": "0.01"}, "ts"),
    ({"dwell": -1.0}, "dwell"), ({"kind": "dwell", "dwell": 0.005}, "dwell"),
    ({"dwell": math.nan}, "dwell"),
    ({"band": -1e-4}, "band"), ({"band": 1.0}, "band"), ({"band": math.inf}, "band"),
    ({"ft_exponent": 0.0}, "ft_exponent"), ({"ft_exponent": 1.0}, "ft_exponent"),
    ({"ft_exponent": 0.3}, "ft_exponent"), ({"ft_exponent": -0.5}, "ft_exponent"),
    ({"q": 4}, "q"), ({"q": 30}, "q"), ({"q": 24.0}, "q"), ({"q": True}, "q"),
    ({"kind": "lqr"}, "kind"),
    ({"k": 1e-8}, "k·ts"),                      # k·Ts = 1e-10 < one LSB of Q1.30
    ({"k": 1e4, "ts": 0.1}, "k·ts"),            # k·Ts = 1000 ≥ 2 does not fit Q1.30
    ({"k": 200.0}, "k·ts"),                     # k·Ts = 2.0 exactly: 2**31 does not fit
    ({"kind": "pi", "h": 1e-8}, "h·ts"),
    ({"h": 250.0}, "h·ts"),                     # h·Ts = 2.5 (checked for every kind)
])
def test_bad_parameter_raises_naming_it(overrides: dict, name: str) -> None:
    with pytest.raises(ParameterError) as e:
        ControllerConfig(**overrides)
    err = e.value
    assert isinstance(err, ValueError)
    assert err.name == name
    value = overrides[name] if name in overrides else err.got
    msg = str(err)
    assert msg.startswith(f"{name}: expected ")
    assert f"but got {value!r}" in msg


def test_to_fixed_refuses_out_of_range() -> None:
    with pytest.raises(ParameterError, match=r"lambda0: expected a value in \[-128, 128\]"):
        fx.to_fixed(200.0, "lambda0")


# --------------------------------------------------------------------------- saturation


def test_lambda_saturates_at_the_int32_edge_and_is_counted() -> None:
    """k·Ts = 1 so Δλ = −ξ: pushing λ = 127.5 up by 1.0 would wrap to −128.5 in C. The
    state saturates to the Q54 image of int32, so the wire λ saturates to int32."""
    c = ctrl("pc", k=100.0)
    assert c.kts == G
    s = c.initial_state(127.5)
    s, o = c.step(s, -ONE)
    assert (s.lam, c.wire_lambda(s), s.saturations) == (fx.STATE_MAX, fx.INT32_MAX, 1)
    s, o = c.step(s, -ONE)
    assert (s.lam, s.saturations) == (fx.STATE_MAX, 2)
    s, o = c.step(s, ONE)                       # back down: exact, not counted
    assert (s.lam, c.wire_lambda(s), s.saturations) == (fx.STATE_MAX - ONE * G,
                                                        fx.INT32_MAX - ONE, 2)
    s = c.initial_state(-127.5)
    s, _ = c.step(s, ONE)
    assert (s.lam, c.wire_lambda(s), s.saturations) == (fx.STATE_MIN, fx.INT32_MIN, 1)


def test_integrator_and_increment_saturate_and_are_counted() -> None:
    c = ctrl("pi", k=100.0, h=150.0)            # k·Ts = 1, h·Ts = 1.5
    s = ControllerState(lam=0, nu=fx.STATE_MAX - 10)
    s, o = c.step(s, fx.INT32_MAX)
    # h·Ts·ν ≈ 192 and k·Ts·ξ ≈ 128: Δλ saturates; ν + Ts·ξ saturates
    assert o.dlam == fx.STATE_MIN
    assert s.nu == fx.STATE_MAX
    assert s.saturations == 2
    xi, sat = consensus_error(c.ar, fx.INT32_MAX, [(ONE, fx.INT32_MIN)], 0, 0)
    assert (xi, sat) == (fx.INT32_MAX, True)


# --------------------------------------------------------------------------- properties

INT32 = st.integers(fx.INT32_MIN, fx.INT32_MAX)


def _expected_sats(c, s: ControllerState, xi: int, reset: bool) -> int:
    """Saturations one step must count: each of Δλ, ν and λ that leaves the state range
    (the Q54 image of int32) unclamped."""
    out = lambda v: not fx.STATE_MIN <= v <= fx.STATE_MAX  # noqa: E731
    kind = c.config.kind
    if kind == "pc":
        dlam = -c.kts * xi
        nu_sat = False
    elif kind == "ft":
        mag = c.kts * c.ar.frac_pow(xi)
        dlam = -mag if xi > 0 else mag if xi < 0 else 0
        nu_sat = False
    else:
        nu = 0 if reset else s.nu
        dlam = -(c.kts * xi + c.hts * fx.narrow(nu))
        nu_sat = out(nu + c.ts_q * xi)
    clamped, _ = fx.saturate_state(dlam)
    return out(dlam) + nu_sat + out(s.lam + clamped)


@settings(max_examples=150, deadline=None)
@given(kind=st.sampled_from(["pc", "pi", "reset", "dwell", "ft"]),
       k=st.floats(0.01, 1e4), h=st.floats(0.01, 1e4),
       ts=st.sampled_from([0.001, 0.01, 0.05]),
       exponent=st.sampled_from([0.25, 0.5, 0.75, 0.9375]),
       lam0=st.integers(fx.STATE_MIN, fx.STATE_MAX), xis=st.lists(INT32, min_size=1, max_size=40))
def test_fixed_core_never_wraps_and_counts_saturations(kind, k, h, ts, exponent, lam0, xis):
    """Property 1: for any ξ sequence over the whole int32 range and any valid gains,
    every state word stays in the Q54 image of int32 (so the wire λ and the ν of h·Ts·ν
    fit an int32, and every intermediate sum an int64), and a step counts exactly as many
    saturations as it has results (increment, integrator, λ) that would have left it."""
    k = min(k, 1.99 / ts)
    h = min(h, 1.99 / ts)
    cfg = ControllerConfig(kind=kind, k=k, h=h, ts=ts, dwell=2 * ts, ft_exponent=exponent)
    c = make_controller(cfg, fixed=True)
    s = ControllerState(lam=lam0)
    for xi in xis:
        new, out = c.step(s, xi)
        for v in (new.lam, new.nu, out.dlam):
            assert isinstance(v, int) and fx.STATE_MIN <= v <= fx.STATE_MAX
        for v in (new.xi_prev, c.wire_lambda(new), fx.narrow(new.nu)):
            assert isinstance(v, int) and fx.INT32_MIN <= v <= fx.INT32_MAX
        assert new.saturations - s.saturations == _expected_sats(c, s, xi, out.reset)
        s = new


LSB = 2.0 ** -24
LSB_C = 2.0 ** -30


@settings(max_examples=150, deadline=None)
@given(kind=st.sampled_from(["pc", "pi", "reset", "dwell", "ft"]),
       k=st.floats(0.1, 10), h=st.floats(0.1, 10), ts=st.sampled_from([0.001, 0.005, 0.01, 0.02]),
       band_lsb=st.integers(0, 5000),
       lam0=st.integers(-10 * 2**24, 10 * 2**24),
       xis=st.lists(st.integers(-2**24, 2**24), min_size=1, max_size=60))
def test_fixed_and_float_twins_stay_within_the_derived_bound(kind, k, h, ts, band_lsb, lam0,
                                                               xis):
    """Property 2: fed the same ξ sequence (exact Q24 values, so every sign, band and
    dwell decision is identical; band a whole number of LSBs), the fixed core and its
    float twin differ by at most a bound accumulated step by step from the rounding budget:

      gains      |k·Ts|_Q − k·Ts ≤ ½·2**-30, same for h·Ts and Ts (quantised once, Q1.30)
      products   exact (Q30·Q24 = Q54), sums exact
      PC / FT    |ΔΔλ| ≤ |Δ(k·Ts)|·|g(ξ)| [+ (k·Ts)·1 LSB for FT: the Q24 integer square
                 root floors, < 1 LSB]                             g(ξ) = ξ or |ξ|^½
      PI family  |ΔΔλ| ≤ |Δ(k·Ts)||ξ| + |Δ(h·Ts)||ν| + (h·Ts)(|Δν| + ½ LSB)  (ν enters
                 h·Ts·ν rounded to Q24)
                 |Δν'| ≤ |Δν| + |ΔTs||ξ|                   (both zero at a reset)
      |Δλ_{n+1}| ≤ |Δλ_n| + |ΔΔλ|,  and the wire λ adds ½ LSB (the rounding to Q24)

    plus 1e-13 per step for the float twin's own rounding. Without guard bits (the Q24
    core before) each step injected up to 1 LSB in Δλ and ½ LSB in ν; now the only
    per-step injection is the ½ LSB of ν in h·Ts·ν, scaled by h·Ts ≪ 1."""
    band = band_lsb * LSB
    cfg = ControllerConfig(kind=kind, k=k, h=h, ts=ts, dwell=3 * ts, band=band, ft_exponent=0.5)
    cx, cf = make_controller(cfg, True), make_controller(cfg, False)
    dk = abs(cx.kts * LSB_C - cf.kts)
    dh = abs(cx.hts * LSB_C - cf.hts)
    dts = abs(cx.ts_q * LSB_C - cf.ts_q)
    assert max(dk, dh, dts) <= 0.5 * LSB_C
    sx, sf = cx.initial_state(lam0 * LSB), cf.initial_state(lam0 * LSB)
    e_lam = e_nu = 0.0
    for xi in xis:
        x = xi * LSB
        nsx, ox = cx.step(sx, xi)
        nsf, of = cf.step(sf, x)
        assert ox.reset == of.reset and nsx.armed == nsf.armed
        if kind == "pc":
            e_d = dk * abs(x)
        elif kind == "ft":
            e_d = dk * math.sqrt(abs(x)) + cf.kts * LSB
        else:
            nu_f = 0.0 if of.reset else sf.nu
            e_nu_used = 0.0 if of.reset else e_nu
            e_d = dk * abs(x) + dh * abs(nu_f) + cx.hts * LSB_C * (e_nu_used + 0.5 * LSB)
            e_nu = e_nu_used + dts * abs(x)
            assert abs(cx.real_state(nsx.nu) - nsf.nu) <= e_nu + 1e-13
        e_lam += e_d + 1e-13
        assert abs(cx.real_state(nsx.lam) - nsf.lam) <= e_lam
        assert abs(cx.real(cx.wire_lambda(nsx)) - nsf.lam) <= e_lam + 0.5 * LSB
        sx, sf = nsx, nsf
    assert sx.saturations == 0
