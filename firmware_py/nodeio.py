"""The frame seam every node shares: receive checks and secured transmit.

Agents, the plant and the router all receive the same way — reject what is not a
classic 11-bit data frame, tell their own frames echoed back (udp_multicast always
echoes) from a sender impersonating them, ignore DBC frames that are not for them,
count IDs the DBC does not define, decode with the DLC/range checks, then verify the
MAC and freshness — and they all transmit signed frames with a freshness value per
message. Every input is a secured frame (the DBC has no E2E-only frame: no CRC, no
rolling-counter rules). ``NodeIO`` does that once. Every rejection is counted in
``counters`` under its cause, its reason kept in ``last_error``, and the first few
logged in full.

Foreign traffic: frames that cannot come from the node's own fleet are counted under
``foreign`` and under one of these causes (their data is never used):

* ``impersonation``: a frame on one of the node's own IDs that it did not send;
* ``foreign_id``: a per-agent DBC frame of an agent outside the run (AGENT_9_MC in a
  4-agent run), when the node knows the fleet size (counted before any decode: no
  node of the run sends on that ID, whatever its payload).

Untrusted sources (docs/safety-model.md, RX-13): ``untrusted_after`` (5, as opendbc's
safety layer) consecutive failures — DLC, range, ``auth``, and the range checks a node
runs after decoding (``fail``) — on one source ID make that ID untrusted for
``untrusted_s`` (1 s at Ts = 10 ms): an alarm (``untrusted_sources`` counts the
verdicts, logged at warning level, ``last_safety`` names the ID). Frames on it are not
blocked: a secured frame's MAC proves its sender frame by frame, so the genuine
sender's frames keep being used while a forger's keep failing (else a forger could
silence any sender with five bad frames). A frame accepted before the streak reaches
the limit resets it; when the time is up the ID starts with a clean streak.

Authentication (docs/security.md). Secured frames (``contract.SECURED_IDS``: price,
command, MC, setpoint, status) are signed on ``send`` with the node's key and a
freshness value Boot ‖ Count per frame ID (the Counter signal is its low 4 bits), and
checked on ``receive`` with the claimed sender's verification key from the node's
``Keyring``: the full freshness value is rebuilt from the last one accepted on that
ID (window of 16) and the MAC must verify, else the frame is rejected under ``auth``
(a streak cause: it adds to the untrusted streak, and names the claimed sender in
``last_safety``). Before the first ``<name>_Sync`` of a sender, its frames are
rejected under ``unsynced``. Syncs move the state forward only; each node sends
its own at start, every ``sync_s``, and again when it hears a peer (re)start, so a
late or restarted node is heard within one round trip. After a sender timed out
(``sender_lost``), its next frames may lie beyond the window: up to
``LOST_WINDOWS`` windows are tried, and frames that still fail count as
``unsynced`` until its next sync, not as forgeries.

Join window (AUTH-26). A sync replayed from earlier in a peer's current boot passes the
boot floors; so for ``join_s`` (0.2 s: two hello periods) after its first own syncs a node
keeps each sender's newest verified sync and takes no frame (counted ``joining``: what
every start does, not an anomaly), then takes
the newest one with the sender marked lost: every live peer's answer to its hello has
superseded a replayed sync by then.

Bounded boot advance (AUTH-27). A verified sync more than ``SYNC_BOOT_JUMP_MAX`` (8) boots
ahead of the sender's expected boot is refused (``sync_jump`` and ``auth``): a key holder
could otherwise lock a sender out for good with one sync of boot 65535. One within the
bound is taken, the value before it kept; a later sync of the sender in the boot it had
left (newer than anything taken of it) undoes the advance (``sync_jump``).

Pending boot advance (AUTH-35). A verified sync that advances the boot of an input in
step (not lost) is held, not taken: a frame that then fails its window is tried once on
the held track, and if it verifies there its sender did restart and the advance is taken.
The sender's next sync of the boot the input is in drops it (``sync_jump``): a forged
sync, even under the sender's own key, moves no receiver. A timeout drops it too (the
lost sender's next sync is taken as it comes).

Late is not forged. A frame that fails the window is tried once more, with the most
recent freshness value at or below the last accepted one that has its low bits
(``STALE_WINDOWS`` = 1 window: the 16 values up to the last accepted, one CMAC, spent
only on frames already rejected), unless a frame with that value was accepted (then
it is a replay or a duplicate: ``auth``, no CMAC). If its MAC verifies there, it is its
sender's genuine frame delivered late or out of order (skipped as lost, then
delivered): counted ``stale``, never used, not a streak cause (no untrusted streak), not
``auth``. Only a frame that verifies nowhere, or repeats an accepted one, is ``auth``.
"""

from __future__ import annotations

import logging
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, NamedTuple

import can

from . import contract
from .errors import ConfigError, EncodeError, FrameError
from .frames import DecodedFrame, FrameCodec, agent_of, format_fault, target_agent
from .secoc import (
    INSECURE_BOOT,
    INSECURE_MASTER,
    SYNC_BOOT_JUMP_MAX,
    FreshnessVerifier,
    Keyring,
    beyond_boot_bound,
    derive_command_key,
    derive_frame_key,
    derive_lambda_tag_key,
    derive_node_key,
    frame_tag,
    frame_verifies,
    pair_label,
    sign_frame,
    sign_tags,
    tag_code,
)

log = logging.getLogger(__name__)

LOG_FIRST = 5   # rejections logged in full per cause, then every 1000th
ECHO_DEPTH = 4  # own frames remembered to recognise their echo (an agent: BD_ECHO_DEPTH)
# the router and the plant, Python processes on a host whose loop may lag its socket: under
# load an echo came back behind 4 later sends of its ID (a false impersonation, CI
# 2026-11-27, case 7 on udp_multicast beside stress-ng); 64 ER_Price frames are 3.2 s
HOST_ECHO_DEPTH = 64
UNTRUSTED_AFTER = 5   # consecutive receive failures from one source ID ...
UNTRUSTED_S = 1.0     # ... make it untrusted this long (s; callers stretch it with Ts)
# the causes that count towards the untrusted streak of the frame's ID (RX-13)
STREAK_CAUSES = frozenset({"dlc", "range", "auth"})
SYNC_S = contract.cycle_ms("ER_Price_Sync") / 1000.0  # a sender's sync cadence (1 s)
HELLO_FRACTION = 0.1  # re-announce own syncs at most every 0.1 sync_s when a peer (re)starts
# AUTH-26: after its first own syncs (its hello) a node keeps the newest sync of each sender
# this long before it takes any: two hello periods, so every live peer's answer is in
JOIN_FRACTION = 2 * HELLO_FRACTION
LOST_WINDOWS = 8      # freshness windows tried after a sender timed out (8·16 frames)
STALE_WINDOWS = 1     # past windows tried before a frame is called forged (16 values)
_FV_WINDOW = 1 << contract.FV_TX_BITS
LOST_SEARCH_COUNTS = LOST_WINDOWS * _FV_WINDOW  # the counts a receiver's widest search covers
_COUNT_MAX = contract.FRESHNESS.max_counter


class SyncSchedule(NamedTuple):
    """When a node's own syncs are next due: every ``sync_s`` and, after a peer
    (re)started, a re-announce (hello) not before ``hello_after``."""

    next: float | None   # None: at the node's first call of syncs()
    hello_due: bool
    hello_after: float


def _reached(t: float, when: float) -> bool:
    """``t`` at or after ``when``, both in whole ns as firmware_c keeps time: a sum of
    floats (a send time plus a period) can land one ulp past the tick it names, where
    the C node's sum of ns lands on it."""
    return round(t * 1e9) >= round(when * 1e9)


class NodeIO:
    """A node's secured receive and transmit path: decode and range-check every frame,
    verify its MAC and freshness, recognise its own echo, count every rejection by
    cause, and sign what it sends (docs/firmware-spec.md, RX and AUTH)."""

    def __init__(self, codec: FrameCodec, who: str, own: Iterable[str],
                 wanted: Iterable[int], fleet_size: int | None = None,
                 untrusted_after: int = UNTRUSTED_AFTER,
                 untrusted_s: float = UNTRUSTED_S, keys: Keyring | None = None,
                 sync_s: float = SYNC_S, join_s: float | None = None,
                 echo_depth: int = ECHO_DEPTH, transfers: Iterable[int] = (),
                 tag_receivers: Sequence[str] = (), timed: Iterable[int] = ()) -> None:
        """``own``: the messages this node sends (the last ``echo_depth`` of each ID are
        remembered: their echo is not an impersonation); ``wanted``: the frame IDs it uses
        (secured ones: ConfigError for any other);
        ``fleet_size``: the agents of the run (None: unknown, per-agent IDs of any agent
        the DBC defines are then not counted as foreign); ``untrusted_after`` consecutive
        receive failures on one ID make it untrusted for ``untrusted_s``; ``keys``: this
        node's keyring (None: the public ``--insecure`` keys, with a warning); ``sync_s``:
        its sync cadence (the DBC's, stretched like every cycle in a time-scaled run);
        ``join_s``: its join window (AUTH-26; None: JOIN_FRACTION·sync_s, 0: none, for
        tests of a receiver alone); ``transfers``: the IDs of transfer frames (no MAC:
        ER_PriceSig, signed_price) it takes, decoded and handed over unverified (the
        caller verifies their signature); ``tag_receivers``: on CAN FD, the receivers of
        its λ in slot order (AUTH-34: its neighbours by index, the plant, the router);
        ``timed``: the inputs whose sender a timeout of this node marks lost
        (``sender_lost``): a sync moves them at most a frame's reach while in step
        (AUTH-27)."""
        own = list(own)
        label = contract.sender_of(own[0])
        if keys is None:
            keys = Keyring.insecure_for(label)
        if keys.node != label:
            raise ConfigError("keyring", "node", f"expected the key of {label}, but got "
                              f"the key of {keys.node}")
        if keys.insecure:
            log.warning("%s runs INSECURE: its frames are signed with the public demo key, "
                        "anyone on the bus can forge them (docs/security.md)", who)
        self.keys = keys
        self.codec = codec
        self.untrusted_after = untrusted_after
        self.untrusted_s = untrusted_s
        self._streak: Counter[int] = Counter()
        self._untrusted_until: dict[int, float] = {}
        self.last_safety: tuple[str, int] | None = None  # (cause, claimed sender ID)
        self.safety_rejections = 0
        self.who = who
        self.fleet_size = fleet_size
        self.counters: Counter[str] = Counter()
        self.last_error: dict[str, str] = {}
        self._sent: dict[int, deque[bytes]] = {codec.frame_id(n): deque(maxlen=echo_depth)
                                               for n in own}
        wanted = list(dict.fromkeys(wanted))
        self._transfers = frozenset(transfers)
        # per input ID, a check of the decoded frame before its MAC and freshness
        # (signed_price, AUTH-33): a frame it refuses never moves its sender's freshness
        self._prechecks: dict[int, Callable[[DecodedFrame], tuple[str, str] | None]] = {}
        # AUTH-33, AUTH-35: per input, whether something beyond its MAC vouches for a boot
        # (the router's price signature of that boot, with signed_price)
        self._vouches: dict[int, Callable[[int], bool]] = {}
        self._inputs = frozenset(wanted)
        unsecured = sorted(self._inputs - contract.SECURED_IDS)
        if unsecured:
            raise ConfigError("inputs", who, "expected secured input IDs (DBC frames with a "
                              "Mac), but got " + ", ".join(f"0x{f:03X}" for f in unsecured))
        # SecOC, transmit: one message counter per own secured ID under this boot
        self._tx_count = {fid: 0 for fid in self._sent if fid in contract.SECURED_IDS}
        for fid in self._tx_count:
            self._sent[contract.SYNC_OF[fid]] = deque(maxlen=echo_depth)
        # AUTH-28, AUTH-29: a link frame or report is signed with its own key, a
        # broadcast with the node's; each sync with its frame's key (AUTH-30: the router's
        # node key for ER_Command_Sync, its frames take their target's command key)
        # AUTH-34: on CAN FD the λ frames and their syncs carry a tag per receiver, each
        # under the pair key of (sender, receiver): no key of a third node tags them
        self._tagged = frozenset(f for f in codec.frame_ids()
                                 if codec.tag_slots(codec.name_of(f)))
        self._tag_code = tag_code(keys.node)
        self._sign_key = {fid: self._key_of(fid, "this node sends it", sync=True)
                          for fid in self._tx_count}
        self._tag_keys = {fid: self._tags_for(fid, list(tag_receivers))
                          for fid in self._tx_count if fid in self._tagged}
        self._command_keys: dict[int, bytes] = {}
        if contract.ER_COMMAND_ID in self._tx_count and fleet_size is not None:
            for i in contract.agent_ids(fleet_size):  # every target's key, at the start
                self._command_key(i)
        self.boot = keys.new_boot() if self._tx_count else keys.boot
        self.sync_s = sync_s
        self._sync_next: float | None = None      # None: at the first call of syncs()
        self._hello_after = -1.0                   # earliest time of a re-announce
        self._hello_due = False
        self.join_s = JOIN_FRACTION * sync_s if join_s is None else join_s
        self._join_until: float | None = None      # None: before its hello
        self._resync_after: dict[int, int] = {}    # own ID -> counts that make a sync due
        self._count_at_sync = dict(self._tx_count)
        # input ID -> the newest sync's FV while joining; None: joined
        self._joining: dict[int, int] | None = {} if self.join_s > 0 else None
        # SecOC, receive: the verification key and freshness state of each secured ID
        self._verify_key = {
            fid: self._key_of(fid, f"sent by {contract.sender_of(codec.name_of(fid))}",
                              "verification key") for fid in wanted}
        self._sync_key = {
            fid: self._key_of(fid, f"sent by {contract.sender_of(codec.name_of(fid))}",
                              "verification key", sync=True) for fid in wanted}
        self._synced_by = {contract.SYNC_OF[fid]: fid for fid in self._verify_key}
        # AUTH-30: the agent this node is (its commands' Target), None for the plant and
        # the router
        self._target = (int(keys.node.removeprefix("agent_"))
                        if keys.node.startswith("agent_") else None)
        self._fv = FreshnessVerifier(tx_bits=contract.FV_TX_BITS)
        self._lost: set[int] = set()  # secured IDs whose sender timed out
        self._timed = frozenset(timed) & self._inputs  # ... that a timeout can mark lost
        # AUTH-27: per secured input, the last value before its latest boot advance
        self._back: dict[int, int] = {}
        self._spoke: set[int] = set()  # secured IDs with a frame taken since their `back`
        # AUTH-35: per secured input in step, the value a verified boot advance announced,
        # held until a frame verifies on it (the sender did restart)
        self._pending: dict[int, int] = {}
        self._peer_boot: dict[int, int] = {}  # sync ID of a frame not used -> its boot
        if keys.insecure:  # every insecure sender starts at boot 1, count 0: no sync needed
            self._joining = None  # and no replay protection to join for
            for fid in self._verify_key:
                self._fv.accept(fid, contract.FRESHNESS.join(INSECURE_BOOT, 0) - 1,
                                frame=False)
                self._lost.add(fid)  # a sender already running: its sync, not a forgery
        self._known = codec.frame_ids()

    def _tags_for(self, fid: int, receivers: list[str]) -> list[tuple[int, bytes]]:
        """AUTH-34: (receiver code, pair key) for each receiver of own tagged frame
        ``fid``, in slot order; ConfigError if they do not fit its slots or a key is
        missing."""
        name = self.codec.name_of(fid)
        slots = self.codec.tag_slots(name)
        if not 0 < len(receivers) <= slots:
            raise ConfigError("neighbours", self.who, f"expected 1..{slots} receivers of "
                              f"{name}'s tags on CAN FD ({slots - 2} neighbours at most, the "
                              f"plant and the router), but got {len(receivers)}")
        out = []
        for r in receivers:
            k = self.keys.tag_key(self.keys.node, r)
            if k is None:
                raise ConfigError("keyring", self.keys.node, f"expected the λ tag key "
                                  f"{self.keys.node}>{r} ({name} on CAN FD), but the key "
                                  "file has none: re-provision with bess-ded keys")
            out.append((tag_code(r), k))
        return out

    def _code_for(self, fid: int) -> int | None:
        """AUTH-34: this node's receiver code if input ``fid`` is tagged, else None."""
        return self._tag_code if fid in self._tagged else None

    def _key_of(self, fid: int, why: str, what: str = "key", sync: bool = False) -> bytes:
        """The keyring's key of message ``fid`` (``sync``: of its ``<name>_Sync``; AUTH-28,
        AUTH-29: a link frame's or report's own, AUTH-30: ER_Command's this agent's
        command key, AUTH-34: a tagged λ's pair key of its sender and this node, else its
        sender's); ConfigError naming ``what`` and ``why`` if the key file has none."""
        name = self.codec.name_of(fid) + ("_Sync" if sync else "")
        if fid in self._tagged and fid not in self._tx_count:  # a λ it receives
            k = self.keys.tag_key(contract.sender_of(self.codec.name_of(fid)), self.keys.node)
        else:
            k = self.keys.key_for(name)
        if k is None:
            raise ConfigError("keyring", self.keys.node, f"expected the {what} of {name} "
                              f"({why}), but the key file has none: re-provision with "
                              "bess-ded keys")
        return k

    def _command_key(self, target: int) -> bytes:
        """AUTH-30: the key of the router's ER_Command to agent ``target``."""
        k = self._command_keys.get(target)
        if k is None:
            k = self.keys.key_for(contract.COMMAND, target=target)
            if k is None:
                raise ConfigError("keyring", self.keys.node, f"expected the command key of "
                                  f"agent_{target} (ER_Command to it), but the key file has "
                                  "none: re-provision with bess-ded keys")
            self._command_keys[target] = k
        return k

    @property
    def inputs(self) -> tuple[int, ...]:
        """The secured IDs this node uses (``wanted``, in its order)."""
        return tuple(self._verify_key)

    @property
    def joining(self) -> bool:
        """In its join window (AUTH-26), where any frame received may close it."""
        return self._joining is not None

    def ignores(self, fid: int) -> bool:
        """A classic data frame on ``fid`` is one ``receive`` drops uncounted and without
        effect once the node has joined: a DBC frame of its fleet for other nodes. A host
        of agents (firmware_py.host) does not hand those over: ~87 % of what a 32-agent
        bus carries, for each agent."""
        return (fid not in self._sent and fid not in self._inputs
                and fid not in self._transfers and fid not in self._synced_by
                and fid not in contract.PEER_SYNCED_BY
                and fid in self._known
                and (self.fleet_size is None or (agent_of(fid) or 0) <= self.fleet_size))

    def accepted_ids(self) -> list[int]:
        """The IDs an acceptance filter must pass: what it uses (and the syncs of it), the
        syncs of the fleet's other nodes whose keys it holds (the router and the plant: to
        notice a restart, ``_peer_sync``) and, for the impersonation check, what it sends."""
        taken = {contract.sender_of(self.codec.name_of(fid)) for fid in self._verify_key}
        peers = set()
        for sid, fid in contract.PEER_SYNCED_BY.items():
            sender = contract.sender_of(self.codec.name_of(fid))
            if (sender not in taken and sender != self.keys.node
                    and (self.fleet_size is None or (agent_of(sid) or 0) <= self.fleet_size)
                    and self.keys.key_for(self.codec.name_of(sid), derive=False)
                    is not None):
                peers.add(sid)
        return sorted(set(self._sent) | self._inputs | set(self._synced_by) | peers
                      | self._transfers)

    def receive(self, msg: can.Message, t: float | None = None,
                defer_trust: bool = False) -> DecodedFrame | None:
        """The decoded frame if it is for this node and carries new data, else None
        (and, if it was bad, counted). ``t``: the receive time, for the freshness and
        untrusted-source rules (None: ``msg.timestamp``). A returned frame resets its ID's
        untrusted streak, unless ``defer_trust``: then the caller, which runs checks of its
        own, calls ``trusted`` once the frame passed them (or ``fail``)."""
        fid = msg.arbitration_id
        if t is None:
            t = msg.timestamp
        if self._joining is not None:
            self._settle(t)
        if msg.is_extended_id:
            self.reject("unknown_id", f"0x{fid:X}: expected an 11-bit ID, but got an "
                        "extended ID")
            return None
        if msg.is_remote_frame or msg.is_error_frame or msg.is_fd != self.codec.fd:
            # LOOP-6: a bus carries one frame format, the DBC's (classic or its FD twin)
            self.reject("malformed", f"0x{fid:03X}: {format_fault(msg, self.codec.fd)}")
            return None
        sent = self._sent.get(fid)
        if sent is not None:
            if bytes(msg.data) not in sent:
                self.foreign("impersonation", f"0x{fid:03X} carries {self.who}'s identity but "
                             "was not sent by it")
            return None
        key = self._verify_key.get(fid)
        if key is None:
            if fid in self._transfers:  # signed_price: its signature is the caller's to check
                page = self._decoded(msg)
                if isinstance(page, FrameError):
                    self.reject("sig_malformed", f"{page} ({page.cause})")
                    return None
                return page
            if fid in self._synced_by:
                self._on_sync(msg, fid, t)
                return None
            if fid in contract.PEER_SYNCED_BY and self._peer_sync(msg, fid, t):
                return None
            if fid not in self._known:
                self.reject("unknown_id", f"0x{fid:03X}: expected an ID defined in the DBC")
            elif self.fleet_size is not None and (agent_of(fid) or 0) > self.fleet_size:
                self.foreign("foreign_id", f"0x{fid:03X}: expected agents 1..{self.fleet_size} "
                             f"of this run, but got a frame of agent {agent_of(fid)}")
            return None  # a DBC frame that is not for this node
        until = self._untrusted_until.get(fid)
        if until is not None and t >= until:  # an untrusted input is not blocked (RX-13)
            del self._untrusted_until[fid]
            log.info("%s trusts 0x%03X again (its untrusted time is over)", self.who, fid)
        frame = self._decoded(msg)
        if isinstance(frame, FrameError):
            self.fail(fid, frame.cause, str(frame), t)
            return None
        if (fid == contract.ER_COMMAND_ID
                and target_agent(frame.raw["Target"]) != self._target):
            return None  # AUTH-30: a command to another agent, under a key it lacks: not for it
        precheck = self._prechecks.get(fid)
        if precheck is not None and (refused := precheck(frame)) is not None:
            self.reject(*refused)
            return None
        return self._authentic(frame, msg, key, t, defer_trust)

    def _decoded(self, msg: can.Message) -> DecodedFrame | FrameError:
        """``msg`` decoded, or the FrameError that refused it (its cause names the
        counter); any other exception is a bug and propagates."""
        try:
            return self.codec.decode(msg)
        except FrameError as e:
            return e

    def precheck(self, fid: int,
                 check: Callable[[DecodedFrame], tuple[str, str] | None]) -> None:
        """Run ``check`` on every decoded frame of input ``fid`` before its MAC and
        freshness: a (cause, reason) it returns rejects the frame under that cause, its
        freshness untouched (AUTH-33: a price that is not the signed one cannot move the
        router's counter ahead of its genuine frames)."""
        if fid not in self._inputs:
            raise KeyError(fid)
        self._prechecks[fid] = check

    def vouch(self, fid: int, check: Callable[[int], bool]) -> None:
        """Take a held boot advance of input ``fid`` (AUTH-35) only when ``check(boot)``
        holds besides its frame's MAC: a frame verifying on a held track ``check`` does not
        vouch for is ``unsynced``, the advance still held (AUTH-33: with signed_price, the
        router's signature of that boot; a key holder forges the MAC, not the
        signature)."""
        if fid not in self._inputs:
            raise KeyError(fid)
        self._vouches[fid] = check

    # ------------------------------------------------------------ SecOC

    def _authentic(self, frame: DecodedFrame, msg: can.Message, key: bytes, t: float,
                   defer_trust: bool) -> DecodedFrame | None:
        """A decoded secured frame if its MAC verifies with a fresh freshness value."""
        fid = frame.frame_id
        last = self._fv.last(fid)
        if last is None:
            if self._joining is not None:
                self.reject("joining", f"{frame.name}: joining (for {self.join_s:g} s after "
                            "its start the node keeps each sender's newest sync and takes "
                            "no frame, AUTH-26)", expected=True)
            else:
                self.reject("unsynced", f"{frame.name}: expected a {frame.name}_Sync first "
                            "(no freshness value of its sender known yet)")
            return None
        code = self._code_for(fid)

        def verifies(v: int) -> bool:
            return frame_verifies(key, fid, msg.data, v, code)

        # AUTH-30: the router's commands to other agents move its count unseen: the wide
        # search (AUTH-13's) for every command
        wide = fid in self._lost or fid == contract.ER_COMMAND_ID
        windows = LOST_WINDOWS if wide else 1
        fv = self._fv.search(fid, frame.counter, windows, verifies)
        if fv is None and fid in self._pending:
            pending = self._pending[fid]
            fv = FreshnessVerifier(contract.FV_TX_BITS, initial={fid: pending}).search(
                fid, frame.counter, windows, verifies)
            if fv is not None:
                if not self._take_pending(fid, frame.name, fv):
                    return None
                last = pending  # the frame's gap counts from the advance it completed
        if fv is None:
            if self._fv.search_late(fid, frame.counter, STALE_WINDOWS, verifies):
                self.reject("stale", f"{frame.name}: its MAC verifies with a freshness value "
                            f"at or below the last accepted {last:#x}: a genuine frame that "
                            "arrived late or out of order (not used)")
                return None
            if fid in self._lost:
                self.reject("unsynced", f"{frame.name}: its sender timed out and this frame "
                            "is beyond the freshness window: waiting for its next sync")
            else:
                self.fail(fid, "auth", f"{frame.name}: expected a MAC that verifies with "
                          f"{contract.sender_of(frame.name)}'s key and freshness "
                          f"{(last + 1):#x}..{(last + _FV_WINDOW):#x}, but it does not "
                          "(forged, replayed or corrupted)", t)
            return None
        self._fv.accept(fid, fv)
        self._spoke.add(fid)  # AUTH-27: a frame since the latest boot advance
        self._lost.discard(fid)
        if fid != contract.ER_COMMAND_ID:  # AUTH-30: a gap in commands is others' commands
            self.counters["lost_frames"] += fv - last - 1
        if not defer_trust:
            self._streak[fid] = 0
        return frame

    def _take_pending(self, fid: int, name: str, fv: int) -> bool:
        """AUTH-35: a frame that failed its window verifies at ``fv`` on the input's held
        boot advance: its sender did restart, so the advance is taken as a sync would have
        been (AUTH-27's ``back`` set, a resync, a hello), unless what vouches for the
        input's boots (``vouch``) does not vouch for this one: then the frame is
        ``unsynced`` and the advance stays held (False)."""
        boot = contract.FRESHNESS.split(fv)[0]
        check = self._vouches.get(fid)
        if check is not None and not check(boot):
            self.reject("unsynced", f"{name}: verifies on a held advance to boot {boot} of "
                        f"{contract.sender_of(name)} that nothing vouches for yet (AUTH-33: "
                        "no price signature of that boot): not taken")
            return False
        self._advance(fid, self._pending.pop(fid))
        log.info("%s: %s verifies at boot %d: its sender restarted, its sync's advance "
                 "taken (AUTH-35)", self.who, name, boot)
        return True

    def _advance(self, fid: int, value: int) -> None:
        """Take a boot advance to ``value`` (a sync's FV − 1): AUTH-27's undo point first.
        A second advance with no frame since the first keeps the first's (forged syncs in
        a row are undone together)."""
        if fid in self._spoke or fid not in self._back:
            last = self._fv.last(fid)
            assert last is not None
            self._back[fid] = last
        self._spoke.discard(fid)
        self._fv.accept(fid, value, frame=False)
        self._lost.discard(fid)
        self.counters["resyncs"] += 1
        self._hello_due = True  # a peer restarted: tell it our freshness now

    def _holds_advance(self, fid: int) -> bool:
        """AUTH-35: a boot advance of input ``fid`` is held (not lost: its sender is
        live, and a restart of it shows in its next frame)."""
        return fid not in self._lost

    def _drop_pending(self, fid: int, name: str, boot: int) -> None:
        """AUTH-35: a verified sync of ``boot``, below the boot of the advance input
        ``fid`` holds (the boot the input is in, or a later one the sender restarted
        to): a sender never goes back, so that advance was forged (a key holder's):
        dropped, ``sync_jump``. Nothing if none is held of a later boot."""
        held = self._pending.get(fid)
        if held is None or contract.FRESHNESS.split(held + 1)[0] <= boot:
            return
        del self._pending[fid]
        self.counters["sync_jump"] += 1
        log.warning("%s: %s of boot %d: its sender is in that boot, so the sync that "
                    "announced boot %d was forged (AUTH-35: never taken)", self.who, name,
                    boot, contract.FRESHNESS.split(held + 1)[0])

    def _on_sync(self, msg: can.Message, sync_id: int, t: float) -> None:
        fid = self._synced_by[sync_id]
        try:
            frame = self.codec.decode(msg)
        except Exception as e:
            cause = getattr(e, "cause", None)
            if cause is None:
                raise
            self.fail(sync_id, cause, str(e), t)
            return
        boot, count = frame.raw["Boot"], frame.raw["Count"]
        fv = contract.FRESHNESS.join(boot, count)
        if not frame_verifies(self._sync_key[fid], sync_id, msg.data, fv,
                              self._code_for(sync_id)):
            self.fail(sync_id, "auth", f"{frame.name}: expected a MAC that verifies with "
                      f"{contract.sender_of(frame.name)}'s key, but it does not (forged or "
                      "corrupted)", t)
            return
        if self._below_floor(frame.name, boot, sync_id, t):
            return
        self._streak[sync_id] = 0
        if self._joining is not None:
            self._join_sync(frame.name, fid, sync_id, fv, t)
            return
        self._take_sync(fid, fv, t)

    def _join_sync(self, name: str, fid: int, sync_id: int, fv: int, t: float) -> None:
        """AUTH-26: a verified sync while joining: kept if it is the sender's newest yet.
        A replay of an earlier sync of the sender's current boot (above its floor) is
        then superseded by the sender's answer to this node's hello before any frame is
        taken; one that comes after a newer sync is a replay (``auth``)."""
        assert self._joining is not None
        newest = self._joining.get(fid)
        if newest is not None and fv < newest:
            self._old_sync(name, sync_id, newest, fv, t)  # older than one already heard
            return
        if newest is None:
            self._hello_due = True  # a first contact: tell the peer our freshness now
        self._joining[fid] = fv

    def _old_sync(self, name: str, sync_id: int, newest: int, value: int, t: float) -> None:
        """A verified sync whose ``value`` is below the ``newest`` known of its sender
        (AUTH-16, AUTH-25; firmware_c's old_sync): less than one window behind, its tick's
        frame overtook it (``stale``, no streak); further, a replayed sync (``auth``)."""
        if self._fv.late_sync(newest - value):
            self.reject("stale", f"{name}: {value:#x}, at most one window behind the newest "
                        f"known {newest:#x}: late (AUTH-25)")
        else:
            self.fail(sync_id, "auth", f"{name}: expected freshness no older than "
                      f"{newest:#x}, but got {value:#x} (a replayed sync)", t)

    def _settle(self, t: float) -> None:
        """AUTH-26: at the end of the join window, take each sender's newest sync."""
        if self._join_until is None or t < self._join_until:
            return
        joined, self._joining = self._joining or {}, None
        for fid, fv in sorted(joined.items()):
            self._take_sync(fid, fv, t, hello=False)  # first contacts were answered
            self._lost.add(fid)  # its frames of the window were not taken: lost (AUTH-13)

    def _take_sync(self, fid: int, fv: int, t: float, hello: bool = True) -> None:
        """A verified sync at or above its sender's floor (AUTH-16, AUTH-17); ``hello``:
        answer a sender that (re)started with this node's own syncs."""
        sync_id = contract.SYNC_OF[fid]
        name = self.codec.name_of(sync_id)
        last = self._fv.last(fid)
        boot = contract.FRESHNESS.split(fv)[0]
        restarted = last is None or contract.FRESHNESS.split(last + 1)[0] != boot
        if last is not None and fv - 1 <= last:
            if fv - 1 == last:
                self._lost.discard(fid)  # in step with the sender: the normal window
                self._drop_pending(fid, name, boot)
                return  # nothing new: the sender sent no frame since its last sync
            if not self.keys.insecure:  # a genuine sync never goes back
                if not self._revert(fid, name, fv, last):
                    self._old_sync(name, sync_id, last, fv - 1, t)
                return
            # --insecure: a restarted sender comes back at boot 1, count 0 (nothing is
            # persisted), so its values go back; insecure mode has no replay protection
            self._fv.forget(fid)
            restarted = True
        elif last is not None and not self.keys.insecure:
            expected = contract.FRESHNESS.split(last + 1)[0]
            if self._boot_jump(name, sync_id, expected, boot, t):
                return
            if boot == expected and self._count_jump(fid, name, sync_id, last, fv, t):
                return
            if boot > expected:
                if self._holds_advance(fid):  # AUTH-35: held until a frame verifies on it
                    self._drop_pending(fid, name, boot)  # one of a later boot: forged
                    self._pending[fid] = fv - 1
                    return
                self._advance(fid, fv - 1)
                return
            self._drop_pending(fid, name, boot)
        self._fv.accept(fid, fv - 1, frame=False)  # its next frame uses fv
        self._lost.discard(fid)
        self.counters["resyncs"] += 1
        if restarted and hello:
            self._hello_due = True  # a peer (re)started: tell it our freshness now

    def _revert(self, fid: int, name: str, fv: int, last: int) -> bool:
        """AUTH-27: a verified sync below the last value, of a boot below the current one
        but not below the one its sender left at its latest boot advance, and newer than
        anything taken of that boot: the sender is alive where the advance said it was
        not, so the advance was forged (a restarted sender never sends its old boot
        again). The sync is taken: the sender recovers at its next sync, or its restart."""
        if not contract.FRESHNESS.undoes_advance(fv, last, self._back.get(fid)):
            return False
        del self._back[fid]
        boot = contract.FRESHNESS.split(fv)[0]
        self._drop_pending(fid, name, boot)
        self._fv.forget(fid)
        self._fv.accept(fid, fv - 1, frame=False)
        self._lost.discard(fid)
        self.counters["resyncs"] += 1
        self.counters["sync_jump"] += 1
        self._hello_due = True
        log.warning("%s: %s of boot %d undoes a boot advance to %d it took earlier: that "
                    "one was forged (AUTH-27)", self.who, name, boot,
                    contract.FRESHNESS.split(last + 1)[0])
        return True

    def _boot_jump(self, name: str, sync_id: int, expected: int, boot: int,
                   t: float) -> bool:
        """AUTH-27: a verified sync whose boot lies more than SYNC_BOOT_JUMP_MAX ahead of
        the ``expected`` one is refused (``sync_jump`` and ``auth``): a genuine sender does
        not jump that far, and taking it would lock the sender out until its own boot
        counter passed the forged one."""
        if not beyond_boot_bound(boot, expected):
            return False
        self.counters["sync_jump"] += 1
        sender = contract.sender_of(name.removesuffix("_Sync"))
        top = expected + SYNC_BOOT_JUMP_MAX
        self.fail(sync_id, "auth", f"{name}: expected boot {expected}..{top} of {sender}, but "
                  f"got boot {boot} (a forged sync: a key holder's, AUTH-27)", t)
        return True

    def _count_jump(self, fid: int, name: str, sync_id: int, last: int, fv: int,
                    t: float) -> bool:
        """AUTH-27: a verified sync of the boot it expects that moves an input in step (not
        lost) further than a frame of it could (its freshness search: one window, the
        wide search for ER_Command) is refused (``sync_jump`` and ``auth``): a receiver
        that missed more of a live sender's frames than that has timed it out (lost), and
        taken, a forged count near 2^24 would make every later genuine frame and sync of
        the boot a replay until the sender restarts (one frame: the fleet in SAFE)."""
        if fid in self._lost or fid not in self._timed:
            return False
        reach = LOST_SEARCH_COUNTS if fid == contract.ER_COMMAND_ID else _FV_WINDOW
        if fv - 1 - last <= reach:
            return False
        self.counters["sync_jump"] += 1
        self.fail(sync_id, "auth", f"{name}: expected a count at most {reach} ahead of the "
                  f"last taken {last:#x} (its sender is in step), but got {fv - 1:#x} (a "
                  "forged sync: a key holder's, AUTH-27)", t)
        return True

    def _peer_sync(self, msg: can.Message, sync_id: int, t: float) -> bool:
        """A sync of a frame this node does not use, from a fleet node whose key it holds
        (the router and the plant hold every agent's): verified only to notice a peer's
        (re)start and re-announce this node's own syncs, so that the restarted peer
        hears it at once. True if the frame was such a sync (whatever its verdict)."""
        agent = agent_of(sync_id)
        if self.fleet_size is not None and (agent or 0) > self.fleet_size:
            return False
        name = self.codec.name_of(sync_id)
        sender = contract.sender_of(name.removesuffix("_Sync"))
        if sender == self.keys.node:
            return False  # a sync in its own name of a frame it does not send: not a peer's
        code = self._code_for(sync_id)
        # None: not held, or a link frame of others (AUTH-28), or a λ not tagged for it
        key = (self.keys.key_for(name) if code is None else
               self.keys.tag_key(sender, self.keys.node))
        if key is None or (code is not None and frame_tag(msg.data, code) is None):
            return False  # (AUTH-34: a λ sync with no tag for this node is not for it)
        try:
            frame = self.codec.decode(msg)
        except Exception as e:
            if getattr(e, "cause", None) is None:
                raise
            return True  # not a usable sync; not this node's input either
        boot = frame.raw["Boot"]
        fv = contract.FRESHNESS.join(boot, frame.raw["Count"])
        if self._peer_boot.get(sync_id) == boot:
            return True  # that boot is known: nothing to check or do
        if not frame_verifies(key, sync_id, msg.data, fv, code):
            self.fail(sync_id, "auth", f"{name}: expected a MAC that verifies with "
                      f"{contract.sender_of(name)}'s key, but it does not (forged or "
                      "corrupted)", t)
            return True
        if self._below_floor(name, boot, sync_id, t):
            return True
        self._peer_boot[sync_id] = boot
        self._hello_due = True
        return True

    def _below_floor(self, name: str, boot: int, sync_id: int, t: float) -> bool:
        """AUTH-21: a verified sync of a boot below its sender's persisted floor is from an
        earlier run or boot (a replay), or its sender's key file was rolled back: rejected
        under ``auth``, before it can set any freshness state."""
        sender = contract.sender_of(name.removesuffix("_Sync"))
        floor = self.keys.floor_of(sender)
        if boot >= floor:
            return False
        self.fail(sync_id, "auth", f"{name}: expected boot {floor} or later of {sender}, but "
                  f"got boot {boot} (a replay of an earlier run or boot, or {sender}'s key "
                  "file rolled back)", t)
        return True

    def last_freshness(self, fid: int) -> int | None:
        """The last freshness value accepted on secured input ``fid`` (None: none yet)."""
        return self._fv.last(fid)

    def assume_synced(self, fid: int, boot: int, count: int = 0) -> None:
        """Set secured input ``fid``'s freshness state as a sync announcing (``boot``,
        ``count``) would, without a sync frame and without counting a resync: for
        benchmarks and tests that drive one receiver alone (AUTH-16's state only)."""
        self._fv.accept(fid, contract.FRESHNESS.join(boot, count) - 1, frame=False)
        self._lost.discard(fid)

    def start_tx_counts(self, count: int) -> None:
        """Start every own secured message counter of this boot at ``count``: a test hook
        (the node vectors' ``setup.tx_count``: AUTH-5's rollover within seconds)."""
        for fid in self._tx_count:
            self._tx_count[fid] = count

    def follow_tx_count(self, fid: int, count: int) -> bool:
        """Send own secured message ``fid`` next at ``count`` (False, nothing set: not an
        own secured ID): the conformance oracle goes on from the counts a device announced
        after it diverged."""
        if fid not in self._tx_count:
            return False
        self._tx_count[fid] = count
        return True

    def sender_lost(self, fid: int) -> None:
        """Input ``fid``'s sender timed out: its counter gap aliases, so its next frames
        get a wider freshness window (LOST_WINDOWS), or wait for its next sync."""
        if fid not in self._inputs:
            raise KeyError(fid)
        self._lost.add(fid)
        self._pending.pop(fid, None)  # its next sync is taken as it comes (AUTH-35)

    @property
    def sync_schedule(self) -> SyncSchedule:
        """When this node's next syncs are due (a tester's oracle follows a device's)."""
        return SyncSchedule(self._sync_next, self._hello_due, self._hello_after)

    @sync_schedule.setter
    def sync_schedule(self, when: SyncSchedule) -> None:
        """Follow another node's schedule (the oracle adopts the device's)."""
        self._sync_next, self._hello_due, self._hello_after = when

    def syncs_sent_at(self, t: float) -> None:
        """This node's syncs went out at ``t``: the next are due ``sync_s`` later, and a
        re-announce not before HELLO_FRACTION·sync_s (summed in whole ns, as firmware_c
        keeps its clock and periods)."""
        sent = round(t * 1e9)
        self._hello_due = False
        self._hello_after = (sent + round(HELLO_FRACTION * self.sync_s * 1e9)) / 1e9
        self._sync_next = (sent + round(self.sync_s * 1e9)) / 1e9

    def constant_tables(self) -> tuple[object, ...]:
        """The tables that neither a frame nor a tick changes (copies of a node may share
        them): the known IDs, the verification keys and sync IDs."""
        return (self._known, self._verify_key, self._sync_key, self._synced_by)

    def resync_after(self, name: str, counts: int) -> None:
        """Make this node's syncs due as soon as own message ``name`` has been sent
        ``counts`` times since its last sync: for a frame receivers verify only in part
        (AUTH-30: an agent checks the commands to it only, so the router's count moves
        unseen in between and must be re-announced before it passes the receivers'
        LOST_WINDOWS search)."""
        self._resync_after[self.codec.frame_id(name)] = counts

    def syncs(self, t: float) -> list[can.Message]:
        """The ``<name>_Sync`` frames due at ``t``: all of them at the first call, every
        ``sync_s``, when a peer (re)started (at most every HELLO_FRACTION·sync_s), and
        when an own message sent ``resync_after`` times since the last sync."""
        due = self._sync_next is None or _reached(t, self._sync_next)
        if any(self._tx_count[f] - self._count_at_sync[f] >= n
               for f, n in self._resync_after.items()):
            due = True
        if self._hello_due and _reached(t, self._hello_after):
            due = True
        if self._join_until is None:
            self._join_until = t + self.join_s  # this first call is the node's hello
        if not due:
            return []
        self.syncs_sent_at(t)
        self._count_at_sync = dict(self._tx_count)
        out = []
        for fid, count in self._tx_count.items():
            sync_id = contract.SYNC_OF[fid]
            msg = self.codec.encode(self.codec.name_of(sync_id),
                                    {"Count": count, "Boot": self.boot}, 0)
            self._sign(fid, sync_id, msg, self._sign_key[fid],
                       contract.FRESHNESS.join(self.boot, count))
            self._sent[sync_id].append(bytes(msg.data))
            out.append(msg)
        return out

    def trusted(self, fid: int) -> None:
        """A frame on ``fid`` passed every check: its untrusted streak starts again."""
        self._streak[fid] = 0

    def fail(self, fid: int, cause: str, reason: str, t: float) -> None:
        """A frame on ``fid`` rejected under ``cause``; a streak cause (STREAK_CAUSES) adds
        to the ID's untrusted streak."""
        self.reject(cause, reason)
        if cause == "auth":
            self.last_safety = ("auth", fid)
        if cause not in STREAK_CAUSES:
            return
        self._streak[fid] += 1
        if self._streak[fid] >= self.untrusted_after:
            self._streak[fid] = 0
            self._untrusted_until[fid] = t + self.untrusted_s
            self.counters["untrusted_sources"] += 1
            self.last_safety = ("untrusted", fid)
            log.warning("%s: 0x%03X untrusted for %.3f s after %d consecutive failures "
                        "(last: %s)", self.who, fid, self.untrusted_s, self.untrusted_after,
                        reason)

    def untrusted(self, fid: int, t: float) -> bool:
        """Whether ``fid`` is untrusted at ``t``."""
        until = self._untrusted_until.get(fid)
        return until is not None and t < until

    def safety_reject(self, cause: str, fid: int, reason: str) -> None:
        """A frame rejected by the safety model (docs/safety-model.md): counted under
        ``cause``, its claimed sender remembered for the diagnostics."""
        self.last_safety = (cause, fid)
        self.safety_rejections += 1
        self.reject(cause, reason)

    def foreign(self, cause: str, reason: str) -> None:
        """A frame that cannot come from this node's fleet: counted under ``cause`` and
        ``foreign``."""
        self.counters["foreign"] += 1
        self.reject(cause, reason)

    def reject(self, cause: str, reason: str, expected: bool = False) -> None:
        """A frame rejected under ``cause``; ``expected``: what every start does (the join
        window), counted and logged at debug level only."""
        self.counters[cause] += 1
        self.last_error[cause] = reason
        n = self.counters[cause]
        if expected:
            log.debug("%s rejected a frame (%s #%d): %s", self.who, cause, n, reason)
        elif n <= LOG_FIRST or n % 1000 == 0:
            log.warning("%s rejected a frame (%s #%d): %s", self.who, cause, n, reason)

    def send_transfer(self, name: str, raw: Mapping[str, int]) -> can.Message:
        """Encode own transfer message ``name`` (no MAC, no counter: ER_PriceSig) and
        remember it for the echo."""
        fid = self.codec.frame_id(name)
        if fid not in self._sent or fid in contract.SECURED_IDS:
            raise EncodeError("message", f"a transfer message {self.who} sends", name)
        msg = self.codec.encode(name, raw, 0)
        self._sent[fid].append(bytes(msg.data))
        return msg

    def _sign(self, fid: int, data_id: int, msg: can.Message, key: bytes, fv: int) -> None:
        """Sign own frame ``msg`` (``data_id``: it or its sync) of own ID ``fid``: its Mac,
        or on CAN FD a tag per receiver of its λ (AUTH-34)."""
        tags = self._tag_keys.get(fid)
        if tags is None:
            sign_frame(key, data_id, msg.data, fv)
        else:
            sign_tags(tags, data_id, msg.data, fv)

    def send(self, name: str, raw: Mapping[str, int]) -> can.Message:
        """Encode own secured message ``name`` with its next freshness value, sign it and
        remember it for the echo (EncodeError for a message this node does not send)."""
        fid = self.codec.frame_id(name)
        count = self._tx_count.get(fid)
        if count is None:
            raise EncodeError("message", f"a secured message {self.who} sends "
                              f"({', '.join(self.codec.name_of(f) for f in self._tx_count)})",
                              name)
        if count > _COUNT_MAX:  # 2^24 frames on one ID: a new boot, synced at once
            self.boot = self.keys.new_boot()
            self._tx_count = dict.fromkeys(self._tx_count, 0)
            self._count_at_sync = dict(self._tx_count)
            self._sync_next, count = None, 0
        msg = self.codec.encode(name, raw, count % _FV_WINDOW)
        key = (self._command_key(target_agent(raw["Target"])) if fid == contract.ER_COMMAND_ID
               else self._sign_key[fid])  # AUTH-30: a command under its target's key
        self._sign(fid, fid, msg, key, contract.FRESHNESS.join(self.boot, count))
        self._tx_count[fid] = count + 1
        self._sent[fid].append(bytes(msg.data))
        return msg


class FleetSender:
    """Frames as any node of a fleet would send them, for tests, tools and HIL rigs:
    the codec's layout, each secured ID's freshness (Boot ‖ Count) and MAC, and its
    syncs.

    ``keys``: label → signing key (e.g. from ``bess-ded keys``' files); None: the public
    ``--insecure`` keys, at boot 1 as every insecure sender (so an insecure receiver
    takes the frames without a sync). ``counter``, when given, is the low 4 bits the
    frame must carry: the full count is the next one with those bits (so a caller
    that skips counters makes the receiver count lost frames, as on a bus)."""

    def __init__(self, codec: FrameCodec | None = None,
                 keys: Mapping[str, bytes] | None = None, boot: int = INSECURE_BOOT,
                 tag_receivers: Mapping[int, Sequence[str]] | None = None) -> None:
        """``tag_receivers``: on a codec whose λ is tagged (AUTH-34), agent i → the
        receivers of its λ in slot order (``contract.lambda_receivers``); their pair keys
        are ``keys["agent_i>receiver"]``."""
        self.codec = codec or FrameCodec()
        self.keys = dict(keys or {})
        self.insecure = keys is None
        self.boot = boot
        self.tag_receivers = dict(tag_receivers or {})
        self._count: dict[int, int] = {}

    def _sign(self, name: str, data_id: int, msg: can.Message, fv: int,
              target: int | None = None) -> None:
        """Its Mac, or a tagged λ's tag per receiver (AUTH-34)."""
        if not self.codec.tag_slots(name):
            sign_frame(self._key(name, target), data_id, msg.data, fv)
            return
        sender = contract.sender_of(name.removesuffix("_Sync"))
        receivers = self.tag_receivers.get(int(sender.removeprefix("agent_")))
        if receivers is None:
            raise EncodeError("tag_receivers", f"the receivers of {sender}'s λ tags (CAN FD, "
                              "AUTH-34)", sorted(self.tag_receivers))
        tags = []
        for r in receivers:
            label = pair_label(sender, r)
            if label not in self.keys and self.insecure:
                self.keys[label] = derive_lambda_tag_key(INSECURE_MASTER, sender, r)
            tags.append((tag_code(r), self.keys[label]))
        sign_tags(tags, data_id, msg.data, fv)

    def _key(self, name: str, target: int | None = None) -> bytes:
        """AUTH-28, AUTH-29: a link frame's or report's own key (``keys[name]``); AUTH-30:
        an ER_Command's its target's (``keys[command_key_name(target)]``); else the
        sender's."""
        if name == contract.COMMAND and target is not None:
            label = contract.command_key_name(target)
            if label not in self.keys and self.insecure:
                self.keys[label] = derive_command_key(INSECURE_MASTER, f"agent_{target}")
            return self.keys[label]
        base = name.removesuffix("_Sync")
        label = base if base in contract.KEYED_FRAMES else contract.sender_of(base)
        if label not in self.keys and self.insecure:
            self.keys[label] = (derive_frame_key(INSECURE_MASTER, label)
                                if base in contract.KEYED_FRAMES
                                else derive_node_key(INSECURE_MASTER, label))
        return self.keys[label]

    def frame(self, name: str, raw: Mapping[str, Any], counter: int | None = None,
              phys: bool = False) -> can.Message:
        """``name`` with ``raw`` signal values (physical ones with ``phys``)."""
        fid = self.codec.frame_id(name)
        last = self._count.get(fid, -1)
        count = last + 1
        if counter is not None:
            count += (counter - count) % _FV_WINDOW
        self._count[fid] = count
        enc = self.codec.encode_phys if phys else self.codec.encode
        msg = enc(name, raw, count % _FV_WINDOW)
        if fid in contract.SECURED_IDS:
            target = None
            if name == contract.COMMAND:  # the agent: phys is it, raw is it − the offset
                target = int(raw["Target"]) if phys else target_agent(raw["Target"])
            self._sign(name, fid, msg, contract.FRESHNESS.join(self.boot, count), target)
        return msg

    def follow(self, name: str, boot: int, count: int) -> None:
        """Continue ``name`` after the frame of freshness (``boot``, ``count``): the next
        frame takes the value a sender heard at that count sends next (a listener's, e.g.
        an insider's that verified the genuine frames, sim.nodes.insider)."""
        self.boot = boot
        self._count[self.codec.frame_id(name)] = count

    def sync(self, name: str) -> can.Message:
        """``<name>_Sync``: the freshness value of the next ``name`` frame."""
        return self.sync_ahead(name)

    def sync_ahead(self, name: str, counts: int = 0, boots: int = 0) -> can.Message:
        """``<name>_Sync`` ``counts`` values past the next frame's, ``boots`` boots on (0,
        0: ``sync``; else a key holder's forgery, AUTH-27's bounds); nothing of the sender
        moves."""
        fid = self.codec.frame_id(name)
        count = self._count.get(fid, -1) + 1 + counts
        boot = self.boot + boots
        sync_id = contract.SYNC_OF[fid]
        msg = self.codec.encode(self.codec.name_of(sync_id), {"Count": count,
                                                              "Boot": boot}, 0)
        self._sign(self.codec.name_of(sync_id), sync_id, msg,
                   contract.FRESHNESS.join(boot, count))
        return msg

    def restart(self) -> None:
        """A new boot: counts from 0 again (send the syncs before the frames)."""
        self.boot += 1
        self._count.clear()

    def reset_counts(self) -> None:
        """Count from 0 again under the same boot: a sender that has just booted (a test's
        fresh start)."""
        self._count.clear()

    def next_count(self, name: str) -> int:
        """The count (of the sender's boot) the next ``name`` frame carries."""
        return self._count.get(self.codec.frame_id(name), -1) + 1

    def skip(self, name: str, frames: int) -> None:
        """Let ``frames`` of ``name``'s counts go by unsent: frames its receivers never
        heard (they count them lost)."""
        fid = self.codec.frame_id(name)
        self._count[fid] = self._count.get(fid, -1) + frames
