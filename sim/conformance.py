"""Conformance of an agent node on the bus (`bess-ded conformance`).

The tester is the rest of the bus for one device under test (DUT), agent I: it plays
the router (price, commands), the plant (agent I's status) and I's neighbours (their MC
frames), all signed with the run's keys, along a fixed schedule of steps (``plan``):
start-up, control with moving neighbours, forged and replayed frames, malformed and
implausible content, every command, and every timeout. It records what the DUT sends.

Verdict (``check``): firmware_py's own agent runtime is the oracle. It receives the same
frames at the times the tester sent them and ticks when the DUT ticked (the receive time
of each DUT MC frame); every DUT frame must then equal the oracle's at the signal level
(MC: State, Lambda, Resets; Setpoint: Enable, PowerSetpoint; Diag: every page value but
DeadlineMisses, which depends on the DUT's host), and every secured DUT frame must carry
a MAC that verifies with the DUT's key at consecutive freshness values. Where the bus
leaves the order open (a frame sent while the DUT was ticking), the oracle tries each
order and keeps the one that explains the DUT, so a conformant DUT passes at any load.

A mismatch fails the requirement IDs of docs/firmware-spec.md that the step exercises and
the mismatching signal belongs to. When a known deviation (``MUTANTS``: e.g. the band
re-armed at the reset sample) explains the DUT's frames from the start, the report names
that requirement.
"""

from __future__ import annotations

import copy
import functools
import logging
import math
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import can

from firmware_py import contract, secoc
from firmware_py import fixedpoint as fx
from firmware_py.config import AgentConfig
from firmware_py.contract import Command, State
from firmware_py.controllers import PIController
from firmware_py.errors import BessDedError
from firmware_py.frames import FrameCodec, diag_name, mc_name, setpoint_name, status_name
from firmware_py.nodeio import FleetSender
from firmware_py.runtime import AgentRuntime
from firmware_py.secoc import Keyring

# docs/firmware-spec.md's requirement IDs in order, shipped as package data (docs/ is not
# installed); tools/gen_spec_ids.py writes it, a test checks it against the spec
REQUIREMENTS_FILE = Path(__file__).resolve().parent / "spec_requirements.txt"


# --------------------------------------------------------------------------- the schedule


@dataclass(frozen=True)
class Step:
    """One part of the schedule, in ticks of the DUT's Ts: what it does and the
    requirements (docs/firmware-spec.md IDs) its frames exercise."""

    name: str
    start: int
    end: int
    what: str
    musts: tuple[str, ...]


STEPS = (
    Step("start", 0, 30, "syncs of every input, then silence: the DUT stays INIT with λ(0), "
         "answers the syncs, sends MC/Setpoint/Diag at their cadences",
         ("GEN-2", "STATE-1", "STATE-10", "TICK-1", "TX-1", "TX-2", "TX-3", "TX-4", "TX-5",
          "SP-3", "DIAG-1", "AUTH-4", "AUTH-6", "AUTH-7", "AUTH-8", "AUTH-9", "AUTH-16",
          "AUTH-21", "RX-4")),
    Step("price-only", 30, 60, "price and neighbours but no plant status: still INIT",
         ("STATE-2", "STATE-5", "TMO-3", "LIVE-1", "LIVE-2", "PRICE-6", "AUTH-12",
          "AUTH-15")),
    Step("running", 60, 100, "plant status too: INIT → RUNNING, the setpoint follows λ",
         ("STATE-4", "STATE-6", "SP-1", "TX-2", "RX-11", "XI-1", "XI-2")),
    Step("control", 100, 450, "neighbours' λ moving (steps and a slow sine): every step "
         "of the reset-PI, bit for bit",
         ("CTRL-1", "CTRL-4", "CTRL-5", "XI-1", "XI-2", "XI-3", "STEP-1", "STEP-2",
          "STEP-3", "STEP-4", "STEP-5", "STEP-6", "STEP-7", "STEP-8", "STEP-9", "BAND-1",
          "BAND-2", "BAND-3", "TX-1", "SP-1", "LAM-2", "DIAG-1", "NUM-1", "NUM-2",
          "NUM-3")),
    Step("authentication", 450, 510, "forged MACs, a replayed frame, a replayed sync, a "
         "frame from another boot, a genuine frame delivered late (stale, not auth): "
         "rejected and counted, λ unmoved by them",
         ("RX-8", "AUTH-10", "AUTH-11", "AUTH-12", "AUTH-13", "AUTH-14", "AUTH-16",
          "AUTH-17", "AUTH-25", "RX-12", "RX-13", "DIAG-4")),
    Step("content", 510, 580, "an extended ID, an unknown ID, the DUT's own ID, a short "
         "frame, a price out of bounds, a persistent price step, a neighbour λ jump",
         ("RX-1", "RX-3", "RX-6", "RX-7", "RX-9", "RX-10", "PRICE-2", "PRICE-3", "PRICE-4",
          "LAM-1", "DIAG-1", "DIAG-4")),
    Step("commands", 580, 710, "SET_GAINS in and out of bounds, a command for another "
         "agent, ISOLATE, RECONNECT",
         ("CMD-1", "CMD-2", "CMD-3", "CMD-4", "CMD-5", "STATE-7", "STATE-8", "STATE-9",
          "STATE-10")),
    Step("timeouts", 710, 910, "a neighbour silent, the price silent (SAFE), a plant "
         "fault (SAFE), each followed by recovery",
         ("LIVE-2", "LIVE-3", "TMO-1", "TMO-2", "TMO-4", "STATE-3", "STATE-4", "STATE-6",
          "RX-11", "AUTH-13")),
)


PULSE = 0.05  # cu/kWh: well above the reset band, below lambda_step_max (10·k·Ts)


@dataclass(frozen=True)
class Planned:
    """A frame the tester sends ``at`` s after the start of the schedule."""

    at: float
    step: str
    msg: can.Message
    note: str = ""


def _tick_of(name: str) -> Callable[[int], bool]:
    every = contract.every_ticks(name)
    return lambda k: k % every == 0


def plan(cfg: AgentConfig, keys: Mapping[str, bytes] | None, price: float,
         codec: FrameCodec | None = None, boot: int = secoc.INSECURE_BOOT) -> list[Planned]:
    """The tester's frames for DUT ``cfg`` (times in s from the start), signed with
    ``keys`` (label → key of the router, the plant and the neighbours; None: the
    insecure keys). ``price``: the ρ to hold (the scenario's first). ``boot``: the boot
    every sender the tester plays runs at, at least the DUT's boot floors (AUTH-21);
    above 1, an earlier run's price sync (boot − 1) comes first."""
    codec = codec or FrameCodec()
    tx = FleetSender(codec, keys, boot=boot if keys is not None else secoc.INSECURE_BOOT)
    ts, i = cfg.controller.ts, cfg.id
    nbrs = [n.id for n in cfg.neighbours]
    out: list[Planned] = []
    price_every, status_every = _tick_of("ER_Price"), _tick_of(status_name(i))
    k_gain, h_gain = cfg.controller.k, cfg.controller.h
    other = i % contract.N_AGENTS_MAX + 1
    at = {s.name: s.start for s in STEPS}

    def add(k: float, step: str, msg: can.Message, note: str = "") -> None:
        out.append(Planned(k * ts, step, msg, note))

    def step_at(k: int) -> str:
        return next(s.name for s in STEPS if s.start <= k < s.end)

    def q(x: float) -> int:
        return round(x * (1 << 24))

    # Until the control step every input sits just off the DUT's λ(0), so that |ξ| stays
    # inside the reset band; at tick 80 the inputs move to the other side: a zero
    # crossing that only an agent armed from the start resets on (BAND-1).
    lam0 = cfg.lambda0
    weights = sum(n.weight for n in cfg.neighbours) + (1.0 if cfg.pinned else 0.0)
    offset = cfg.controller.band / (2 * weights) if weights else 0.0
    if cfg.pinned and not cfg.rho_min + offset <= lam0 <= cfg.rho_max - offset:
        lam0, offset = price, 0.0  # a price at λ(0) would be implausible: no BAND-1 test

    def start_value(k: int) -> float:
        return lam0 - offset if k < 80 else lam0 + offset

    def ramp(k: int, target: float) -> float:
        """From the start value to ``target`` over the first 60 ticks of control."""
        w = min(1.0, max(0.0, (k - at["control"]) / 60))
        return start_value(k) + (target - start_value(k)) * w

    def lam_j(j: int, k: int) -> int:
        """Neighbour j's λ at tick k: from the control step on, a slow sine (per j) with
        steps below the plausibility limit and one-tick pulses of either sign: a pulse
        against the sign of ξ is a zero crossing at once followed by another (a reset
        sample followed by a crossing: BAND-2, STEP-2..5)."""
        base = price + 0.05 * (nbrs.index(j) + 1) * (-1) ** j
        if k < at["control"]:
            return q(start_value(k))
        c = k - at["control"]
        square = 0.04 if (c // 70) % 2 else -0.04
        pulse = PULSE if c % 20 == 10 and c < 340 else 0.0
        pulse *= -1 if c % 40 == 10 else 1
        return q(ramp(k, base + square + pulse + 0.2 * math.sin(2 * math.pi * c /
                                                                  (230 + 17 * j))))

    status = {"FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
              "Power": 0, "Soc": 100}
    inputs = ["ER_Price", "ER_Command", status_name(i), *map(mc_name, nbrs)]
    if tx.boot > secoc.INSECURE_BOOT:  # below the DUT's floor: auth, it sets nothing
        earlier = FleetSender(codec, keys, boot=tx.boot - 1)
        add(0, "start", earlier.sync("ER_Price"), "an earlier run's price sync (AUTH-21)")
    for name in inputs:
        add(0, "start", tx.sync(name), f"sync of {name}")
    first_sync = next(p.msg for p in out if p.note == "sync of ER_Price")
    genuine: list[can.Message] = []
    held: list[can.Message] = []   # a genuine frame delivered late (AUTH-25)
    for k in range(30, STEPS[-1].end):
        step = step_at(k)
        silent_nbr = 10 <= k - at["timeouts"] < 20
        silent_price = 40 <= k - at["timeouts"] < 80
        fault = 120 <= k - at["timeouts"] < 140
        for j in nbrs:
            if silent_nbr and j == nbrs[0]:
                continue
            lam = lam_j(j, k)
            if k == at["content"] + 30 and j == nbrs[0]:
                lam += q(0.5)  # a jump above lambda_step_max per sample: implausible
            msg = tx.frame(mc_name(j), {"State": int(State.RUNNING), "Lambda": lam,
                                        "Resets": 0})
            add(k + 0.5, step, msg)
            genuine.append(msg)
        if price_every(k) and not silent_price:
            r = q(ramp(k, price))
            if 20 <= k - at["content"] < 25:
                r = q(6.0)  # above rho_max: implausible
            elif 40 <= k - at["content"] < 70:
                r = q(price + 0.6)  # a step above price_step_max, persistent
            add(k + 0.25, step, tx.frame("ER_Price", {"PriceValid": 1, "Segment": 0,
                                                      "Rho": r}))
        if k >= 60 and status_every(k):
            add(k + 0.75, step, tx.frame(status_name(i), {**status,
                                                          "FaultOverCurrent": int(fault)}))
        if k == at["authentication"] + 10:  # a forged MAC on a neighbour's frame with a wild λ
            forged = tx.frame(mc_name(nbrs[0]) if nbrs else "ER_Price", {
                "State": int(State.RUNNING), "Lambda": q(3.0), "Resets": 0} if nbrs else {
                "PriceValid": 1, "Segment": 0, "Rho": q(3.0)})
            forged.data[0] ^= 0x5A
            add(k + 0.6, step, forged, "forged MAC")
        if k == at["authentication"] + 20:
            add(k + 0.6, step, _copy(genuine[-40]), "replay of a genuine frame")
        if k == at["authentication"] + 30:
            add(k + 0.6, step, _copy(first_sync), "replay of the first price sync")
        if k == at["authentication"] + 40:  # the right key, but a boot never announced
            later = FleetSender(codec, keys, boot=tx.boot + 5)
            add(k + 0.6, step, later.frame("ER_Price", {"PriceValid": 1, "Segment": 0,
                                                        "Rho": q(price)}),
                "frame from another boot")
        if k == at["authentication"] + 50:  # a genuine frame held back: lost for now
            held.append(tx.frame(mc_name(nbrs[0]), {
                "State": int(State.RUNNING), "Lambda": lam_j(nbrs[0], k), "Resets": 0})
                if nbrs else tx.frame("ER_Price", {"PriceValid": 1, "Segment": 0,
                                                   "Rho": q(price)}))
        if k == at["authentication"] + 53:  # ... delivered 3 ticks late: stale, not auth
            add(k + 0.6, step, held[0], "a genuine frame delivered 3 ticks late")
        if k == at["content"] + 5:
            add(k + 0.6, step, can.Message(arbitration_id=0x100 + i, is_extended_id=True,
                                           data=bytes(8)), "extended ID")
        if k == at["content"] + 7:
            add(k + 0.6, step, can.Message(arbitration_id=_unknown_id(codec),
                                           is_extended_id=False, data=bytes(8)), "unknown ID")
        if k == at["content"] + 9:
            add(k + 0.6, step, can.Message(arbitration_id=codec.frame_id(mc_name(i)),
                                           is_extended_id=False, data=bytes(range(8))),
                "the DUT's own MC ID")
        if k == at["content"] + 11 and nbrs:
            short = tx.frame(mc_name(nbrs[0]), {"State": int(State.RUNNING),
                                                 "Lambda": lam_j(nbrs[0], k), "Resets": 0})
            add(k + 0.6, step, can.Message(arbitration_id=short.arbitration_id,
                                           is_extended_id=False, data=short.data[:7]),
                "DLC 7")
        for tick, cmd, target, kk, hh, note in (
                (10, Command.SET_GAINS, i, 1.5 * k_gain, 1.5 * h_gain, "SET_GAINS in bounds"),
                (20, Command.SET_GAINS, i, 3 * k_gain, h_gain, "SET_GAINS out of bounds"),
                (30, Command.ISOLATE, other, 0, 0, "ISOLATE for another agent"),
                (40, Command.ISOLATE, i, 0, 0, "ISOLATE"),
                (50, Command.ISOLATE, i, 0, 0, "ISOLATE while ISOLATED"),
                (70, Command.RECONNECT, i, 0, 0, "RECONNECT")):
            if k == at["commands"] + tick:
                add(k + 0.6, step, tx.frame("ER_Command", {
                    "Command": int(cmd), "Target": target, "GainK": round(kk * 1000),
                    "GainH": round(hh * 1000)}), note)
    out.sort(key=lambda p: p.at)
    return out


def _copy(msg: can.Message) -> can.Message:
    return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False,
                       data=bytes(msg.data))


def _unknown_id(codec: FrameCodec) -> int:
    return next(fid for fid in range(0x7FF, 0, -1) if fid not in codec.frame_ids())


# --------------------------------------------------------------------------- deviations


class _BandAtReset(PIController):
    """The band re-armed at the reset sample itself (BAND-2 violated)."""

    def step(self, s: Any, xi: Any) -> Any:
        out_state, out = super().step(s, xi)
        if out.reset and abs(xi) > self.band:
            out_state = replace(out_state, armed=True)
        return out_state, out


def _band_at_reset(rt: AgentRuntime) -> None:
    _patch_controller(rt, "_BandAtReset", _BandAtReset)


def _armed_false(rt: AgentRuntime) -> None:
    rt.cstate = replace(rt.cstate, armed=False)


def _patch_controller(rt: AgentRuntime, name: str, mixin: type) -> None:
    cls = type(rt.ctrl)
    rt.ctrl.__class__ = type(name + cls.__name__, (mixin, cls), {})


MUTANTS: dict[str, tuple[str, Callable[[AgentRuntime], None]]] = {
    "BAND-2": ("the reset band re-arms at the reset sample itself", _band_at_reset),
    "BAND-1": ("the reset is not armed at start", _armed_false),
}
"""Known deviations: requirement → (what the DUT does instead, how to make the oracle do
it). Used only to name the requirement when the DUT fails."""


# --------------------------------------------------------------------------- the record


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
        return self.t if self.t_end is None else self.t_end


@dataclass
class Mismatch:
    t: float
    tick: int
    step: str
    message: str
    signal: str
    expected: Any
    got: Any

    def __str__(self) -> str:
        return (f"t = {self.t:.3f} s (the device's tick {self.tick}, step {self.step}): "
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


# Which requirements a mismatch on a signal violates (besides the step's)
SIGNAL_MUSTS: dict[str, tuple[str, ...]] = {
    "MC.Lambda": ("XI-2", "STEP-6", "STEP-7", "STEP-8", "TX-1"),
    "MC.State": ("STATE-3", "STATE-4", "STATE-5", "STATE-7", "STATE-8", "STATE-9"),
    "MC.Resets": ("STEP-3", "BAND-3", "TX-1"),
    "Setpoint.Enable": ("TX-2", "SP-3"),
    "Setpoint.PowerSetpoint": ("SP-1", "TX-2"),
    "Diag.RejectedAuth": ("AUTH-14", "AUTH-16", "AUTH-21", "RX-8"),
    "Diag.Unsynced": ("AUTH-11", "AUTH-14"),
    "Diag.Resyncs": ("AUTH-16", "AUTH-21"),
    "Diag.LostFrames": ("AUTH-15",),
    "Diag.RejectedDlc": ("RX-7",),
    "Diag.RejectedRange": ("RX-7", "RX-9"),
    "Diag.RejectedUnknownId": ("RX-1", "RX-6"),
    "Diag.RejectedImpersonation": ("RX-3",),
    "Diag.ImplausiblePrice": ("PRICE-2", "PRICE-4"),
    "Diag.ImplausibleLambda": ("LAM-1",),
    "Diag.ImplausibleGains": ("CMD-5",),
    "Diag.NeighbourTimeouts": ("LIVE-3",),
    "Diag.PriceTimeouts": ("TMO-2",),
    "Diag.StatusTimeouts": ("TMO-2",),
    "Diag.PlantFaults": ("RX-11",),
    "Diag.SafetySender": ("DIAG-4",),
    "Diag.SafetyCause": ("DIAG-4",),
    "Diag.Untrusted": ("RX-13",),
    "Diag.Resets": ("DIAG-1", "STEP-1"),
    "Diag.NeighboursAlive": ("DIAG-1", "LIVE-2"),
    "Diag.Saturations": ("DIAG-3", "STEP-9"),
}


@contextmanager
def _quiet_firmware() -> Iterator[None]:
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
        rt, io = self.rt, self.rt.io
        self._shared = {id(x): x for x in (
            codec, keyring, cfg, rt.setpoint, rt._diag_max, rt._mc_max, io._known,
            io._cyclic, io._verify_key, io._synced_by)}

    def clone(self) -> _Oracle:
        twin = copy.copy(self)
        twin.rt = copy.deepcopy(self.rt, dict(self._shared))
        return twin


def _signals(codec: FrameCodec, msg: can.Message) -> dict[str, int]:
    return dict(codec.decode(msg).raw)


def check(cfg: AgentConfig, keyring: Keyring, dut_key: bytes, frames: Sequence[Frame],
          codec: FrameCodec | None = None,
          deviation: Callable[[AgentRuntime], None] | None = None,
          max_mismatches: int = 20, filtered_first: bool = False) -> Outcome:
    """Compare the DUT's frames in ``frames`` (time order) with the oracle's. A DUT may
    filter in its CAN controller what it neither uses nor sends (GEN-5), and then never
    counts the frames of foreign IDs: when the oracle without (``filtered_first``: with)
    a filter does not explain the DUT, the other is tried, and the one that explains
    more is the verdict."""
    first = _check(cfg, keyring, dut_key, frames, codec, deviation, max_mismatches,
                   filtered_first)
    if not first.mismatches:
        return first
    other = _check(cfg, keyring, dut_key, frames, codec, deviation, max_mismatches,
                   not filtered_first)
    if not other.mismatches or ((other.mismatches[0].tick, other.ticks)
                                > (first.mismatches[0].tick, first.ticks)):
        return other
    return first


def _check(cfg: AgentConfig, keyring: Keyring, dut_key: bytes, frames: Sequence[Frame],
           codec: FrameCodec | None, deviation: Callable[[AgentRuntime], None] | None,
           max_mismatches: int, filtered: bool) -> Outcome:
    codec = codec or FrameCodec()
    i = cfg.id
    mc_id, sp_id, diag_id = (codec.frame_id(n(i)) for n in (mc_name, setpoint_name, diag_name))
    own = {mc_id, sp_id, diag_id}
    syncs = {contract.SYNC_OF[fid]: fid for fid in (mc_id, sp_id, diag_id)}
    outcome = Outcome()
    dut_groups = _tick_groups(frames, mc_id, own | set(syncs))
    if not dut_groups:
        outcome.problems.append("no MC frame of the DUT was recorded")
        return outcome
    _check_auth(codec, dut_key, frames, syncs, outcome)
    inputs = [f for f in frames if f.sent]
    outcome.filtered = filtered
    if filtered:
        passed = set(AgentRuntime(cfg, codec, keys=keyring).io.accepted_ids())
        inputs = [f for f in inputs
                  if not f.msg.is_extended_id and f.msg.arbitration_id in passed]
    first_sent = inputs[0].t if inputs else math.inf
    # align the oracle's tick count with the DUT's: the first Diag page before any input
    align = next(((g, f) for g in dut_groups for f in g if f.msg.arbitration_id == diag_id
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
    prev_t = align[0][0].t
    with _quiet_firmware():
        # the last group may be cut short by the end of the recording
        for group in dut_groups[start:-1]:
            t_tick = group[0].t
            step = _step_name(inputs, t_tick)
            if step:
                outcome.steps_seen.add(step)
            found: list[tuple[tuple[int, int, int, int], _Oracle, int]] = []
            failure: tuple[_Oracle, int, list[Mismatch]] | None = None
            for h, (oracle, pending) in enumerate(hyps):
                # inputs sent before the DUT's previous frames reached it before this tick;
                # those sent since may or may not have (each order is a hypothesis)
                sure = pending
                while sure < len(inputs) and inputs[sure].done < prev_t - 0.001:
                    oracle.rt.on_frame(inputs[sure].msg, inputs[sure].done)
                    sure += 1
                maybe = sure + sum(1 for f in inputs[sure:] if f.t < t_tick)
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
                        guesses = _tick_times(chain.rt, prev_t, t_tick)
                        for g, t_guess in enumerate(guesses):
                            # a chain's last use ticks the chain itself, not a copy
                            last = cut == maybe and g == len(guesses) - 1
                            twin = chain if last else chain.clone()
                            diffs = _compare(codec, twin.rt.tick(t_guess), group,
                                             outcome.ticks, step, t_tick - first_sent)
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
                hyps = list(matching.values())[:MAX_HYPOTHESES]
            else:
                assert failure is not None
                outcome.mismatches.extend(failure[2])
                if len(outcome.mismatches) >= max_mismatches:
                    break
                _adopt(failure[0].rt, codec, group, mc_id)
                hyps = [(failure[0], failure[1])]
            outcome.ticks += 1
            prev_t = t_tick
    return outcome


MAX_HYPOTHESES = 16


def _fingerprint(rt: AgentRuntime) -> tuple:
    """What a hypothesis remembers that the DUT's frames can show, receive times aside:
    hypotheses that differ only in when frames arrived are one (the likeliest kept);
    whether an input was late matters at the tick it is late for, and each tick tries
    that again."""
    return (rt.state, rt.cstate, rt.price, rt._price_fresh, rt._status_fresh,
            rt.plant_fault, rt._price_candidate, rt._price_candidate_n, rt.ctrl.kts,
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
    earliest = max(prev_t - LATE_TICKS * rt.period, rt._now)
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


def _compare(codec: FrameCodec, expected: Sequence[can.Message], group: Sequence[Frame],
             tick: int, step: str, t: float) -> list[Mismatch]:
    """The DUT's frames of one tick against the oracle's (``t``: from the schedule's
    start, for the report)."""
    got = [f.msg for f in group if f.msg.arbitration_id not in contract.SYNCED_BY]
    exp = [m for m in expected if m.arbitration_id not in contract.SYNCED_BY]
    diffs: list[Mismatch] = []
    names_got = [codec.name_of(m.arbitration_id) for m in got]
    names_exp = [codec.name_of(m.arbitration_id) for m in exp]
    if names_got != names_exp:
        return [Mismatch(t, tick, step, "frames of the tick", "", names_exp, names_got)]
    for e, g in zip(exp, got, strict=True):
        kind = codec.name_of(e.arbitration_id).split("_")[-1]
        se = _signals(codec, e)
        try:
            sg = _signals(codec, g)
        except BessDedError as err:
            diffs.append(Mismatch(t, tick, step, kind, "frame", "a frame of the DBC", str(err)))
            continue
        for name, value in se.items():
            if name in ("Mac", "Counter", "CRC", "DeadlineMisses"):
                continue
            if sg.get(name) != value:
                diffs.append(Mismatch(t, tick, step, kind, name, _show(name, value),
                                      _show(name, sg.get(name))))
    return diffs


def _show(name: str, raw: Any) -> Any:
    if name == "Lambda" and isinstance(raw, int):
        return f"{raw} ({raw / (1 << 24):.9f})"
    if name == "State" and isinstance(raw, int):
        return State(raw).name
    return raw


def _adopt(rt: AgentRuntime, codec: FrameCodec, group: Sequence[Frame], mc_id: int) -> None:
    """After a mismatch, go on from what the DUT says (λ, state) to check the rest."""
    mc = next(f.msg for f in group if f.msg.arbitration_id == mc_id)
    s = _signals(codec, mc)
    rt.state = State(s["State"])
    if rt.lambda_q24 != s["Lambda"]:  # its guard bits are unknown: take the wire value's
        rt.cstate = replace(rt.cstate, lam=fx.widen(s["Lambda"]))


def _check_auth(codec: FrameCodec, key: bytes, frames: Sequence[Frame],
                syncs: Mapping[int, int], outcome: Outcome) -> None:
    """Every secured DUT frame verifies at the freshness its syncs announce, +1 per
    frame (AUTH-4, AUTH-6..8)."""
    nxt: dict[int, int] = {}
    for f in frames:
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
            if not secoc.frame_verifies(key, fid, f.msg.data, fv):
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
            elif counter is not None and not secoc.frame_verifies(key, fid, f.msg.data, fv):
                outcome.auth_errors.append(f"t = {f.t:.3f} s: {codec.name_of(fid)} MAC does "
                                           f"not verify at freshness {fv:#x}")
            nxt[fid] = fv + 1
    if not nxt:
        outcome.auth_errors.append("the DUT sent no sync frame: its freshness is unknown "
                                   "(AUTH-9: syncs at start, every 100 Ts, and after a "
                                   "peer's restart)")


# --------------------------------------------------------------------------- the report


@dataclass(frozen=True)
class Result:
    must: str
    passed: bool
    detail: str


@functools.cache
def spec_requirements() -> tuple[str, ...]:
    """Every requirement ID of docs/firmware-spec.md, in order (the packaged list)."""
    lines = REQUIREMENTS_FILE.read_text(encoding="utf-8").splitlines()
    return tuple(line for line in lines if line and not line.startswith("#"))


def verdict(outcome: Outcome, steps: Sequence[Step] = STEPS) -> list[Result]:
    """Pass or fail for each requirement the schedule exercises."""
    exercised: dict[str, list[str]] = {}
    for s in steps:
        for m in s.musts:
            exercised.setdefault(m, []).append(s.name)
    failed: dict[str, list[str]] = {}
    for mm in outcome.mismatches:
        musts = set(SIGNAL_MUSTS.get(f"{mm.message}.{mm.signal}", ()))
        step = next((s for s in steps if s.name == mm.step), None)
        if step is not None and musts & set(step.musts):
            musts &= set(step.musts)
        if not musts:
            musts = set(step.musts) if step else {"TICK-1"}
        for must in musts:
            failed.setdefault(must, []).append(str(mm))
    for err in outcome.auth_errors:
        for must in ("AUTH-4", "AUTH-6", "AUTH-7", "AUTH-8"):
            failed.setdefault(must, []).append(err)
    if outcome.explained_by:  # a known deviation explains the DUT: name that one
        first = str(outcome.mismatches[0])
        failed = {must: [f"the DUT behaves as if {what} (first difference: {first})"]
                  for must, what in outcome.explained_by.items()} | {
                 must: why for must, why in failed.items() if must.startswith("AUTH-")}
    results = []
    for must in sorted(exercised, key=_must_order):
        if must in failed:
            results.append(Result(must, False, failed[must][0]))
        elif not set(exercised[must]) & outcome.steps_seen:
            results.append(Result(must, False, "not exercised: the run ended before step "
                                  + exercised[must][0]))
        else:
            results.append(Result(must, True, "steps " + ", ".join(exercised[must])))
    for must in sorted(set(failed) - set(exercised), key=_must_order):
        results.append(Result(must, False, failed[must][0]))
    return results


def _must_order(must: str) -> tuple[int, int]:
    order = spec_requirements()
    prefix, n = must.rsplit("-", 1)
    return (order.index(must) if must in order else len(order), int(n))


def explain(cfg: AgentConfig, keyring: Keyring, dut_key: bytes, frames: Sequence[Frame],
            outcome: Outcome, codec: FrameCodec | None = None) -> None:
    """Name the requirement when a known deviation explains the DUT better than the spec."""
    if not outcome.mismatches:
        return
    first = outcome.mismatches[0].tick
    for must, (what, deviation) in MUTANTS.items():
        alt = check(cfg, keyring, dut_key, frames, codec, deviation, max_mismatches=1,
                    filtered_first=outcome.filtered)
        if not alt.mismatches or alt.mismatches[0].tick > first + 50:
            # check the rest of the schedule with that deviation modelled
            rest = check(cfg, keyring, dut_key, frames, codec, deviation,
                         filtered_first=alt.filtered)
            outcome.explained_by[must] = what
            outcome.steps_seen, outcome.ticks = rest.steps_seen, rest.ticks
            outcome.mismatches[1:] = rest.mismatches
            return


def junit(results: Sequence[Result], path: Path, name: str) -> None:
    """JUnit XML: one test case per requirement."""
    suite = ET.Element("testsuite", name=name, tests=str(len(results)),
                       failures=str(sum(not r.passed for r in results)))
    for r in results:
        case = ET.SubElement(suite, "testcase", classname=f"conformance.{r.must.split('-')[0]}",
                             name=r.must)
        if not r.passed:
            ET.SubElement(case, "failure", message=r.detail[:200]).text = r.detail
    root = ET.Element("testsuites", name=name)
    root.append(suite)
    tree = ET.ElementTree(root)
    ET.indent(tree)
    path.parent.mkdir(parents=True, exist_ok=True)
    tree.write(path, encoding="utf-8", xml_declaration=True)


# --------------------------------------------------------------------------- running it


def simulate(cfg: AgentConfig, keyring: Keyring, planned: Sequence[Planned],
             deviation: Callable[[AgentRuntime], None] | None = None,
             codec: FrameCodec | None = None, lead_ticks: int = 12,
             phase: float = 0.37, latency: float = 2e-4, jitter: float = 0.0,
             seed: int = 0, filtered: bool = False,
             make_dut: Callable[[AgentConfig, FrameCodec, Keyring], Any] | None = None
             ) -> list[Frame]:
    """The schedule played against firmware_py's agent (with ``deviation``), or the
    agent ``make_dut`` builds (any object with the node seam: the C agent, sim.cagent),
    on a simulated clock: the record a bus run of a DUT would give, without the bus. The DUT
    ticks ``lead_ticks`` times before the schedule starts (as a device already running
    when the tester starts) at the phase ``phase`` of Ts; ``jitter``: each tick and each
    tester frame up to that fraction of Ts late (seeded), as on a loaded host;
    ``filtered``: the DUT's CAN controller passes only its acceptance IDs (GEN-5)."""
    import random

    rnd = random.Random(seed)
    codec = codec or FrameCodec()
    ts = cfg.controller.ts
    dut: Any = (make_dut or AgentRuntime)(cfg, codec, keyring)
    if deviation is not None:
        deviation(dut)
    t0 = (lead_ticks + 0.5) * ts  # the schedule's start, after the DUT's first Diag
    inputs = sorted((Frame(t0 + p.at + rnd.uniform(0, jitter * ts), p.msg, True, p.step,
                           p.note) for p in planned), key=lambda f: f.t)
    end = t0 + STEPS[-1].end * ts + 3 * ts
    passed = set(getattr(dut, "io", dut).accepted_ids())
    record: list[Frame] = []
    nxt = 0
    k = 0
    with _quiet_firmware():
        while (tick := (k + phase + rnd.uniform(0, jitter)) * ts) < end:
            while nxt < len(inputs) and inputs[nxt].t + latency < tick:
                msg = inputs[nxt].msg
                if not filtered or (not msg.is_extended_id
                                    and msg.arbitration_id in passed):
                    dut.on_frame(msg, inputs[nxt].t + latency)
                record.append(inputs[nxt])
                nxt += 1
            for msg in dut.tick(tick):
                record.append(Frame(tick + latency, msg, False))
            k += 1
    return record


def drive(bus: can.BusABC, planned: Sequence[Planned], dut_ids: set[int], diag_id: int,
          wait_s: float, ts: float, progress: Callable[[str], None] | None = None,
          clock: Callable[[], float] | None = None) -> tuple[list[Frame], float]:
    """Play the schedule on ``bus`` once the DUT is heard (its Diag frame, within
    ``wait_s``), recording the DUT's frames and the tester's own (send times). Also
    returns how late the tester sent its latest frame (s): a loaded tester plays a
    schedule the DUT may time out on, which the oracle then has to explain."""
    import threading
    import time

    clock = clock or time.time
    record: list[Frame] = []
    lock = threading.Lock()
    heard = threading.Event()
    # the tester's own frames on the DUT's IDs (impersonation tests), should the
    # interface echo them
    ours = {(p.msg.arbitration_id, bytes(p.msg.data)) for p in planned}

    class Rec(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            if (msg.arbitration_id in dut_ids and not msg.is_error_frame
                    and not msg.is_extended_id
                    and (msg.arbitration_id, bytes(msg.data)) not in ours):
                with lock:
                    record.append(Frame(msg.timestamp, msg, False))
                if msg.arbitration_id == diag_id:
                    heard.set()

        def on_error(self, exc: Exception) -> None:
            """An input that is no frame (node.RX_CAUSES): not the DUT's, reading goes on."""
            from firmware_py.node import rx_cause

            logging.getLogger(__name__).warning("conformance tester: dropped a bus input "
                                                "(%s): %s", rx_cause(exc), exc)

    notifier = can.Notifier(bus, [Rec()], timeout=0.05)
    try:
        if not heard.wait(wait_s):
            raise TimeoutError(f"no {diag_id:#x} frame of the device under test in "
                               f"{wait_s:g} s")
        with lock:
            record.clear()  # from its Diag on: the oracle starts there
        heard.clear()
        heard.wait(wait_s)  # a fresh Diag: the tick count is aligned from it
        # t0 is the DUT's tick (its Diag just heard): the schedule's frames at k + 0.25,
        # 0.5, 0.75 fall between its ticks, not on them, so a tick a few ms late does not
        # swap a frame with the next one (a one-tick pulse stays one tick for the DUT)
        t0 = clock()
        last_report = -1
        worst = 0.0
        for p in planned:
            delay = t0 + p.at - clock()
            if delay > 0:
                time.sleep(delay)
            before = clock()
            worst = max(worst, before - t0 - p.at)
            bus.send(p.msg)
            with lock:
                record.append(Frame(before, p.msg, True, p.step, p.note, clock()))
            if progress is not None and int(p.at) != last_report:
                last_report = int(p.at)
                progress(f"t = {p.at:5.1f} s  step {p.step}")
        time.sleep(3 * ts)
    finally:
        notifier.stop()
    record.sort(key=lambda f: f.t)
    return record, worst
