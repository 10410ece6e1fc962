"""argparse ``type=`` checkers shared by ``python -m firmware_py`` and ``bess-ded``.

Each factory returns a converter that raises argparse.ArgumentTypeError with an
"expected X, but got Y" message; argparse then prints ``PROG: error: argument
--name: expected a finite number > 0, but got -1`` and exits with 2. Here, not in
sim, so the agent entry point stays free of numpy/matplotlib.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def _number(text: str, expected: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, but got {text!r}") from None
    if not math.isfinite(x):  # float() takes "nan" and "inf"
        raise argparse.ArgumentTypeError(f"expected {expected}, but got {text}")
    return x


def float_in(lo: float = -math.inf, hi: float = math.inf, *, lo_open: bool = False,
             what: str = "a finite number") -> Callable[[str], float]:
    """A finite float in [lo, hi] (or (lo, hi] with ``lo_open``)."""
    bounds = []
    if lo > -math.inf and hi < math.inf and not lo_open:
        bounds.append(f"in [{lo:g}, {hi:g}]")
    elif lo > -math.inf:
        bounds.append(f"{'>' if lo_open else '≥'} {lo:g}")
    if hi < math.inf and not bounds[0:1] == [f"in [{lo:g}, {hi:g}]"]:
        bounds.append(f"≤ {hi:g}")
    expected = f"{what} {' and '.join(bounds)}".strip() if bounds else what

    def convert(text: str) -> float:
        x = _number(text, expected)
        if x < lo or x > hi or (lo_open and x == lo):
            raise argparse.ArgumentTypeError(f"expected {expected}, but got {text}")
        return x

    convert.__name__ = "number"  # argparse names the type in some of its messages
    return convert


def positive_float(what: str = "a finite number") -> Callable[[str], float]:
    """Durations, periods, rates, time scales: finite and > 0."""
    return float_in(0.0, lo_open=True, what=what)


# the longest a node, a run or a capture may be asked to last (27.8 h): larger values are
# typos (1e300 ran until killed), and a run's log must stay analysable
MAX_DURATION_S = 1e5
# the longest tick period (--period): Ts = 1 s (the scenarios' largest) at the largest scale
MAX_PERIOD_S = 1000.0
# the largest --time-scale: Ts = 10 ms stretched to 10 s per sample
MAX_TIME_SCALE = 1000.0


def duration_s(what: str = "a finite number") -> Callable[[str], float]:
    """--duration, --wait: > 0 and at most MAX_DURATION_S."""
    return float_in(0.0, MAX_DURATION_S, lo_open=True, what=what)


def time_scale(text: str) -> float:
    """--time-scale F: the time axis stretched by F, 1..MAX_TIME_SCALE (a slower host
    needs a larger Ts; a smaller one than the scenario's is not what the option means)."""
    return float_in(1.0, MAX_TIME_SCALE, what="a factor")(text)


def nonnegative_float(what: str = "a finite number") -> Callable[[str], float]:
    """Bands, delays, jitters: finite and ≥ 0."""
    return float_in(0.0, what=what)


def probability(text: str) -> float:
    """An argparse type: a float in [0, 1]."""
    return float_in(0.0, 1.0, what="a probability")(text)


def int_in(lo: int | None = None, hi: int | None = None, *, also: tuple[int, ...] = (),
           what: str = "an integer") -> Callable[[str], int]:
    """An integer in [lo, hi] (either end open when None), or one of ``also``
    (e.g. 0 = off for --rt-priority 1..99)."""
    if lo is not None and hi is not None:
        expected = f"{what} in {lo}..{hi}"
    elif lo is not None:
        expected = f"{what} ≥ {lo}"
    elif hi is not None:
        expected = f"{what} ≤ {hi}"
    else:
        expected = what
    if also:
        expected += " or " + " or ".join(map(str, also))

    def convert(text: str) -> int:
        try:
            x = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, but got {text!r}") from None
        if x in also:
            return x
        if (lo is not None and x < lo) or (hi is not None and x > hi):
            raise argparse.ArgumentTypeError(f"expected {expected}, but got {text}")
        return x

    convert.__name__ = "integer"
    return convert


def positive_int(what: str = "an integer") -> Callable[[str], int]:
    """Counts: ≥ 1."""
    return int_in(1, what=what)


RT_PRIORITY = int_in(1, 99, also=(0,), what="a SCHED_FIFO priority")
