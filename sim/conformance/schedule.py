"""The conformance schedule: the steps (``STEPS``, each with the requirements it
exercises) and the frames the tester sends along them (``plan``).

Over 500 lines: the steps are one table, read in order beside docs/conformance.md's
(generated from it); splitting it would part a step from its frames.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import can

from firmware_py import contract, pricesig, secoc
from firmware_py import fixedpoint as fx
from firmware_py.config import EVENT_THRESHOLD, AgentConfig, Neighbour, parse_agent_config
from firmware_py.contract import Command, State
from firmware_py.frames import PIN_OFF, PIN_ON, FrameCodec, mc_name, status_name, target_raw
from firmware_py.nodeio import LOST_SEARCH_COUNTS, FleetSender
from firmware_py.secoc import SYNC_BOOT_JUMP_MAX


@dataclass(frozen=True)
class Step:
    """One part of the schedule, in ticks of the DUT's Ts: what it does and the
    requirements (docs/firmware-spec.md IDs) its frames exercise. ``moments``: what
    its noted frames exercise, (note, requirements), for the verdict to name a
    difference that follows one of them (sim.conformance.results ``MOMENTS`` holds the
    schedule's own; a note ending in "…" is a prefix)."""

    name: str
    start: int
    end: int
    what: str
    musts: tuple[str, ...]
    moments: tuple[tuple[str, tuple[str, ...]], ...] = ()


STEPS = (
    Step("start", 0, 30, "syncs of every input but the command's, then silence: the DUT "
         "stays INIT with λ(0), answers the syncs, sends MC/Setpoint/Diag at their "
         "cadences; after the join window a command frame before its sync (unsynced), "
         "then the command's sync",
         ("GEN-2", "STATE-1", "STATE-10", "TICK-1", "TX-1", "TX-2", "TX-3", "TX-4", "TX-5",
          "SP-3", "DIAG-1", "AUTH-4", "AUTH-6", "AUTH-7", "AUTH-8", "AUTH-9", "AUTH-11",
          "AUTH-16", "AUTH-21", "AUTH-26", "AUTH-28", "AUTH-29", "RX-4", "GEN-1", "GEN-4",
          "AUTH-1", "AUTH-20", "TX-7", "CFG-9", "AUTH-3")),
    Step("price-only", 30, 60, "price and neighbours but no plant status: still INIT",
         ("STATE-2", "STATE-5", "TMO-3", "LIVE-1", "LIVE-2", "PRICE-6", "AUTH-12",
          "AUTH-15", "AUTH-31", "AUTH-33")),
    Step("running", 60, 100, "plant status too: INIT → RUNNING, the setpoint follows λ",
         ("STATE-4", "STATE-6", "SP-1", "TX-2", "RX-11", "XI-1", "XI-2", "WMSR-1",
          "WMSR-2", "AUTH-31", "AUTH-33", "TX-7")),
    Step("control", 100, 450, "neighbours' λ moving (steps and a slow sine): every step "
         "of the device's controller (the reset-PI; pc, ft on case 2's variants), bit for "
         "bit",
         ("CTRL-1", "CTRL-4", "CTRL-5", "XI-1", "XI-2", "XI-3", "STEP-1", "STEP-2",
          "STEP-3", "STEP-4", "STEP-5", "STEP-6", "STEP-7", "STEP-8", "STEP-9", "BAND-1",
          "BAND-2", "BAND-3", "STEP-10", "STEP-11", "CTRL-3", "NUM-5", "TX-1", "SP-1",
          "LAM-2", "DIAG-1", "NUM-1", "NUM-2", "NUM-3", "NUM-6", "NUM-7", "NUM-8", "CFG-3",
          "CFG-4", "AUTH-34", "WMSR-1", "TX-7", "CFG-9")),
    Step("authentication", 450, 510, "forged MACs, a replayed frame, a replayed sync, a "
         "frame from another boot, a genuine frame delivered late (stale, not auth) and "
         "again (seen: auth): rejected and counted, λ unmoved by them",
         ("RX-8", "AUTH-10", "AUTH-11", "AUTH-12", "AUTH-13", "AUTH-14", "AUTH-16",
          "AUTH-17", "AUTH-25", "RX-12", "RX-13", "DIAG-4", "AUTH-20", "AUTH-34")),
    Step("content", 510, 580, "an extended ID, the DUT's own ID, untrusted_after short "
         "frames in a row on one ID (untrusted), an FD frame on a classic bus, a price out "
         "of bounds, a persistent price step, a neighbour λ jump",
         ("RX-1", "RX-2", "RX-3", "RX-7", "RX-9", "RX-10", "RX-13", "PRICE-2", "PRICE-3",
          "PRICE-4", "PRICE-5", "LAM-1", "DIAG-1", "DIAG-4", "GEN-3", "GEN-5", "CFG-7")),
    Step("commands", 580, 710, "SET_GAINS in and out of bounds, a command for another "
         "agent (under its command key), ISOLATE, RECONNECT; PIN the other way, for "
         "another agent, with a GainK that is neither way, and back; an unknown ID",
         ("CMD-1", "CMD-2", "CMD-3", "CMD-4", "CMD-5", "CMD-7", "STATE-7", "STATE-8",
          "STATE-9", "STATE-10", "XI-2", "RX-6", "RX-7", "AUTH-30")),
    Step("timeouts", 710, 910, "a neighbour silent (its ID lost; a sync in step, then a "
         "forgery: auth), the price silent (SAFE; with --signed-price then a key holder's "
         "prices, unsigned, under a bad, an older or a malformed signature: refused), a "
         "plant fault (SAFE), each followed by recovery",
         ("LIVE-2", "LIVE-3", "TMO-1", "TMO-2", "TMO-4", "STATE-3", "STATE-4", "STATE-6",
          "RX-11", "AUTH-13", "AUTH-14", "AUTH-16", "CFG-6", "AUTH-32", "AUTH-33"),
         (("an unsigned price: …", ("AUTH-33",)), ("a price under a…", ("AUTH-32",)),
          ("the router's price after a key holder's refused …", ("AUTH-33", "AUTH-12")))),
    Step("limits", 910, 1060, "SET_GAINS exactly at k_max/h_max and k_min/h_min, a gain "
         "that rounds half up, then one LSB beyond each bound; a neighbour λ step of "
         "exactly the LAM-1 bound, one LSB more, and back by the bound; a price step of "
         "exactly price_step_max, one LSB more "
         "(a candidate kept across a PriceValid = 0 frame); a neighbour ramp to the top of "
         "the λ range (large |ξ|), alive but INIT for 5 ticks; a status with FaultSoc and "
         "PowerLimited set",
         ("CMD-5", "CMD-6", "LAM-1", "LAM-2", "PRICE-1", "PRICE-3", "PRICE-4", "PRICE-5",
          "PRICE-6", "XI-1", "XI-2", "XI-3", "STEP-1", "STEP-6", "STEP-7", "STEP-8",
          "STEP-10", "STEP-11", "CTRL-3", "NUM-5", "STEP-12", "NUM-3", "NUM-4", "RX-11",
          "DIAG-3", "CFG-7", "WMSR-1")),
    Step("freshness", 1060, 1130, "every input's periodic sync in step; untrusted_after "
         "consecutive forged frames on one ID and one fewer on another (the plant's "
         "status, whose one more after valid frames comes in the states step); a price "
         "frame 16 freshness values on; a neighbour's frames lost on the bus past its "
         "timeout, its count 120 on when it returns (window 8); price syncs 9 boots and "
         "17 values on (refused), then 16 on (taken), a command sync 129 on (refused); a "
         "price sync 8 boots on (held: the prices go on), dropped by the router's next; a "
         "neighbour's Setpoint sync (a peer's boot: a hello), then again (no hello)",
         ("AUTH-9", "AUTH-12", "AUTH-13", "AUTH-14", "AUTH-15", "AUTH-16", "AUTH-18",
          "AUTH-19", "AUTH-27", "AUTH-35", "RX-5", "RX-10", "RX-12", "RX-13", "LIVE-2", "LIVE-3",
          "TMO-4", "DIAG-4", "CFG-7")),
    Step("states", 1130, 1350, "RECONNECT in RUNNING; PriceValid = 0 frames only (SAFE); "
         "RECONNECT and ISOLATE in SAFE; the price silent and a plant fault while ISOLATED; "
         "RECONNECT with the price stale (INIT), ISOLATE in INIT, RECONNECT when fresh and a "
         "SET_GAINS a tick before it (ISOLATED); one more forged plant status after valid "
         "ones (the streak ended: no verdict)",
         ("STATE-2", "STATE-3", "STATE-4", "STATE-5", "STATE-6", "STATE-7", "STATE-8",
          "STATE-9", "STATE-10", "PRICE-1", "TMO-1", "TMO-2", "RX-10", "RX-11", "CMD-3",
          "CMD-4", "CMD-5", "TX-7", "CFG-9")),
    Step("band", 1350, 1470, "an ISOLATE and a RECONNECT (the neighbours INIT meanwhile), "
         "so that the device's controller starts from ISOLATE's state whatever races "
         "earlier; then a trajectory planned on the reference (firmware_py run on "
         "the schedule up to here): the band armed, a reset, then ξ = −BAND exactly (not "
         "re-armed: BAND-3 is strict) and a crossing inside the band (no reset); a plant "
         "fault (SAFE) and back (RUNNING: armed kept, STATE-6), then a crossing inside the "
         "band (no reset); on a dwell device (D = 8 samples) then a crossing armed after "
         "SAFE (a reset: the dwell counted through SAFE), and crossings D − 1 (none) and D "
         "(a reset) samples after it",
         ("BAND-2", "BAND-3", "STEP-2", "STEP-3", "STEP-5", "STATE-3", "STATE-4", "STATE-6",
          "XI-2", "RX-11", "CTRL-2", "DWELL-1", "DWELL-2"),
         (("ξ = −BAND exactly after a reset …", ("BAND-3",)),
          ("|ξ| between the default band …", ("BAND-3", "CFG-3")),
          ("a crossing inside the band after entering RUNNING …", ("STATE-6",)),
          ("a crossing D or more samples after a reset, SAFE between …", ("DWELL-2",
                                                                         "DWELL-1")),
          ("a crossing D − 1 samples after a reset …", ("DWELL-1", "CTRL-2")),
          ("a crossing D samples after a reset …", ("DWELL-1", "CTRL-2")))),
    Step("extremes", 1470, 1620, "every neighbour INIT at lambda_min, then RUNNING there "
         "(no LAM-1 step after INIT): |Σ W_j (Λ − λ_j)| past int32 (ξ saturates, counted), "
         "the own λ driven past lambda_min (not clamped), to a Diag page of Saturations; "
         "on a band-planned device first, pinned meanwhile, one tick with the sum exactly "
         "2^31 − 1 (not clamped, not counted)",
         ("NUM-3", "XI-2", "XI-3", "STEP-1", "STEP-12", "RX-9", "LAM-2", "DIAG-3", "CFG-7",
          "CMD-7", "WMSR-1", "WMSR-2", "DIAG-2", "TX-6"),
         (("every neighbour at lambda_min in ξ …", ("NUM-3", "XI-3")),
          ("a neighbour INIT at lambda_min", ("LAM-2", "RX-9")),
          ("a neighbour at the λ that makes the sum of ξ exactly …", ("XI-3", "NUM-3")),
          # not "PIN …" (ξ's price term, XI-2): λ is not what these two are for
          ("a PIN on, for the sum of ξ …", ("CMD-7",)), ("a PIN off after it", ("CMD-7",)))),
)


# `bess-ded conformance --quick`: the first steps only (7.1 of 16.2 s at Ts = 10 ms), for
# development: start-up, a state change to RUNNING, the controller bit for bit, the
# authentication, the content rules, every command: one step per requirement class (GEN,
# NUM, CTRL, XI, STEP, BAND, STATE, LIVE, TMO, TICK, TX, SP, DIAG, RX, PRICE, LAM, CMD,
# AUTH, CFG). A prefix, so that every step played runs from the state the whole schedule
# gives it; the requirements only the later steps exercise (the timeouts, the edges of
# the limits, the freshness windows, each state's reaction to each command) are "not
# run", never passed.
QUICK = ("start", "price-only", "running", "control", "authentication", "content",
         "commands")

# Requirements a step exercises on some runs only: on a device of one controller kind
# (the PI family's step and band, pc's and ft's step: the scenario's kind, e.g. case 2's
# variants; the band step's dwell edges), on a CAN FD bus with λ tags (--fd: every neighbour λ
# carries the DUT's tag, the forged ones a wrong one), with --insecure (every key derived
# from the public master; a command before its sync and a replayed sync taken), with
# the resilient update (--resilient F), with --price-persist 1 (every in-bounds price step
# taken at once), in an exact-timing run in process (a Diag counter
# driven past 65535 by a flood of unknown IDs: seconds of a full bus, none on a real one).
# Another run's verdict leaves them out; ``exercised_on`` says which conditions a run
# meets.
ONLY_ON: dict[str, str] = {"CTRL-2": "dwell", "DWELL-1": "dwell", "DWELL-2": "dwell",
                           "AUTH-34": "lambda tags", "AUTH-1": "insecure",
                           "AUTH-20": "insecure", "WMSR-1": "resilient",
                           "WMSR-2": "resilient ties", "DIAG-2": "flood", "TX-6": "flood",
                           # the controller kind's own step (section 6)
                           **{f"STEP-{n}": "pi family" for n in range(2, 10)},
                           **{f"BAND-{n}": "pi family" for n in range(1, 4)},
                           "STEP-10": "pc", "STEP-11": "ft", "CTRL-3": "ft", "NUM-5": "ft",
                           "PRICE-5": "persist 1",
                           **{f"AUTH-{n}": "signed price" for n in (31, 32, 33)},
                           "TX-7": "event", "CFG-9": "event"}
ON_WHAT = {"dwell": "on a dwell device", "pi family": "on a pi, reset or dwell device",
           "pc": "on a pc device: --case 2 --variant PC",
           "ft": "on an ft device: --case 2 --variant finite-time",
           "lambda tags": "on --fd, with λ tags", "persist 1": "with --price-persist 1",
           "signed price": "with --signed-price", "event": "with --event-transmit",
           "insecure": "with --insecure", "resilient": "with --resilient F",
           "resilient ties": "with --resilient F on a device of more than F neighbours",
           "flood": "in process, in an exact-timing run: its flood of unknown IDs"}

# The requirements no step exercises, and why: what a bus run cannot show, or what this
# schedule leaves to the unit tests and vectors (docs/conformance.md's coverage table
# lists them; a test fails when a spec requirement is in neither STEPS nor here).
NOT_ON_BUS: dict[str, str] = {
    "SP-2": "setpoint_limited is not on the Diag frame (DIAG-5): not visible on the bus",
    "DIAG-5": "these counters are not on any frame: not visible on the bus",
    "AUTH-2": "every MAC of the schedule is a CMAC, but a wrong CMAC fails everything "
              "(AUTH-4, AUTH-7): no step isolates it; the secoc vectors check it",
    "AUTH-5": "2^24 frames on one ID take 46.6 h at Ts = 10 ms; the node vector "
              "tx_count_wrap checks it through the binding",
    "CFG-1": "the DUT reads the configuration the tester writes, whose tables are all "
             "allowed: a refused file never starts (LOOP-5); unit tests (test_config.py)",
    "CFG-2": "id, lambda0 and pinned are the scenario's (no default to take instead; "
             "lambda0's q24 rounds up: a truncating DUT fails NUM-4); fleet_size and "
             "resilient_f change no frame of the schedule: unit tests",
    "CFG-5": "the battery keys are all required (no default to take instead); a misread "
             "one fails SP-1 (the setpoint) or CMD-3 (the idle λ): unit tests",
    "CFG-8": "the key file: a misread key fails every MAC (AUTH-4..8); the refusals "
             "(a sender's key missing, a symbolic link) stop the start: unit tests",
    "LOOP-1": "the run loop's timing depends on the DUT's host, not on the bus",
    "LOOP-2": "deadline misses depend on the DUT's host (DeadlineMisses is not compared)",
    "LOOP-3": "the DUT's clock is not visible on the bus",
    "LOOP-4": "error frames: python-can's virtual buses cannot carry them",
    "LOOP-5": "a configuration that never starts cannot be run on a bus",
    "LOOP-6": "inputs that are no CAN frame cannot be sent on a CAN bus",
    "SCALE-1": "the DUT gets the scaled configuration (--time-scale); that it does not "
               "know F is not visible; unit tests",
    "SCALE-2": "as SCALE-1",
}

# ------------------------------------------------------------------ the DUT's configuration


def _rounds_up(x: float, bits: int, scale: float = 1.0) -> float:
    """A value next to ``x`` whose ``value·scale·2^bits`` has a fraction of 0.625: its
    fixed-point word rounds up (q24, q30: NUM-4, NUM-6), so a device that truncates, or
    that takes another value (a default), holds another word."""
    word = math.floor(x * scale * (1 << bits))
    return (word + 0.625) / (1 << bits) / scale


FILED_BOOT = 6
"""The boot counter the tester writes into the device's fresh key file (AUTH-3: the
device's syncs then carry boot 7; one that keeps the file's counter sends 6)."""

EVENT_HEARTBEAT = 3
"""The heartbeat the tester writes for an event-triggered device (CFG-9: the default 13
must exceed the neighbour timeout, 4 periods here): at least every 3rd tick an MC frame."""

PRICE_PERSIST = 5
"""The price persistence the tester writes: two above the default 3, so that a device
counting one frame short or long, and one taking the default, each accept a step at
another frame (PRICE-4); ``--price-persist 1`` writes 1 instead (PRICE-5)."""


def conformance_config(cfg: AgentConfig, price_persist: int = PRICE_PERSIST) -> AgentConfig:
    """The configuration the tester writes for the DUT (its TOML file, CFG-1..9): the
    scenario's agent ``cfg`` with every key whose effect the schedule observes set off
    its default (CFG-3: ts, k, h, band; CFG-4: the weights; CFG-6: neighbour_periods,
    price_s, status_s; CFG-7: the limits the steps meet at their bounds) and every
    value that goes to a fixed-point word one whose word rounds up (``_rounds_up``), so
    that a device taking a default instead of the file's value, truncating instead of
    rounding, or rounding ``neighbour_periods`` instead of truncating it (4.7 → 4) runs
    differently from the oracle, which reads the same file with the reference parser.
    ts moves by less than one Q30 LSB (< 1 ns): the period on the bus stays Ts."""
    c = cfg.controller
    ts = _rounds_up(c.ts, 30)
    if round(ts * 1e9) != round(c.ts * 1e9):  # keep the period's ns (the C node's clock)
        ts = c.ts
    k = _rounds_up(1.1 * c.k, 30, ts)
    h = _rounds_up(0.9 * c.h, 30, ts)
    ctrl = replace(c, ts=ts, k=k, h=h, band=_rounds_up(1.5 * c.band, 24))
    if c.kind == "dwell":  # D = ceil(7.2) = 8 samples (CTRL-2): the band step's edges fit
        ctrl = replace(ctrl, dwell=round(7.2 * ts, 12))  # one nearest-rounding makes 7
    # event-triggered sending (TX-7): the threshold and the heartbeat off their defaults
    # (CFG-9), the heartbeat below the neighbour timeout the file gives (4 periods)
    transmit = (replace(cfg.transmit, threshold=_rounds_up(2 * EVENT_THRESHOLD, 24),
                        heartbeat=EVENT_HEARTBEAT) if cfg.transmit.event else cfg.transmit)
    if c.kind == "ft" and c.ft_exponent == 0.5:  # off the default: a = 3/4, two roots and
        ctrl = replace(ctrl, ft_exponent=0.75)  # two products in fpow (CTRL-3)
    # with the resilient update each neighbour's weight its own (WMSR-2 trims the larger
    # of two equal λ first: equal weights would hide the order)
    spread = 0.25 if cfg.resilient_f else 0.0
    nbrs = tuple(Neighbour(n.id, _tie_weight(1.25 * n.weight * (1 + spread * k)))
                 for k, n in enumerate(cfg.neighbours))
    step_max = _rounds_up(0.9 * 10.0 * k * ts, 24)  # below the default 10·k·Ts
    # a price step of 0.45: the content step's persistent 0.6 stays above it
    price_step = _rounds_up(min(cfg.price_step_max, 0.45), 24)
    return replace(
        cfg, controller=ctrl, neighbours=nbrs, lambda0=_rounds_up(cfg.lambda0, 24),
        neighbour_timeout_periods=4.7,  # type: ignore[arg-type]  # CFG-6 truncates: 4
        # 0.32 s and 0.29 s at Ts = 10 ms (the defaults: 0.25 s), stretched with Ts;
        # price_s a multiple of 2^-16 s (0.3200073 s): a difference of two times of the
        # run (a tick, a receive time) can equal it exactly (an exact-timing run's edge)
        price_timeout_s=round(1.28 * cfg.price_timeout_s * (1 << 16)) / (1 << 16),
        status_timeout_s=round(1.16 * cfg.status_timeout_s, 9),
        # λ limits near the DBC's ±128 (RX-9): a neighbour at lambda_min drives |ξ| past
        # int32 (NUM-3, XI-3) and the own λ past lambda_min (STEP-12); the edge step
        # `extremes` does both
        lambda_min=-LAMBDA_LIMIT, lambda_max=LAMBDA_LIMIT, rho_min=max(cfg.rho_min, -4.5),
        rho_max=min(cfg.rho_max, 4.5), price_step_max=price_step, price_persist=price_persist,
        lambda_step_max=step_max, k_min=_milli(0.6 * k), k_max=_milli(1.8 * k),
        h_min=_milli(0.6 * h), h_max=_milli(1.8 * h), untrusted_after=6, transmit=transmit,
        source=f"{cfg.source} (conformance)")


LAMBDA_LIMIT = 120.0
"""The conformance configuration's λ limits (±): a neighbour λ at ``-LAMBDA_LIMIT`` is
more than 128/W from any own λ near 0 (W = 1.25: ξ saturates)."""


def _tie_weight(x: float) -> float:
    """A weight next to ``x`` whose Q24 word is a multiple of 2^22 but not of 2^23, and
    whose value·2^24 has a fraction of 0.625 (it rounds up to that word, NUM-4): then
    mulq(W, Λ − λ_j) is a tie (NUM-2) whenever Λ − λ_j ≡ 2 (mod 4) LSB, a quarter of all
    differences, so that the control step meets ties of either sign."""
    word = round(x * (1 << 24) / (1 << 22))
    word = (word | 1) << 22
    return (word - 0.375) / (1 << 24)


def _milli(x: float) -> float:
    """The gain bound nearest ``x`` that a SET_GAINS meets exactly (CMD-5: raw·0.001 in
    binary64 equals it), so that the steps at the bounds tell ≤ from <."""
    return round(x * 1000) * 0.001


def written_config(cfg: AgentConfig, price_persist: int = PRICE_PERSIST
                   ) -> tuple[str, AgentConfig]:
    """The DUT's configuration file (``conformance_config`` of the scenario's agent
    ``cfg``) and the oracle's configuration: that text read by the reference parser
    (firmware_py.config), as the DUT reads it with its own."""
    text = conformance_config(cfg, price_persist).to_toml()
    return text, read_config(text, cfg.source)


def read_config(text: str, src: str = "<conformance>") -> AgentConfig:
    """An agent TOML text read by the reference parser (firmware_py.config)."""
    return parse_agent_config(tomllib.loads(text), src)


REFUSED_AT = 69
"""The timeouts step's tick (the price stale since tick 68: SAFE) from which a key holder
plays the prices a signed_price device refuses (``_PriceSigner.refused``), each 2 ticks
apart: a device that takes one leaves SAFE at once; the router's price returns at 80."""

PULSE = 0.05  # cu/kWh: well above the reset band, below lambda_step_max (10·k·Ts)


@dataclass(frozen=True)
class Planned:
    """A frame the tester sends ``at`` s after the start of the schedule."""

    at: float
    step: str
    msg: can.Message
    note: str = ""
    # an exact-timing run (``simulate(..., exact=True)``: the device's clock trusted) puts
    # this frame so that it is exactly ``age`` s old at a tick of the device (a timeout's
    # boundary: ≤ against <); a bus run sends it at ``at`` as any other
    age: float | None = None
    # an exact-timing run puts this frame exactly ``after`` s after the tester's previous
    # frame of its ID (as the device subtracts: in binary64 and in whole ns); a tie of
    # LAM-1's rne. Only in an exact-timing run's plan (``plan``'s ``flood``)
    after: float | None = None


def _tick_of(name: str) -> Callable[[int], bool]:
    every = contract.every_ticks(name)
    return lambda k: k % every == 0


def plan(cfg: AgentConfig, keys: Mapping[str, bytes] | None, price: float,
         codec: FrameCodec | None = None, boot: int = secoc.INSECURE_BOOT,
         quick: bool = False, flood: bool = False,
         other_format: bool = True) -> list[Planned]:
    """The tester's frames for DUT ``cfg`` (times in s from the start), signed with
    ``keys`` (label → key of the router, the plant and the neighbours; None: the
    insecure keys). ``price``: the ρ to hold (the scenario's first). ``boot``: the boot
    every sender the tester plays runs at, at least the DUT's boot floors (AUTH-21);
    above 1, an earlier run's price sync (boot − 1) comes first. ``quick``: the steps
    of ``QUICK`` only. ``flood``: in process only (an exact-timing run), ``FLOOD``
    frames of an unknown ID at once in the extremes step, so that RejectedUnknownId
    passes 65535 and must stay there (DIAG-2); a bus run would take seconds of a full
    bus for them, and the tolerant oracle one hypothesis per frame; and a neighbour
    frame exactly 2.5 periods after its last (LAM-1's tie, ``Planned.after``), which a
    bus cannot time. ``other_format``: the
    bus carries an FD frame beside classic ones (in process and udp_multicast; not a
    classic SocketCAN bus): the content step sends one (RX-2)."""
    out = _plan(cfg, keys, price, codec, boot, other_format=other_format, tie_rne=flood)
    if flood:
        codec = codec or FrameCodec()
        at = next(s.start for s in STEPS if s.name == "extremes") + 1.6
        junk = can.Message(arbitration_id=_unknown_id(codec), is_extended_id=False,
                           data=bytes(8), **_format(codec))
        out += [Planned(at * cfg.controller.ts, "extremes", junk,
                        FLOOD_NOTE if n == 0 else "")
                for n in range(FLOOD)]
        out.sort(key=lambda p: p.at)
    return [p for p in out if p.step in QUICK] if quick else out


OTHER_FORMAT = "an FD frame on a classic bus"
"""The note of the content step's frame of the other format (RX-2): the one frame of the
schedule not in the bus's format."""

FLOOD_NOTE = "a flood of unknown IDs past 65535"
FLOOD = 65536
"""The unknown-ID frames of an exact-timing run's flood (``plan``'s ``flood``): with the
two of the schedule, RejectedUnknownId's count is past 65535 (DIAG-2: it saturates)."""


def played_steps(planned: Sequence[Planned]) -> tuple[Step, ...]:
    """The steps ``planned`` plays (all of ``STEPS``, or ``QUICK``'s)."""
    names = {p.step for p in planned}
    return tuple(s for s in STEPS if s.name in names)


class _BandPlan:
    """The band step's trajectory, planned on the reference: firmware_py's agent run on
    the schedule's frames (twins of them under the public demo keys: the same contents
    and order, so the same λ) up to the step, then driven tick by tick with the
    neighbour λ this plan chooses from its own λ (a conformant device is bit-exact with
    it): ``lam[c]`` the neighbours' λ (Q24) sent at tick ``start + c``, ``fault[c]`` the
    plant fault then, ``note[c]`` what that frame exercises, ``state[c]`` the
    neighbours' State.

    The step starts with an ISOLATE and a RECONNECT of the device (at ``ISOLATE_AT`` and
    ``RECONNECT_AT``): its controller state is then the one ISOLATE sets, whatever a
    race of an earlier frame with a tick (the ordering tolerance) made of it, so the
    reference's λ is the device's from there on even when their trajectories parted
    before the step."""

    ISOLATE_AT, RECONNECT_AT = 1, 3  # the step's ticks whose commands ISOLATE, RECONNECT
    COMMAND_AT = 0.45  # of Ts after the tick: before the device's next tick at any load

    def __init__(self, cfg: AgentConfig, price: float, codec: FrameCodec, start: int,
                 length: int, other_format: bool = True, secure: bool = True) -> None:
        from firmware_py.runtime import AgentRuntime
        from sim.conformance.oracle import quiet_firmware

        ts = cfg.controller.ts
        twin = sorted(_plan(cfg, None, price, codec, secoc.INSECURE_BOOT,
                            planned_band=False, other_format=other_format),
                      key=lambda p: p.at)
        frames = [p for p in twin if p.at < start * ts]
        # the step's ISOLATE and RECONNECT, from the twins' own sender (their counts)
        command_id = codec.frame_id("ER_Command")
        isolate, reconnect = (p for p in twin
                              if p.step == "band" and p.msg.arbitration_id == command_id)
        commands = {self.ISOLATE_AT: isolate, self.RECONNECT_AT: reconnect}
        node = f"agent_{cfg.id}"
        keys = secoc.Keyring.insecure_for(node)
        if secure:  # the demo keys, judged as a keyed device judges: an insecure receiver
            # takes any sync (no AUTH-27 bounds), a keyed one refuses the schedule's jumps
            keys = secoc.Keyring(node, keys.key, keys.boot, lambda _b: None,
                                 master=secoc.INSECURE_MASTER, fleet=keys.fleet_id)
        if cfg.signed_price:  # the twins' prices are signed with the demo master's key
            keys.price_verify = pricesig.public_key(secoc.derive_price_sign_key(
                secoc.INSECURE_MASTER))
        rt = AgentRuntime(cfg, codec, keys=keys)
        nxt = 0
        self.lam: list[dict[int, int]] = []
        self.fault: list[bool] = []
        self.note: list[str] = []
        self.state: list[State] = []
        # the extremes step's first ticks (``_drive_extremes``): the neighbours' λ and
        # State, the first one's note; the ticks whose commands PIN on and off (None: no
        # tick of ξ exactly 2^31 − 1 was found, nor PIN sent)
        self.ext_lam: list[dict[int, int]] = []
        self.ext_state: list[State] = []
        self.ext_first: list[tuple[State, str]] = []
        self.pin_on_at: int | None = None
        self.pin_off_at: int | None = None
        with quiet_firmware():
            for j in range(start + 1):
                while nxt < len(frames) and frames[nxt].at < j * ts:
                    rt.on_frame(frames[nxt].msg, frames[nxt].at)
                    nxt += 1
                rt.tick(j * ts)
            self._drive(rt, cfg, start, length, commands)
            self._drive_extremes(rt, cfg, start + length)

    def _drive(self, rt: Any, cfg: AgentConfig, start: int, length: int,
               commands: Mapping[int, Planned]) -> None:
        band = int(getattr(rt.ctrl, "band", 0))
        # the default band's word (CFG-3): a device that takes it re-arms at |ξ| above it
        from firmware_py.controllers import DEFAULT_BAND
        lower = fx.to_fixed(DEFAULT_BAND)
        slots = list(rt.neighbours.values())
        step_max = rt.lambda_step_max
        last = {s.id: int(s.lam) for s in slots}
        # a dwell device (DWELL-1, DWELL-2): crossings at the dwell's edge after re-entry
        dwell = _DwellEdges(rt.ctrl.dwell_samples) if cfg.controller.kind == "dwell" else None
        fault = False
        entered: int | None = None  # the c at which the device is back in RUNNING
        placed = 0  # ticks in a row with every neighbour where the plan wanted it
        c0: int | None = None  # the first tick of the edges (every neighbour in place)

        def toward(j: int, want: int) -> int:
            return last[j] + max(-step_max, min(step_max, want - last[j]))

        def solve(target: int, lam: int, w: int) -> int | None:
            """λ_j with mulq(W, Λ − λ_j) = target exactly, if there is one."""
            guess = round(target * (1 << 24) / w)
            for d in range(guess - 3, guess + 4):
                if rt.ctrl.ar.mul(w, d) == target:
                    return lam - d
            return None

        for c in range(length):
            if c in commands:  # taken on receipt, before the next tick (as the device)
                rt.on_frame(commands[c].msg, commands[c].at)
            lam = int(rt.ctrl.wire_lambda(rt.cstate))
            want = dict.fromkeys(last, lam)
            note = ""
            first = slots[0]
            w = int(first.weight)
            e = None if c0 is None else c - c0  # the edges' own tick count
            # the neighbours INIT while the device is isolated: their next RUNNING frame
            # is no LAM-1 step, so they join its λ(0) at once
            nbr_state = (State.INIT if self.ISOLATE_AT <= c <= self.RECONNECT_AT
                         else State.RUNNING)
            if nbr_state == State.INIT:
                want = dict(last)
            elif e is None:  # |ξ| well above BAND (armed), the neighbours closing in on Λ
                want[first.id] = lam + 10 * band
            elif e == 0:  # a crossing, armed: a reset (disarmed, BAND-2)
                want[first.id] = lam - 2 * band
                note = "a crossing after |ξ| > BAND (a reset)"
            elif e == 1:  # ξ = −BAND exactly: a crossing, unarmed, and no re-arm
                exact = solve(-band, lam, w)
                if exact is not None:
                    want[first.id] = exact
                    note = "ξ = −BAND exactly after a reset (no re-arm)"
            elif e in (2, 4):  # a crossing inside the band: no reset (still unarmed)
                want[first.id] = lam - band // 2
            elif e == 3 and lower < band:  # |ξ| between the default band and the file's:
                want[first.id] = lam + (lower + band) // 2 * (1 << 24) // w  # no re-arm
                note = "|ξ| between the default band and the file's (no re-arm)"
            elif 12 <= e < 22:
                fault = True
            elif e >= 22:
                fault = False
                if entered is None and rt.state == State.RUNNING:
                    entered = c
                if entered is not None and c - entered in (0, 1):
                    sign = -1 if c == entered else 1
                    want[first.id] = lam - sign * band // 2
                    note = ("a crossing inside the band after entering RUNNING "
                            "(armed kept: no reset)" if c > entered else "")
                elif dwell is not None and entered is not None and c - entered >= 2:
                    x, note = dwell.next(rt.cstate, band)
                    if x is not None:
                        want[first.id] = lam - x
            joined = c == self.RECONNECT_AT + 1  # the first RUNNING frame after INIT
            chosen = want if joined else {j: toward(j, v) for j, v in want.items()}
            if note and chosen[first.id] != want[first.id]:
                note = ""  # the step was too large for LAM-1: not at the edge
            placed = placed + 1 if all(chosen[j] == v for j, v in want.items()) else 0
            if c0 is None and c >= 8 and placed >= 3 and (  # a dwell device: its reset
                    dwell is None or rt.cstate.since_reset >= dwell.samples):  # allowed
                c0 = c + 1
            self.lam.append(chosen)
            self.fault.append(fault)
            self.note.append(note)
            self.state.append(nbr_state)
            last = chosen
            _feed(rt, cfg, start + c, chosen, dict.fromkeys(chosen, nbr_state), fault)


    PIN_ON_AT = 1  # the extremes step's tick whose command pins the device (CMD-7)
    EXACT_FROM, EXACT_UNTIL = 7, 13  # the ticks to find ξ = 2^31 − 1 exactly at

    def _drive_extremes(self, rt: Any, cfg: AgentConfig, start: int) -> None:
        """The extremes step's first ticks, on the reference: the neighbours held (0..4),
        INIT at lambda_min (5, 6), the device pinned meanwhile (``PIN_ON_AT``: its ξ has
        the price term); then, at the first tick where one exists, the first neighbour
        RUNNING at the λ for which acc = (Λ − ρ) + mulq(W, Λ − λ_j) is exactly 2^31 − 1
        (XI-3: no saturation, none counted; one neighbour's mulq alone cannot be: with
        W = 1.25 it takes no value ≡ 2 mod 5); then INIT again, the pin off, and every
        neighbour RUNNING at lambda_min (ξ saturates), where the step goes on as for
        any device."""
        from firmware_py.controllers import consensus_error

        slots = list(rt.neighbours.values())
        first = slots[0]
        bottom = round(cfg.lambda_min * (1 << 24))
        held = {sl.id: int(sl.lam) for sl in slots}
        exact_at: int | None = None  # the tick of the exact sum (or of giving up)
        c = 0
        while exact_at is None or c <= exact_at + 2:
            lam_now = int(rt.ctrl.wire_lambda(rt.cstate))
            state, lams, note = State.INIT, dict.fromkeys(held, bottom), ""
            if c < 5:
                state, lams = State.RUNNING, dict(held)
            elif c == 5:
                note = "a neighbour INIT at lambda_min"
            elif exact_at is not None and c == exact_at + 2:
                state, note = State.RUNNING, "every neighbour at lambda_min in ξ (ξ saturates)"
            first_state = state
            if c == self.PIN_ON_AT:
                rt.pin = fx.ONE
            if exact_at is not None and c == exact_at + 1:
                rt.pin = 0
                self.pin_off_at = c
            if exact_at is None and c >= self.EXACT_FROM and rt.price is not None:
                target = fx.INT32_MAX - (lam_now - rt.price)  # mulq(ONE, x) = x
                w = int(first.weight)
                guess = round(target * (1 << 24) / w)
                d = next((d for d in range(guess - 3, guess + 4)
                          if rt.ctrl.ar.mul(w, d) == target), None)
                if d is not None and bottom <= lam_now - d:
                    xi, sat = consensus_error(rt.ctrl.ar, lam_now, [(w, lam_now - d)],
                                              rt.pin, rt.price, cfg.resilient_f)
                    if xi == fx.INT32_MAX and not sat:
                        exact_at, first_state = c, State.RUNNING
                        lams[first.id] = lam_now - d
                        note = ("a neighbour at the λ that makes the sum of ξ exactly "
                                "2^31 − 1 (no saturation)")
                if exact_at is None and c >= self.EXACT_UNTIL:
                    exact_at = c  # none found: on as for any device
            self.ext_lam.append(lams)
            self.ext_state.append(state)
            self.ext_first.append((first_state, note))
            states = dict.fromkeys(lams, state) | {first.id: first_state}
            _feed(rt, cfg, start + c, lams, states, False)
            c += 1
        self.pin_on_at = self.PIN_ON_AT  # the loop ends after the pin goes off


def _feed(rt: Any, cfg: AgentConfig, k: int, lams: Mapping[int, int],
          states: Mapping[int, State], fault: bool) -> None:
    """One planned tick ``k`` of the reference: the neighbours' frames (λ, State) taken
    half a period after tick k, the price kept fresh, the plant's status (with ``fault``)
    on its ticks, then the tick at k + 1."""
    ts = cfg.controller.ts
    t_rx = (k + 0.5) * ts
    for slot in rt.neighbours.values():
        slot.lam, slot.last_rx, slot.state = lams[slot.id], t_rx, states[slot.id]
    if rt.price_rx is not None:
        rt.price_rx = t_rx
    if _tick_of(status_name(cfg.id))(k):  # the status frame of this tick
        rt.status_rx, rt.plant_fault = t_rx + 0.25 * ts, fault
    rt.tick((k + 1) * ts)


def band_planned(cfg: AgentConfig) -> bool:
    """Whether the band step plays a trajectory planned on the reference for ``cfg``'s
    device (one with neighbours and no pin: a pinned device's ξ has the price term)."""
    return bool(cfg.neighbours) and not cfg.pinned


def exercised_on(cfg: AgentConfig, lambda_tags: bool, insecure: bool,
                 flood: bool = False) -> frozenset[str]:
    """The conditions of ``ONLY_ON`` a run of ``cfg``'s device meets: its controller's
    step ("pi family", "pc" or "ft"), its controller kind where the band step is planned
    for it (``kind_exercised``: "dwell" for the dwell edges), "lambda tags" on a
    tagged CAN FD bus, "insecure" with the public demo keys, "resilient" with the
    resilient update on, "signed price" with signed_price, "event" with event-triggered
    sending (TX-7), and "resilient ties" where more than F neighbours (each of its own
    weight, ``conformance_config``) meet at lambda_min in the extremes step: the larger
    weight is trimmed first (WMSR-2); "flood" where the tester sent ``plan``'s flood."""
    trim = cfg.resilient_f if cfg.neighbours else 0
    kind = cfg.controller.kind
    return frozenset({kind_exercised(cfg), kind if kind in ("pc", "ft") else "pi family"}
                     - {""}
                     | ({"lambda tags"} if lambda_tags else set())
                     | ({"insecure"} if insecure else set())
                     | ({"resilient"} if trim else set())
                     | ({"resilient ties"} if trim and len(cfg.neighbours) > trim else set())
                     | ({"flood"} if flood else set())
                     | ({"persist 1"} if cfg.price_persist == 1 else set())
                     | ({"signed price"} if cfg.signed_price else set())
                     | ({"event"} if cfg.transmit.event else set()))


def kind_exercised(cfg: AgentConfig) -> str:
    """The controller kind whose own requirements (``ONLY_ON``) the schedule exercises
    on ``cfg``'s device: its kind where the band step is planned, else none ("")."""
    return cfg.controller.kind if band_planned(cfg) else ""


class _DwellEdges:
    """The band step's end on a dwell device (DWELL-1, DWELL-2), from the reference's
    controller state before each tick: a crossing armed and at least D samples after the
    last reset, a few samples after the device re-entered RUNNING from SAFE (a reset, if
    since_reset kept counting through SAFE), then crossings exactly D − 1 (blocked) and D
    (a reset) samples after it. ``next`` gives the neighbour's offset below Λ (ξ =
    W·offset, mulq) and the note of the tick; None once done."""

    def __init__(self, samples: int) -> None:
        self.samples = samples
        self.phase = "arm"   # arm, reset, hold, done

    def next(self, s: Any, band: int) -> tuple[int | None, str]:
        away = 2 * band  # |ξ| = 2.5 BAND at W = 1.25: outside the band (armed)
        sign = 1 if s.xi_prev >= 0 else -1  # the side ξ is on
        if self.phase == "arm":  # the same side, outside the band: armed
            self.phase = "reset"
            return sign * away, ""
        if self.phase == "reset":  # a crossing D or more samples after the last reset
            if not (s.armed and s.since_reset >= self.samples):
                return sign * away, ""
            self.phase = "hold"
            return -sign * away, ("a crossing D or more samples after a reset, SAFE between "
                                  "(dwell: a reset)")
        if self.phase == "hold":
            if s.since_reset == self.samples - 1:
                return -sign * away, "a crossing D − 1 samples after a reset (dwell: none)"
            if s.since_reset == self.samples:
                self.phase = "done"
                return -sign * away, "a crossing D samples after a reset (dwell: a reset)"
            return sign * away, ""
        return None, ""


class _PriceSigner:
    """The router's price signatures on a signed_price run (AUTH-32): a transfer before
    each price whose (PriceValid, ρ) is not the signed segment's, its segment number 8 on
    (ER_Price.Segment stays 0), and the held one again every second. The key: ``keys``'
    ``pricesig.TESTER_SIGN`` seed (a key set's router file), else the public demo
    master's (an insecure twin, ``_BandPlan``)."""

    def __init__(self, codec: FrameCodec, keys: Mapping[str, bytes] | None, boot: int
                 ) -> None:
        self.codec = codec
        self.seed = (keys or {}).get(pricesig.TESTER_SIGN) or secoc.derive_price_sign_key(
            secoc.INSECURE_MASTER)
        self.fleet = (secoc.fleet_id(secoc.INSECURE_MASTER) if not keys
                      else keys.get(pricesig.MONITOR_FLEET, b"").hex())
        self.boot = boot
        self.current: pricesig.SignedSegment | None = None

    def transfer(self, seg: pricesig.SignedSegment, seed: bytes | None = None
                 ) -> list[can.Message]:
        """The 11 ER_PriceSig pages of ``seg`` signed with ``seed`` (default the router's)."""
        signature = pricesig.sign(seed or self.seed, self.fleet, seg)
        return [self.codec.encode(pricesig.MESSAGE, raw, 0)
                for raw in pricesig.pages(seg, signature)]

    def before(self, valid: int, rho: int) -> list[can.Message]:
        """The transfer a price (``valid``, ``rho``) needs first: none if it is signed."""
        cur = self.current
        if cur is not None and (cur.valid, cur.rho) == (valid, rho):
            return []
        number = 0 if cur is None else (cur.number + pricesig.SEGMENT_LOW_MOD) % \
            pricesig.SEGMENT_MOD
        self.current = pricesig.SignedSegment(self.boot, number, valid, rho)
        return self.transfer(self.current)

    def refused(self, insider: FleetSender) -> list[tuple[int, list[can.Message], str]]:
        """What a key holder of the router's node key (``insider``: its MACs verify, its
        counts run 8 ahead of the router's) plays while the price is stale: (tick offset,
        frames, the note of the last frame, a price), each a price no conformant device
        takes (AUTH-32, AUTH-33)."""
        cur = self.current
        assert cur is not None
        nxt = (cur.number + pricesig.SEGMENT_LOW_MOD) % pricesig.SEGMENT_MOD

        def price(seg: pricesig.SignedSegment, **raw: int) -> can.Message:
            return insider.frame("ER_Price", {"PriceValid": seg.valid, "Rho": seg.rho,
                                              "Segment": seg.number % pricesig.SEGMENT_LOW_MOD,
                                              **raw})

        bad = pricesig.SignedSegment(cur.boot, nxt, 1, cur.rho + 2)
        older = pricesig.SignedSegment(cur.boot, (cur.number - pricesig.SEGMENT_LOW_MOD)
                                       % pricesig.SEGMENT_MOD, 1, cur.rho + 3)
        repeat = pricesig.SignedSegment(cur.boot, nxt, 1, cur.rho + 4)
        extra = pricesig.SignedSegment(cur.boot, nxt, 1, cur.rho + 5)
        pages = self.transfer(repeat)

        def altered(msg: can.Message, flip: int) -> can.Message:
            raw = self.codec.decode(msg).raw
            return self.codec.encode(pricesig.MESSAGE, {**raw, "Signature":
                                                        raw["Signature"] ^ flip}, 0)

        other = altered(pages[3], 0x5A)     # page 3 again, with other bytes
        long_last = self.transfer(extra)     # its last page: a byte past the signature
        long_last[-1] = altered(long_last[-1], 1 << 8)
        return [
            (0, [price(cur, Segment=cur.number % pricesig.SEGMENT_LOW_MOD + 1)],
             "an unsigned price: the signed ρ under another Segment"),
            (2, [price(cur, Rho=cur.rho + 1)], "an unsigned price: ρ one LSB off the signed one"),
            (4, [*self.transfer(bad, bytes(pricesig.SEED_BYTES)), price(bad)],
             "a price under a bad signature (another key's)"),
            (6, [*self.transfer(older), price(older)],
             "a price under an older segment's genuine signature (a replay)"),
            (8, [*pages[:3], other, *pages[3:], price(repeat)],
             "a price under a signature with a page repeated with other bytes"),
            (10, [*long_last, price(extra)],
             "a price under a signature whose last page has bytes beyond it"),
        ]


def _plan(cfg: AgentConfig, keys: Mapping[str, bytes] | None, price: float,
          codec: FrameCodec | None, boot: int, planned_band: bool = True,
          other_format: bool = True, tie_rne: bool = False) -> list[Planned]:
    codec = codec or FrameCodec()
    ts, i = cfg.controller.ts, cfg.id
    nbrs = [n.id for n in cfg.neighbours]
    # on a tagged FD bus (AUTH-34) each neighbour's λ carries the DUT's tag (the other
    # receivers are the tester's own roles: the plant and the router)
    tags = {j: [f"agent_{i}", "plant", "router"] for j in nbrs}
    tx = FleetSender(codec, keys, boot=boot if keys is not None else secoc.INSECURE_BOOT,
                     tag_receivers=tags)
    out: list[Planned] = []
    price_every, status_every = _tick_of("ER_Price"), _tick_of(status_name(i))
    # signed_price (AUTH-31..33): the router signs every price it plays, and again every
    # sync period; while the price is stale a key holder of its node key plays prices no
    # conformant device takes, 8 counts ahead of the router's (``_PriceSigner.refused``)
    signer = _PriceSigner(codec, keys, tx.boot) if cfg.signed_price else None
    sig_every = _tick_of("ER_Price_Sync")
    k_gain, h_gain = cfg.controller.k, cfg.controller.h
    other = i % contract.N_AGENTS_MAX + 1
    at = {s.name: s.start for s in STEPS}
    span = next(s.end - s.start for s in STEPS if s.name == "band")
    band_start = band_planned(cfg)
    band = (_BandPlan(cfg, price, codec, at["band"], span, other_format, keys is not None)
            if planned_band and band_start else None)

    def add(k: float, step: str, msg: can.Message, note: str = "",
            age: float | None = None, after: float | None = None) -> None:
        out.append(Planned(k * ts, step, msg, note, age, after))

    def step_at(k: int) -> str:
        return next(s.name for s in STEPS if s.start <= k < s.end)

    def command(cmd: Command, target: int = i, gain_k: int = 0, gain_h: int = 0
                ) -> can.Message:
        """The router's next ER_Command (to the DUT unless ``target`` says otherwise)."""
        return tx.frame("ER_Command", {"Command": int(cmd), "Target": target_raw(target),
                                       "GainK": gain_k, "GainH": gain_h})

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
        if name != "ER_Command":  # held back past the DUT's join window (AUTH-11)
            add(0, "start", tx.sync(name), f"sync of {name}")
    add(22.6, "start", command(Command.ISOLATE),  # to the DUT: another's is not its input
        "a command before its sync, after the join window: unsynced")
    add(25, "start", tx.sync("ER_Command"), "sync of ER_Command")
    first_sync = next(p.msg for p in out if p.note == "sync of ER_Price")
    lam_step = q(_set(cfg.lambda_step_max))   # LAM-1's bound for one sample
    price_step = q(cfg.price_step_max)  # PRICE-3's bound
    # the price step's sign: the edges of the limits step stay inside [rho_min, rho_max]
    p_sign = 1 if q(price) + 2 * price_step < q(cfg.rho_max) else -1
    # where the ramp of the limits step ends: the top of the scenario's λ range (±9.5)
    top = q(min(cfg.lambda_max, 9.5)) - lam_step

    def lam_edge(j: int, k: int) -> tuple[int, str]:
        """Neighbour j's λ from the limits step on, and what its frame exercises: held
        where the schedule left it; for the first neighbour, LAM-1 at its edges (a step
        of exactly the bound, accepted; one LSB more than the bound from the slot's λ,
        rejected; the slot's λ again, which only a device that took the rejected frame
        refuses), then a ramp at 0.9 of the bound per tick to the top of the λ range, so
        that |ξ| is large for long (a gain's last KTS bit shows on the wire λ)."""
        hold = lam_j(j, at["limits"])
        c = k - at["limits"]
        if j != nbrs[0] or c < 20:
            return hold, ""
        if c == 20:
            return hold + lam_step, "a neighbour λ step of exactly the LAM-1 bound"
        if c == 21:
            return (hold + 2 * lam_step + 1,
                    "a neighbour λ step one LSB beyond the LAM-1 bound")
        if c == 22:
            return (hold + lam_step,
                    "a neighbour λ step back to the slot's λ (the one beyond not taken)")
        if c < 25:
            return hold + lam_step, ""
        return max(hold, min(hold + (c - 24) * (9 * lam_step // 10), top)), ""

    def price_edge(k: int) -> tuple[int, int, str]:
        """(PriceValid, ρ, what the frame exercises) of the price at tick k of the limits
        step: a step of exactly q24(price_step_max) (accepted) and back; then one LSB
        more (a candidate), a PriceValid = 0 frame (the candidate kept), the candidate
        price_persist − 1 times more (accepted at the last: the frame after the invalid
        one must count as the second), then back by exactly the bound."""
        c, base, d = k - at["limits"], q(price), p_sign * price_step
        until = 55 + 5 * (cfg.price_persist + 1)  # the price goes every 5 ticks
        if 30 <= c < 45:
            return 1, base + d, "a price step of exactly price_step_max" if c == 30 else ""
        if c == 60:
            return 0, base, "a PriceValid = 0 frame between candidates"
        if 55 <= c < until:
            return 1, base + d + p_sign, "a price step one LSB beyond price_step_max (a candidate)"
        if until <= c < until + 5:
            return (1, base + p_sign,
                    "a price step back by exactly price_step_max" if c == until else "")
        return 1, base, ""

    def extreme(j: int, k: int, lam: int) -> tuple[int, str, State]:
        """Neighbour j's λ, note and State in the extremes step: INIT at lambda_min (a
        State change: the next RUNNING frame is no LAM-1 step, LAM-2), then RUNNING there:
        with W = 1.25 and Λ near the top of the scenario's range, the sum is past int32
        (ξ = sat32, counted: NUM-3, XI-3) and drives the own λ to, and past, lambda_min
        (STEP-12: only sat54 limits it)."""
        c = k - at["extremes"]
        if band is not None and band.ext_lam:  # planned on the reference (ξ's exact edge)
            if c >= len(band.ext_lam):
                return q(cfg.lambda_min), "", State.RUNNING
            first_state, first_note = band.ext_first[c]
            return (band.ext_lam[c][j], first_note if j == nbrs[0] else "",
                    first_state if j == nbrs[0] else band.ext_state[c])
        if c < 5:  # where the band step left them (near the device's λ)
            return (band.lam[-1][j] if band is not None else lam), "", State.RUNNING
        first = j == nbrs[0]
        if c < 7:
            return (q(cfg.lambda_min), "a neighbour INIT at lambda_min" if first and c == 5
                    else "", State.INIT)
        return (q(cfg.lambda_min), "every neighbour at lambda_min in ξ (ξ saturates)"
                if first and c == 7 else "", State.RUNNING)

    # the states step: (tick, command) and the price's and plant's conditions
    st = at["states"]
    gains_raw = _gain_raw_rounding_up(cfg)
    k_raw = _raw_bounds(_set(cfg.k_min), _set(cfg.k_max))
    h_raw = _raw_bounds(_set(cfg.h_min), _set(cfg.h_max))
    genuine: list[can.Message] = []
    held: list[can.Message] = []   # a genuine frame delivered late (AUTH-25)
    fr = at["freshness"]
    window = 1 << contract.FV_TX_BITS   # a freshness window (AUTH-12)
    for k in range(30, STEPS[-1].end):
        step = step_at(k)
        silent_nbr = 10 <= k - at["timeouts"] < 20
        lost_nbr = 30 <= k - fr < 55  # sent, but lost on the bus: the count moves on
        silent_price = 40 <= k - at["timeouts"] < 80 or 60 <= k - st < 110
        invalid_price = 10 <= k - st < 50  # PriceValid = 0 only: an outage all the same
        fault = (120 <= k - at["timeouts"] < 140 or 65 <= k - st < 75
                 or band is not None and at["band"] <= k < at["extremes"]
                 and band.fault[k - at["band"]])
        soc = 100 <= k - at["limits"] < 120
        for j in nbrs:
            if silent_nbr and j == nbrs[0]:
                continue
            lam, lam_note = lam_edge(j, k) if k >= at["limits"] else (lam_j(j, k), "")
            nbr_state = State.RUNNING
            if band is not None and at["band"] <= k < at["extremes"]:
                lam, nbr_state = band.lam[k - at["band"]][j], band.state[k - at["band"]]
                lam_note = band.note[k - at["band"]] if j == nbrs[0] else ""
            if k >= at["extremes"]:
                lam, lam_note, nbr_state = extreme(j, k, lam)
            if k == at["content"] + 30 and j == nbrs[0]:
                lam += q(0.5)  # a jump above lambda_step_max per sample: implausible
            if 60 <= k - at["limits"] < 65 and j == nbrs[0]:
                nbr_state = State.INIT  # alive, but not in ξ (XI-1)
            # an exact-timing run: the first neighbour's frame at limits + 11 lost, the
            # next exactly 2.5 periods after its last and 2.5 bounds away (LAM-1: rne's
            # tie to even gives 2 samples: rejected; 3 would take it)
            tie = tie_rne and j == nbrs[0] and k - at["limits"] in (11, 12)
            if tie and k - at["limits"] == 12:
                lam, lam_note = (lam + 2 * lam_step + lam_step // 2,
                                 "a neighbour frame exactly 2.5 periods after its last, "
                                 "2.5 LAM-1 bounds away")
            msg = tx.frame(mc_name(j), {"State": int(nbr_state), "Lambda": lam,
                                        "Resets": 0})
            if tie:
                if lam_note:
                    add(k + 0.5, step, msg, lam_note, after=2.5 * ts)
                    genuine.append(msg)
                continue
            if lost_nbr and j == nbrs[0]:
                if k - fr == 54:  # and more values spent unseen: the next is 120 on, in
                    for _ in range(120 - 26):  # the 8th window of a lost ID (AUTH-13)
                        tx.frame(mc_name(j), {"State": int(nbr_state), "Lambda": lam,
                                              "Resets": 0})
                continue
            if j == nbrs[0] and k - fr == 55:
                lam_note = ("a neighbour's first frame after 25 lost on the bus, 120 "
                            "freshness values on")
            elif j == nbrs[0] and nbr_state == State.INIT and step != "band":
                lam_note = "a neighbour alive but INIT (not in ξ)"
            elif j == nbrs[0] and k == at["content"] + 30:
                lam_note = "a neighbour λ jump above lambda_step_max"
            elif at["control"] < k < at["authentication"] and (k - at["control"]) % 70 == 0:
                lam_note = "a neighbour λ square step"  # 0.08: near LAM-1's bound
            # the neighbour's last frame before it falls silent: in an exact-timing run
            # exactly neighbour_periods·Ts old at a tick (still alive there, LIVE-2). No
            # note: its ξ = 0 when it dies is a zero crossing (STEP-2) the tester did
            # not cause; a reset at another tick names LIVE-2 by its signal and step
            last = j == nbrs[0] and k - at["timeouts"] == 9
            add(k + 0.5, step, msg, lam_note,
                cfg.neighbour_timeout_periods * ts if last else None)
            genuine.append(msg)
        if price_every(k) and not silent_price:
            valid, r, note = 1, q(ramp(k, price)), ""
            if 20 <= k - at["content"] < 25:
                r = q(6.0)  # above rho_max: implausible
            elif 40 <= k - at["content"] < 70:
                r = q(price + 0.6)  # a step above price_step_max, persistent
                note = "a price step above price_step_max, persistent"
            elif at["limits"] <= k < at["freshness"]:
                valid, r, note = price_edge(k)
            elif invalid_price:
                valid, note = 0, "a PriceValid = 0 frame in an outage"
            elif signer is not None and k - at["timeouts"] == REFUSED_AT + 11:
                note = "the router's price after a key holder's refused ones, 8 counts ahead"
            if k == fr + 20:  # 15 frames lost on the bus: this one is 16 values on
                for _ in range(15):
                    tx.frame("ER_Price", {"PriceValid": valid, "Segment": 0, "Rho": r})
                note = "a price frame 16 freshness values on"
            # the price's last frame before it falls silent: in an exact-timing run
            # exactly price_s old at a tick (still fresh there, STATE-2)
            last = k - at["timeouts"] == 35
            for m in signer.before(valid, r) if signer is not None else ():
                add(k + 0.25, step, m)  # the pages, then the price: one burst
            add(k + 0.25, step, tx.frame("ER_Price", {"PriceValid": valid, "Segment": 0,
                                                      "Rho": r}),
                "the price's last frame, exactly price_s old at a tick" if last else note,
                cfg.price_timeout_s if last else None)
        if signer is not None and signer.current is not None and sig_every(k) \
                and not silent_price:
            for m in signer.transfer(signer.current):  # the sync period's repeat
                add(k + 0.1, step, m)
        if signer is not None and k - at["timeouts"] == REFUSED_AT:
            insider = FleetSender(codec, keys, boot=tx.boot)
            insider.follow("ER_Price", tx.boot, tx.next_count("ER_Price") + 7)
            for off, frames, note in signer.refused(insider):
                for n, m in enumerate(frames):
                    add(k + off + 0.25, step, m, note if n == len(frames) - 1 else "")
        if k >= 60 and status_every(k):
            add(k + 0.75, step, tx.frame(status_name(i), {
                **status, "FaultOverCurrent": int(fault), "FaultSoc": int(soc),
                "PowerLimited": int(soc)}),
                "a status with FaultSoc and PowerLimited set" if soc else "")
        if k == fr + 5:  # every sender's periodic sync, in step with its frames
            for name in inputs:
                add(k + 0.9, step, tx.sync(name), f"periodic sync of {name}")
        if k == fr + 10:  # untrusted_after forged frames in a row on one ID (RX-13), to
            for n in range(cfg.untrusted_after):  # the DUT (AUTH-30: another's is not its input)
                add(k + 0.6 + 0.01 * n, step, _forged(command(Command.ISOLATE)),
                    "forged command")
        # AUTH-27's bounds, both sides: key holders' price syncs 9 boots on and, in the
        # router's boot, 17 values on (refused: sync_jump, auth), then the router's own 16
        # on (frames the DUT missed: taken); a command sync 129 on (its search reaches 128)
        if k == fr + 30:
            add(k + 0.6, step, tx.sync_ahead("ER_Price", boots=SYNC_BOOT_JUMP_MAX + 1),
                "a price sync 9 boots on (a key holder's)")
        if k == fr + 31:
            add(k + 0.6, step, tx.sync_ahead("ER_Price", counts=window + 1),
                "a price sync 17 values on in the router's boot (a key holder's)")
        if k == fr + 32:
            tx.skip("ER_Price", window)
            add(k + 0.6, step, tx.sync("ER_Price"), "the router's price sync 16 values on")
        if k == fr + 33:
            add(k + 0.6, step, tx.sync_ahead("ER_Command", counts=LOST_SEARCH_COUNTS + 1),
                "a command sync 129 values on (a key holder's)")
        # AUTH-35: a key holder's price sync 8 boots on is held, not taken (the router's
        # prices go on being taken); the router's next sync of its boot drops it
        if k == fr + 34:
            add(k + 0.6, step, tx.sync_ahead("ER_Price", boots=SYNC_BOOT_JUMP_MAX),
                "a price sync 8 boots on (a key holder's: held)")
        if k == fr + 37:
            add(k + 0.6, step, tx.sync("ER_Price"), "the router's price sync of its boot "
                "(drops the held advance)")
        if k in (fr + 40, fr + 60) and nbrs:  # a peer's sync: first of its boot, then again
            add(k + 0.6, step, tx.sync(f"AGENT_{nbrs[0]}_Setpoint"),
                "a neighbour's Setpoint sync (a peer sync)")
        # one fewer on another ID, with no failure before (the plant's status): no
        # verdict; then, after valid frames (STREAK_GAP ticks later), one more: no
        # verdict either, the valid frames ended the streak (RX-10)
        if k in (fr + 12, fr + 12 + STREAK_GAP):
            for n in range(cfg.untrusted_after - 1 if k == fr + 12 else 1):
                add(k + 0.3 + 0.01 * n, step, _forged(tx.frame(status_name(i), status)),
                    "forged status" if k == fr + 12
                    else "one more forged status after valid ones (the streak ended)")
        # the silent neighbour's ID is lost after its timeout; a sync in step with its
        # last frame ends that (AUTH-16), so a forgery then is auth, not unsynced
        if k == at["timeouts"] + 17 and nbrs:
            add(k + 0.6, step, tx.sync(mc_name(nbrs[0])), "an in-step sync of a lost ID")
        if k == at["timeouts"] + 18 and nbrs:
            add(k + 0.6, step, _forged(tx.frame(mc_name(nbrs[0]), {
                "State": int(State.RUNNING), "Lambda": lam_j(nbrs[0], k), "Resets": 0})),
                "a forged frame after an in-step sync of a lost ID")
        if k == at["timeouts"] + 19:  # an auth on the price (not lost either way): the
            # last safety event is the same in both cases, the counters tell them apart
            add(k + 0.6, step, _forged(tx.frame("ER_Price", {
                "PriceValid": 1, "Segment": 0, "Rho": q(price)})))
        if k == at["authentication"] + 10:  # a forged MAC on a neighbour's frame with a wild λ
            forged = tx.frame(mc_name(nbrs[0]) if nbrs else "ER_Price", {
                "State": int(State.RUNNING), "Lambda": q(3.0), "Resets": 0} if nbrs else {
                "PriceValid": 1, "Segment": 0, "Rho": q(3.0)})
            forged = _forged(forged)
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
        if k == at["authentication"] + 56:  # ... and again: its FV was marked seen, a replay
            add(k + 0.6, step, _copy(held[0]), "a genuine frame delivered late again (auth)")
        if k == at["content"] + 5:
            add(k + 0.6, step, can.Message(arbitration_id=0x100 + i, is_extended_id=True,
                                           data=bytes(8), **_format(codec)), "extended ID")
        # a Diag page (13 of them, 10 ticks apart) after the extended ID, so that the
        # page's RejectedUnknownId shows each alone (RX-1, RX-6)
        if k == at["commands"] + 120:
            add(k + 0.6, step, can.Message(arbitration_id=_unknown_id(codec),
                                           is_extended_id=False, data=bytes(8),
                                           **_format(codec)), "unknown ID")
        if k == at["content"] + 9:
            add(k + 0.6, step, can.Message(arbitration_id=codec.frame_id(mc_name(i)),
                                           is_extended_id=False, data=bytes(range(8)),
                                           **_format(codec)),
                "the DUT's own MC ID")
        if k == at["content"] + 11 and nbrs:
            short = tx.frame(mc_name(nbrs[0]), {"State": int(State.RUNNING),
                                                 "Lambda": lam_j(nbrs[0], k), "Resets": 0})
            # untrusted_after of them in a row: DLC errors add to the ID's streak (RX-13)
            for n in range(cfg.untrusted_after):
                add(k + 0.6 + 0.01 * n, step, can.Message(
                    arbitration_id=short.arbitration_id, is_extended_id=False,
                    data=short.data[:7], **_format(codec)),
                    "DLC 7" if n < cfg.untrusted_after - 1 else "DLC 7, untrusted_after in a row")
        if k == at["content"] + 15 and nbrs and other_format and not codec.fd:
            # a genuine neighbour frame, the tick's last, as an FD frame on a classic bus:
            # malformed (RX-2), its λ never used; a device that takes it moves. 0.55 Ts
            # after the tick: before the next one at any lateness the schedule tolerates
            # (at 0.8 a late device ticked first, and the λ it took was never used)
            fd = tx.frame(mc_name(nbrs[0]), {"State": int(State.RUNNING),
                                             "Lambda": lam_j(nbrs[0], k) + q(0.01),
                                             "Resets": 0})
            add(k + 0.55, step, can.Message(arbitration_id=fd.arbitration_id,
                                           is_extended_id=False, data=bytes(fd.data),
                                           is_fd=True, bitrate_switch=True), OTHER_FORMAT)
        for tick, cmd, target, kk, hh, note in (
                (10, Command.SET_GAINS, i, 1.5 * k_gain, 1.5 * h_gain, "SET_GAINS in bounds"),
                (20, Command.SET_GAINS, i, 3 * k_gain, h_gain, "SET_GAINS out of bounds"),
                (30, Command.ISOLATE, other, 0, 0, "ISOLATE for another agent"),
                (40, Command.ISOLATE, i, 0, 0, "ISOLATE"),
                (50, Command.ISOLATE, i, 0, 0, "ISOLATE while ISOLATED"),
                (70, Command.RECONNECT, i, 0, 0, "RECONNECT")):
            if k == at["commands"] + tick:
                add(k + 0.6, step, command(cmd, target, round(kk * 1000),
                                           round(hh * 1000)), note)
        # the extremes step pins a band-planned device for ξ's exact edge (its plan)
        for pin_at, way, note in ((band.pin_on_at if band else None, PIN_ON,
                                   "a PIN on, for the sum of ξ exactly 2^31 − 1"),
                                  (band.pin_off_at if band else None, PIN_OFF,
                                   "a PIN off after it")):
            if pin_at is not None and k == at["extremes"] + pin_at:
                add(k + 0.6, step, command(Command.PIN, i, way), note)
        # PIN (CMD-7) flips the DUT's price term, whichever way its configuration starts:
        # ξ gains or loses (ρ − λ) at the next sample; a PIN for another agent, or with a
        # GainK that is neither way (range, before authentication), changes nothing
        for tick, target, way, note in (
                (80, i, PIN_OFF if cfg.pinned else PIN_ON, "PIN the other way"),
                (85, other, PIN_ON if cfg.pinned else PIN_OFF, "PIN for another agent"),
                (90, i, 3, "PIN with GainK 3 (range)"),
                (100, i, PIN_ON if cfg.pinned else PIN_OFF, "PIN back")):
            if k == at["commands"] + tick:  # the encoder checks only the DBC's range
                add(k + 0.6, step, command(Command.PIN, target, way), note)
        for tick, cmd, graw, hraw, note in (
                (5, Command.SET_GAINS, _raw_bounds(_set(cfg.k_min), _set(cfg.k_max))[1],
                 _raw_bounds(_set(cfg.h_min), _set(cfg.h_max))[1], "SET_GAINS at k_max and h_max"),
                (10, Command.SET_GAINS, _raw_bounds(_set(cfg.k_min), _set(cfg.k_max))[0],
                 _raw_bounds(_set(cfg.h_min), _set(cfg.h_max))[0], "SET_GAINS at k_min and h_min"),
                (15, Command.SET_GAINS, gains_raw, round(h_gain * 1000),
                 "SET_GAINS whose KTS rounds half up"),
                # one LSB beyond each bound: refused (a device with wider bounds, e.g.
                # the defaults 0.5·k..2·k instead of the file's, takes them: CFG-7)
                (17, Command.SET_GAINS, k_raw[1] + 1, round(h_gain * 1000),
                 "SET_GAINS one LSB above k_max"),
                (18, Command.SET_GAINS, gains_raw, h_raw[1] + 1,
                 "SET_GAINS one LSB above h_max"),
                (19, Command.SET_GAINS, k_raw[0] - 1, round(h_gain * 1000),
                 "SET_GAINS one LSB below k_min"),
                (20, Command.SET_GAINS, gains_raw, h_raw[0] - 1,
                 "SET_GAINS one LSB below h_min")):
            if k == at["limits"] + tick and 0 <= min(graw, hraw) and max(graw, hraw) < 16384:
                add(k + 0.6, step, command(cmd, i, graw, hraw), note)
        for tick, cmd, note in ((5, Command.RECONNECT, "RECONNECT in RUNNING"),
                                (40, Command.RECONNECT, "RECONNECT in SAFE"),
                                (45, Command.ISOLATE, "ISOLATE in SAFE"),
                                (95, Command.RECONNECT, "RECONNECT, the price stale"),
                                (100, Command.ISOLATE, "ISOLATE in INIT"),
                                (120, Command.RECONNECT, "RECONNECT, all fresh")):
            if k == st + tick:
                add(k + 0.6, step, command(cmd), note)
        if band_start and k - at["band"] in (_BandPlan.ISOLATE_AT, _BandPlan.RECONNECT_AT):
            cmd = (Command.ISOLATE if k - at["band"] == _BandPlan.ISOLATE_AT
                   else Command.RECONNECT)  # the band plan's known start (its twins too)
            add(k + _BandPlan.COMMAND_AT, step, command(cmd))
        if k == st + 119:  # SET_GAINS a tick before the RECONNECT, so surely outside
            # RUNNING (after it, a late device took it in RUNNING): its gains are the
            # controller's from the first step in RUNNING (CMD-5)
            add(k + 0.65, step, command(Command.SET_GAINS, i, round(1.5 * k_gain * 1000),
                                        round(1.5 * h_gain * 1000)),
                "SET_GAINS outside RUNNING (ISOLATED)")
    out.sort(key=lambda p: p.at)
    return out


def _format(codec: FrameCodec) -> dict[str, bool]:
    """The bus's frame format (GEN-1): a hand-made frame of the schedule is malformed,
    extended or unknown for its own reason, not for its format."""
    return {"is_fd": codec.fd, "bitrate_switch": codec.fd}


def _copy(msg: can.Message) -> can.Message:
    return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False,
                       data=bytes(msg.data), is_fd=msg.is_fd,
                       bitrate_switch=msg.bitrate_switch)


# ticks from the freshness step's forged statuses to the one more (in the states step):
# 19 valid statuses between end the streak (RX-10)
STREAK_GAP = 95


def _forged(msg: can.Message) -> can.Message:
    """``msg`` with its first byte changed: its MAC no longer verifies (a tagged λ's
    first slot, the DUT's tag, too: AUTH-34)."""
    msg.data[0] ^= 0x5A
    if len(msg.data) > 9:
        msg.data[9] ^= 0x5A
    return msg


def _set(value: float | None) -> float:
    """A bound AgentConfig derives when not given (never None after __post_init__)."""
    assert value is not None
    return value


def _raw_bounds(low: float, high: float) -> tuple[int, int]:
    """CMD-5's raw bounds of a gain: the smallest raw r in 0..16383 with r·0.001 ≥ low and
    the largest with r·0.001 ≤ high (binary64): a SET_GAINS exactly at the bounds."""
    def fits(r: int) -> bool:
        return 0 <= r <= 16383 and low <= r * 0.001 <= high

    # the binary64 product is within an ulp of r/1000: search only next to low·1000, high·1000
    lo = next((r for r in range(max(0, math.floor(low * 1000) - 2), 16384) if fits(r)), None)
    hi = next((r for r in range(min(16383, math.ceil(high * 1000) + 2), -1, -1) if fits(r)),
              None)
    return (lo, hi) if lo is not None and hi is not None else (0, 0)


def _gain_raw_rounding_up(cfg: AgentConfig) -> int:
    """A GainK raw value inside [k_min, k_max] (CMD-5) whose ``raw·TSQ/1000`` has a
    fraction of at least ½ (so KTS' rounds up, not down), the nearest to 1.25·k."""
    tsq = round(cfg.controller.ts * (1 << 30))
    lo, hi = _raw_bounds(_set(cfg.k_min), _set(cfg.k_max))
    want = round(1.25 * cfg.controller.k * 1000)
    fits = [r for r in range(max(lo, 1), hi + 1) if (r * tsq) % 1000 >= 500]
    return min(fits, key=lambda r: abs(r - want)) if fits else round(cfg.controller.k * 1000)


def _unknown_id(codec: FrameCodec) -> int:
    return next(fid for fid in range(0x7FF, 0, -1) if fid not in codec.frame_ids())
