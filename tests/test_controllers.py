"""The control core, pure: hand-computed Q24 steps, parameter validation, saturation,
and two properties (no wrap-around; fixed vs float twin inside a derived bound).

Constants used by the hand computations (k = 1, h = 2, Ts = 10 ms, Q24, LSB = 2**-24):
    k·Ts = round(0.01·2**24) = round(167772.16) = 167772
    h·Ts = round(0.02·2**24) = round(335544.32) = 335544
    Ts   = 167772
    band = round(1e-4·2**24) = round(1677.72) = 1678
    mul(a, b) = (a·b + 2**23) >> 24   (round to nearest, ties toward +∞)
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

KTS, HTS, TSQ, BAND = 167772, 335544, 167772, 1678
ONE = 1 << 24


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


# --------------------------------------------------------------------------- hand-computed


def test_pc_steps_by_hand() -> None:
    c = ctrl("pc")
    s = c.initial_state(1.0)
    assert s.lam == ONE
    # ξ = 0.5 = 2**23: k·Ts·ξ = (167772·2**23 + 2**23) >> 24 = floor(167773/2) = 83886
    s, o = c.step(s, 1 << 23)
    assert (o.dlam, s.lam, s.nu, o.reset) == (-83886, ONE - 83886, 0, False)
    # ξ = −2**21: (−167772·2**21 + 2**23) >> 24 = floor(−20971.5 + 0.5) = −20971 → dlam = +20971
    s, o = c.step(s, -(1 << 21))
    assert (o.dlam, s.lam) == (20971, ONE - 83886 + 20971)


def test_pi_steps_by_hand() -> None:
    """Three PI steps; the third crosses zero but PI never resets."""
    c = ctrl("pi")
    s = c.initial_state(1.0)
    (s1, o1), (s2, o2), (s3, o3) = run(c, s, [1 << 23, 1 << 22, -(1 << 21)])
    # step 0, ξ = 0.5: dlam = −(83886 + mul(h·Ts, 0)) ; ν ← 0 + mul(Ts, ξ) = 83886
    assert (o1.dlam, s1.lam, s1.nu) == (-83886, 16693330, 83886)
    # step 1, ξ = 0.25: mul(167772, 2**22) = floor(167774/4) = 41943;
    #   mul(335544, 83886) = (28147443984 + 2**23) >> 24 = floor(1678.22) = 1678
    #   dlam = −(41943 + 1678) = −43621 ; ν = 83886 + 41943 = 125829
    assert (o2.dlam, s2.lam, s2.nu) == (-43621, 16693330 - 43621, 125829)
    # step 2, ξ = −0.125: mul(167772, −2**21) = −20971;
    #   mul(335544, 125829) = (42221165976 + 2**23) >> 24 = floor(2517.08) = 2517
    #   dlam = −(−20971 + 2517) = 18454 ; ν = 125829 − 20971 = 104858
    assert (o3.dlam, s3.lam, s3.nu, o3.reset) == (18454, 16649709 + 18454, 104858, False)
    assert s3.resets == 0


def test_reset_step_by_hand() -> None:
    """Same inputs as the PI test; at the crossing ν is zeroed before it is used."""
    c = ctrl("reset")
    (_, _), (s2, _), (s3, o3) = run(c, c.initial_state(1.0), [1 << 23, 1 << 22, -(1 << 21)])
    assert s2.nu == 125829
    # ξ went 0.25 → −0.125 (> 0 to ≤ 0) and the agent is armed: ν := 0, so
    #   dlam = −(mul(167772, −2**21) + mul(335544, 0)) = 20971 ; ν = 0 + (−20971)
    assert (o3.reset, o3.dlam, s3.lam, s3.nu, s3.resets) == (True, 20971, 16670680, -20971, 1)
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
    # the blocked crossing did not zero ν: ν after it = mul(Ts, −500) + mul(Ts, 600) = −5 + 6
    assert outs[2][0].nu == fx.mul(TSQ, -500) + fx.mul(TSQ, 600) == 1


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
    assert outs[2][0].nu == fx.mul(TSQ, x) * 2 + fx.mul(TSQ, -x)
    assert outs[3][0].nu == fx.mul(TSQ, -x)  # zeroed, then this sample's ξ·Ts


def test_dwell_equal_to_ts_is_plain_reset() -> None:
    c, r = ctrl("dwell", dwell=0.01), ctrl("reset")
    xis = [1 << 20, -(1 << 20), 1 << 20, -(1 << 20)]
    a, b = run(c, c.initial_state(0.3), xis), run(r, r.initial_state(0.3), xis)
    assert [s for s, _ in a] == [s for s, _ in b]


def test_finite_time_exponent_half_by_hand() -> None:
    c = ctrl("ft", ft_exponent=0.5)
    s = c.initial_state(1.0)
    # ξ = 0.25 = 2**22: √ = isqrt(2**22 << 24) = isqrt(2**46) = 2**23 (0.5);
    #   k·Ts·0.5 = mul(167772, 2**23) = 83886 ; ξ > 0 → dlam = −83886
    s, o = c.step(s, 1 << 22)
    assert (o.dlam, s.lam) == (-83886, ONE - 83886)
    # ξ = −0.0625 = −2**20: √|ξ| = isqrt(2**44) = 2**22 (0.25); mul(167772, 2**22) = 41943
    s, o = c.step(s, -(1 << 20))
    assert (o.dlam, s.lam) == (41943, ONE - 83886 + 41943)
    # ξ = 0.3 → round(0.3·2**24) = 5033165; isqrt(5033165 << 24) = 9189259 (0.547722518,
    #   floor of √0.3·2**24 = 9189259.66); mul(167772, 9189259) = 91893
    s, o = c.step(s, 5033165)
    assert o.dlam == -91893
    s, o = c.step(s, 0)
    assert o.dlam == 0


def test_finite_time_exponent_three_quarters_by_hand() -> None:
    c = ctrl("ft", ft_exponent=0.75)
    # ξ = 0.0625 = 2**20: two square roots give 0.0625**(1/4) = 0.5 = 2**23, then
    #   two products 0.5·0.5·0.5 = 0.125 = 2**21 (0.0625**0.75 = 0.125 exactly);
    #   k·Ts·0.125 = mul(167772, 2**21) = (167772·2**21 + 2**23) >> 24 = 20971.5 + 0.5 → 20972
    #   (a tie, rounded toward +∞)
    assert c.ar.frac_pow(1 << 20) == 1 << 21
    s, o = c.step(c.initial_state(0.0), 1 << 20)
    assert o.dlam == -20972
    # ξ = −1.0: 1**0.75 = 1 → dlam = +k·Ts = +167772
    s, o = c.step(s, -ONE)
    assert o.dlam == KTS


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
    ({"ts": 0.0}, "ts"), ({"ts": -0.01}, "ts"), ({"ts": 11.0}, "ts"), ({"ts": "0.01"}, "ts"),
    ({"dwell": -1.0}, "dwell"), ({"kind": "dwell", "dwell": 0.005}, "dwell"),
    ({"dwell": math.nan}, "dwell"),
    ({"band": -1e-4}, "band"), ({"band": 1.0}, "band"), ({"band": math.inf}, "band"),
    ({"ft_exponent": 0.0}, "ft_exponent"), ({"ft_exponent": 1.0}, "ft_exponent"),
    ({"ft_exponent": 0.3}, "ft_exponent"), ({"ft_exponent": -0.5}, "ft_exponent"),
    ({"q": 4}, "q"), ({"q": 30}, "q"), ({"q": 24.0}, "q"), ({"q": True}, "q"),
    ({"kind": "lqr"}, "kind"),
    ({"k": 1e-7}, "k·ts"),                      # k·Ts = 1e-9 < one LSB
    ({"k": 1e4, "ts": 0.1}, "k·ts"),            # k·Ts = 1000 ≥ 128 does not fit Q7.24
    ({"kind": "pi", "h": 1e-7}, "h·ts"),
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
    """k·Ts = 1 so dlam = −ξ: pushing λ = 127.5 up by 1.0 would wrap to −128.5 in C."""
    c = ctrl("pc", k=100.0)
    assert c.kts == ONE
    s = c.initial_state(127.5)
    s, o = c.step(s, -ONE)
    assert (s.lam, s.saturations) == (fx.INT32_MAX, 1)
    s, o = c.step(s, -ONE)
    assert (s.lam, s.saturations) == (fx.INT32_MAX, 2)
    s, o = c.step(s, ONE)                       # back down: exact, not counted
    assert (s.lam, s.saturations) == (fx.INT32_MAX - ONE, 2)
    s = c.initial_state(-127.5)
    s, _ = c.step(s, ONE)
    assert (s.lam, s.saturations) == (fx.INT32_MIN, 1)


def test_integrator_and_increment_saturate_and_are_counted() -> None:
    c = ctrl("pi", k=100.0, h=1000.0)           # k·Ts = 1, h·Ts = 10
    s = ControllerState(lam=0, nu=fx.INT32_MAX - 10)
    s, o = c.step(s, fx.INT32_MAX)
    # h·Ts·ν ≈ 1280 and k·Ts·ξ ≈ 128: dlam saturates; ν + Ts·ξ saturates
    assert o.dlam == fx.INT32_MIN
    assert s.nu == fx.INT32_MAX
    assert s.saturations == 2
    xi, sat = consensus_error(c.ar, fx.INT32_MAX, [(ONE, fx.INT32_MIN)], 0, 0)
    assert (xi, sat) == (fx.INT32_MAX, True)


# --------------------------------------------------------------------------- properties

INT32 = st.integers(fx.INT32_MIN, fx.INT32_MAX)


def _expected_sats(c, s: ControllerState, xi: int, reset: bool) -> int:
    """Saturations one step must count: each of dlam, ν and λ that leaves int32 unclamped."""
    out = lambda v: not fx.INT32_MIN <= v <= fx.INT32_MAX  # noqa: E731
    kind = c.config.kind
    if kind == "pc":
        dlam = -fx.mul(c.kts, xi)
        nu_sat = False
    elif kind == "ft":
        mag = fx.mul(c.kts, c.ar.frac_pow(xi))
        dlam = -mag if xi > 0 else mag if xi < 0 else 0
        nu_sat = False
    else:
        nu = 0 if reset else s.nu
        dlam = -(fx.mul(c.kts, xi) + fx.mul(c.hts, nu))
        nu_sat = out(nu + fx.mul(c.ts_q, xi))
    clamped, _ = fx.saturate(dlam)
    return out(dlam) + nu_sat + out(s.lam + clamped)


@settings(max_examples=150, deadline=None)
@given(kind=st.sampled_from(["pc", "pi", "reset", "dwell", "ft"]),
       k=st.floats(0.01, 1e4), h=st.floats(0.01, 1e4),
       ts=st.sampled_from([0.001, 0.01, 0.05]),
       exponent=st.sampled_from([0.25, 0.5, 0.75, 0.9375]),
       lam0=INT32, xis=st.lists(INT32, min_size=1, max_size=40))
def test_fixed_core_never_wraps_and_counts_saturations(kind, k, h, ts, exponent, lam0, xis):
    """Property 1: for any ξ sequence over the whole int32 range and any valid gains,
    every state word stays in int32, and a step counts exactly as many saturations as
    it has results (increment, integrator, λ) that would have left int32."""
    k = min(k, 127 / ts)
    h = min(h, 127 / ts)
    cfg = ControllerConfig(kind=kind, k=k, h=h, ts=ts, dwell=2 * ts, ft_exponent=exponent)
    c = make_controller(cfg, fixed=True)
    s = ControllerState(lam=lam0)
    for xi in xis:
        new, out = c.step(s, xi)
        for v in (new.lam, new.nu, new.xi_prev, out.dlam):
            assert isinstance(v, int) and fx.INT32_MIN <= v <= fx.INT32_MAX
        assert new.saturations - s.saturations == _expected_sats(c, s, xi, out.reset)
        s = new


LSB = 2.0 ** -24


@settings(max_examples=150, deadline=None)
@given(kind=st.sampled_from(["pc", "pi", "reset", "dwell", "ft"]),
       k=st.floats(0.1, 10), h=st.floats(0.1, 10), ts=st.sampled_from([0.005, 0.01, 0.02]),
       band_lsb=st.integers(0, 5000),
       lam0=st.integers(-10 * 2**24, 10 * 2**24),
       xis=st.lists(st.integers(-2**24, 2**24), min_size=1, max_size=60))
def test_fixed_and_float_twins_stay_within_the_derived_bound(kind, k, h, ts, band_lsb, lam0,
                                                               xis):
    """Property 2: fed the same ξ sequence (exact Q24 values, so every sign, band and
    dwell decision is identical; band a whole number of LSBs), the Q24 core and its float
    twin differ by at most a bound accumulated step by step from the rounding budget:

      gains      |k·Ts|_Q − k·Ts ≤ ½ LSB, same for h·Ts and Ts (quantised once)
      PC / FT    |Δdlam| ≤ ½ LSB (product) + |Δ(k·Ts)|·|g(ξ)| [+ (k·Ts)·1 LSB for FT:
                 the integer square root floors, < 1 LSB]         g(ξ) = ξ or |ξ|^½
      PI family  |Δdlam| ≤ 1 LSB (two products) + |Δ(k·Ts)||ξ| + |Δ(h·Ts)||ν| + (h·Ts)|Δν|
                 |Δν'|  ≤ |Δν| + ½ LSB + |ΔTs||ξ|          (both zero at a reset)
      |Δλ_{n+1}| ≤ |Δλ_n| + |Δdlam|   (λ itself adds exactly: an integer sum)

    plus 1e-13 per step for the float twin's own rounding. In open loop this grows
    ~linearly (PC/FT) or ~quadratically (through ν) in the number of steps; in the
    closed loop of a case the same per-step injection is attenuated by the stable loop
    (measured in tests/test_cases.py)."""
    band = band_lsb * LSB
    cfg = ControllerConfig(kind=kind, k=k, h=h, ts=ts, dwell=3 * ts, band=band, ft_exponent=0.5)
    cx, cf = make_controller(cfg, True), make_controller(cfg, False)
    dk = abs(cx.kts * LSB - cf.kts)
    dh = abs(cx.hts * LSB - cf.hts)
    dts = abs(cx.ts_q * LSB - cf.ts_q)
    sx, sf = ControllerState(lam=lam0), ControllerState(lam=lam0 * LSB)
    e_lam = e_nu = 0.0
    for xi in xis:
        x = xi * LSB
        nsx, ox = cx.step(sx, xi)
        nsf, of = cf.step(sf, x)
        assert ox.reset == of.reset and nsx.armed == nsf.armed
        if kind == "pc":
            e_d = 0.5 * LSB + dk * abs(x)
        elif kind == "ft":
            e_d = 0.5 * LSB + dk * math.sqrt(abs(x)) + cf.kts * LSB
        else:
            nu_f = 0.0 if of.reset else sf.nu
            e_nu_used = 0.0 if of.reset else e_nu
            e_d = LSB + dk * abs(x) + dh * abs(nu_f) + cx.hts * LSB * e_nu_used
            e_nu = e_nu_used + 0.5 * LSB + dts * abs(x)
            assert abs(nsx.nu * LSB - nsf.nu) <= e_nu + 1e-13
        e_lam += e_d + 1e-13
        assert abs(nsx.lam * LSB - nsf.lam) <= e_lam
        sx, sf = nsx, nsf
    assert sx.saturations == 0
