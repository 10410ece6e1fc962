"""The recorder's view of SecOC: every secured frame of a recording checked with the
run's keys as a receiver would (syncs included, AUTH-27's bound and undo too), with the
wider windows a recorder that misses frames needs. ``read_log`` (sim.run.buslog) runs
each frame of a log through one ``Monitor``; the test kit's Tester does so live."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Mapping

from firmware_py import contract
from firmware_py.contract import MC_CYCLE_S
from firmware_py.frames import DecodedFrame, target_agent
from firmware_py.nodeio import LOST_WINDOWS
from firmware_py.secoc import (
    FreshnessVerifier,
    beyond_boot_bound,
    frame_verifies,
    tags_verify,
)


def cycle_or_inf(name: str, ts: float) -> float:
    """The message's cycle in a run at sample time ``ts``; inf for event frames."""
    return contract.cycle_s(name, ts) if contract.is_cyclic(name) else math.inf


UNVOUCHED = -1  # Monitor._on_held: verifies on a held track nothing vouches for yet


class Monitor:
    """Checks the MAC and freshness of every secured frame with the run's keys, as a
    receiver would (syncs included), but with a wider window: a recorder misses frames.
    ``boot_floors`` (label → the lowest boot counter the sender may use in this
    recording): a sync of an earlier boot is a replay even before the sender's genuine
    sync is seen, the receiver-side state a node does not have (docs/security.md).

    Three outcomes for a secured frame (docs/firmware-spec.md AUTH-25):

    * fresh: its MAC verifies at most ``windows`` freshness windows ahead of the last
      accepted value, where ``windows`` grows with the time since that value (a sender
      sends one frame per cycle: 1 + RATE_MARGIN · elapsed / (16 cycles), at most
      MAX_WINDOWS: 4,096 frames, 10 s of a 10 ms sender at RATE_MARGIN). A forged frame
      in a flood (short elapsed time) gets one window, one chance in 2^24, as at a
      node; the recorder missing frames gets more (a starved recorder once lost 2.3 s,
      230 frames of each agent, beyond a node's LOST_WINDOWS);
    * stale (``Stale``): its MAC verifies with one of the STALE_WINDOWS windows at or
      below the last accepted value, at a value no frame carried yet (a frame already
      seen again is a replay): its sender's genuine frame, late (a capture that
      delivered it behind a newer one, or behind a forgery accepted by chance);
    * forged (``Forged``): neither.
    """

    RATE_MARGIN = 4       # a sender may burst up to 4x its cycle without being called forged
    STALE_WINDOWS = 2     # past windows tried (32 values): 2 CMACs, only for rejected frames
    MAX_WINDOWS = 256     # after a long silence: 256 CMACs at most, offline

    def __init__(self, keys: Mapping[str, bytes],
                 boot_floors: Mapping[str, int] | None = None,
                 cycle_of: Callable[[str], float] | None = None) -> None:
        self.keys = keys
        self.boot_floors = boot_floors or {}
        self.fv = FreshnessVerifier(tx_bits=contract.FV_TX_BITS)
        self.cycle_of = cycle_of or (lambda name: cycle_or_inf(name, MC_CYCLE_S))
        self.t_last: dict[int, float] = {}   # per secured ID: when its state last moved
        self.boots: dict[str, int] = {}  # label -> the boot of its latest verified sync
        self.spoke: set[int] = set()  # secured IDs with a frame since their `back`
        self.back: dict[int, int] = {}  # per secured ID: its value before its last boot advance
        # per secured ID: the value of a boot advance held until a frame verifies on it
        self.pending: dict[int, int] = {}
        # per secured ID: whether something beyond the MAC vouches for a boot (AUTH-33:
        # with signed_price, the router's price signature of that boot), as at the nodes
        self.vouches: dict[int, Callable[[int], bool]] = {}
        # syncs that undid a boot advance: their sender carried on in the boot it had left
        self.undone: Counter[str] = Counter()

    def _key(self, f: DecodedFrame) -> bytes | None:
        # AUTH-28..30: a link frame's or report's own key, a command's its target's
        target = f.raw.get("Target")
        return contract.frame_key(self.keys, f.name,
                                  None if target is None else target_agent(target))

    def _verifier(self, f: DecodedFrame, data: bytes | bytearray
                  ) -> Callable[[int], bool] | None:
        """Whether ``data`` verifies at a freshness value: its Mac under the frame's key,
        or on CAN FD every receiver's tag of a λ frame (AUTH-34); None: no key."""
        if f.tag_slots:
            sender = contract.sender_of(f.name.removesuffix("_Sync"))
            return lambda v: tags_verify(self.keys.get, sender, f.frame_id, data, v)
        key = self._key(f)
        if key is None:
            return None
        return lambda v: frame_verifies(key, f.frame_id, data, v)

    def sync(self, f: DecodedFrame, data: bytes | bytearray, t: float = 0.0) -> None:
        """Take a sync frame: its freshness becomes the sender's (raises ``StaleBoot``,
        ``SyncJump``, ``Stale`` or ``Forged`` when it does not verify as the newest). A
        sync that advances its ID's boot is held until a frame verifies on it (AUTH-35);
        one of the boot its ID is in drops a held advance, and one that undoes a boot
        advance taken (AUTH-27) is taken: either counts in ``undone``."""
        verifies = self._verifier(f, data)
        fv = contract.FRESHNESS.join(f.raw["Boot"], f.raw["Count"])
        fid = contract.SYNCED_BY[f.frame_id]
        label = contract.sender_of(f.name.removesuffix("_Sync"))
        floor = max(self.boot_floors.get(label, 0), self.boots.get(label, 0))
        verified = verifies is not None and verifies(fv)
        boot = f.raw["Boot"]
        last, back = self.fv.last(fid), self.back.get(fid)
        split = contract.FRESHNESS.split
        if verified and last is not None and contract.FRESHNESS.undoes_advance(fv, last, back):
            # AUTH-27, as the nodes do: the sender is alive in the boot a forged sync
            # advanced it from; back to its genuine freshness
            del self.back[fid]
            self._drop(fid, f.name, boot)
            self.fv.forget(fid)
            self.fv.accept(fid, fv - 1, frame=False)
            self.boots[label] = boot
            self.t_last[fid] = t
            self.undone[f.name] += 1
            return
        # below the sender's floor, unless this ID is still in that boot (another of the
        # sender's IDs taken to a later boot by a forged sync must not condemn it)
        if verified and boot < floor and (last is None or boot < split(last + 1)[0]):
            raise StaleBoot(label, boot, floor)
        known = self.boots.get(label, self.boot_floors.get(label))
        if verified and known is not None and beyond_boot_bound(boot, known):
            raise SyncJump  # a key holder's forged boot, refused as the nodes do (AUTH-27)
        if (verified and last is not None and boot == split(last + 1)[0]
                and fv - 1 - last > self._reach(fid, f.name.removesuffix("_Sync"), t)):
            raise SyncJump  # a count no frame could reach: forged, as the nodes refuse it
        if verified:
            if last is not None and boot > split(last + 1)[0]:
                self._drop(fid, f.name, boot)  # one held of a later boot was forged
                self.pending[fid] = fv - 1  # AUTH-35: held until a frame verifies on it
                return
            if last is not None and fv - 1 >= last:
                self._drop(fid, f.name, boot)  # its sender is in the boot its ID is in
            self.boots[label] = boot
            if last is None or fv - 1 > last:
                self.fv.accept(fid, fv - 1, frame=False)
            if last is None or fv - 1 >= last:
                self.t_last[fid] = t
                return
            if self.fv.late_sync(last - (fv - 1)):
                raise Stale  # its tick's frame overtook it (AUTH-16, AUTH-25)
        raise Forged  # forged, or a replayed sync (a genuine one never goes back)

    def _drop(self, fid: int, name: str, boot: int) -> None:
        """AUTH-35: a held boot advance of ``fid`` later than ``boot``, the boot of a
        verified sync of its sender (which never goes back): forged, dropped and counted
        in ``undone``, as the nodes do."""
        held = self.pending.get(fid)
        if held is not None and contract.FRESHNESS.split(held + 1)[0] > boot:
            del self.pending[fid]
            self.undone[name] += 1

    def _on_held(self, f: DecodedFrame, verifies: Callable[[int], bool],
                 t: float) -> int | None:
        """AUTH-35: a frame that failed its window, tried on its ID's held boot advance:
        its value if it verifies there and the advance is taken as the nodes take it
        (AUTH-27's ``back`` set); UNVOUCHED if it verifies there but ``vouches`` does not
        vouch for that boot (the nodes' ``unsynced``: held still); None if neither."""
        fid, pending = f.frame_id, self.pending.get(f.frame_id)
        if pending is None:
            return None
        track = FreshnessVerifier(tx_bits=contract.FV_TX_BITS, initial={fid: pending})
        fv = track.search(fid, f.counter, self.windows(f, t), verifies)
        if fv is None:
            return None
        boot = contract.FRESHNESS.split(fv)[0]
        if (check := self.vouches.get(fid)) is not None and not check(boot):
            return UNVOUCHED
        del self.pending[fid]
        last = self.fv.last(fid)
        if fid in self.spoke or fid not in self.back:  # as the nodes (AUTH-27)
            assert last is not None
            self.back[fid] = last
        self.spoke.discard(fid)
        self.fv.accept(fid, pending, frame=False)
        self.boots[contract.sender_of(f.name)] = boot
        return fv

    def windows(self, f: DecodedFrame, t: float) -> int:
        """Freshness windows a frame at ``t`` may lie ahead (the class docstring)."""
        return self._windows(f.frame_id, f.name, t)

    def _reach(self, fid: int, name: str, t: float) -> int:
        """The counts a sync of ID ``fid`` at ``t`` may move it ahead (AUTH-27): what its
        frames could have advanced by since the last one heard."""
        return self._windows(fid, name, t) << contract.FV_TX_BITS

    def _windows(self, fid: int, name: str, t: float) -> int:
        t_last, cycle = self.t_last.get(fid), self.cycle_of(name)
        if t_last is None or not math.isfinite(cycle):
            return LOST_WINDOWS   # an event frame (ER_Command): no rate to bound it by
        frames = self.RATE_MARGIN * max(t - t_last, 0.0) / cycle
        return min(self.MAX_WINDOWS, 1 + int(frames) // (1 << contract.FV_TX_BITS))

    def check(self, f: DecodedFrame, data: bytes | bytearray, t: float = 0.0) -> bool:
        """True: authentic and fresh; False: not checkable yet (no sync seen); raises
        ``Stale`` (genuine, late) or ``Forged``."""
        verifies = self._verifier(f, data)
        if verifies is None or self.fv.last(f.frame_id) is None:
            return False
        fv = self.fv.search(f.frame_id, f.counter, self.windows(f, t), verifies)
        if fv is None:
            fv = self._on_held(f, verifies, t)
            if fv == UNVOUCHED:
                return False  # on a held track nothing vouches for yet: not checkable
        if fv is not None:
            self.fv.accept(f.frame_id, fv)
            self.spoke.add(f.frame_id)  # a frame since the latest boot advance
            self.t_last[f.frame_id] = t
            return True
        if self.fv.search_late(f.frame_id, f.counter, self.STALE_WINDOWS, verifies):
            raise Stale
        raise Forged


class SyncJump(Exception):
    """``Monitor``: a verified sync whose boot lies more than SYNC_BOOT_JUMP_MAX above the
    highest its sender used (or its boot at the run's start): refused (AUTH-27)."""


class Forged(Exception):
    """``Monitor``: a frame whose MAC verifies in no window (forged, or a replayed sync)."""


class Stale(Exception):
    """``Monitor``: a genuine frame, late (its MAC verifies at or below the last value)."""


class StaleBoot(Exception):
    """``Monitor``: a verified sync of a boot below the sender's floor (AUTH-21)."""

    def __init__(self, label: str, boot: int, floor: int) -> None:
        super().__init__(label)
        self.label, self.boot, self.floor = label, boot, floor
