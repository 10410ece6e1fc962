"""What `bess-ded up`'s own process does while its nodes run: record every frame
(``Recorder``, its receive thread, writing through ``Cutoff`` to run.log), show the live
view (``Progress``) and read what the socket still queues after the stop (``drain``).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Sequence

import can

from firmware_py import contract
from firmware_py.errors import FrameError
from firmware_py.frames import FrameCodec
from firmware_py.node import GuardedBus
from sim.run.busopts import bus_socket, udp_drops
from sim.run.nodeprocs import START_TIMEOUT_S


class Progress(can.Listener):
    """Live view from the frames: max|λ−ρ| and frames per second."""

    def __init__(self, codec: FrameCodec, n: int) -> None:
        self.codec, self.n = codec, n
        self.rho: float | None = None
        self.lam: dict[int, float] = {}
        self.frames = 0
        self.t_last_frame = 0.0  # its timestamp (wall-clock)
        self.t_first_price: float | None = None
        self.seen: set[int] = set()  # every frame ID heard so far
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        """Count a recorded frame; keep ρ and each agent's λ for the live view."""
        fid = msg.arbitration_id
        with self.lock:
            self.frames += 1
            self.t_last_frame = msg.timestamp
            self.seen.add(fid)
            if fid != contract.ER_PRICE_ID and not 0 < fid - contract.MC_BASE <= self.n:
                return
            try:
                f = self.codec.decode(msg)
            except FrameError:
                return
            if f.name == "ER_Price":
                self.rho = f.phys("Rho")
                if self.t_first_price is None:
                    self.t_first_price = time.monotonic()
            elif f.agent is not None:
                self.lam[f.agent] = f.phys("Lambda")

    def error(self) -> float | None:
        """max|λ_i − ρ| over every agent heard, whatever its state (as the verdict judges)."""
        with self.lock:
            if self.rho is None or not self.lam:
                return None
            return max(abs(v - self.rho) for v in self.lam.values())



class Recorder:
    """The recorder's receive thread (in place of can.Notifier, which ends at the first
    exception python-can raises from recv): every frame goes to ``listeners``; what the
    bus delivers that is not a frame is counted by cause (GuardedBus, ``counters``) and
    the recording goes on."""

    def __init__(self, bus: can.BusABC, listeners: Sequence[can.Listener],
                 rt_priority: int = 0) -> None:
        self.bus = GuardedBus(bus, lambda cause: None, who="recorder")
        self.listeners = list(listeners)
        self.rt_priority = rt_priority
        # A recorder the host starves longer than its receive buffer lasts (record()
        # enlarges it: enlarge_receive_buffer) loses frames, in stretches the 4-bit
        # counters cannot show; the kernel's drops are counted (``rx_overflow``).
        self._socket = bus_socket(bus)
        self._overflow = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        # Above the nodes' SCHED_FIFO priority (``rt_priority``: theirs, 0: they run at
        # normal priority): at normal priority the recorder got only what 14 real-time
        # nodes left of 2 CPUs, and lost 2.3 s of frames at a stretch beside them.
        if self.rt_priority:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK,
                                      os.sched_param(min(self.rt_priority + 1, 99)))
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=0.1)
            if msg is not None:
                for listener in self.listeners:
                    listener.on_message_received(msg)

    def counters(self) -> dict[str, int]:
        """The inputs dropped so far, by cause (only those that occurred), the kernel's
        drops at a full receive buffer (``rx_overflow``) included."""
        out = {k: v for k, v in self.bus.counters.items() if v}
        if self._socket is not None and self._socket.fileno() >= 0:  # the bus still open
            self._overflow = udp_drops(self._socket)
        if self._overflow:
            out["rx_overflow"] = self._overflow
        return out

    def stop(self) -> None:
        """Stop the receive thread (within 5 s) and read the socket's drop count."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        if self._socket is not None and self._socket.fileno() >= 0:
            self._overflow = udp_drops(self._socket)



class Cutoff(can.Listener):
    """Pass frames to ``inner`` up to ``t_stop`` (frame time), once it is set."""

    def __init__(self, inner: can.Listener) -> None:
        self.inner = inner
        self.t_stop: float | None = None

    def on_message_received(self, msg: can.Message) -> None:
        """Pass ``msg`` on unless it is stamped after ``t_stop``."""
        if self.t_stop is None or msg.timestamp <= self.t_stop:
            self.inner.on_message_received(msg)

    def stop(self) -> None:
        """Stop (close) the inner listener."""
        self.inner.stop()



RECORDER_QUIET_S = 0.5  # the recorder is done when no frame came for this long


def drain(progress: Progress) -> None:
    """After the nodes have stopped, let the recorder read what its socket still queues:
    in the loaded QEMU guest it ran up to ~40 s behind the bus (case 7), and stopping
    it at once cut that off the log. Done when it has read a frame stamped after the
    stop (the queue is FIFO; other senders may go on) or nothing came for a while."""
    t_stop = time.time()  # frame timestamps are wall-clock
    deadline = time.monotonic() + START_TIMEOUT_S
    last, t_last = -1, time.monotonic()
    while time.monotonic() < deadline and progress.t_last_frame < t_stop:
        n = progress.frames
        if n != last:
            last, t_last = n, time.monotonic()
        elif time.monotonic() - t_last >= RECORDER_QUIET_S:
            return
        time.sleep(0.05)
