"""The tick bookkeeping the simulated nodes (plant, router) share."""

from __future__ import annotations

from collections import Counter


class SimNodeClock:
    """Mixin: ``counters``, ``note`` for run_node, and the time since the first tick."""

    counters: Counter[str]

    def _init_clock(self) -> None:
        self.t0: float | None = None
        self.t_last: float | None = None
        self.ticks = 0

    def note(self, event: str, count: int = 1) -> None:
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
