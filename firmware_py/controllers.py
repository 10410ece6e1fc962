"""The pure control core: five consensus controllers behind one interface.

Each controller advances one agent by one sample Ts (forward Euler, what an MCU
runs): ``step(state, xi) -> (state, StepOutput)``. The clock is never read and
nothing is printed; the runtime feeds ξ and applies the output.

The algorithm is written once against an ``Arithmetic`` and instantiated twice:
``FixedArithmetic`` (what the firmware runs: Q24 words on the wire and in ξ, Q1.30
constants, a Q54 state with 30 guard bits, saturating; see firmware_py/fixedpoint.py)
and ``FloatArithmetic`` (the float twin, used to bound the quantisation error).
The λ an agent sends, and uses as its own λ in ξ, is the state rounded to Q24
(``Controller.wire_lambda``).

Controllers (u is the MC rate dλ/dt; ν is the integral of ξ):

* ``pc``     proportional consensus         u = −k ξ
* ``pi``     PI without reset                u = −k ξ − h ν,  ν̇ = ξ
* ``reset``  reset-PI (Clegg)                as pi, ν := 0 when ξ crosses zero
* ``dwell``  reset-PI with dwell Δ           reset only if ≥ Δ since the last one
* ``ft``     finite-time baseline            u = −k sign(ξ) |ξ|^a

Discrete zero crossing: ξ went from > 0 to ≤ 0 or from < 0 to ≥ 0 between two
samples. With quantised λ, ξ flips sign around zero almost every sample near
equilibrium, so a plain discrete Clegg reset chatters. The *reset band* fixes
that: after a reset, the next reset is armed only once |ξ| has exceeded the
band. The controller start counts as a reset (ν(0) = 0), so the first dwell
interval runs from t = 0.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Protocol

from . import fixedpoint as fx
from .errors import ParameterError

KINDS = ("pc", "pi", "reset", "dwell", "ft")

# Default re-arm band on |ξ| (cu/kWh), ≈ 1700 LSB of Q24. Measured on cases 1, 4, 5, 7
# (docs/performance.md): it cuts resets by 1.4–1.7× against the plain Clegg reset with
# the same settling time. A wider band (2e-3) stalls the slow modes of case 7.
DEFAULT_BAND = 1e-4


@dataclass(frozen=True)
class ControllerConfig:
    """Physical controller parameters, validated on construction."""

    kind: str = "reset"
    k: float = 1.0
    h: float = 2.0
    ts: float = 0.01
    dwell: float = 0.0
    band: float = DEFAULT_BAND
    ft_exponent: float = 0.5
    q: int = fx.Q

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ParameterError("kind", f"one of {', '.join(KINDS)}", self.kind)
        fx.check_q(self.q)
        _positive("ts", self.ts, upper=1.0)
        _positive("k", self.k, upper=1e4)
        if self.kind in ("pi", "reset", "dwell"):
            _positive("h", self.h, upper=1e4)
        elif not (_finite(self.h) and self.h >= 0):
            raise ParameterError("h", "a finite number ≥ 0", self.h)
        # at most DWELL_MAX_S: D = ceil(dwell/ts) then fits firmware_c's uint32 (CTRL-2)
        if not (_finite(self.dwell) and 0 <= self.dwell <= DWELL_MAX_S):
            raise ParameterError("dwell", f"a finite number of seconds in [0, {DWELL_MAX_S:g}]",
                                 self.dwell)
        if self.kind == "dwell" and self.dwell < self.ts:
            raise ParameterError("dwell", f"Δ ≥ Ts = {self.ts} s for the dwell controller",
                                 self.dwell)
        if self.kind == "dwell" and math.ceil(self.dwell / self.ts - 1e-9) > 0xFFFFFFFF:
            raise ParameterError("dwell", "Δ/Ts < 2^32 (D = ceil(Δ/Ts) is a uint32, CTRL-2)",
                                 self.dwell)
        if not (_finite(self.band) and 0 <= self.band < 1):
            raise ParameterError("band", "a reset band in [0, 1) cu/kWh", self.band)
        if not (_finite(self.ft_exponent) and 0 < self.ft_exponent < 1
                and (self.ft_exponent * 16).is_integer()):
            raise ParameterError("ft_exponent", "a in (0, 1) that is a multiple of 1/16",
                                 self.ft_exponent)
        # the controller's constants are int32 Q1.30 (fixedpoint.to_q30): < 2, and 0 or
        # at least one LSB (2**-30)
        for name, value in (("k·ts", self.k * self.ts), ("h·ts", self.h * self.ts),
                            ("ts", self.ts)):
            fx.to_q30(value, name)

    def with_gains(self, k: float, h: float) -> ControllerConfig:
        """This config with the gains a SET_GAINS carried (CMD-5). Not re-validated: the
        runtime checked the gains in integers, and the controller's constants come from
        them, not from k·ts and h·ts."""
        new = copy.copy(self)
        object.__setattr__(new, "k", k)
        object.__setattr__(new, "h", h)
        return new

    @property
    def dwell_samples(self) -> int:
        """Δ as a whole number of samples (rounded up: never shorter than asked)."""
        return math.ceil(self.dwell / self.ts - 1e-9) if self.kind == "dwell" else 0


DWELL_MAX_S = 1e5  # the longest run (sim.model.scenario's duration bound), 27.8 h


def _finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _positive(name: str, x: object, upper: float) -> None:
    if not (_finite(x) and 0 < x <= upper):  # type: ignore[operator]
        raise ParameterError(name, f"a finite number in (0, {upper:g}]", x)


# --------------------------------------------------------------------------- arithmetic


class Arithmetic(Protocol):
    """What the control law needs of its numbers. "Word": a Q24 value as on the wire (λ_j,
    ρ, ξ, weights, band); "gain": a controller constant k·Ts, h·Ts, Ts; "state": λ, ν and
    the increments, which keep more fractional bits than a word in the fixed core."""

    def quantise(self, x: float, name: str) -> float | int:
        """A configuration value or wire quantity as a word."""
        ...

    def quantise_gain(self, x: float, name: str) -> float | int:
        """A controller constant as a gain (finer than a word: no gain error to speak of)."""
        ...

    def real(self, v: float | int) -> float:
        """A word's real value."""
        ...

    def real_state(self, v: float | int) -> float:
        """A state word's real value."""
        ...

    def mul(self, a: float | int, b: float | int) -> float | int:
        """word · word → word (rounded)."""
        ...

    def gain_mul(self, c: float | int, v: float | int) -> float | int:
        """gain · word → state word (exact in the fixed core: Q30·Q24 = Q54)."""
        ...

    def sat(self, v: float | int) -> tuple[float | int, bool]:
        """Clamp a word to its range; (value, clamped?)."""
        ...

    def sat_state(self, v: float | int) -> tuple[float | int, bool]:
        """Clamp a state word to its range; (value, clamped?)."""
        ...

    def narrow(self, v: float | int) -> float | int:
        """A state word rounded to a word: the λ that goes on the wire, ν in h·Ts·ν."""
        ...

    def widen(self, v: float | int) -> float | int:
        """A word as a state word (exact): λ(0)."""
        ...

    def frac_pow(self, v: float | int) -> float | int:
        """|v|**a, a word."""
        ...


class FixedArithmetic:
    """int32 Q-format words, int32 Q1.30 gains, int64 Q(q+30) state; counted saturation."""

    def __init__(self, q: int = fx.Q, exponent: float = 0.5) -> None:
        self.q = fx.check_q(q)
        f = Fraction(exponent).limit_denominator(16)
        self._pow_num = f.numerator
        self._pow_sqrts = f.denominator.bit_length() - 1  # denominator is 2**n

    @property
    def pow_num(self) -> int:
        """The exponent a = pow_num / 2**pow_sqrts: its numerator (firmware_c's pow_num)."""
        return self._pow_num

    @property
    def pow_sqrts(self) -> int:
        """The exponent's square roots: a's denominator is 2**pow_sqrts."""
        return self._pow_sqrts

    def quantise(self, x: float, name: str) -> int:
        """A real value as a Q-format word (round to nearest); refuses one that does not fit."""
        return fx.to_fixed(x, name, self.q)

    def quantise_gain(self, x: float, name: str) -> int:
        """A controller constant as an int32 Q1.30 gain (fixedpoint.to_q30)."""
        return fx.to_q30(x, name)

    def real(self, v: float | int) -> float:
        """A word's real value."""
        return fx.to_float(int(v), self.q)

    def real_state(self, v: float | int) -> float:
        """A state word's real value (q + GUARD fractional bits)."""
        return fx.to_float(int(v), self.q + fx.GUARD)

    def mul(self, a: float | int, b: float | int) -> int:
        """word · word → word, rounded to nearest (not yet saturated)."""
        return fx.mul(int(a), int(b), self.q)

    def gain_mul(self, c: float | int, v: float | int) -> int:
        """gain · word → state word, exact (int32 × int32 → int64)."""
        return int(c) * int(v)          # int32 × int32 → int64, exact (SMULL)

    def sat(self, v: float | int) -> tuple[int, bool]:
        """A word clamped to int32: (value, clamped?)."""
        return fx.saturate(int(v))

    def sat_state(self, v: float | int) -> tuple[int, bool]:
        """A state word clamped to the Q54 image of int32: (value, clamped?)."""
        return fx.saturate_state(int(v))

    def narrow(self, v: float | int) -> int:
        """A state word rounded to a word (the λ on the wire)."""
        return fx.narrow(int(v))

    def widen(self, v: float | int) -> int:
        """A word as a state word (exact)."""
        return fx.widen(int(v))

    def frac_pow(self, v: float | int) -> int:
        """|v|**(p/2**n): n integer square roots, then p − 1 products."""
        root = abs(int(v))
        for _ in range(self._pow_sqrts):
            root = fx.sqrt_q(root, self.q)
        out = root
        for _ in range(self._pow_num - 1):
            out = fx.mul(out, root, self.q)
        return out


class FloatArithmetic:
    """The float twin: same algorithm, IEEE doubles, no saturation."""

    def __init__(self, exponent: float = 0.5) -> None:
        self.exponent = exponent

    def quantise(self, x: float, name: str) -> float:
        """The value itself, as a float (no quantisation in the twin)."""
        return float(x)

    def quantise_gain(self, x: float, name: str) -> float:
        """The constant itself, as a float."""
        return float(x)

    def real(self, v: float | int) -> float:
        """The value itself, as a float."""
        return float(v)

    def real_state(self, v: float | int) -> float:
        """The value itself, as a float."""
        return float(v)

    def mul(self, a: float | int, b: float | int) -> float:
        """The plain product a · b."""
        return a * b

    def gain_mul(self, c: float | int, v: float | int) -> float:
        """The plain product c · v."""
        return c * v

    def sat(self, v: float | int) -> tuple[float, bool]:
        """(v, False): the float twin never saturates."""
        return float(v), False

    def sat_state(self, v: float | int) -> tuple[float, bool]:
        """(v, False): the float twin never saturates."""
        return float(v), False

    def narrow(self, v: float | int) -> float:
        """The value itself: the twin's state and wire λ are one float."""
        return float(v)

    def widen(self, v: float | int) -> float:
        """The value itself: the twin's state and wire λ are one float."""
        return float(v)

    def frac_pow(self, v: float | int) -> float:
        """|v|**exponent in double precision."""
        return abs(v) ** self.exponent


# --------------------------------------------------------------------------- state


@dataclass(frozen=True, slots=True)
class ControllerState:
    """Everything one agent's controller remembers between samples.

    λ and ν are state words (fixed core: int64 Q54 = Q24 + 30 guard bits); the λ the
    agent sends is ``Controller.wire_lambda(state)``, not ``lam`` itself."""

    lam: float | int            # λ, the marginal cost (state word)
    nu: float | int = 0         # ν, integral of ξ since the last reset (state word)
    xi_prev: float | int = 0    # ξ at the previous sample (zero-crossing detection), a word
    armed: bool = True          # reset band: may the next crossing reset?
    since_reset: int = 0        # samples since the last reset (the start counts as one)
    resets: int = 0
    saturations: int = 0


@dataclass(frozen=True, slots=True)
class StepOutput:
    """What one controller step did besides the new state: Δλ and whether ν was reset."""

    dlam: float | int   # λ increment applied this sample (= Ts·u), a state word (Q54)
    reset: bool         # ν was reset at this sample


def resilient_trim(lam: float | int, neighbours: Sequence[tuple[float | int, float | int]],
                   f: int) -> list[tuple[float | int, float | int]]:
    """W-MSR (LeBlanc et al. 2013): ``neighbours`` without up to ``f`` of the λ_j strictly
    above ``lam`` (the largest) and up to ``f`` strictly below it (the smallest).

    A neighbour whose λ_j equals ``lam`` is never dropped. Ties: the terms are ranked by
    (distance from ``lam``, weight), largest first, and the first ``f`` of each side go;
    terms equal in both are interchangeable (their products are equal), so the result's
    sum does not depend on the order the neighbours come in (firmware-spec WMSR-2).
    ``f`` = 0 returns the list as given (the default update, bit for bit)."""
    if f <= 0:
        return list(neighbours)
    above = sorted((t for t in neighbours if t[1] > lam), key=lambda t: (t[1], t[0]),
                   reverse=True)
    below = sorted((t for t in neighbours if t[1] < lam), key=lambda t: (-t[1], t[0]),
                   reverse=True)
    level = [t for t in neighbours if t[1] == lam]
    return above[f:] + below[f:] + level


def consensus_error(ar: Arithmetic, lam: float | int,
                    neighbours: Sequence[tuple[float | int, float | int]],
                    pin: float | int, price: float | int,
                    trim: int = 0) -> tuple[float | int, bool]:
    """ξ_i = Σ_j a_ij (λ_i − λ_j) + b_ii (λ_i − ρ). Returns (ξ, saturated?).

    ``neighbours`` holds (a_ij, λ_j) for the neighbours currently alive; ``pin`` is
    b_ii (0 when the agent does not hear the price, or the price is lost). ``trim`` > 0:
    the resilient update, the neighbour terms after ``resilient_trim(lam, ..., trim)``;
    the price term is never trimmed (the router's price is authenticated, not a vote).
    """
    if trim:
        neighbours = resilient_trim(lam, neighbours, trim)
    acc = ar.mul(pin, lam - price) if pin else 0
    for weight, lam_j in neighbours:
        acc += ar.mul(weight, lam - lam_j)
    return ar.sat(acc)


# --------------------------------------------------------------------------- controllers


class Controller:
    """Base: holds the validated config, its quantised constants, and the step."""

    def __init__(self, config: ControllerConfig, fixed: bool = True) -> None:
        self.config = config
        self.fixed = fixed
        self.ar: Arithmetic = (FixedArithmetic(config.q, config.ft_exponent) if fixed
                               else FloatArithmetic(config.ft_exponent))
        self.kts = self.ar.quantise_gain(config.k * config.ts, "k·ts")
        self.hts = self.ar.quantise_gain(config.h * config.ts, "h·ts")
        self.ts_q = self.ar.quantise_gain(config.ts, "ts")
        self.band = self.ar.quantise(config.band, "band")
        self.dwell_samples = config.dwell_samples

    def initial_state(self, lam0: float) -> ControllerState:
        """λ = q24(lam0) widened to the state (so λ(0) on the wire is q24(lam0))."""
        return ControllerState(lam=self.ar.widen(self.ar.quantise(lam0, "lambda0")))

    def wire_lambda(self, s: ControllerState) -> float | int:
        """The λ the agent sends (MC frame), uses as its own λ in ξ, maps to a setpoint
        and reports: the state's λ rounded to Q24 (fixed core), λ itself (float twin)."""
        return self.ar.narrow(s.lam)

    def quantise(self, x: float, name: str = "value") -> float | int:
        """A wire quantity (λ_j, ρ, a weight) as the core's word."""
        return self.ar.quantise(x, name)

    def real(self, v: float | int) -> float:
        """A word's (wire λ, ξ) real value."""
        return self.ar.real(v)

    def real_state(self, v: float | int) -> float:
        """A state word's (λ, ν, Δλ) real value."""
        return self.ar.real_state(v)

    def step(self, s: ControllerState, xi: float | int) -> tuple[ControllerState, StepOutput]:
        """One sample: the state after consensus error ``xi``, and what the step did."""
        raise NotImplementedError

    def _advance(self, s: ControllerState, xi: float | int, dlam: float | int, sats: int,
                 nu: float | int, reset: bool, armed: bool) -> tuple[ControllerState,
                                                                     StepOutput]:
        lam, s1 = self.ar.sat_state(s.lam + dlam)
        return (ControllerState(lam=lam, nu=nu, xi_prev=xi, armed=armed,
                                since_reset=1 if reset else s.since_reset + 1,
                                resets=s.resets + reset, saturations=s.saturations + sats + s1),
                StepOutput(dlam=dlam, reset=reset))


class ProportionalController(Controller):
    """Proportional consensus (PC): Δλ = −k·Ts·ξ, no integral state."""

    def step(self, s: ControllerState, xi: float | int) -> tuple[ControllerState, StepOutput]:
        """Δλ = −k·Ts·ξ (saturated and counted); ν stays 0."""
        dlam, sat = self.ar.sat_state(-self.ar.gain_mul(self.kts, xi))
        return self._advance(s, xi, dlam, sat, 0, False, s.armed)


class FiniteTimeController(Controller):
    """Finite-time consensus: Δλ = −k·Ts·sign(ξ)·|ξ|**a."""

    def step(self, s: ControllerState, xi: float | int) -> tuple[ControllerState, StepOutput]:
        """Δλ = −k·Ts·sign(ξ)·|ξ|**a (saturated and counted); ν stays 0."""
        mag = self.ar.gain_mul(self.kts, self.ar.frac_pow(xi))
        dlam, sat = self.ar.sat_state(-mag if xi > 0 else mag if xi < 0 else 0)
        return self._advance(s, xi, dlam, sat, 0, False, s.armed)


class PIController(Controller):
    """PI without reset; the reset variants only decide when ν is zeroed."""

    def _reset_now(self, s: ControllerState, xi: float | int) -> bool:
        return False

    def step(self, s: ControllerState, xi: float | int) -> tuple[ControllerState, StepOutput]:
        """Δλ = −(k·Ts·ξ + h·Ts·ν), ν += Ts·ξ; ν zeroed first when the
        variant's ``_reset_now`` says so, and the reset band re-armed once |ξ| leaves it."""
        reset = self._reset_now(s, xi)
        nu = 0 if reset else s.nu
        # re-arm once |ξ| has left the band *after* the last reset (not at the reset
        # sample itself: in continuous time ξ = 0 there, and counting it would let a
        # crossing detected a sample late re-arm at once and fire an echo reset)
        armed = not reset and (s.armed or abs(xi) > self.band)
        # every product is a gain times a word, exact; ν enters h·Ts·ν rounded to a word
        nu_word = self.ar.narrow(nu)
        dlam, sat1 = self.ar.sat_state(-(self.ar.gain_mul(self.kts, xi)
                                         + self.ar.gain_mul(self.hts, nu_word)))
        nu_next, sat2 = self.ar.sat_state(nu + self.ar.gain_mul(self.ts_q, xi))
        return self._advance(s, xi, dlam, sat1 + sat2, nu_next, reset, armed)


class ResetPIController(PIController):
    """Clegg reset: ν := 0 at a zero crossing of ξ, if re-armed by the band."""

    def _reset_now(self, s: ControllerState, xi: float | int) -> bool:
        crossed = (s.xi_prev > 0 and xi <= 0) or (s.xi_prev < 0 and xi >= 0)
        return crossed and s.armed


class DwellResetPIController(ResetPIController):
    """Zeno-free variant: a crossing resets only if ≥ Δ has passed since the last reset."""

    def _reset_now(self, s: ControllerState, xi: float | int) -> bool:
        return super()._reset_now(s, xi) and s.since_reset >= self.dwell_samples


_CLASSES: dict[str, type[Controller]] = {
    "pc": ProportionalController,
    "pi": PIController,
    "reset": ResetPIController,
    "dwell": DwellResetPIController,
    "ft": FiniteTimeController,
}


def make_controller(config: ControllerConfig, fixed: bool = True) -> Controller:
    """The controller for ``config.kind``; ``fixed=False`` gives its float twin."""
    return _CLASSES[config.kind](config, fixed)
