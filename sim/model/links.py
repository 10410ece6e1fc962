"""The neighbours' MC frames of the lockstep, each lost at random (issue 23, loss tolerance).

At every sample each directed link j → i carries agent j's λ; with ``loss`` > 0 each frame
is lost independently with that probability (one seeded draw per sample for every link,
in the agents' and then their neighbours' order, so the per-agent loop and the arrays lose
the same frames). The receiver does what firmware_py's runtime does: it keeps the last λ
it heard, and drops the neighbour from ξ (XI-1) once that is more than the neighbour
timeout old (LIVE-2: alive while ``now − last_rx ≤ neighbour_periods·Ts``). The bus runs
have the same fault on real frames (``bess-ded agent --inject-rx-loss``).

``Transmitter``: which agents send at a sample (event-triggered transmission, TX-7); a
receiver holds the λ a silent neighbour last sent, as it holds a lost frame's.
"""

from __future__ import annotations

import numpy as np

from firmware_py.config import NEIGHBOUR_PERIODS, Transmit

NEVER = np.int64(1 << 40)  # samples since the last frame of a link that never carried one


class Links:
    """The links' last heard λ and their age in samples."""

    def __init__(self, n_links: int, loss: float = 0.0, seed: int = 0,
                 neighbour_periods: int = NEIGHBOUR_PERIODS) -> None:
        if not 0.0 <= loss < 1.0:
            raise ValueError(f"loss: expected a probability in [0, 1), but got {loss!r}")
        self.loss, self.periods = loss, neighbour_periods
        self.rng = np.random.default_rng(seed)
        self.held: np.ndarray | None = None  # the sent values' dtype: Q24 words or floats
        self.age = np.full(n_links, NEVER, dtype=np.int64)
        self.lost = 0  # frames lost so far

    def exchange(self, sent: np.ndarray, fresh: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """One sample: ``sent`` (the λ on each link) → (the λ each receiver holds, whether
        the neighbour is alive). ``fresh``: the links whose sender sent a frame at this
        sample (None: all; event-triggered senders skip some, Transmitter). Without loss:
        ``sent`` itself (a silent sender's value is the one it last sent), every link
        alive (a heartbeat comes before the timeout)."""
        if self.loss == 0.0:
            return sent, np.ones(len(sent), dtype=bool)
        got = self.rng.random(len(sent)) >= self.loss
        if fresh is not None:
            got &= fresh
        self.lost += int(len(sent) - got.sum())
        self.held = np.where(got, sent, sent if self.held is None else self.held)
        self.age = np.where(got, 0, self.age + 1)
        return self.held, self.age <= self.periods


class Transmitter:
    """The agents' MC transmission (firmware-spec TX-1, TX-7): periodic, every agent every
    sample; or event-triggered, an agent sends when its λ moved more than the threshold
    from the λ it last sent, when its State changes (``force``), and at least every
    ``heartbeat`` samples. Receivers use the value last sent (``publish``'s result)."""

    def __init__(self, n: int, tx: Transmit, threshold: float | int) -> None:
        self.event, self.heartbeat, self.threshold = tx.event, tx.heartbeat, threshold
        self.last: np.ndarray | None = None   # the λ each agent last sent
        self.age = np.zeros(n, dtype=np.int64)  # samples since then
        self.all = np.ones(n, dtype=bool)

    def publish(self, lam: np.ndarray, force: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """One sample: each agent's wire λ ``lam`` → (the λ its neighbours hold, whether it
        sent a frame). ``force``: agents whose State changes at this sample."""
        if not self.event:
            return lam, self.all
        self.age += 1
        if self.last is None:
            sent = self.all
        else:
            sent = (self.age >= self.heartbeat) | (np.abs(lam - self.last) > self.threshold)
            if force is not None:
                sent = sent | force
        self.last = lam.copy() if self.last is None else np.where(sent, lam, self.last)
        self.age[sent] = 0
        return self.last, sent
