"""Fixed-point arithmetic of the control core.

Words on the bus and in ξ are signed 32-bit integers; the controller's constants are
int32 Q1.30 and its state (λ, ν) is int64 with 30 guard bits. Every product is a
32×32→64 multiply (what a Cortex-M does with SMULL/SMLAL); nothing needs 64×64 bits.

=========================  =========  ===========================  ====================
quantity                   format     LSB                          range
=========================  =========  ===========================  ====================
λ_j, ρ (wire), own λ sent  Q7.24      2**-24 ≈ 5.96e-8 cu/kWh      [-128, 128)
ξ (consensus error)        Q7.24      2**-24                       [-128, 128)
edge weights a_ij, b, band Q7.24      2**-24                       [0, 128)
k·Ts, h·Ts, Ts             Q1.30      2**-30 ≈ 9.31e-10            [0, 2)
λ, ν (controller state)    Q54 int64  2**-54 ≈ 5.55e-17            Q54 image of int32
                                                                   Q24: [-128, 128)
Δλ, Ts·ξ (increments)      Q54 int64  2**-54                       same
=========================  =========  ===========================  ====================

λ is Q24 on the wire because it travels on the bus in that format (dbc/ declares the
factor 2**-24), so every node sees bit-identical values; the state keeps 30 more bits
(``GUARD``) so that an increment k·Ts·ξ far below one Q24 LSB still moves λ (no dead
zone), and k·Ts is quantised at 2**-30 (a relative gain error ≤ 5e-8 at Ts = 1 ms
instead of 3e-5 in Q24). A Q30 constant times a Q24 word is exactly a Q54 number: the
controller's products are never rounded. The wire λ is the state rounded to Q24
(``narrow``).

Rounding: Q24·Q24 products (ξ, the finite-time power) and the Q54 → Q24 narrowing are
rounded to nearest, ties toward +∞ (add half an LSB, then arithmetic shift right). That
is one add and one shift on an MCU. Configuration constants are rounded to nearest, ties
to even (Python's ``round``).

Overflow: every result that can leave its range saturates to it and is counted by the
caller; nothing wraps silently. The state saturates to the Q54 image of the int32 range
(``saturate_state``), so its Q24 rounding always fits an int32.
"""

from __future__ import annotations

import math

from .errors import ParameterError

Q = 24
ONE = 1 << Q
INT32_MAX = (1 << 31) - 1
INT32_MIN = -(1 << 31)

# Controller constants (k·Ts, h·Ts, Ts) are int32 Q1.30; the state is Q(q + GUARD).
QC = 30
GUARD = QC                      # guard bits of the state over the wire format
STATE_MAX = INT32_MAX << GUARD  # the Q54 image of the int32 range (for q = 24)
STATE_MIN = INT32_MIN << GUARD


def check_q(q: int) -> int:
    """Validate a Q format's number of fractional bits for an int32 word."""
    if not isinstance(q, int) or isinstance(q, bool) or not 8 <= q <= 28:
        raise ParameterError("q", "an int number of fractional bits in [8, 28]", q)
    return q


def to_fixed(x: float, name: str = "value", q: int = Q) -> int:
    """Quantise a float to Q format (round to nearest); refuses values that do not fit."""
    raw = round(x * (1 << q))
    if not INT32_MIN <= raw <= INT32_MAX:
        lo, hi = INT32_MIN / (1 << q), INT32_MAX / (1 << q)
        raise ParameterError(name, f"a value in [{lo:g}, {hi:g}] (int32 Q{q})", x)
    return raw


def to_q30(x: float, name: str = "value") -> int:
    """Quantise a controller constant (k·Ts, h·Ts, Ts) to int32 Q1.30 (round to nearest,
    ties to even). Refuses negative values, values whose Q30 does not fit an int32
    (x ≥ 2 − 2**-31) and non-zero values below one LSB (they would quantise to 0)."""
    raw = round(x * (1 << QC)) if math.isfinite(x) else -1
    if not 0 <= raw <= INT32_MAX:
        raise ParameterError(name, "a value in [0, 2) (int32 Q1.30, at most "
                             "(2**31 − 1)·2**-30)", x)
    if x != 0 and x < 2.0 ** -QC:
        raise ParameterError(name, "0 or ≥ 2**-30 (one LSB of Q1.30)", x)
    return raw


def to_float(raw: int, q: int = Q) -> float:
    """The real value of a Q``q`` raw word (exact: the factor is a power of 2)."""
    return raw / (1 << q)


def saturate(x: int) -> tuple[int, bool]:
    """Clamp to int32. Returns (value, saturated?) so the caller counts it."""
    if x > INT32_MAX:
        return INT32_MAX, True
    if x < INT32_MIN:
        return INT32_MIN, True
    return x, False


def saturate_state(x: int) -> tuple[int, bool]:
    """Clamp a state word (λ, ν, Δλ) to [INT32_MIN·2**30, INT32_MAX·2**30], the Q54 image
    of the int32 Q24 range ("sat54"). Returns (value, saturated?) so the caller counts it."""
    if x > STATE_MAX:
        return STATE_MAX, True
    if x < STATE_MIN:
        return STATE_MIN, True
    return x, False


def narrow(x: int) -> int:
    """A state word rounded to the wire format: ``(x + 2**29) >> 30``, round to nearest,
    ties toward +∞. Fits an int32 for every saturated state word."""
    return (x + (1 << (GUARD - 1))) >> GUARD


def widen(raw: int) -> int:
    """A wire-format word as a state word (exact)."""
    return raw << GUARD


def mul(a: int, b: int, q: int = Q) -> int:
    """Q·Q → Q product, rounded to nearest (ties toward +∞). Not yet saturated."""
    return (a * b + (1 << (q - 1))) >> q


def sqrt_q(x: int, q: int = Q) -> int:
    """√x for x ≥ 0 in Q format, by integer square root (exact floor of the true root)."""
    from math import isqrt

    return isqrt(x << q)
