#!/usr/bin/env python3
"""Generate ``dbc/bess_ded.dbc``, the single source of truth for every frame on the bus,
and its CAN FD twins ``dbc/bess_ded_fd.dbc`` and ``dbc/bess_ded_fd_untagged.dbc``.

The DBC is built from cantools objects rather than written by hand so that the
layout rules below are applied uniformly to all 64 agents' frames and cannot
drift between copies. The generated file is committed (other tools, C code
generators and CAN analysers read the DBC, not this script); a test checks that
the committed file is what this script produces.

Layout rules (every frame):

* classic CAN, 11-bit IDs, DLC 8, 500 kbit/s, Intel (little-endian) signals;
* the FD twin (``bess_ded_fd.dbc``, ``--fd`` on the nodes) is the same database, built by
  the same code, with every message a CAN FD frame (``VFrameFormat`` StandardCAN_FD,
  ``CANFD_BRS`` 1: the bit-rate switch), ``BusType`` "CAN FD" and the data phase's
  ``BaudrateCANFD``; the layouts stay 8 bytes, so IDs, signals and MACs are the same
  on either bus and only the frame format (and its time on the bus) differs, but for
  ``AGENT_<i>_MC`` and its sync: 32 bytes, the classic 8 and six slots of a receiver code
  and its 24-bit tag (AUTH-34: a tag per receiver under the pair's key, so that no key
  but the sender's own tags its λ); ``bess_ded_fd_untagged.dbc`` (``[security]
  lambda_tags = false``, ``--no-lambda-tags``) keeps λ at 8 bytes under its sender's
  node key, for a bus that cannot afford the tags;
* every frame is **secured** (those that can change the dispatch: price, command, MC,
  setpoint, status; and those that report or account: diagnostics, balance) in the
  style of AUTOSAR SecOC (docs/security.md): bytes 0..2 are ``Mac``
  (the first 3 bytes of CMAC-AES-128 under the sender's key over data ID ‖ payload ‖
  full freshness value), the low nibble of byte 3 is ``Counter``, the low 4 bits of
  the freshness value (+1 per transmission, so it is also the E2E sequence counter),
  and the payload is bits 28..63;
* every secured frame has a ``<name>_Sync`` frame at its ID + 0x400 carrying the full
  freshness value (``Boot`` ‖ ``Count``) under a MAC, at start, every second and when
  a new peer appears;
* multiplexed frames (``AGENT_<i>_Diag``, ``ER_Balance``) carry ``Page`` in bits 28..31;
* every signal has an explicit [min|max]; receivers range-check raw values
  against it (cantools' decode does not).

Usage::

    python tools/gen_dbc.py            # (re)write the three DBC files
    python tools/gen_dbc.py --check    # exit 1 if a committed file is stale
    python tools/gen_dbc.py -o FILE    # write the classic DBC elsewhere (--fd-output: the twin)
"""

from __future__ import annotations

import argparse
import re
import sys
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from cantools.database.can import Bus, Database, Message, Node, Signal
from cantools.database.can.formats.dbc import DbcSpecifics
from cantools.database.can.formats.dbc.dbc_attribute import DbcAttribute
from cantools.database.can.formats.dbc.dbc_attribute_definition import DbcAttributeDefinition
from cantools.database.conversion import BaseConversion

if TYPE_CHECKING:
    from cantools.typechecking import Choices

N_AGENTS = 64  # the ID plan's per-agent blocks hold 64 (MC 0x101..0x140 .. Diag ..0x340)
BAUDRATE = 500_000
FD_BAUDRATE = 2_000_000  # the FD data phase (bit-rate switch); the arbitration stays BAUDRATE
BUS_NAME = "bess_ded"
LAMBDA_Q = 24
Q24 = 2.0**-LAMBDA_Q  # exactly 5.9604644775390625e-08; a power of two, so exact in binary64

ER_PRICE_ID = 0x010
ER_COMMAND_ID = 0x020
ER_PRICE_SIG_ID = 0x008  # below ER_Price: queued together, the signature wins arbitration
PRICE_SIG_PAGES = 11     # ER_PriceSig: page 0 the signed segment, 1..10 the signature
MC_BASE = 0x100
SETPOINT_BASE = 0x200
STATUS_BASE = 0x280
DIAG_BASE = 0x300
ER_BALANCE_ID = 0x3E0  # its sync (+ SYNC_OFFSET) must fit 11 bits and stay out of
                      # 0x7F0..0x7FF, the tests' noise IDs (tests/vcan: cangen -I 7F0)
PLANT_TOTALS_ID = 0x3E1  # a report beside ER_Balance: no per-agent block loses room

MC_CYCLE_MS = 10
SETPOINT_CYCLE_MS = 50
STATUS_CYCLE_MS = 50
PRICE_CYCLE_MS = 50
DIAG_CYCLE_MS = 100
BALANCE_CYCLE_MS = 100
SYNC_CYCLE_MS = 1000
SYNC_OFFSET = 0x400  # <name>_Sync ID = the secured frame's ID + SYNC_OFFSET

DEFAULT_OUTPUT = Path(__file__).resolve().parent.parent / "dbc" / "bess_ded.dbc"
DEFAULT_FD_OUTPUT = DEFAULT_OUTPUT.with_name("bess_ded_fd.dbc")
DEFAULT_FD_UNTAGGED_OUTPUT = DEFAULT_OUTPUT.with_name("bess_ded_fd_untagged.dbc")

STATE_CHOICES = {0: "INIT", 1: "RUNNING", 2: "ISOLATED", 3: "SAFE"}
COMMAND_CHOICES = {0: "PIN", 1: "ISOLATE", 2: "RECONNECT", 3: "SET_GAINS"}
# PIN (issue 23.5) took the one free value of the 2-bit Command: its GainK says which way
# (firmware_py.frames PIN_ON / PIN_OFF)
# AGENT_<i>_Diag SafetyCause (firmware_py.runtime.SAFETY_CAUSES, docs/safety-model.md)
SAFETY_CAUSE_CHOICES = {0: "NONE", 1: "UNTRUSTED", 2: "IMPLAUSIBLE_PRICE",
                        3: "IMPLAUSIBLE_LAMBDA", 4: "IMPLAUSIBLE_GAINS", 5: "AUTH"}

BUS_COMMENT = (
    "bess-ded: distributed economic dispatch of battery energy storage systems. "
    "{format}, 11-bit standard IDs, {dlc}, Intel byte order. "
    "Every frame is secured (AUTOSAR SecOC style, "
    "docs/security.md): bytes 0..2 = Mac, the first 3 bytes of CMAC-AES-128 under the "
    "sender's key over data ID (CAN ID, 2 bytes big-endian) + payload (bytes 3..7 with "
    "bits 24..27 zeroed) + the full 40-bit freshness value (8 bytes big-endian); low "
    "nibble of byte 3 = Counter, the low 4 bits of the freshness value. <name>_Sync "
    "(ID + 0x400) carries the full freshness value. Lambda and Rho are int32 Q24 "
    "fixed point (factor 2^-24 exactly). Generated by tools/gen_dbc.py: do not edit."
)

DIAG_SATURATION = "uint16, saturating at 65535 (the sender saturates, it never wraps)."


def _all_agents() -> list[str]:
    return [f"AGENT_{i}" for i in range(1, N_AGENTS + 1)]


def _sig(
    name: str,
    start: int,
    length: int,
    *,
    comment: str,
    receivers: list[str],
    signed: bool = False,
    scale: float = 1,
    minimum: float | None = None,
    maximum: float | None = None,
    unit: str | None = None,
    choices: dict[int, str] | None = None,
    offset: int = 0,
    is_multiplexer: bool = False,
    page: int | list[int] | None = None,
) -> Signal:
    """One Intel integer signal. [min|max] default to the full raw range, scaled.

    Explicit limits matter: the firmware's receive path rejects a raw value
    outside them, so they are the contract's range, not decoration.
    """
    raw_lo = -(1 << (length - 1)) if signed else 0
    raw_hi = (1 << (length - 1)) - 1 if signed else (1 << length) - 1
    if minimum is None:
        minimum = raw_lo * scale + offset
    if maximum is None:
        maximum = raw_hi * scale + offset
    if scale == 1:
        minimum, maximum = int(minimum), int(maximum)
    named_choices = None if choices is None else dict(choices.items())
    return Signal(
        name=name,
        start=start,
        length=length,
        byte_order="little_endian",
        is_signed=signed,
        conversion=BaseConversion.factory(scale=scale, offset=offset, choices=named_choices),  # type: ignore[arg-type]
        minimum=minimum,
        maximum=maximum,
        unit=unit,
        comment=comment,
        receivers=list(receivers),
        is_multiplexer=is_multiplexer,
        multiplexer_ids=None if page is None else [page] if isinstance(page, int) else page,
        multiplexer_signal=None if page is None else "Page",
    )


SECOC_MAC_COMMENT = (
    "SecOC authenticator: the first 3 bytes of CMAC-AES-128 under the sender's key over "
    "data ID (2 bytes BE) + bytes 3..7 with bits 24..27 zeroed + the full freshness value "
    "(8 bytes BE), in bytes 0, 1, 2 in that order (the Intel value is their little-endian "
    "reading). Receivers drop the frame on mismatch (docs/security.md)."
)
SECOC_COUNTER_COMMENT = (
    "Truncated freshness value: its low 4 bits, +1 mod 16 per transmission of this frame. "
    "The receiver rebuilds the full value as the smallest one above the last it accepted "
    "with these low bits; (step - 1) frames were lost."
)


def _secoc(receivers: list[str]) -> list[Signal]:
    return [
        _sig("Mac", 0, 24, comment=SECOC_MAC_COMMENT, receivers=receivers),
        _sig("Counter", 24, 4, comment=SECOC_COUNTER_COMMENT, receivers=receivers),
    ]


# CAN FD: AGENT_i_MC and its sync carry a 24-bit tag per receiver (AUTH-34, issue 25):
# the classic 8 bytes, then TAG_SLOTS slots of (receiver code, tag), 4 bytes each.
TAG_SLOTS = 6
TAG_SLOT_START = 64  # bit of the first slot (byte 8)
TAG_RX_PLANT, TAG_RX_ROUTER = 0xFE, 0xFF  # receiver codes; an agent's is its index
TAG_RX_CHOICES = {0: "EMPTY", TAG_RX_PLANT: "PLANT", TAG_RX_ROUTER: "ROUTER"}
FD_MC_BYTES = 8 + 4 * TAG_SLOTS  # a CAN FD payload size (32)
TAG_RX_COMMENT = (
    "Receiver of slot {k}'s tag: agent j = j (1..64), the plant = 254, the router = 255, "
    "0 = an empty slot. A sender fills the slots with its neighbours by index, then the "
    "plant, then the router (AUTH-34).")
TAG_COMMENT = (
    "Slot {k}'s tag: the first 3 bytes of CMAC-AES-128 under the key of the pair (this "
    "sender, slot {k}'s receiver) over the same input as a Mac (data ID, bytes 3..7 with "
    "bits 24..27 zeroed, the full freshness value), in bytes {b}, {b1}, {b2} in that "
    "order (the Intel value is their little-endian reading). 0 in an empty slot.")


def _tag_slots(receivers: list[str]) -> list[Signal]:
    out = []
    for k in range(TAG_SLOTS):
        start = TAG_SLOT_START + 32 * k
        b = start // 8 + 1
        out += [_sig(f"TagRx{k}", start, 8, receivers=receivers, choices=TAG_RX_CHOICES,
                     comment=TAG_RX_COMMENT.format(k=k)),
                _sig(f"Tag{k}", start + 8, 24, receivers=receivers,
                     comment=TAG_COMMENT.format(k=k, b=b, b1=b + 1, b2=b + 2))]
    return out


def _with_tags(m: Message) -> Message:
    """The FD twin's AGENT_i_MC or its sync: the same signals and the receivers' tags
    (AUTH-34); its Mac is 0 (a tag per receiver replaces the sender's one MAC)."""
    rx = sorted({r for s in m.signals for r in s.receivers})
    return Message(frame_id=m.frame_id, name=m.name, length=FD_MC_BYTES,
                   signals=[*m.signals, *_tag_slots(rx)],
                   comment=f"{m.comment} CAN FD: a 24-bit tag per receiver (AUTH-34); Mac 0.",
                   senders=m.senders, cycle_time=m.cycle_time, send_type=m.send_type,
                   dbc_specifics=m.dbc, is_extended_frame=False, strict=True)


def _sync(secured: Message) -> Message:
    rx = sorted({r for s in secured.signals for r in s.receivers})
    return _msg(secured.frame_id + SYNC_OFFSET, f"{secured.name}_Sync", secured.senders[0], [
        _sig("Mac", 0, 24, receivers=rx,
             comment="SecOC authenticator over this frame's ID, bytes 3..7 with bits 24..27 "
                     "zeroed and the carried freshness value Boot:Count (8 bytes BE)."),
        _sig("Count", 24, 24, receivers=rx,
             comment=f"Message counter of the next {secured.name} frame (low 24 bits of its "
                     "freshness value)."),
        _sig("Boot", 48, 16, minimum=1, receivers=rx,
             comment="Boot counter of the sender (high 16 bits of the freshness value), "
                     "persisted before the first frame of every start."),
    ], f"Freshness synchronisation of {secured.name}: the full freshness value its next frame "
       "uses. Sent at start, every second, and when a peer (re)appears; a receiver moves "
       "its state forward only.", SYNC_CYCLE_MS)


_SEND_TYPE_DEF = DbcAttributeDefinition[Any](
    "GenMsgSendType", default_value="Cyclic", kind="BO_", type_name="ENUM",
    choices=["Cyclic", "Event"])


def _msg(
    frame_id: int,
    name: str,
    sender: str,
    signals: list[Signal],
    comment: str,
    cycle_ms: int | None,
) -> Message:
    dbc = None
    if cycle_ms is None:
        dbc = DbcSpecifics(attributes=OrderedDict(
            GenMsgSendType=DbcAttribute[Any](1, _SEND_TYPE_DEF)))  # ENUM: value = index
    return Message(
        frame_id=frame_id,
        name=name,
        length=8,
        signals=signals,
        comment=comment,
        senders=[sender],
        cycle_time=cycle_ms,
        send_type="Cyclic" if cycle_ms is not None else "Event",
        dbc_specifics=dbc,
        is_extended_frame=False,
        strict=True,
    )


def _er_price() -> Message:
    rx = _all_agents()
    return _msg(ER_PRICE_ID, "ER_Price", "ER", [
        *_secoc(rx),
        _sig("PriceValid", 28, 1, receivers=rx,
             comment="1 = Rho is a valid price; 0 = the router has no price (treat as no price "
                     "frame)."),
        _sig("Segment", 29, 3, receivers=rx,
             comment="Index of the active segment of the time-phased price schedule, mod 8."),
        _sig("Rho", 32, 32, signed=True, scale=Q24, unit="cu/kWh", receivers=rx,
             comment="Grid price rho(t), the consensus leader. int32 Q24 fixed point: phys = raw "
                     "* 2^-24 exactly (5.9604644775390625e-08), the firmware's native format."),
    ], "Energy router price broadcast: the time-phased price rho(t) every agent pins to.",
        PRICE_CYCLE_MS)


def _er_price_sig() -> Message:
    """The signed price segment (issue 25, item 1, ``signed_price``): no MAC of its own."""
    rx = _all_agents()
    sig_pages = list(range(1, PRICE_SIG_PAGES))
    return _msg(ER_PRICE_SIG_ID, "ER_PriceSig", "ER", [
        _sig("Page", 0, 4, minimum=0, maximum=PRICE_SIG_PAGES - 1, is_multiplexer=True,
             receivers=rx,
             comment="Multiplexer: page 0 = the signed segment, pages 1..10 = the 64-byte "
                     "Ed25519 signature, 7 bytes a page (page 10: its last byte). Sent 0..10 "
                     "in one burst before the first ER_Price of a new segment and every "
                     "second (signed_price only; docs/security.md)."),
        _sig("PriceValid", 4, 1, receivers=rx, page=0,
             comment="ER_Price.PriceValid of the signed segment."),
        _sig("Segment", 5, 3, receivers=rx, page=0,
             comment="ER_Price.Segment of the signed segment (the low 3 bits of its number)."),
        _sig("Rho", 8, 32, signed=True, scale=Q24, unit="cu/kWh", receivers=rx, page=0,
             comment="ER_Price.Rho of the signed segment (int32 Q24)."),
        _sig("Boot", 40, 16, receivers=rx, page=0,
             comment="The router's boot counter when it signed the segment."),
        _sig("SegmentHigh", 56, 8, receivers=rx, page=0,
             comment="Bits 3..10 of the segment number (mod 2048; it only grows within a "
                     "boot)."),
        _sig("Signature", 8, 56, receivers=rx, page=sig_pages,
             comment="7 bytes of the Ed25519 signature (bytes 1..7 of the frame in order; "
                     "page 10: 1 byte, the rest 0) over the fleet ID, the boot, the segment "
                     "number, PriceValid and Rho (firmware_py/pricesig.py)."),
    ], "Energy router price signature (signed_price): an Ed25519 signature of the price "
       "segment, multi-frame; no Mac or Counter (the signature authenticates it). Event "
       "frame: sent at each segment change and every second.", None)


def _er_command() -> Message:
    rx = _all_agents()
    return _msg(ER_COMMAND_ID, "ER_Command", "ER", [
        *_secoc(rx),
        _sig("Command", 28, 2, minimum=0, maximum=3, choices=COMMAND_CHOICES, receivers=rx,
             comment="ISOLATE: agent Target leaves the consensus (plug-and-play out); RECONNECT: "
                     "it re-enters; SET_GAINS: it adopts GainK and GainH; PIN: it hears the "
                     "price in its consensus error (GainK = 1) or no longer (GainK = 2), "
                     "GainH = 0; any other PIN is out of range."),
        # 6 bits hold 64 values and no bit is free beside them: raw 0..63 = agent 1..64
        _sig("Target", 30, 6, offset=1, minimum=1, maximum=N_AGENTS, receivers=rx,
             comment=f"Agent index 1..{N_AGENTS} the command is addressed to (raw = index - 1: "
                     "DBC offset 1); other agents ignore it."),
        _sig("GainK", 36, 14, scale=0.001, receivers=rx,
             comment="Proportional consensus gain k (SET_GAINS); PIN: 1 = pin, 2 = unpin; 0 "
                     "otherwise."),
        _sig("GainH", 50, 14, scale=0.001, receivers=rx,
             comment="Integral consensus gain h (SET_GAINS only; 0 otherwise)."),
    ], "Energy router command to one agent (event frame, sent on demand; its counter still "
       "advances per transmission).", None)


def _agent_mc(i: int) -> Message:
    rx = [a for a in _all_agents() if a != f"AGENT_{i}"] + ["ER"]
    return _msg(MC_BASE + i, f"AGENT_{i}_MC", f"AGENT_{i}", [
        *_secoc(rx),
        _sig("State", 28, 2, minimum=0, maximum=3, choices=STATE_CHOICES, receivers=rx,
             comment="Agent state machine. Neighbours only use Lambda from RUNNING agents."),
        _sig("Resets", 30, 2, receivers=rx,
             comment="Number of Clegg resets of the integrator so far, mod 4 (at most one per "
                     "step; the full count is on AGENT_i_Diag page 0)."),
        _sig("Lambda", 32, 32, signed=True, scale=Q24, unit="cu/kWh", receivers=rx,
             comment="Marginal cost lambda_i. int32 Q24 fixed point: phys = raw * 2^-24 exactly "
                     "(5.9604644775390625e-08), bit-identical to the firmware's state."),
    ], f"Agent {i} marginal cost broadcast, the consensus exchange.", MC_CYCLE_MS)


def _agent_setpoint(i: int) -> Message:
    rx = ["PLANT"]
    return _msg(SETPOINT_BASE + i, f"AGENT_{i}_Setpoint", f"AGENT_{i}", [
        *_secoc(rx),
        _sig("Enable", 28, 1, receivers=rx,
             comment="1 = follow PowerSetpoint; 0 = hold zero power (INIT, ISOLATED, SAFE)."),
        _sig("PowerSetpoint", 32, 16, signed=True, scale=0.01, unit="kW", receivers=rx,
             comment="Power setpoint of BESS i, positive = discharge into the grid."),
    ], f"Agent {i} power setpoint to its DC-DC chopper (plant).", SETPOINT_CYCLE_MS)


def _plant_status(i: int) -> Message:
    # agent i alone: the router's ledger takes PLANT_Totals, so the status's key is the
    # plant's and agent i's only (AUTH-28) and agent i cannot misreport to the router
    rx = [f"AGENT_{i}"]
    return _msg(STATUS_BASE + i, f"PLANT_{i}_Status", "PLANT", [
        *_secoc(rx),
        _sig("FaultOverCurrent", 28, 1, receivers=rx, comment="1 = over-current trip."),
        _sig("FaultVoltage", 29, 1, receivers=rx, comment="1 = voltage out of range."),
        _sig("FaultSoc", 30, 1, receivers=rx, comment="1 = state of charge at a hard limit."),
        _sig("PowerLimited", 31, 1, receivers=rx,
             comment="1 = the delivered power is clipped below the setpoint (P limits)."),
        _sig("Power", 32, 16, signed=True, scale=0.01, unit="kW", receivers=rx,
             comment="Measured power of BESS i, positive = discharge into the grid."),
        _sig("Soc", 48, 8, scale=0.5, maximum=100, unit="%", receivers=rx,
             comment="State of charge, 0..100 % (raw 0..200)."),
    ], f"Plant (battery + chopper) {i} status: power, state of charge, fault flags.",
        STATUS_CYCLE_MS)


def _plant_totals() -> Message:
    rx = ["ER"]
    return _msg(PLANT_TOTALS_ID, "PLANT_Totals", "PLANT", [
        *_secoc(rx),
        _sig("BatteryPower", 28, 18, signed=True, scale=0.1, unit="kW", receivers=rx,
             comment="Sum of the measured powers of every BESS, as their PLANT_i_Status "
                     "frames of the same cycle report them; positive = discharge."),
        _sig("BatteryCostRate", 46, 18, signed=True, scale=0.1, unit="cu/h", receivers=rx,
             comment="Sum of the batteries' cost rates (1+m_i)(alpha_i P_i^2 + beta_i P_i) "
                     "at those powers."),
    ], "Plant totals for the router's ledger (ER_Balance), sent with the status frames of "
       "each status cycle: under a key only the plant and the router hold (AUTH-29), so no "
       "agent can misreport its battery to the router.", STATUS_CYCLE_MS)


# AGENT_<i>_Diag: two 16-bit slots per page (DIAG_SLOT_STARTS), filled in this order; a
# slot holds one counter, or small signals side by side (name, bits, extra _sig arguments).
# A slot whose comment starts with "Reserved" is always 0 (firmware_py contract.DIAG_RESERVED
# reads the mark; firmware_c's diag_value returns 0 for it): it counted a check of the
# E2E-only frames the DBC no longer has, and stays so that no later slot moves.
_RESERVED = "Reserved, always 0 (kept for layout compatibility): "
DIAG_SLOT_STARTS = (32, 48)
_U16 = 16
_DIAG_SLOTS: tuple[tuple[tuple[str, int, dict[str, Any]], ...], ...] = (
    (("Resets", _U16, {"what": "Clegg resets since start (not mod 4, unlike the MC frame)."}),),
    (("DeadlineMisses", _U16, {"what": "Control periods whose step started late."}),),
    (("NeighboursAlive", 8, {"comment": "Neighbours currently heard and RUNNING."}),
     ("State", 4, {"minimum": 0, "maximum": 3, "choices": STATE_CHOICES,
                   "comment": "Agent state machine (same as the MC frame)."})),
    (("RejectedCrc", _U16, {"comment": _RESERVED + "counted frames dropped for a CRC "
                                       "mismatch; every frame is secured (a corrupted one "
                                       "counts under RejectedAuth)."}),),
    (("RejectedDlc", _U16, {"what": "Received frames dropped for DLC != 8."}),),
    (("RejectedRange", _U16, {"what": "Received frames dropped for a signal outside its "
                                      "range."}),),
    (("RejectedUnknownId", _U16, {"what": "Received frames dropped for an ID not in the "
                                          "DBC."}),),
    (("RejectedImpersonation", _U16, {"what": "Received frames carrying this agent's own ID "
                                              "that it did not send."}),),
    (("RepeatedCounter", _U16, {"comment": _RESERVED + "counted E2E frames repeating "
                                           "their rolling counter; a replayed secured frame "
                                           "counts under RejectedAuth."}),),
    (("LostFrames", _U16, {"what": "Frames inferred lost from counter gaps."}),),
    (("Saturations", _U16, {"what": "Fixed-point results clamped to the int32 range."}),),
    (("NeighbourTimeouts", _U16, {"what": "Neighbours that went silent past their "
                                          "timeout."}),),
    (("PriceTimeouts", _U16, {"what": "Times the ER price went stale (no valid ER_Price for "
                                      "the price timeout)."}),),
    (("StatusTimeouts", _U16, {"what": "Times PLANT_<i>_Status went stale (none for the "
                                       "status timeout)."}),),
    (("PlantFaults", _U16, {"what": "Over-current or voltage faults reported by "
                                    "PLANT_<i>_Status (rising edges)."}),),
    (("ForeignFrames", _U16, {"what": "Received frames that cannot come from this agent's "
                                      "fleet: impersonation, IDs of agents outside the "
                                      "run."}),),
    (("ForeignIds", _U16, {"what": "Of ForeignFrames: frames on IDs of agents outside the "
                                   "run."}),),
    (("InterleavedCounters", _U16, {"comment": _RESERVED + "counted E2E rolling counters "
                                               "that stepped back or repeated with another "
                                               "payload; a second sender on a secured ID "
                                               "counts under RejectedAuth."}),),
    (("Untrusted", _U16, {"what": "Untrusted-source alarms: times a source ID reached 5 "
                                  "consecutive DLC, range or authentication failures "
                                  "(untrusted for 1 s; docs/safety-model.md)."}),),
    (("ImplausiblePrice", _U16, {"what": "ER_Price frames rejected as implausible (outside "
                                         "rho_min..rho_max, or a step above price_step_max "
                                         "not yet persistent)."}),),
    (("ImplausibleLambda", _U16, {"what": "Neighbour MC frames rejected for a lambda step "
                                          "above lambda_step_max per sample (last good lambda "
                                          "kept)."}),),
    (("ImplausibleGains", _U16, {"what": "SET_GAINS commands rejected for gains outside "
                                         "k_min..k_max, h_min..h_max (gains unchanged)."}),),
    (("SafetySender", 11, {"minimum": 0, "maximum": 0x7FF,
                           "comment": "Claimed sender (CAN ID) of the last frame the safety "
                                      "model rejected (0: none yet)."}),
     ("SafetyCause", 4, {"minimum": 0, "maximum": len(SAFETY_CAUSE_CHOICES) - 1,
                         "choices": SAFETY_CAUSE_CHOICES,
                         "comment": "Cause of the last frame the safety model rejected."})),
    (("RejectedAuth", _U16, {"what": "Secured frames and syncs rejected for a MAC that does "
                                     "not verify (forged, replayed, corrupted or out of the "
                                     "freshness window)."}),),
    (("Unsynced", _U16, {"what": "Secured frames dropped because no freshness value of their "
                                 "sender was known yet (before its first sync)."}),),
    (("Resyncs", _U16, {"what": "Sync frames that moved a sender's freshness value "
                                "forward."}),),
)
DIAG_PAGES = -(-len(_DIAG_SLOTS) // len(DIAG_SLOT_STARTS))  # the pages the slots fill


def _agent_diag(i: int) -> Message:
    rx = ["ER"]
    signals = [
        *_secoc(rx),
        _sig("Page", 28, 4, minimum=0, maximum=DIAG_PAGES - 1, is_multiplexer=True,
             receivers=rx,
             comment="Multiplexer: which diagnostics page this frame carries "
                     f"(0..{DIAG_PAGES - 1}, sent in turn)."),
    ]
    for k, slot in enumerate(_DIAG_SLOTS):
        page, bit = divmod(k, len(DIAG_SLOT_STARTS))
        start = DIAG_SLOT_STARTS[bit]
        for name, bits, extra in slot:
            extra = dict(extra)
            what = extra.pop("what", None)
            if what is not None:
                extra["comment"] = f"{what.replace('<i>', str(i))} {DIAG_SATURATION}"
            signals.append(_sig(name, start, bits, page=page, receivers=rx, **extra))
            start += bits
    return _msg(DIAG_BASE + i, f"AGENT_{i}_Diag", f"AGENT_{i}", signals,
                f"Agent {i} diagnostics, multiplexed over {DIAG_PAGES} pages (one page per "
                "frame, in turn).", DIAG_CYCLE_MS)


def _er_balance() -> Message:
    rx: list[str] = []
    return _msg(ER_BALANCE_ID, "ER_Balance", "ER", [
        *_secoc(rx),
        _sig("Page", 28, 4, minimum=0, maximum=1, is_multiplexer=True, receivers=rx,
             comment="Multiplexer: page 0 = GridPower and CostRate, page 1 = OptimalCostRate; "
                     "the router sends both pages every balance cycle, 0 then 1 (the rates "
                     "of one instant)."),
        _sig("GridPower", 32, 16, signed=True, scale=0.1, unit="kW", receivers=rx, page=0,
             comment="Grid exchange P_e = D - sum(P_i); positive = drawn from the utility grid."),
        _sig("CostRate", 48, 16, signed=True, scale=0.1, unit="cu/h", receivers=rx, page=0,
             comment="Instantaneous expenditure F_c = sum (1+m_i)(alpha_i P_i^2 + beta_i P_i) "
                     "+ rho P_e."),
        _sig("OptimalCostRate", 32, 16, signed=True, scale=0.1, unit="cu/h", receivers=rx,
             page=1, comment="Expenditure at the KKT optimum for the current load and price."),
    ], "Energy router bookkeeping: grid exchange and cost, actual vs optimal (monitoring "
       "only), in two pages sent together every balance cycle.",
        BALANCE_CYCLE_MS)


_MC_NAME = re.compile(r"AGENT_[0-9]+_MC(_Sync)?")
_FORMATS = {
    (False, False): "Classic CAN, 500 kbit/s",
    (True, True): "CAN FD, 500 kbit/s arbitration, 2 Mbit/s data (bit-rate switch), the "
                  "classic DBC's frames as FD frames, AGENT_i_MC and its sync with a tag per "
                  "receiver in 32 bytes",
    (True, False): "CAN FD, 500 kbit/s arbitration, 2 Mbit/s data (bit-rate switch), the "
                   "classic DBC's frames as FD frames (lambda_tags = false: every frame 8 "
                   "bytes, lambda under its sender's node key)"}


def build_database(fd: bool = False, tags: bool = True) -> Database:
    """The whole bus as a cantools Database (not yet written); ``fd``: the FD twin, every
    message a CAN FD frame with the bit-rate switch (same IDs and layouts; with ``tags``,
    λ and its sync 32 bytes with a tag per receiver, AUTH-34)."""
    nodes = [
        Node("ER", comment="Energy router: broadcasts the price rho(t), sends commands, and "
                           "accounts grid exchange and cost."),
        Node("PLANT", comment="Plant simulator (or real hardware): one battery + DC-DC chopper "
                              "per agent; follows setpoints, reports status."),
        *(Node(f"AGENT_{i}", comment=f"Firmware node of BESS agent {i}: reset-PI marginal-cost "
                                     "consensus.") for i in range(1, N_AGENTS + 1)),
    ]
    messages = [_er_price(), _er_command()]
    messages += [_agent_mc(i) for i in range(1, N_AGENTS + 1)]
    messages += [_agent_setpoint(i) for i in range(1, N_AGENTS + 1)]
    messages += [_plant_status(i) for i in range(1, N_AGENTS + 1)]
    messages.append(_plant_totals())
    messages += [_agent_diag(i) for i in range(1, N_AGENTS + 1)]
    messages.append(_er_balance())
    messages.append(_er_price_sig())
    messages += [_sync(m) for m in list(messages)
                 if any(s.name == "Counter" and s.start == 24 for s in m.signals)]
    if fd and tags:  # λ and its sync carry a tag per receiver (AUTH-34)
        messages = [_with_tags(m) if _MC_NAME.fullmatch(m.name) else m for m in messages]
    for m in messages:
        m.is_fd = fd  # cantools writes VFrameFormat (and CANFD_BRS, default 1) for it

    bus_type_def = DbcAttributeDefinition("BusType", default_value="CAN", type_name="STRING")
    db_name_def = DbcAttributeDefinition("DBName", default_value="", type_name="STRING")
    attributes = OrderedDict(BusType=DbcAttribute("CAN FD" if fd else "CAN", bus_type_def),
                             DBName=DbcAttribute(BUS_NAME, db_name_def))
    definitions = OrderedDict(BusType=bus_type_def, DBName=db_name_def,
                              GenMsgSendType=_SEND_TYPE_DEF)
    if fd:  # the data phase's bit rate (Vector's network attribute; cantools keeps it)
        fd_rate_def = DbcAttributeDefinition("BaudrateCANFD", default_value=0, type_name="INT",
                                             minimum=0, maximum=8_000_000)
        attributes["BaudrateCANFD"] = DbcAttribute(FD_BAUDRATE, fd_rate_def)
        definitions["BaudrateCANFD"] = fd_rate_def
    specifics = DbcSpecifics(
        attributes=attributes,
        attribute_definitions=definitions,
        # Named value tables, for tools that offer them when editing signals.
        value_tables=OrderedDict(AgentState=cast("Choices", OrderedDict(STATE_CHOICES)),
                                 ErCommand=cast("Choices", OrderedDict(COMMAND_CHOICES))),
    )
    return Database(
        messages=messages,
        nodes=nodes,
        buses=[Bus(BUS_NAME, comment=BUS_COMMENT.format(
                       format=_FORMATS[fd, fd and tags],
                       dlc=f"DLC 8 (AGENT_i_MC and its sync {FD_MC_BYTES})" if fd and tags
                       else "DLC 8"), baudrate=BAUDRATE,
                   fd_baudrate=FD_BAUDRATE if fd else None)],
        version="1.0",
        dbc_specifics=specifics,
        strict=True,
    )


def render(fd: bool = False, tags: bool = True) -> str:
    """The DBC text exactly as committed (cantools' writer; CRLF line ends, ASCII only)."""
    text = build_database(fd, tags).as_dbc_string()
    text.encode("ascii")  # DBC readers assume cp1252; keep comments plain ASCII
    return text


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("-o", "--output", type=Path, default=DEFAULT_OUTPUT)
    p.add_argument("--fd-output", type=Path, default=DEFAULT_FD_OUTPUT)
    p.add_argument("--fd-untagged-output", type=Path, default=DEFAULT_FD_UNTAGGED_OUTPUT)
    p.add_argument("--check", action="store_true",
                   help="do not write; exit 1 if an output file differs from the generator")
    args = p.parse_args(argv)
    stale = 0
    for path, fd, tags in ((args.output, False, False), (args.fd_output, True, True),
                           (args.fd_untagged_output, True, False)):
        text = render(fd, tags).encode("ascii")
        if not args.check:
            path.write_bytes(text)
        elif (path.read_bytes() if path.exists() else b"") != text:
            sys.stderr.write(f"{path} is stale: run python tools/gen_dbc.py\n")
            stale = 1
    return stale


if __name__ == "__main__":
    raise SystemExit(main())
