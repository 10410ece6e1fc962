"""The neighbours' MC frames of the lockstep, each lost at random (issue 23, loss tolerance).

At every sample each directed link j → i carries agent j's λ; with ``loss`` > 0 each frame
is lost independently with that probability (one seeded draw per sample for every link,
in the agents' and then their neighbours' order, so the per-agent loop and the arrays lose
the same frames). The receiver does what firmware_py's runtime does: it keeps the last λ
it heard, and drops the neighbour from ξ (XI-1) once that is more than the neighbour
timeout old (LIVE-2: alive while ``now − last_rx ≤ neighbour_periods·Ts``). The bus runs
have the same fault on real frames (``bess-ded agent --inject-rx-loss``).
"""

from __future__ import annotations

import numpy as np

from firmware_py.config import AgentConfig

NEVER = np.int64(1 << 40)  # samples since the last frame of a link that never carried one


class Links:
    """The links' last heard λ and their age in samples."""

    def __init__(self, n_links: int, loss: float = 0.0, seed: int = 0,
                 neighbour_periods: int = AgentConfig.neighbour_timeout_periods) -> None:
        if not 0.0 <= loss < 1.0:
            raise ValueError(f"loss: expected a probability in [0, 1), but got {loss!r}")
        self.loss, self.periods = loss, neighbour_periods
        self.rng = np.random.default_rng(seed)
        self.held: np.ndarray | None = None  # the sent values' dtype: Q24 words or floats
        self.age = np.full(n_links, NEVER, dtype=np.int64)
        self.lost = 0  # frames lost so far

    def exchange(self, sent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One sample: ``sent`` (the λ on each link) → (the λ each receiver holds, whether
        the neighbour is alive). Without loss: ``sent`` itself, every link alive."""
        if self.loss == 0.0:
            return sent, np.ones(len(sent), dtype=bool)
        got = self.rng.random(len(sent)) >= self.loss
        self.lost += int(len(sent) - got.sum())
        self.held = np.where(got, sent, sent if self.held is None else self.held)
        self.age = np.where(got, 0, self.age + 1)
        return self.held, self.age <= self.periods
