"""What the simulated nodes (plant, router) share: tick bookkeeping, fault windows."""

from __future__ import annotations

import math
from collections import Counter

from firmware_py.errors import ParameterError


class TimeWindow:
    """Mixin of an injected fault window: active for t_start ≤ t < t_end, in s from the
    node's first tick (the plant's --fault, the router's --silent)."""

    t_start: float
    t_end: float

    def check_window(self, what: str, node: str) -> None:
        """Refuse a window that is not 0 ≤ T0 < T1 (ParameterError naming ``what``)."""
        if not (math.isfinite(self.t_start) and self.t_start >= 0
                and self.t_end > self.t_start):  # also refuses a NaN end
            raise ParameterError(what, f"0 ≤ T0 < T1 (seconds from the {node}'s start)",
                                 f"{self.t_start}:{self.t_end}")

    def active(self, t_rel: float) -> bool:
        """True when ``t_rel`` (s from the node's first tick) is in [T0, T1)."""
        return self.t_start <= t_rel < self.t_end


class SimNodeClock:
    """Mixin: ``counters``, ``note`` for run_node, and the time since the first tick."""

    counters: Counter[str]

    def _init_clock(self) -> None:
        self.t0: float | None = None
        self.t_last: float | None = None
        self.ticks = 0

    def note(self, event: str, count: int = 1) -> None:
        """Count a runtime event reported by run_node."""
        self.counters[event] += count

    def _advance(self, t: float) -> tuple[float, float]:
        """Count a tick at ``t``; returns (s since the last tick, s since the first)."""
        if self.t0 is None:
            self.t0 = t
        dt = 0.0 if self.t_last is None else max(0.0, t - self.t_last)
        self.t_last = t
        self.ticks += 1
        return dt, t - self.t0

    @property
    def elapsed(self) -> float:
        """s from the first to the last tick (0 before two ticks)."""
        return 0.0 if self.t0 is None or self.t_last is None else self.t_last - self.t0
