"""The frame seam every node shares: receive checks and E2E transmit.

Agents, the plant and the router all receive the same way — reject what is not a
classic 11-bit data frame, tell their own frames echoed back (udp_multicast always
echoes) from a sender impersonating them, ignore DBC frames that are not for them,
count IDs the DBC does not define, decode with the CRC/DLC/range checks, then run the
E2E counter check — and they all transmit with a rolling counter per message.
``NodeIO`` does that once. Every rejection is counted in ``counters`` under its
cause, its reason kept in ``last_error``, and the first few logged in full.
"""

from __future__ import annotations

import logging
from collections import Counter, deque
from collections.abc import Iterable, Mapping

import can

from .frames import CounterTracker, DecodedFrame, FrameCodec

log = logging.getLogger(__name__)

LOG_FIRST = 5   # rejections logged in full per cause, then every 1000th
ECHO_DEPTH = 4  # own frames remembered to recognise their echo


class NodeIO:
    def __init__(self, codec: FrameCodec, who: str, own: Iterable[str],
                 wanted: Iterable[int]) -> None:
        """``own``: the messages this node sends; ``wanted``: the frame IDs it uses."""
        self.codec = codec
        self.who = who
        self.counters: Counter[str] = Counter()
        self.last_error: dict[str, str] = {}
        self._sent: dict[int, deque[bytes]] = {codec.frame_id(n): deque(maxlen=ECHO_DEPTH)
                                               for n in own}
        self.trackers = {fid: CounterTracker() for fid in wanted}
        self._known = codec.frame_ids()
        self._tx: Counter[str] = Counter()

    def accepted_ids(self) -> list[int]:
        """The IDs an acceptance filter must pass: what it uses and, for the impersonation
        check, what it sends."""
        return sorted(set(self._sent) | set(self.trackers))

    def receive(self, msg: can.Message) -> DecodedFrame | None:
        """The decoded frame if it is for this node and carries new data, else None
        (and, if it was bad, counted)."""
        fid = msg.arbitration_id
        if msg.is_extended_id:
            self.reject("unknown_id", f"0x{fid:X}: expected an 11-bit ID, but got an "
                        "extended ID")
            return None
        if msg.is_remote_frame or msg.is_error_frame or msg.is_fd:
            self.reject("malformed", f"0x{fid:03X}: expected a classic CAN data frame, but "
                        "got a remote, error or FD frame")
            return None
        sent = self._sent.get(fid)
        if sent is not None:
            if bytes(msg.data) not in sent:
                self.reject("impersonation", f"0x{fid:03X} carries {self.who}'s identity but "
                            "was not sent by it")
            return None
        tracker = self.trackers.get(fid)
        if tracker is None:
            if fid not in self._known:
                self.reject("unknown_id", f"0x{fid:03X}: expected an ID defined in the DBC")
            return None  # a DBC frame that is not for this node
        try:
            frame = self.codec.decode(msg)
        except Exception as e:  # FrameError: its cause names the counter
            cause = getattr(e, "cause", None)
            if cause is None:
                raise
            self.reject(cause, str(e))
            return None
        status = tracker.update(frame.counter)
        self.counters["lost_frames"] += status.lost
        if not status.new_data:
            self.counters["repeated_counter"] += 1
            return None
        return frame

    def reject(self, cause: str, reason: str) -> None:
        self.counters[cause] += 1
        self.last_error[cause] = reason
        n = self.counters[cause]
        if n <= LOG_FIRST or n % 1000 == 0:
            log.warning("%s rejected a frame (%s #%d): %s", self.who, cause, n, reason)

    def send(self, name: str, raw: Mapping[str, int]) -> can.Message:
        """Encode with the next rolling counter of ``name`` and remember it for the echo."""
        msg = self.codec.encode(name, raw, self._tx[name] % 16)
        self._tx[name] += 1
        self._sent[msg.arbitration_id].append(bytes(msg.data))
        return msg
