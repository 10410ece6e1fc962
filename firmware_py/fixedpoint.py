"""Fixed-point arithmetic of the control core.

Formats (all stored as signed 32-bit integers, products formed in 64 bits, the
way a Cortex-M would do it with SMULL):

====================  ========  ===========================  ==================
quantity              format    LSB                          range
====================  ========  ===========================  ==================
λ, ρ (MC, price)      Q7.24     2**-24 ≈ 5.96e-8 cu/kWh      [-128, 128)
ξ (consensus error)   Q7.24     2**-24                       [-128, 128)
ν (integral of ξ)     Q7.24     2**-24 (cu/kWh·s)            [-128, 128)
u·Ts (λ increment)    Q7.24     2**-24                       [-128, 128)
k·Ts, h·Ts, Ts        Q7.24     2**-24                       (0, 128)
edge weights a_ij, b  Q7.24     2**-24                       (0, 128)
====================  ========  ===========================  ==================

λ is Q24 because it travels on the bus in that format (dbc/ declares the
factor 2**-24), so every node sees bit-identical values. Q24 keeps a λ increment
of k·Ts·ξ = 0.01·1e-5 above one LSB, which is what lets λ settle to 1e-6.

Rounding: products are rounded to nearest, ties toward +∞ (add half an LSB,
then arithmetic shift right). That is one add and one shift on an MCU.

Overflow: every result that can leave the int32 range saturates to it and is
counted by the caller; nothing wraps silently.
"""

from __future__ import annotations

from .errors import ParameterError

Q = 24
ONE = 1 << Q
HALF = 1 << (Q - 1)
INT32_MAX = (1 << 31) - 1
INT32_MIN = -(1 << 31)


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


def to_float(raw: int, q: int = Q) -> float:
    return raw / (1 << q)


def saturate(x: int) -> tuple[int, bool]:
    """Clamp to int32. Returns (value, saturated?) so the caller counts it."""
    if x > INT32_MAX:
        return INT32_MAX, True
    if x < INT32_MIN:
        return INT32_MIN, True
    return x, False


def mul(a: int, b: int, q: int = Q) -> int:
    """Q·Q → Q product, rounded to nearest (ties toward +∞). Not yet saturated."""
    return (a * b + (1 << (q - 1))) >> q


def sqrt_q(x: int, q: int = Q) -> int:
    """√x for x ≥ 0 in Q format, by integer square root (exact floor of the true root)."""
    from math import isqrt

    return isqrt(x << q)
