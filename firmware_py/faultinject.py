"""Receive-side fault injection for tests and HIL rigs: lose, delay and jitter frames.

A real bus loses and delays frames between a sender and *one* receiver; a
broadcast medium cannot be made to do that from outside. So the fault sits
where a flaky transceiver or a congested gateway would: between the bus and the
node's receive path. Only frames whose ID matches are affected (by default the MC
frames of the node's neighbours: the echo of its own frames is its own loopback, no
network path, so a delay there would only test how many sent payloads it recalls,
RX-3, against how long the host starves it); every injected
loss is counted here, and the firmware must notice it by itself (E2E counter).

Delay and jitter never reorder frames of one ID: CAN delivers one sender's frames
in order, so a frame is held until at least the release of the previous frame with
its ID (its hold stays within [delay, delay + jitter] all the same). Out-of-order
delivery would show up in the firmware as 15 lost frames (4-bit counter) plus stale
data, a fault a CAN link does not produce.
"""

from __future__ import annotations

import hashlib
import heapq
import itertools
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import can

from .contract import MC_BASE, N_AGENTS_MAX
from .node import RxTxBus


def neighbour_mc(own_agent: int | None) -> Callable[[can.Message], bool]:
    """Matches every AGENT_i_MC frame but the node's own (None: every one)."""
    own = None if own_agent is None else MC_BASE + own_agent
    return lambda m: (MC_BASE < m.arbitration_id <= MC_BASE + N_AGENTS_MAX
                      and m.arbitration_id != own)


def every_frame(msg: can.Message) -> bool:
    """Matches every frame a node receives (the bus runs' ``--loss`` fault mode)."""
    return True


def node_seed(seed: int, node: str) -> int:
    """The loss seed of one node of a run from the run's ``seed`` and the node's name
    (``agent_3``, ``plant``, ...): every node draws its own, reproducible sequence."""
    return int.from_bytes(hashlib.sha256(f"{seed}/{node}".encode()).digest()[:6], "big")


@dataclass
class RxFaults:
    """What FaultyBus does to the frames ``match`` selects: lose each with
    probability ``loss``, hold it ``delay`` plus up to ``jitter`` s; seeded."""

    loss: float = 0.0          # probability a matching frame is dropped
    delay: float = 0.0         # s, fixed delay added to matching frames
    jitter: float = 0.0        # s, extra uniform random delay in [0, jitter]
    seed: int = 0
    match: Callable[[can.Message], bool] = field(default_factory=lambda: neighbour_mc(None))
    # frames on an ID the node itself has sent (its echo: loopback, no network path)
    # pass untouched, whatever ``match`` says
    spare_own: bool = False

    @property
    def active(self) -> bool:
        """True when any fault is set (else the node reads its bus unwrapped)."""
        return self.loss > 0 or self.delay > 0 or self.jitter > 0


class FaultyBus:
    """Wraps a python-can bus; ``recv`` applies RxFaults, ``send`` passes through."""

    def __init__(self, bus: RxTxBus, faults: RxFaults,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not 0 <= faults.loss < 1:
            raise ValueError(f"loss: expected a probability in [0, 1), but got {faults.loss}")
        if faults.delay < 0 or faults.jitter < 0:
            raise ValueError("delay and jitter: expected ≥ 0 s")
        self.bus, self.faults, self.clock = bus, faults, clock
        self.rng = random.Random(faults.seed)
        self.pending: list[tuple[float, int, can.Message]] = []
        self.seq = itertools.count()
        self.last_release: dict[int, float] = {}  # per ID: keeps one sender's frames in order
        self.own: set[int] = set()  # the IDs sent through this wrapper (spare_own)
        self.matched = 0  # frames the faults applied to (dropped ones included)
        self.dropped = 0
        self.delayed = 0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Pass the frame on to the wrapped bus (faults are on the receive side only)."""
        self.own.add(msg.arbitration_id)
        self.bus.send(msg, timeout=timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame the faults let through within ``timeout`` (None: none):
        dropped frames are counted in ``dropped``, held ones in ``delayed`` and
        released in their ID's order."""
        end = None if timeout is None else self.clock() + timeout
        while True:
            now = self.clock()
            if self.pending and self.pending[0][0] <= now:
                return heapq.heappop(self.pending)[2]
            wait = None if end is None else max(0.0, end - now)
            if self.pending:
                due = self.pending[0][0] - now
                wait = due if wait is None else min(wait, due)
            msg = self.bus.recv(timeout=wait)
            if msg is not None:
                f = self.faults
                if f.match(msg) and not (f.spare_own and msg.arbitration_id in self.own):
                    self.matched += 1
                    if self.rng.random() < f.loss:
                        self.dropped += 1
                        continue
                    hold = f.delay + self.rng.uniform(0, f.jitter)
                    if hold > 0:
                        self.delayed += 1
                        fid = msg.arbitration_id
                        release = max(now + hold, self.last_release.get(fid, now))
                        self.last_release[fid] = release
                        heapq.heappush(self.pending, (release, next(self.seq), msg))
                        continue
                return msg
            if end is not None and self.clock() >= end and not (
                    self.pending and self.pending[0][0] <= self.clock()):
                return None

    def summary(self, who: str) -> str:
        """What it injected, as the node prints it at exit."""
        return (f"{who}: injected {self.dropped} losses of {self.matched} frames, "
                f"{self.delayed} delays")

    def shutdown(self) -> None:
        """Shut the wrapped bus down, if it has a shutdown."""
        shutdown = getattr(self.bus, "shutdown", None)  # a python-can bus, or a wrapper
        if shutdown is not None:
            shutdown()
