"""The record of a conformance run (``Frame``, ``Outcome``) and its check against
the oracle, firmware_py's own agent runtime fed the same frames (``check``).

Over 500 lines: the check is one search over hypotheses of the order of events (the
clones, their fingerprints, the tick-time guesses and the re-synchronisation to the
device's frames share its state); the record types at the top are its input.
"""

from __future__ import annotations

import copy
import logging
import math
import re
from collections import Counter, deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace
from enum import Enum
from types import BuiltinFunctionType, FunctionType
from typing import Any, cast

import can

from firmware_py import contract, secoc
from firmware_py import fixedpoint as fx
from firmware_py.config import AgentConfig
from firmware_py.contract import State
from firmware_py.errors import BessDedError
from firmware_py.frames import (
    DecodedFrame,
    FrameCodec,
    diag_name,
    format_fault,
    mc_name,
    setpoint_name,
)
from firmware_py.nodeio import SyncSchedule
from firmware_py.runtime import AgentRuntime
from firmware_py.secoc import Keyring
from sim.conformance.schedule import FLOOD_NOTE, exercised_on


@dataclass(frozen=True)
class Frame:
    """A frame on the bus: ``t`` in the tester's clock (s); ``sent``: by the tester,
    who sent it between ``t`` and ``t_end`` (the clock read before and after the send)."""

    t: float
    msg: can.Message
    sent: bool
    step: str = ""
    note: str = ""
    t_end: float | None = None

    @property
    def done(self) -> float:
        """When the frame's step is over: its end, else its own time."""
        return self.t if self.t_end is None else self.t_end


@dataclass
class Mismatch:
    """One signal of the device under test that differs from the oracle's:
    when, in which step and message, what was expected and what came."""

    t: float
    tick: int
    step: str
    message: str
    signal: str
    expected: Any
    got: Any
    # what the schedule was exercising at that tick: the notes of the tester's frames of
    # the last MOMENT_TICKS ticks (latest first) and the oracle's state transitions there
    moment: tuple[str, ...] = ()
    transition: tuple[str, ...] = ()
    # the tick of the first divergence of the episode this one follows (a difference in
    # the ticks right after another, the oracle re-synchronised each time), or None
    follows: int | None = None
    raw: tuple[Any, Any] = (None, None)  # the raw expected and observed values

    def __str__(self) -> str:
        at = f", after {self.moment[0]!r}" if self.moment else ""
        return (f"t = {self.t:.3f} s (the device's tick {self.tick}, step {self.step}{at}): "
                f"{self.message}."
                f"{self.signal} = {self.got!r}, expected {self.expected!r}")


@dataclass
class Outcome:
    """What ``check`` found."""

    ticks: int = 0
    mismatches: list[Mismatch] = field(default_factory=list)
    auth_errors: list[str] = field(default_factory=list)
    explained_by: dict[str, str] = field(default_factory=dict)  # MUST → deviation
    steps_seen: set[str] = field(default_factory=set)
    problems: list[str] = field(default_factory=list)  # the run itself (not the DUT)
    filtered: bool = False  # the DUT filters foreign IDs in its CAN controller (GEN-5)
    auth_times: list[float] = field(default_factory=list)  # of auth_errors, from the start
    # DUT frames not in the bus's format (GEN-1: classic on an FD bus, FD on a classic
    # one, FD without the bit-rate switch): (time from the start, what); each is then
    # judged by its content as if sent in the bus's format
    format_errors: list[tuple[float, str]] = field(default_factory=list)
    stopped: str = ""  # why the check stopped before the end of the record, if it did
    differing_ticks: int = 0  # ticks with a difference (mismatches keeps the first ones)
    exact: bool = False  # checked with the device's clock trusted (``check``'s ``exact``)
    # the conditions of the run under which steps exercise more requirements (ONLY_ON:
    # a dwell device, λ tags, --insecure; ``schedule.exercised_on``)
    exercised_on: frozenset[str] = frozenset()


# Which requirements a mismatch on a signal violates (besides the step's)
SIGNAL_MUSTS: dict[str, tuple[str, ...]] = {
    # pc's and ft's step first: judged only on those devices (ONLY_ON), where it is the
    # one controller rule of λ besides ξ's
    "MC.Lambda": ("STEP-10", "STEP-11", "XI-2", "STEP-6", "STEP-7", "STEP-8", "TX-1",
                  "STEP-12", "STATE-10", "WMSR-1", "WMSR-2", "CTRL-3", "NUM-5"),
    # and the inputs' rules that decide health (STATE-2): a valid price, a plant fault
    # (signed_price: a price refused or taken against AUTH-32/33 is a health change)
    "MC.State": ("STATE-3", "STATE-4", "STATE-5", "STATE-7", "STATE-8", "STATE-9",
                 "PRICE-1", "RX-11", "AUTH-33", "AUTH-32"),
    # ISOLATE zeroes the count; a neighbour dying at another tick (LIVE-2) is a zero
    # crossing of ξ at another tick; entering RUNNING or SAFE is no reset (STATE-6)
    "MC.Resets": ("STEP-3", "BAND-3", "TX-1", "STATE-7", "LIVE-2", "STATE-6", "DWELL-1",
                  "DWELL-2"),
    "Setpoint.Enable": ("TX-2", "SP-3"),
    "Setpoint.PowerSetpoint": ("SP-1", "TX-2"),
    "Diag.RejectedAuth": ("AUTH-14", "AUTH-16", "AUTH-21", "RX-8", "AUTH-25"),
    "Diag.Unsynced": ("AUTH-11", "AUTH-14"),
    "Diag.Resyncs": ("AUTH-16", "AUTH-21"),
    "Diag.LostFrames": ("AUTH-15", "AUTH-12", "AUTH-13"),  # the candidate taken
    "Diag.RejectedDlc": ("RX-7",),
    "Diag.RejectedRange": ("RX-7", "RX-9"),
    "Diag.RejectedUnknownId": ("RX-1", "RX-6"),
    "Diag.RejectedImpersonation": ("RX-3",),
    "Diag.ImplausiblePrice": ("PRICE-2", "PRICE-3", "PRICE-4", "PRICE-5"),
    "Diag.ImplausibleLambda": ("LAM-1",),
    "Diag.ImplausibleGains": ("CMD-5",),
    "Diag.NeighbourTimeouts": ("LIVE-3",),
    "Diag.PriceTimeouts": ("TMO-2", "TMO-3"),
    "Diag.StatusTimeouts": ("TMO-2", "TMO-3"),
    "Diag.PlantFaults": ("RX-11",),
    "Diag.SafetySender": ("DIAG-4",),
    "Diag.SafetyCause": ("DIAG-4",),
    "Diag.Untrusted": ("RX-13", "RX-10"),  # RX-10: a valid frame ends the streak
    "Diag.Resets": ("DIAG-1", "STEP-1", "STATE-7", "STATE-6"),
    "Diag.NeighboursAlive": ("DIAG-1", "LIVE-2"),
    "Diag.Saturations": ("DIAG-3", "XI-3", "STEP-9"),
    "Sync.frames": ("AUTH-9",),
    "Sync.Boot": ("AUTH-3",),
    "MC.sent": ("TX-7", "CFG-9"),  # event-triggered sending: whether the MC frame was due
    "Sync.Count": ("AUTH-9", "AUTH-4"),
}


@contextmanager
def quiet_firmware() -> Iterator[None]:
    """The oracle logs what the DUT does (commands, SAFE): not the tester's output."""
    logger = logging.getLogger("firmware_py")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)


class _Oracle:
    """firmware_py's agent, cloned per hypothesis of the order of events."""

    def __init__(self, cfg: AgentConfig, keyring: Keyring, codec: FrameCodec,
                 deviation: Callable[[AgentRuntime], None] | None = None) -> None:
        self.rt = AgentRuntime(cfg, codec, keys=keyring)
        if deviation is not None:
            deviation(self.rt)
        # what no tick changes is shared by every clone, not copied (the clones are most
        # of the check's time): the contract tables, the keys, the configuration
        self._shared = {id(x): x for x in (keyring, *self.rt.constant_tables())}

    def clone(self) -> _Oracle:
        twin = copy.copy(self)
        twin.rt = _twin(self.rt, dict(self._shared))
        return twin


_ATOMS = {int, float, bool, str, bytes, type(None), complex}
"""Types a deep copy returns as they are (frozen values; enum members and functions too,
by ``_kind``)."""


def _kind(t: type) -> str:
    """How ``_twin`` copies an instance of ``t``: "atom", "map" (dict, Counter), "seq"
    (list, deque, set), "tuple", "frozen" (a frozen dataclass), "obj" (a plain class of
    ours: its __dict__ and __slots__), or "deep" (anything else: copy.deepcopy)."""
    if t in _ATOMS or issubclass(t, (Enum, type)) or t in (FunctionType, BuiltinFunctionType):
        return "atom"
    if t in (dict, Counter):
        return "map"
    if t in (list, deque, set):
        return "seq"
    if t is tuple:
        return "tuple"
    params = getattr(t, "__dataclass_params__", None)
    if params is not None and params.frozen:
        return "frozen"
    custom = ("__deepcopy__", "__reduce__", "__reduce_ex__", "__getstate__", "__copy__")
    if t.__module__.split(".")[0] in ("firmware_py", "sim") and not any(
            name in vars(c) for c in t.__mro__[:-1] for name in custom):
        return "obj"
    return "deep"


_KINDS: dict[type, str] = {}


def _twin(x: Any, memo: dict[int, Any]) -> Any:
    """``copy.deepcopy(x, memo)`` for what an agent runtime holds, several times faster
    (the clones are most of a check's time): flat containers of values are copied whole,
    our own classes field by field, anything else by copy.deepcopy. ``memo`` maps id →
    copy, pre-seeded with what the clones share."""
    t = type(x)
    kind = _KINDS.get(t) or _KINDS.setdefault(t, _kind(t))
    if kind == "atom":
        return x
    done = memo.get(id(x), memo)
    if done is not memo:
        return done
    if kind == "deep":
        return copy.deepcopy(x, memo)
    if kind == "tuple":
        out: Any = tuple(_twin(v, memo) for v in x)
    elif kind == "frozen":  # a frozen dataclass of values (ControllerState) is a value
        if all(_KINDS.get(type(getattr(x, f.name))) == "atom" for f in fields(x)):
            return x
        return copy.deepcopy(x, memo)
    elif kind == "map":
        out = x.copy()
        for k, v in x.items():
            if _KINDS.get(type(v)) != "atom":
                out[k] = _twin(v, memo)
    elif kind == "seq":
        out = x.copy()
        if not all(_KINDS.get(type(v)) == "atom" for v in x):
            out = t(_twin(v, memo) for v in x) if t is not deque else deque(
                (_twin(v, memo) for v in x), maxlen=x.maxlen)
    else:
        out = object.__new__(t)
        memo[id(x)] = out
        if hasattr(x, "__dict__"):
            attrs = x.__dict__.copy()
            for k, v in attrs.items():
                if _KINDS.get(type(v)) != "atom":
                    attrs[k] = _twin(v, memo)
            out.__dict__.update(attrs)
        for c in t.__mro__[:-1]:
            for slot in vars(c).get("__slots__", ()):
                if slot not in ("__dict__", "__weakref__") and hasattr(x, slot):
                    object.__setattr__(out, slot, _twin(getattr(x, slot), memo))
    memo[id(x)] = out
    return out


def _signals(codec: FrameCodec, msg: can.Message) -> dict[str, int]:
    return dict(codec.decode(msg).raw)


class _DutFrames:
    """The codec a check reads with: each of the DUT's frames decoded once per ``check``
    however many hypotheses, passes and re-synchronisations read it (a decode error is
    kept and raised again); the oracle's own frames go straight to ``codec``."""

    def __init__(self, codec: FrameCodec, frames: Sequence[Frame]) -> None:
        self.codec = codec
        self._dut = {id(f.msg): f.msg for f in frames if not f.sent}
        self._memo: dict[int, DecodedFrame | BessDedError] = {}

    def decode(self, msg: can.Message) -> DecodedFrame:
        """``codec.decode(msg)``, once for a DUT frame."""
        if self._dut.get(id(msg)) is not msg:  # not a DUT frame (held by ``frames``)
            return self.codec.decode(msg)
        hit = self._memo.get(id(msg))
        if hit is None:
            try:
                hit = self.codec.decode(msg)
            except BessDedError as e:
                hit = e
            self._memo[id(msg)] = hit
        if isinstance(hit, BessDedError):
            raise hit
        return hit

    def __getattr__(self, name: str) -> Any:
        return getattr(self.codec, name)  # frame_id, name_of, ...: the codec's own


WMSR_TIE = "a W-MSR trim through equal λ_j of unequal weights"


def _wmsr_tie(rt: AgentRuntime) -> bool:
    """Whether the resilient update's trim falls inside a group of neighbours at the same
    λ_j whose weights differ (WMSR-2 decides which go), on either side of the own λ."""
    f = rt.cfg.resilient_f
    if not f:
        return False
    lam, pairs = rt.lambda_q24, rt.xi_terms()
    for side in ([p for p in pairs if p[1] > lam], [p for p in pairs if p[1] < lam]):
        side.sort(key=lambda p: abs(p[1] - lam), reverse=True)
        if len(side) > f and side[f - 1][1] == side[f][1] and side[f - 1][0] != side[f][0]:
            return True
    return False


def check(cfg: AgentConfig, keyring: Keyring, dut_key: bytes, frames: Sequence[Frame],
          codec: FrameCodec | None = None,
          deviation: Callable[[AgentRuntime], None] | None = None,
          max_mismatches: int | None = None, filtered_first: bool = False,
          exact: bool = False) -> Outcome:
    """Compare the DUT's frames in ``frames`` (time order) with the oracle's. A DUT may
    filter in its CAN controller what it neither uses nor sends (GEN-5), and then never
    counts the frames of foreign IDs: when the oracle without (``filtered_first``: with)
    a filter does not explain the DUT, the other is tried, and the one that explains
    more is the verdict. After a difference the oracle takes what the DUT's frames show
    (λ, state, counters) and checks on to the end of the record; ``max_mismatches``:
    stop after that many ticks with a difference (``Outcome.stopped`` says so).
    ``exact``: the device's clock is trusted (``simulate(..., exact=True)``, or a host that
    stamps the device's frames with its tick times and the inputs with its receive
    times): it ticked when its MC frame is stamped and took every input at its stamp, so
    no other order or tick time is a hypothesis (a timeout one period late, or a frame
    exactly a timeout old taken as stale, is a difference, not the clock's noise)."""
    frames, wrong = _in_bus_format(codec or FrameCodec(), frames)
    codec = cast(FrameCodec, _DutFrames(codec or FrameCodec(), frames))
    outcome = _check_either(cfg, keyring, dut_key, frames, codec, deviation, max_mismatches,
                            filtered_first, exact)
    outcome.format_errors = wrong
    outcome.exact = exact
    outcome.exercised_on = exercised_on(cfg, bool(codec.tag_slots(mc_name(cfg.id))),
                                        keyring.insecure,
                                        any(f.note == FLOOD_NOTE for f in frames if f.sent))
    return outcome


def _check_either(cfg: AgentConfig, keyring: Keyring, dut_key: bytes, frames: Sequence[Frame],
                  codec: FrameCodec, deviation: Callable[[AgentRuntime], None] | None,
                  max_mismatches: int | None, filtered_first: bool,
                  exact: bool = False) -> Outcome:
    """``check`` with the DUT's frames in the bus's format: the model with the acceptance
    filter or without, whichever explains more."""
    first = _check(cfg, keyring, dut_key, frames, codec, deviation, max_mismatches,
                   filtered_first, exact)
    if not first.mismatches:
        return first
    # the other model, as far as its first difference: checked in full only if it
    # explains more
    other = _check(cfg, keyring, dut_key, frames, codec, deviation, 1, not filtered_first,
                   exact)
    if not other.mismatches:
        return other
    if (other.mismatches[0].tick, other.ticks) > (first.mismatches[0].tick, first.ticks):
        if max_mismatches == 1:
            return other
        return _check(cfg, keyring, dut_key, frames, codec, deviation, max_mismatches,
                      not filtered_first, exact)
    return first


def _in_bus_format(codec: FrameCodec, frames: Sequence[Frame]
                   ) -> tuple[list[Frame], list[tuple[float, str]]]:
    """The record with each DUT frame of another format than the bus's (GEN-1) put in
    the bus's, and what was wrong with each (time from the tester's first frame): a
    format slip fails GEN-1 once per frame, not every signal check after it."""
    t0 = next((f.t for f in frames if f.sent), frames[0].t if frames else 0.0)
    out: list[Frame] = []
    wrong: list[tuple[float, str]] = []
    for f in frames:
        m = f.msg
        if f.sent or (m.is_fd == codec.fd and m.bitrate_switch == codec.fd):
            out.append(f)
            continue
        what = (format_fault(m, codec.fd) if m.is_fd != codec.fd
                else "expected the bit-rate switch, but got a CAN FD frame without it")
        name = (codec.name_of(m.arbitration_id) if m.arbitration_id in codec.frame_ids()
                else f"0x{m.arbitration_id:03X}")
        wrong.append((f.t - t0, f"t = {f.t:.3f} s: {name}: {what}"))
        out.append(replace(f, msg=can.Message(
            timestamp=m.timestamp, arbitration_id=m.arbitration_id, is_extended_id=False,
            data=bytes(m.data), is_fd=codec.fd, bitrate_switch=codec.fd)))
    return out, wrong


MOMENT_TICKS = 10
"""How long (in ticks) a tester's noted frame (a command, a forged MAC, ...) is what the
schedule exercises: a difference within that many ticks after it is attributed to it."""

LAMBDA_HELD = "λ held outside RUNNING"
"""The oracle's edge at a tick where it is neither in RUNNING nor entering a state: λ is
held there (STATE-10), which names a λ that differs."""

EPISODE_GAP = 2
"""A difference within this many ticks of the previous one continues its episode (the
oracle re-synchronised in between, and the DUT diverged again: the same cause)."""

MAX_KEPT = 400
"""Mismatches kept in an outcome (every episode's first ones are kept)."""


def _check(cfg: AgentConfig, keyring: Keyring, dut_key: bytes, frames: Sequence[Frame],
           codec: FrameCodec | None, deviation: Callable[[AgentRuntime], None] | None,
           max_mismatches: int | None, filtered: bool, exact: bool = False) -> Outcome:
    codec = codec or FrameCodec()
    filed = keyring.boot  # the key file's counter (AUTH-3): the oracle's start takes a boot
    keyring = copy.copy(keyring)  # of a copy, so that the caller's stays as filed
    i = cfg.id
    mc_id, sp_id, diag_id = (codec.frame_id(n(i)) for n in (mc_name, setpoint_name, diag_name))
    own = {mc_id, sp_id, diag_id}
    syncs = {contract.SYNC_OF[fid]: fid for fid in (mc_id, sp_id, diag_id)}
    outcome = Outcome()
    dut_groups = (_event_ticks(frames, mc_id, own | set(syncs), cfg.controller.ts)
                  if cfg.transmit.event else
                  [(g[0].t, g) for g in _tick_groups(frames, mc_id, own | set(syncs))])
    if not dut_groups:
        outcome.problems.append("no MC frame of the DUT was recorded")
        return outcome
    inputs = [f for f in frames if f.sent]
    first_sent = inputs[0].t if inputs else math.inf
    # AUTH-28, AUTH-29: the setpoint and the Diag under their own keys, the MC under the
    # DUT's
    keys = {fid: keyring.key_for(codec.name_of(fid)) or dut_key for fid in own}
    keys[mc_id] = dut_key
    verifiers = {fid: _verifier(codec, keyring, keys[fid], fid) for fid in own}
    _check_auth(codec, verifiers, frames, syncs, outcome,
                0.0 if math.isinf(first_sent) else first_sent)
    # AUTH-3: a boot of its own start, above the key file's (--insecure: above 0)
    _check_new_boot(codec, frames, set(syncs), filed, inputs, outcome)
    outcome.filtered = filtered
    if filtered:
        passed = set(AgentRuntime(cfg, codec, keys=keyring).io.accepted_ids())
        inputs = [f for f in inputs
                  if not f.msg.is_extended_id and f.msg.arbitration_id in passed]
    # align the oracle's tick count with the DUT's: the first Diag page before any input
    align = next(((g, f) for g in dut_groups for f in g[1] if f.msg.arbitration_id == diag_id
                  and f.t < first_sent), None)
    if align is None:
        outcome.problems.append("the DUT sent no Diag frame before the tester's first frame "
                                "(start the schedule only once the DUT is heard)")
        return outcome
    page = _signals(codec, align[1].msg)["Page"]
    first = _Oracle(cfg, keyring, codec, deviation)
    first.rt.ticks = 10 * page  # the aligned group is this tick
    # the hypotheses: (oracle, index of the first input it has not received yet)
    hyps: list[tuple[_Oracle, int]] = [(first, 0)]
    start = dut_groups.index(align[0])
    prev_t = align[0][0]
    if cfg.transmit.event:  # TX-7: the MC frame the DUT sent last before the record
        _adopt_last_mc(first.rt, codec, dut_groups[:start], mc_id)
    noted = [f for f in inputs if f.note]
    transitions: list[tuple[float, str]] = []  # the oracle's state changes (t, "A → B")
    state, xi_prev = first.rt.state, first.rt.cstate.xi_prev
    page_t: dict[int | None, float] = {}  # when the DUT last sent each Diag page
    episode: tuple[int, int] | None = None  # (its first tick, its last tick)
    # a DUT started before the record: its sync schedule and counts are known from its
    # first sync in the record on (the oracle's first syncs are its own start's)
    syncs_known = any(f.msg.arbitration_id in contract.SYNCED_BY for f in align[0][1])
    with quiet_firmware():
        # the last group may be cut short by the end of the recording
        for idx in range(start, len(dut_groups) - 1):
            t_tick, group = dut_groups[idx]
            step = _step_name(inputs, t_tick)
            if step:
                outcome.steps_seen.add(step)
            found: list[tuple[tuple[int, int, int, int], _Oracle, int]] = []
            failure: tuple[_Oracle, int, list[Mismatch]] | None = None
            for h, (oracle, pending) in enumerate(hyps):
                # inputs sent before the DUT's previous frames reached it before this tick;
                # those sent since may or may not have (each order is a hypothesis)
                sure = pending
                while sure < len(inputs) and (inputs[sure].t < t_tick if exact else
                                              inputs[sure].done < prev_t - 0.001):
                    oracle.rt.on_frame(inputs[sure].msg, inputs[sure].t if exact
                                       else inputs[sure].done)
                    sure += 1
                maybe = sure if exact else sure + sum(1 for f in inputs[sure:]
                                                      if f.t < t_tick)
                # each input received when it was sent, or (a starved DUT reads its socket
                # late and stamps the frames then) just before this tick
                # late and stamped alike, a frame makes no other state: the late chain
                # starts at the first frame it stamps otherwise
                late: _Oracle | None = None
                for cut in range(sure, maybe + 1):
                    if cut > sure:
                        f = inputs[cut - 1]
                        if late is None and f.done < t_tick - 1e-6:
                            late = oracle.clone()
                        oracle.rt.on_frame(f.msg, f.done)
                        if late is not None:
                            late.rt.on_frame(f.msg, max(f.done, t_tick - 1e-6))
                    for d, chain in enumerate((oracle,) if late is None else (oracle, late)):
                        guesses = [t_tick] if exact else _tick_times(chain.rt, prev_t,
                                                                     t_tick)
                        for g, t_guess in enumerate(guesses):
                            # a chain's last use ticks the chain itself, not a copy
                            last = cut == maybe and g == len(guesses) - 1
                            twin = chain if last else chain.clone()
                            io = twin.rt.io
                            before = io.sync_schedule
                            sent = twin.rt.tick(t_guess)
                            diffs = _compare(codec, sent, group, outcome.ticks, step,
                                             t_tick - first_sent, syncs_known,
                                             (twin.rt.state, twin.rt.lambda_q24)
                                             if cfg.transmit.event else None)
                            if diffs and syncs_known:
                                diffs = _sync_slack(twin.rt, codec, before, sent, group,
                                                    diffs, t_guess)
                            if not diffs:
                                found.append(((h, d, g, maybe - cut), twin, cut))
                            elif failure is None or cut == maybe and d + g + h == 0:
                                failure = (twin, cut, diffs)
            # the likeliest first: the previous likeliest, the DUT ticking when it sent,
            # every frame sent before that received
            matching: dict[tuple[int, tuple], tuple[_Oracle, int]] = {}
            for _, twin, cut in sorted(found, key=lambda m: m[0]):
                matching.setdefault((cut, _fingerprint(twin.rt)), (twin, cut))
            if matching:
                hyps = list(matching.values())[:MAX_HYPOTHESES if not outcome.mismatches
                                               else DIVERGED_HYPOTHESES]
            else:
                assert failure is not None
                tick = outcome.ticks
                if episode is not None and tick - episode[1] <= EPISODE_GAP:
                    episode = (episode[0], tick)
                    follows: int | None = episode[0]
                else:
                    episode, follows = (tick, tick), None
                since = t_tick - MOMENT_TICKS * cfg.controller.ts
                # a Diag value shows what happened since its page was last sent
                since_page = min(since, page_t.get(_page(codec, group, diag_id), -math.inf))
                rt = failure[0].rt
                went = _state_change(state, rt.state)
                trans = tuple(w for t, w in reversed(transitions) if t >= since)
                edges = tuple(e for e, hit in (
                    ("ξ = 0 after ξprev ≠ 0", rt.cstate.xi_prev == 0 and xi_prev != 0),
                    ("|ξ| = BAND", abs(rt.cstate.xi_prev) == getattr(rt.ctrl, "band", None)),
                    ("λ beyond the λ limits", not fx.widen(rt.lam_min) <= rt.cstate.lam
                     <= fx.widen(rt.lam_max)),
                    (WMSR_TIE, _wmsr_tie(rt)))
                    if hit and rt.state == State.RUNNING)
                # λ is held in every other state (STATE-10): not one the oracle entered at
                # this tick (its entry has a rule of its own); an edge of λ's only
                held = (LAMBDA_HELD,) if rt.state == state != State.RUNNING else ()
                # the DUT gone SAFE where the oracle is not: an input it did not take
                # a whole timeout ago (STATE-2)
                since_safe = since - max(cfg.price_timeout_s, cfg.status_timeout_s)
                for mm in failure[2]:
                    went_safe = (mm.message, mm.signal, str(mm.got)) == ("MC", "State", "SAFE")
                    mm.moment = tuple(f.note for f in reversed(noted)
                                      if (since_page if mm.message == "Diag" else
                                          since_safe if went_safe else since)
                                      <= f.t < t_tick)
                    mm.follows = follows
                    lam = (mm.message, mm.signal) == ("MC", "Lambda")
                    mm.transition = (edges + (held if lam else ()) + ((went,) if went else ())
                                     + trans)
                    if (mm.message, mm.signal, mm.expected) == ("MC", "sent", "sent") and \
                            _next_state(codec, dut_groups[idx + 1:], mc_id) == rt.state:
                        # the DUT's next frame shows the state the oracle sent: it kept
                        # its MC frame back (TX-7), whatever the moment was
                        mm.moment, mm.transition = (), ()
                outcome.differing_ticks += 1
                if follows is None or len(outcome.mismatches) < MAX_KEPT:
                    outcome.mismatches.extend(failure[2])
                if max_mismatches is not None and outcome.differing_ticks >= max_mismatches:
                    outcome.stopped = (f"the check stopped at the device's tick {tick} after "
                                       f"{outcome.differing_ticks} ticks with differences")
                    break
                _adopt(failure[0].rt, codec, group, mc_id, diag_id)
                hyps = [(failure[0], failure[1])]
            if not syncs_known and any(f.msg.arbitration_id in contract.SYNCED_BY
                                       for f in group):
                syncs_known = True
                for oracle, _ in hyps:
                    _adopt_syncs(oracle.rt, codec, group)
            now = hyps[0][0].rt.state
            went = _state_change(state, now)
            if went:
                transitions.append((t_tick, went))
            state, xi_prev = now, hyps[0][0].rt.cstate.xi_prev
            page_t[_page(codec, group, diag_id)] = t_tick
            outcome.ticks += 1
            prev_t = t_tick
    return outcome


def _page(codec: FrameCodec, group: Sequence[Frame], diag_id: int) -> int | None:
    for f in group:
        if f.msg.arbitration_id == diag_id:
            try:
                return _signals(codec, f.msg)["Page"]
            except (BessDedError, KeyError):
                return None
    return None


def _state_change(before: State, after: State) -> str:
    return f"{before.name} → {after.name}" if before != after else ""


# the orders of reception kept per tick: up to 64 while the device has matched every
# frame (at 0.5 Ts of lateness on ticks and frames, 16 dropped a conformant device's
# order: a λ one LSB off), 16 once it differs (enough to follow a deviant device on, at
# half the cost of checking it)
MAX_HYPOTHESES = 64
DIVERGED_HYPOTHESES = 16


def _fingerprint(rt: AgentRuntime) -> tuple:
    """What a hypothesis remembers that the DUT's frames can show, receive times aside:
    hypotheses that differ only in when frames arrived are one (the likeliest kept);
    whether an input was late matters at the tick it is late for, and each tick tries
    that again."""
    return (rt.state, rt.cstate, rt.price, *rt.input_memory(), *rt.transmit_memory(),
            rt.plant_fault, rt.ctrl.kts,
            rt.ctrl.hts, tuple((s.lam, s.state, s.alive) for s in rt.neighbours.values()),
            tuple(sorted(rt.counters.items())))


def _tick_times(rt: AgentRuntime, prev_t: float, t_tick: float) -> list[float]:
    """When the DUT may have ticked, as far as timeouts can tell: at the receive time of
    its frame, or just before or after any instant where an input goes stale (the
    DUT's receive times are not ours: frames reach its loop later on a busy host)."""
    cfg = rt.cfg
    stale = [s.last_rx + cfg.neighbour_timeout_periods * rt.period
             for s in rt.neighbours.values() if s.last_rx is not None]
    stale += [t + dt for t, dt in ((rt.price_rx, cfg.price_timeout_s),
                                   (rt.status_rx, cfg.status_timeout_s)) if t is not None]
    # the DUT's clock never goes back: not before this hypothesis's previous tick
    earliest = max(prev_t - LATE_TICKS * rt.period, rt.now)
    near = sorted(b for b in stale if earliest < b - 1e-6 and b < t_tick)
    return [t_tick, *(b - 1e-6 for b in near)]


LATE_TICKS = 10
"""How late (in ticks) a DUT's loop may take a frame that the tester has sent, as far as
its timeouts are concerned: on a starved host frames wait in the socket, and the DUT
stamps them when it reads them (LOOP-1)."""


def _step_name(inputs: Sequence[Frame], t: float) -> str:
    last = ""
    for f in inputs:
        if f.t > t:
            break
        last = f.step
    return last


def _tick_groups(frames: Sequence[Frame], mc_id: int, dut_ids: set[int]) -> list[list[Frame]]:
    """The DUT's frames grouped by tick (TICK-1: syncs, MC, Setpoint, Diag), the MC
    first in each group (its receive time is the group's time)."""
    groups: list[list[Frame]] = []
    current: list[Frame] = []
    for f in frames:
        fid = f.msg.arbitration_id
        if f.sent or fid not in dut_ids:
            continue
        if (fid == mc_id or fid in contract.SYNCED_BY) and any(
                g.msg.arbitration_id == mc_id for g in current):
            groups.append(current)
            current = []
        current.append(f)
    groups.append(current)
    return [sorted(g, key=lambda f: f.msg.arbitration_id != mc_id) for g in groups
            if any(f.msg.arbitration_id == mc_id for f in g)]


def dut_ticks(cfg: AgentConfig, codec: FrameCodec, frames: Sequence[Frame]) -> list[float]:
    """When the DUT of a record ticked: at its MC frames, or in event mode (TX-7) at
    ``_event_ticks``' ticks."""
    mc_id = codec.frame_id(mc_name(cfg.id))
    if not cfg.transmit.event:
        return [f.t for f in frames if not f.sent and f.msg.arbitration_id == mc_id]
    own = {codec.frame_id(n(cfg.id)) for n in (mc_name, setpoint_name, diag_name)}
    return [t for t, _ in _event_ticks(frames, mc_id, own | {contract.SYNC_OF[f] for f in own},
                                       cfg.controller.ts)]


def _check_new_boot(codec: FrameCodec, frames: Sequence[Frame], sync_ids: set[int],
                    filed: int, inputs: Sequence[Frame], outcome: Outcome) -> None:
    """AUTH-3: the boot of the DUT's first sync in the record is above ``filed``, the
    key file's boot counter as the tester wrote it (B + 1 at the device's start)."""
    sync = next((f for f in frames if not f.sent and f.msg.arbitration_id in sync_ids), None)
    try:
        boot = _signals(codec, sync.msg)["Boot"] if sync is not None else None
    except BessDedError:
        return  # a malformed sync: its own difference
    if boot is not None and sync is not None and boot <= filed:
        t0 = inputs[0].t if inputs else sync.t
        want = f"above {filed} (the key file's boot counter, + 1 at the start)"
        outcome.mismatches.append(Mismatch(sync.t - t0, 0, _step_name(inputs, sync.t) or
                                           "start", "Sync", "Boot", want, boot,
                                           raw=(filed + 1, boot)))


def _next_state(codec: FrameCodec, after: Sequence[tuple[float, list[Frame]]],
                mc_id: int) -> State | None:
    """The State of the DUT's next MC frame in ``after`` (None: none)."""
    for _, group in after:
        for f in group:
            if f.msg.arbitration_id == mc_id:
                try:
                    return State(_signals(codec, f.msg)["State"])
                except (BessDedError, ValueError):
                    return None
    return None


def _adopt_last_mc(rt: AgentRuntime, codec: FrameCodec,
                   before: Sequence[tuple[float, list[Frame]]], mc_id: int) -> None:
    """Event mode (TX-7): the oracle starts with the DUT's memory of its last MC frame
    (the newest in ``before``, the ticks preceding the oracle's first)."""
    for ago, (_, group) in enumerate(reversed(before)):
        mc = next((f for f in group if f.msg.arbitration_id == mc_id), None)
        if mc is not None:
            try:
                s = _signals(codec, mc.msg)
                rt.adopt_transmit((s["Lambda"], State(s["State"])), ago)
            except (BessDedError, ValueError):
                pass  # a malformed frame: the oracle starts with no memory of one
            return


def _event_ticks(frames: Sequence[Frame], mc_id: int, dut_ids: set[int], ts: float
                 ) -> list[tuple[float, list[Frame]]]:
    """Event-triggered sending (TX-7): the DUT's ticks, (time, frames), a tick's frames
    being those it sends together (a frame of an ID the tick already has, or one more
    than half a period after its first, starts the next), MC first; and between two
    ticks n periods apart the n − 1 that sent nothing (MC not due, no Setpoint, Diag or
    sync either), at their times by the period."""
    groups: list[list[Frame]] = []
    for f in frames:
        fid = f.msg.arbitration_id
        if f.sent or fid not in dut_ids:
            continue
        if (not groups or f.t - groups[-1][0].t > 0.5 * ts
                or any(g.msg.arbitration_id == fid for g in groups[-1])):
            groups.append([])
        groups[-1].append(f)
    ticks: list[tuple[float, list[Frame]]] = []
    for g in groups:
        if ticks:
            t_prev = ticks[-1][0]
            n = max(1, round((g[0].t - t_prev) / ts))
            ticks += [(t_prev + k * (g[0].t - t_prev) / n, []) for k in range(1, n)]
        ticks.append((g[0].t, sorted(g, key=lambda f: f.msg.arbitration_id != mc_id)))
    return ticks


def _compare(codec: FrameCodec, expected: Sequence[can.Message], group: Sequence[Frame],
             tick: int, step: str, t: float, syncs: bool = True,
             event: tuple[State, int] | None = None) -> list[Mismatch]:
    """The DUT's frames of one tick against the oracle's (``t``: from the schedule's
    start, for the report): its sync frames first (AUTH-9: which are due, and their
    Count), then MC, Setpoint and Diag. ``event``: the oracle's (State, λ) on an
    event-triggered device (TX-7), to judge an MC frame it sent and the oracle did not."""
    diffs: list[Mismatch] = []
    if not syncs:  # ``syncs``: compare the sync frames too
        group = [f for f in group if f.msg.arbitration_id not in contract.SYNCED_BY]
        expected = [m for m in expected if m.arbitration_id not in contract.SYNCED_BY]
    got_syncs = [f.msg for f in group if f.msg.arbitration_id in contract.SYNCED_BY]
    exp_syncs = [m for m in expected if m.arbitration_id in contract.SYNCED_BY]
    names = [codec.name_of(m.arbitration_id) for m in got_syncs]
    names_exp = [codec.name_of(m.arbitration_id) for m in exp_syncs]
    if names != names_exp:
        diffs.append(Mismatch(t, tick, step, "Sync", "frames", names_exp or "no sync",
                              names or "no sync", raw=(names_exp, names)))
    else:
        for e, g in zip(exp_syncs, got_syncs, strict=True):
            diffs += _compare_signals(codec, e, g, "Sync", tick, step, t)
    got = [f.msg for f in group if f.msg.arbitration_id not in contract.SYNCED_BY]
    exp = [m for m in expected if m.arbitration_id not in contract.SYNCED_BY]
    if event is not None:  # TX-7: whether the MC frame was due is a signal of its own
        mc = [[m for m in ms if codec.name_of(m.arbitration_id).endswith("_MC")]
              for ms in (exp, got)]
        if bool(mc[0]) != bool(mc[1]):
            if mc[1]:  # sent, not due: first what its State and λ show against the oracle's
                try:
                    shown = _signals(codec, mc[1][0])
                except BessDedError:
                    shown = {}  # a malformed frame: MC.sent alone
                diffs += [Mismatch(t, tick, step, "MC", name, _show(name, want),
                                   _show(name, shown[name]), raw=(want, shown[name]))
                          for name, want in zip(("State", "Lambda"), (int(event[0]), event[1]),
                                                strict=True)
                          if name in shown and shown[name] != want]
            want, sent = ("sent" if m else "not sent" for m in mc)
            diffs.append(Mismatch(t, tick, step, "MC", "sent", want, sent, raw=(want, sent)))
            exp, got = ([m for m in ms if m not in mc[0] + mc[1]] for ms in (exp, got))
    names_got = [codec.name_of(m.arbitration_id) for m in got]
    names_exp = [codec.name_of(m.arbitration_id) for m in exp]
    if names_got != names_exp:
        return diffs + [Mismatch(t, tick, step, "frames of the tick", "", names_exp,
                                 names_got)]
    for e, g in zip(exp, got, strict=True):
        kind = codec.name_of(e.arbitration_id).split("_")[-1]
        diffs += _compare_signals(codec, e, g, kind, tick, step, t)
    return diffs


def _compare_signals(codec: FrameCodec, e: can.Message, g: can.Message, kind: str,
                     tick: int, step: str, t: float) -> list[Mismatch]:
    """``g``'s signals against ``e``'s: a Mismatch per signal that differs (one for the
    frame when ``g`` cannot be decoded)."""
    se = _signals(codec, e)
    try:
        sg = _signals(codec, g)
    except BessDedError as err:
        return [Mismatch(t, tick, step, kind, "frame", "a frame of the DBC", str(err))]
    # not compared: what the MAC check covers (Mac, Counter, a λ's tags: AUTH-34; their
    # receivers are), the host's DeadlineMisses, and a sync's Boot (the DUT's key file's,
    # which _check_auth verifies it at)
    return [Mismatch(t, tick, step, kind, name, _show(name, value), _show(name, sg.get(name)),
                     raw=(value, sg.get(name)))
            for name, value in se.items()
            if name not in ("Mac", "Counter", "CRC", "DeadlineMisses", "Boot")
            and not _TAG.fullmatch(name) and sg.get(name) != value]


_TAG = re.compile(r"Tag[0-9]+")  # a tag slot's tag (not its receiver, TagRx<k>)


def _show(name: str, raw: Any) -> Any:
    if name == "Lambda" and isinstance(raw, int):
        return f"{raw} ({raw / (1 << 24):.9f})"
    if name == "State" and isinstance(raw, int):
        return State(raw).name
    return raw


# Diag signal → the counter of AgentRuntime.counters it shows (the others are derived)
_DIAG_COUNTERS = {
    "RejectedCrc": "crc", "RejectedDlc": "dlc", "RejectedRange": "range",
    "RejectedUnknownId": "unknown_id", "RejectedImpersonation": "impersonation",
    "RepeatedCounter": "repeated_counter", "LostFrames": "lost_frames",
    "NeighbourTimeouts": "neighbour_timeouts", "PriceTimeouts": "price_timeouts",
    "StatusTimeouts": "status_timeouts", "PlantFaults": "plant_faults",
    "ForeignFrames": "foreign", "ForeignIds": "foreign_id",
    "InterleavedCounters": "counter_jump", "Untrusted": "untrusted_sources",
    "ImplausiblePrice": "implausible_price", "ImplausibleLambda": "implausible_lambda",
    "ImplausibleGains": "implausible_gains", "RejectedAuth": "auth",
    "Unsynced": "unsynced", "Resyncs": "resyncs", "Saturations": "saturations"}


def _adopt(rt: AgentRuntime, codec: FrameCodec, group: Sequence[Frame], mc_id: int,
           diag_id: int) -> None:
    """After a difference, re-synchronise the oracle to what the DUT's frames show (λ,
    state, the reset count, the Diag counters of the page; in event mode whether it sent
    its MC frame) and check the rest from there: one fault then fails where it shows,
    not every frame after it."""
    _adopt_syncs(rt, codec, group)
    for f in group:
        fid = f.msg.arbitration_id
        try:
            s = _signals(codec, f.msg)
        except BessDedError:
            continue
        if fid == mc_id:
            rt.state = State(s["State"])
            rt.adopt_transmit((s["Lambda"], rt.state), 0)  # TX-7: sent at this tick
            if rt.lambda_q24 != s["Lambda"]:  # its guard bits are unknown: the wire value's
                rt.cstate = replace(rt.cstate, lam=fx.widen(s["Lambda"]))
            mod = rt.resets_modulo
            if rt.cstate.resets % mod != s["Resets"]:
                rt.cstate = replace(rt.cstate, resets=rt.cstate.resets
                                    + (s["Resets"] - rt.cstate.resets) % mod)
        elif fid == diag_id:
            values = rt.diag_values()
            for name, got in s.items():
                want = min(values.get(name, got), rt.diag_max.get(name, got))
                if name not in values or got == want or got >= rt.diag_max.get(name, 1 << 62):
                    continue
                if name == "Resets":
                    rt.cstate = replace(rt.cstate, resets=got)
                elif name in _DIAG_COUNTERS:
                    rt.counters[_DIAG_COUNTERS[name]] += got - values[name]


def _sync_slack(rt: AgentRuntime, codec: FrameCodec,
                before: SyncSchedule, sent: Sequence[can.Message],
                group: Sequence[Frame], diffs: list[Mismatch], t: float) -> list[Mismatch]:
    """A sync due exactly on a tick (every ``sync_s``, ``hello_gap`` after a hello) is
    due on either side of it by the clocks' noise: syncs one tick early or late are in
    time (the oracle's schedule then follows the DUT's)."""
    rest = [d for d in diffs if not (d.message == "Sync" and d.signal == "frames")]
    if len(rest) == len(diffs):
        return diffs
    io = rt.io
    dut = any(f.msg.arbitration_id in contract.SYNCED_BY for f in group)
    ours = any(m.arbitration_id in contract.SYNCED_BY for m in sent)
    slack = 1.5 * rt.period
    if dut and not ours:
        when = io.sync_schedule
        nxt = [x for x in (when.next, when.hello_after if when.hello_due else None)
               if x is not None]
        if nxt and min(nxt) - t <= slack:  # the oracle's were due at the next tick
            _adopt_syncs(rt, codec, group)
            return rest
    elif ours and not dut:
        sync_next, hello_due, hello_after = before
        due = [x for x in (sync_next, hello_after if hello_due else None)
               if x is not None and x <= t]
        if due and t - min(due) <= slack:  # the DUT's are due at its next tick
            io.sync_schedule = before
            return rest
    return diffs


def _adopt_syncs(rt: AgentRuntime, codec: FrameCodec, group: Sequence[Frame]) -> None:
    """The DUT sent its syncs at this tick: the oracle's sync schedule and message counts
    go on from the DUT's."""
    io = rt.io
    if not any(f.msg.arbitration_id in contract.SYNCED_BY for f in group):
        return
    t = group[0].t
    io.syncs_sent_at(t)
    for f in group:
        synced = contract.SYNCED_BY.get(f.msg.arbitration_id)
        if synced is None:
            continue
        try:
            count = _signals(codec, f.msg)["Count"]
        except BessDedError:
            continue
        # the count it announces, then the tick's frames of that ID
        io.follow_tx_count(synced, count + sum(g.msg.arbitration_id == synced for g in group))


Verifier = Callable[[int, bytes | bytearray, int], bool]
"""Whether a DUT frame's bytes verify for a data ID at a freshness value."""


def _verifier(codec: FrameCodec, keyring: Keyring, key: bytes, fid: int) -> Verifier:
    """How the DUT's frames of ``fid`` (and its sync) verify: the Mac under ``key``, or on
    a tagged FD bus every receiver's tag of its λ under the pair's key (AUTH-34)."""
    name = codec.name_of(fid)
    if not codec.tag_slots(name):
        return lambda data_id, data, fv: secoc.frame_verifies(key, data_id, data, fv)
    sender = contract.sender_of(name)

    def pair_key(label: str) -> bytes | None:
        sender, receiver = label.split(">")
        return keyring.tag_key(sender, receiver)
    return lambda data_id, data, fv: secoc.tags_verify(pair_key, sender, data_id, data, fv)


def _check_auth(codec: FrameCodec, keys: Mapping[int, Verifier], frames: Sequence[Frame],
                syncs: Mapping[int, int], outcome: Outcome, t0: float = 0.0) -> None:
    """Every secured DUT frame verifies at the freshness its syncs announce, +1 per
    frame (AUTH-4, AUTH-6..8). ``t0``: the schedule's start (``auth_times``)."""
    nxt: dict[int, int] = {}
    prev_t = t0
    for f in frames:
        while len(outcome.auth_times) < len(outcome.auth_errors):
            outcome.auth_times.append(prev_t - t0)
        prev_t = f.t
        fid = f.msg.arbitration_id
        if f.sent:
            continue
        if fid in syncs:
            try:
                s = _signals(codec, f.msg)
            except BessDedError as e:
                outcome.auth_errors.append(f"t = {f.t:.3f} s: {e}")
                continue
            fv = contract.FRESHNESS.join(s["Boot"], s["Count"])
            if not keys[syncs[fid]](fid, f.msg.data, fv):
                outcome.auth_errors.append(f"t = {f.t:.3f} s: {codec.name_of(fid)} MAC does "
                                           f"not verify at Boot {s['Boot']} Count {s['Count']}")
            elif syncs[fid] in nxt and fv != nxt[syncs[fid]]:
                outcome.auth_errors.append(f"t = {f.t:.3f} s: {codec.name_of(fid)} announces "
                                           f"{fv:#x}, the frames reached {nxt[syncs[fid]]:#x}")
            nxt[syncs[fid]] = fv
        elif fid in nxt:
            fv = nxt[fid]
            want = secoc.truncate(fv, contract.FV_TX_BITS)  # AUTH-6: the Counter on the wire
            try:
                counter = _signals(codec, f.msg)["Counter"]
            except BessDedError as e:
                counter = None
                outcome.auth_errors.append(f"t = {f.t:.3f} s: {e}")
            if counter is not None and counter != want:
                outcome.auth_errors.append(f"t = {f.t:.3f} s: {codec.name_of(fid)} Counter "
                                           f"{counter}, expected {want}")
            elif counter is not None and not keys[fid](fid, f.msg.data, fv):
                outcome.auth_errors.append(f"t = {f.t:.3f} s: {codec.name_of(fid)} MAC does "
                                           f"not verify at freshness {fv:#x}")
            nxt[fid] = fv + 1
    while len(outcome.auth_times) < len(outcome.auth_errors):
        outcome.auth_times.append(frames[-1].t - t0 if frames else 0.0)
    if not nxt:
        outcome.auth_times.append(0.0)
        outcome.auth_errors.append("the DUT sent no sync frame: its freshness is unknown "
                                   "(AUTH-9: syncs at start, every 100 Ts, and after a "
                                   "peer's restart)")
