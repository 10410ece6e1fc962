"""The DBC and the firmware's frame codec: golden byte traces, SecOC layout, rejections.

Two kinds of frame (``FrameCodec.kind``, tools/gen_dbc.py); a DBC message of neither
(an E2E-only frame: CRC and rolling counter, no Mac) is refused on load:

* **secured** (every frame of the project's DBC: ER_Price, ER_Command, ER_Balance,
  AGENT_<i>_MC, AGENT_<i>_Setpoint, AGENT_<i>_Diag, PLANT_<i>_Status):
  bytes 0..2 = Mac, low nibble of byte 3 = Counter (the truncated freshness value),
  payload from bit 28; the codec leaves Mac = 0 on encode and does not check it on
  decode (NodeIO signs and verifies with the keys, firmware_py.secoc);
* **sync** (<name>_Sync at the secured frame's ID + 0x400): Mac 0|24, Count 24|24,
  Boot 48|16, no Counter.

The expected bytes below were written by hand from the layout in tools/gen_dbc.py
(Intel order) and cross-checked with cantools' ``Message.encode``.
"""

from __future__ import annotations

import math
import pickle
import re
import runpy
import shutil
import subprocess
import sys
import timeit
from pathlib import Path
from typing import Any

import can
import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dbc import DBC_PATH
from firmware_py import contract, frames
from firmware_py.contract import Command
from firmware_py.errors import (
    ConfigError,
    EncodeError,
    FrameError,
    FrameLengthError,
    RangeError,
    UnknownFrameError,
)
from firmware_py.frames import (
    LAMBDA_Q,
    N_AGENTS_MAX,
    PIN_OFF,
    PIN_ON,
    FrameCodec,
    agent_of,
    diag_name,
    mc_name,
    setpoint_name,
    status_name,
)
from firmware_py.runtime import AgentRuntime
from firmware_py.secoc import (
    FreshnessVerifier,
    authenticator,
    frame_mac,
    frame_payload,
    frame_verifies,
    sign_frame,
)

ROOT = Path(__file__).resolve().parent.parent
GEN_DBC = ROOT / "tools" / "gen_dbc.py"

SYNC_OFFSET = 0x400
SECURED_TYPES = frozenset({"ER_Price", "ER_Command", "MC", "Setpoint", "Status", "Diag",
                           "ER_Balance", "Totals"})
KINDS = ("secured", "sync")
# the transfer messages (no MAC; signed_price, AUTH-32): their golden frames are in
# tests/test_pricesig.py
TRANSFER_TYPES = frozenset({"ER_PriceSig"})


def frame(frame_id: int, data: bytes, **kw: Any) -> can.Message:
    return can.Message(arbitration_id=frame_id, is_extended_id=False, data=data, **kw)


def msg_type(name: str) -> str:
    """AGENT_7_MC -> MC, PLANT_1_Status_Sync -> Status_Sync, PLANT_Totals -> Totals,
    ER_Price -> ER_Price."""
    per_agent = re.fullmatch(r"(?:AGENT|PLANT)_[0-9]+_(.+)", name)
    return per_agent.group(1) if per_agent else name.removeprefix("PLANT_")


def expected_kind(name: str) -> str:
    """The kind of a message by its name, as the contract defines it (not read from the
    codec under test)."""
    if name.endswith("_Sync"):
        return "sync"
    if name in TRANSFER_TYPES:
        return "transfer"
    assert msg_type(name) in SECURED_TYPES, name
    return "secured"


def protection(kind: str, data: bytes, counter: int) -> dict[str, int]:
    """The raw protection signals a decode of ``data`` reports (Mac as cantools reads it:
    bytes 0..2 little-endian)."""
    mac = {"Mac": int.from_bytes(data[0:3], "little")}
    return {**mac, "Counter": counter} if kind == "secured" else mac


@pytest.fixture(scope="module")
def codec() -> FrameCodec:
    return FrameCodec()


# --------------------------------------------------------------------------- golden traces

# (message, counter, raw signals, expected 8 bytes (hex), physical checks)
# Secured frames: bytes 0..2 = Mac (0: the codec leaves it to NodeIO), byte 3 = Counter |
# the first payload nibble (bits 28..31) << 4. Sync frames: Mac 0, Count in bytes 3..5,
# Boot in bytes 6..7 (no Counter: pass 0).
GOLDEN = [
    # byte3 = 0x55: counter 5 | PriceValid<<4 | Segment 2<<5; Rho = round(0.8·2^24) =
    # 0x00CCCCCD in bytes 4..7
    ("ER_Price", 5, {"PriceValid": 1, "Segment": 2, "Rho": 13421773},
     "00 00 00 55 CD CC CC 00", {"Rho": 13421773 / 2**24, "Segment": 2}),
    # byte3 = 0x3F: counter 15 | SET_GAINS(3)<<4 | (agent 17: raw Target 16 = 0b010000 (DBC
    # offset 1): low bits 00)<<6; byte4 = (GainK 12345 = 0x3039: low nibble 9)<<4 | Target's
    # high bits 0b0100; byte5 = GainK bits 4..11 = 0x03; byte6 = GainK bits 12..13 (3) |
    # (GainH 2000 = 0x7D0: low 6 bits 0x10)<<2 = 0x43; byte7 = 2000 >> 6 = 0x1F
    ("ER_Command", 15, {"Command": 3, "Target": 16, "GainK": 12345, "GainH": 2000},
     "00 00 00 3F 94 03 43 1F", {"Target": 17, "GainK": 12.345, "GainH": 2.0}),
    # byte3 = 0xD0: counter 0 | RUNNING<<4 | Resets 3<<6; λ = -1.5 → int32 0xFE800000
    ("AGENT_3_MC", 0, {"State": 1, "Resets": 3, "Lambda": -25165824},
     "00 00 00 D0 00 00 80 FE", {"Lambda": -1.5, "Resets": 3}),
    # byte3 = 0x19: counter 9 | Enable<<4; -12.34 kW → -1234 = 0xFB2E in bytes 4..5
    ("AGENT_1_Setpoint", 9, {"Enable": 1, "PowerSetpoint": -1234},
     "00 00 00 19 2E FB 00 00", {"PowerSetpoint": -12.34}),
    # byte3 = 0xAC: counter 12 | (PowerLimited<<3 | FaultVoltage<<1)<<4; Power 50 kW →
    # 5000 = 0x1388 in bytes 4..5; Soc 75.5 % → 151 = 0x97 in byte 6
    ("PLANT_4_Status", 12, {"FaultOverCurrent": 0, "FaultVoltage": 1, "FaultSoc": 0,
                            "PowerLimited": 1, "Power": 5000, "Soc": 151},
     "00 00 00 AC 88 13 97 00", {"Power": 50.0, "Soc": 75.5}),
    # sync frames: Count 0x123456 → bytes 3..5 = 56 34 12; Boot 0x0102 → bytes 6..7 = 02 01
    ("ER_Price_Sync", 0, {"Count": 0x123456, "Boot": 0x0102},
     "00 00 00 56 34 12 02 01", {"Count": 0x123456, "Boot": 258}),
    # the first freshness value of a sender: boot 1, message counter 0
    ("ER_Command_Sync", 0, {"Count": 0, "Boot": 1},
     "00 00 00 00 00 00 01 00", {"Count": 0, "Boot": 1}),
    # every payload bit set
    ("AGENT_7_MC_Sync", 0, {"Count": 0xFFFFFF, "Boot": 0xFFFF},
     "00 00 00 FF FF FF FF FF", {"Count": 16777215, "Boot": 65535}),
    ("AGENT_32_Setpoint_Sync", 0, {"Count": 17, "Boot": 2},
     "00 00 00 11 00 00 02 00", {"Count": 17}),
    ("PLANT_1_Status_Sync", 0, {"Count": 0x0A0B0C, "Boot": 0x3000},
     "00 00 00 0C 0B 0A 00 30", {"Count": 0x0A0B0C, "Boot": 0x3000}),
    # diag pages: byte3 = counter | Page<<4; two 16-bit slots in bytes 4..5 and 6..7.
    # page 0: Resets 300 = 0x012C; DeadlineMisses 2
    ("AGENT_5_Diag", 1, {"Page": 0, "Resets": 300, "DeadlineMisses": 2},
     "00 00 00 01 2C 01 02 00", {"Resets": 300}),
    # page 1: NeighboursAlive 4 (byte 4), State SAFE (3) in bits 40..43; RejectedCrc saturated
    ("AGENT_5_Diag", 2, {"Page": 1, "NeighboursAlive": 4, "State": 3, "RejectedCrc": 65535},
     "00 00 00 12 04 03 FF FF", {"State": 3, "RejectedCrc": 65535}),
    # page 2: RejectedDlc 1; RejectedRange 0x1234
    ("AGENT_5_Diag", 3, {"Page": 2, "RejectedDlc": 1, "RejectedRange": 0x1234},
     "00 00 00 23 01 00 34 12", {"RejectedRange": 0x1234}),
    # page 3: RejectedUnknownId 10; RejectedImpersonation 0
    ("AGENT_5_Diag", 4, {"Page": 3, "RejectedUnknownId": 10, "RejectedImpersonation": 0},
     "00 00 00 34 0A 00 00 00", {"RejectedUnknownId": 10}),
    # page 4: RepeatedCounter 0x0201; LostFrames 7
    ("AGENT_5_Diag", 5, {"Page": 4, "RepeatedCounter": 513, "LostFrames": 7},
     "00 00 00 45 01 02 07 00", {"RepeatedCounter": 513}),
    # page 5: Saturations 0x0100; NeighbourTimeouts 0xFFFE
    ("AGENT_5_Diag", 6, {"Page": 5, "Saturations": 256, "NeighbourTimeouts": 65534},
     "00 00 00 56 00 01 FE FF", {"Saturations": 256}),
    # page 6: PriceTimeouts 1; StatusTimeouts 2
    ("AGENT_5_Diag", 7, {"Page": 6, "PriceTimeouts": 1, "StatusTimeouts": 2},
     "00 00 00 67 01 00 02 00", {"StatusTimeouts": 2}),
    # page 7: PlantFaults 0x0300; ForeignFrames saturated 0xFFFF
    ("AGENT_5_Diag", 8, {"Page": 7, "PlantFaults": 0x0300, "ForeignFrames": 65535},
     "00 00 00 78 00 03 FF FF", {"ForeignFrames": 65535}),
    # page 8: ForeignIds 0x10; InterleavedCounters 0x0102
    ("AGENT_5_Diag", 9, {"Page": 8, "ForeignIds": 16, "InterleavedCounters": 0x0102},
     "00 00 00 89 10 00 02 01", {"ForeignIds": 16}),
    # page 9: Untrusted 95; ImplausiblePrice 2
    ("AGENT_5_Diag", 10, {"Page": 9, "Untrusted": 95, "ImplausiblePrice": 2},
     "00 00 00 9A 5F 00 02 00", {"Untrusted": 95}),
    # page 10: ImplausibleLambda 0x0400; ImplausibleGains 1
    ("AGENT_5_Diag", 11, {"Page": 10, "ImplausibleLambda": 0x0400, "ImplausibleGains": 1},
     "00 00 00 AB 00 04 01 00", {"ImplausibleGains": 1}),
    # page 11: SafetySender 0x101 (11 bits at 32) | SafetyCause IMPLAUSIBLE_LAMBDA (3) << 11
    # = 0x1901 in bytes 4..5; RejectedAuth 3
    ("AGENT_5_Diag", 12, {"Page": 11, "SafetySender": 0x101, "SafetyCause": 3,
                          "RejectedAuth": 3},
     "00 00 00 BC 01 19 03 00", {"SafetySender": 257, "SafetyCause": 3, "RejectedAuth": 3}),
    # page 12: Unsynced 0x0100; Resyncs saturated 0xFFFF
    ("AGENT_5_Diag", 13, {"Page": 12, "Unsynced": 256, "Resyncs": 65535},
     "00 00 00 CD 00 01 FF FF", {"Unsynced": 256, "Resyncs": 65535}),
    ("AGENT_5_Diag_Sync", 0, {"Count": 0x000102, "Boot": 3},
     "00 00 00 02 01 00 03 00", {"Count": 258}),
    # balance page 0: byte3 = 0x06; GridPower -123.4 kW → 0xFB2E; CostRate 56.7 → 0x0237
    ("ER_Balance", 6, {"Page": 0, "GridPower": -1234, "CostRate": 567},
     "00 00 00 06 2E FB 37 02", {"GridPower": -123.4, "CostRate": 56.7}),
    # page 1: byte3 = 0x17; OptimalCostRate -0.1 → 0xFFFF
    ("ER_Balance", 7, {"Page": 1, "OptimalCostRate": -1},
     "00 00 00 17 FF FF 00 00", {"OptimalCostRate": -0.1}),
    ("ER_Balance_Sync", 0, {"Count": 7, "Boot": 1},
     "00 00 00 07 00 00 01 00", {"Count": 7}),
    # plant totals (18-bit signals): byte3 = 0x25 (counter 5, BatteryPower's low nibble);
    # BatteryPower 123.4 kW → 1234 at bit 28, BatteryCostRate -0.3 cu/h → 0x3FFFD at bit 46
    ("PLANT_Totals", 5, {"BatteryPower": 1234, "BatteryCostRate": -3},
     "00 00 00 25 4D 40 FF FF", {"BatteryPower": 123.4, "BatteryCostRate": -0.3}),
    # the extremes: BatteryPower -0.1 kW (all ones), BatteryCostRate 13107.1 cu/h (0x1FFFF)
    ("PLANT_Totals", 7, {"BatteryPower": -1, "BatteryCostRate": 131071},
     "00 00 00 F7 FF FF FF 7F", {"BatteryPower": -0.1, "BatteryCostRate": 13107.1}),
    ("PLANT_Totals_Sync", 0, {"Count": 3, "Boot": 2},
     "00 00 00 03 00 00 02 00", {"Count": 3}),
]


def test_golden_covers_every_message_type(codec: FrameCodec) -> None:
    types = {msg_type(name) for name, *_ in GOLDEN}
    assert types == SECURED_TYPES | {f"{t}_Sync" for t in SECURED_TYPES}
    assert {msg_type(m.name) for m in codec.database.messages} == types | TRANSFER_TYPES
    assert {expected_kind(name) for name, *_ in GOLDEN} == {"secured", "sync"}
    assert {raw["Page"] for name, _, raw, *_ in GOLDEN if name.endswith("_Diag")} == set(
        range(len(AgentRuntime.DIAG_PAGES)))


@pytest.mark.parametrize(("name", "counter", "raw", "hexdata", "phys"), GOLDEN,
                         ids=[f"{g[0]}-{g[1]}" for g in GOLDEN])
def test_golden_trace(codec: FrameCodec, name: str, counter: int, raw: dict[str, int],
                      hexdata: str, phys: dict[str, float]) -> None:
    expected = bytes.fromhex(hexdata)
    fid = codec.frame_id(name)
    kind = codec.kind(fid)
    assert kind == expected_kind(name)
    assert expected[0:3] == bytes(3), "golden Mac: the codec leaves it 0 for NodeIO"
    if kind == "secured":
        assert expected[3] & 0x0F == counter, "golden Counter nibble (byte 3)"
    else:
        assert counter == 0, "sync frames have no Counter"
    prot = protection(kind, expected, counter)

    msg = codec.encode(name, raw, counter)
    assert msg.arbitration_id == fid
    assert not msg.is_extended_id and not msg.is_fd and not msg.is_remote_frame
    assert msg.dlc == 8
    assert bytes(msg.data) == expected

    # cantools agrees on the layout (it computes no MAC: we pass the golden bytes)
    dbc_msg = codec.database.get_message_by_name(name)
    ct = dbc_msg.encode({**raw, **prot}, scaling=False)
    assert bytes(ct) == expected

    d = codec.decode(frame(fid, expected))
    assert (d.name, d.frame_id, d.counter) == (name, fid, counter)
    assert d.agent == agent_of(fid)
    assert d.raw == {**prot, **raw}
    for sig, value in phys.items():
        assert d.phys(sig) == pytest.approx(value, abs=1e-12)


@pytest.mark.parametrize("counter", [1, 7, 15])
def test_sync_frames_ignore_the_counter_argument(codec: FrameCodec, counter: int) -> None:
    """A sync frame has no Counter signal: its freshness is Boot ‖ Count."""
    for name, _, raw, hexdata, _ in GOLDEN:
        if expected_kind(name) == "sync":
            msg = codec.encode(name, raw, counter)
            assert bytes(msg.data) == bytes.fromhex(hexdata)
            assert "Counter" not in codec.decode(msg).raw
    with pytest.raises(EncodeError, match=r"ER_Price_Sync\.Counter.*0\.\.15.*16"):
        codec.encode("ER_Price_Sync", {"Count": 0, "Boot": 1}, 16)


def test_golden_lambda_and_rho_are_exact_q24(codec: FrameCodec) -> None:
    d = codec.decode(frame(0x103, bytes.fromhex("00 00 00 D0 00 00 80 FE")))
    assert d.phys("Lambda") == -1.5  # exact: the factor is a power of two
    assert d.label("State") == "RUNNING"
    assert d.label("Lambda") is None
    assert d.label("Resets") is None
    with pytest.raises(KeyError, match="Lamda"):
        d.phys("Lamda")
    p = codec.decode(frame(0x010, bytes.fromhex("00 00 00 55 CD CC CC 00")))
    assert p.phys("Rho") == 13421773 * 2.0**-24 == 0.800000011920929


def test_diag_page_carries_only_its_signals(codec: FrameCodec) -> None:
    d = codec.decode(frame(0x305, bytes.fromhex("00 00 00 12 04 03 FF FF")))
    assert set(d.raw) == {"Mac", "Counter", "Page", "NeighboursAlive", "State", "RejectedCrc"}
    assert d.agent == 5
    d12 = codec.decode(frame(0x305, bytes.fromhex("00 00 00 CD 00 01 FF FF")))
    assert set(d12.raw) == {"Mac", "Counter", "Page", "Unsynced", "Resyncs"}
    b1 = codec.decode(frame(0x3E0, bytes.fromhex("00 00 00 17 FF FF 00 00")))
    assert set(b1.raw) == {"Mac", "Counter", "Page", "OptimalCostRate"}


def test_encode_phys_matches_raw_encoding(codec: FrameCodec) -> None:
    phys = codec.encode_phys("PLANT_4_Status", {
        "FaultOverCurrent": 0, "FaultVoltage": 1, "FaultSoc": 0, "PowerLimited": 1,
        "Power": 50.0, "Soc": 75.5}, 12)
    assert bytes(phys.data) == bytes.fromhex("00 00 00 AC 88 13 97 00")
    cmd = codec.encode_phys("ER_Command", {"Command": "SET_GAINS", "Target": 17,
                                           "GainK": 12.345, "GainH": 2.0}, 15)
    assert bytes(cmd.data) == bytes.fromhex("00 00 00 3F 94 03 43 1F")
    sync = codec.encode_phys("ER_Price_Sync", {"Count": 0x123456, "Boot": 0x0102}, 0)
    assert bytes(sync.data) == bytes.fromhex("00 00 00 56 34 12 02 01")
    diag = codec.encode_phys("AGENT_5_Diag", {"Page": 12, "Unsynced": 256, "Resyncs": 65535},
                             13)
    assert bytes(diag.data) == bytes.fromhex("00 00 00 CD 00 01 FF FF")  # Mac: NodeIO's
    mc = codec.encode_phys("AGENT_2_MC", {"State": "RUNNING", "Lambda": 0.8, "Resets": 0}, 1)
    assert bytes(mc.data[0:3]) == bytes(3) and mc.data[3] == 0x11
    assert codec.decode(mc).raw["Lambda"] == round(0.8 * 2**24)
    with pytest.raises(EncodeError, match=r"PLANT_1_Status.*Soc.*100"):
        codec.encode_phys("PLANT_1_Status", {
            "FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
            "Power": 0.0, "Soc": 100.5}, 0)
    with pytest.raises(EncodeError, match="Enabel"):
        codec.encode_phys("AGENT_1_Setpoint", {"Enabel": 1, "PowerSetpoint": 0.0}, 0)
    with pytest.raises(EncodeError, match="not in this frame Current, Voltage"):
        codec.encode_phys("PLANT_1_Status", {
            "FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
            "Power": 0.0, "Soc": 50.0, "Current": 0.0, "Voltage": 400.0}, 0)
    with pytest.raises(EncodeError, match=r"ER_Price_Sync.*Boot"):
        codec.encode_phys("ER_Price_Sync", {"Count": 0, "Boot": 0}, 0)


# --------------------------------------------------------------------------- ID plan


def test_names_ids_and_agent_of(codec: FrameCodec) -> None:
    assert N_AGENTS_MAX == 64
    assert codec.frame_id("ER_Price") == 0x010
    assert codec.frame_id("ER_Command") == 0x020
    assert codec.frame_id("ER_Balance") == 0x3E0
    assert codec.frame_id("ER_Balance_Sync") == 0x7E0
    assert codec.frame_id("ER_Price_Sync") == 0x410
    assert codec.frame_id("ER_Command_Sync") == 0x420
    assert frames.AGENT_BASES == (0x100, 0x200, 0x280, 0x300, 0x500, 0x600, 0x680, 0x700)
    for i in (1, 17, 32, 33, 64):
        assert codec.frame_id(mc_name(i)) == 0x100 + i
        assert codec.frame_id(setpoint_name(i)) == 0x200 + i
        assert codec.frame_id(status_name(i)) == 0x280 + i
        assert codec.frame_id(diag_name(i)) == 0x300 + i
        assert codec.frame_id(mc_name(i) + "_Sync") == 0x500 + i
        assert codec.frame_id(setpoint_name(i) + "_Sync") == 0x600 + i
        assert codec.frame_id(status_name(i) + "_Sync") == 0x680 + i
        assert codec.frame_id(diag_name(i) + "_Sync") == 0x700 + i
        for base in (0x100, 0x200, 0x280, 0x300, 0x500, 0x600, 0x680, 0x700):
            assert agent_of(base + i) == i
    for fid in (0x010, 0x020, 0x3E0, 0x3E1, 0x410, 0x420, 0x100, 0x141, 0x2C1, 0x341, 0x500, 0x541,
                0x600, 0x641, 0x680, 0x6C1, 0x700, 0x741, 0x7E0, 0x7FF):
        assert agent_of(fid) is None
    # 3 ER frames, PLANT_Totals, 4 per agent, and a sync of each (every frame is secured);
    # and the one transfer message, ER_PriceSig (signed_price, no MAC, no sync)
    assert len(codec.frame_ids()) == 2 * (4 + 4 * 64) + 1 == 521
    assert len(codec.database.messages) == 521
    assert codec.name_of(0x120) == "AGENT_32_MC"
    assert codec.name_of(0x520) == "AGENT_32_MC_Sync"
    assert codec.name_of(0x6A0) == "PLANT_32_Status_Sync"
    assert codec.name_of(0x140) == "AGENT_64_MC"
    assert codec.name_of(0x740) == "AGENT_64_Diag_Sync"
    for bad in (0, 65, -1, True, 1.0):
        with pytest.raises(EncodeError, match="agent index"):
            mc_name(bad)  # type: ignore[arg-type]
    with pytest.raises(EncodeError, match="AGENT_65_MC"):
        codec.frame_id("AGENT_65_MC")
    with pytest.raises(EncodeError, match="AGENT_1_MC_Sync_Sync"):
        codec.frame_id("AGENT_1_MC_Sync_Sync")  # a sync has no sync


def test_frame_kinds(codec: FrameCodec) -> None:
    """Every ID's kind as the contract names it, and every secured frame's sync."""
    by_kind: dict[str, set[int]] = {k: set() for k in (*KINDS, "transfer")}
    for fid in codec.frame_ids():
        assert codec.kind(fid) == expected_kind(codec.name_of(fid))
        by_kind[codec.kind(fid)].add(fid)
    agents = range(1, N_AGENTS_MAX + 1)
    secured = {0x010, 0x020, 0x3E0, 0x3E1} | {b + i for b in (0x100, 0x200, 0x280, 0x300)
                                       for i in agents}
    assert by_kind["secured"] == secured == contract.SECURED_IDS
    assert by_kind["sync"] == {fid + SYNC_OFFSET for fid in secured}
    assert by_kind["transfer"] == {0x008}  # ER_PriceSig
    assert contract.SYNC_OF == {fid: fid + SYNC_OFFSET for fid in secured}
    assert contract.SYNCED_BY == {fid + SYNC_OFFSET: fid for fid in secured}
    for fid in secured:
        assert codec.name_of(fid + SYNC_OFFSET) == codec.name_of(fid) + "_Sync"
    assert (contract.MAC_BITS, contract.FV_TX_BITS) == (24, 4)
    assert (contract.FV_COUNT_BITS, contract.FV_BOOT_BITS) == (24, 16)
    with pytest.raises(UnknownFrameError, match="0x541.*unknown ID") as e:
        codec.kind(0x541)
    assert e.value.cause == "unknown_id"


# --------------------------------------------------------------------------- receive rejections


def valid_mc(codec: FrameCodec, counter: int = 3) -> can.Message:
    """A secured frame (Mac left 0 by the codec)."""
    return codec.encode(mc_name(2), {"State": 1, "Lambda": 1 << 24, "Resets": 0}, counter)


def valid_diag(codec: FrameCodec, counter: int = 3) -> can.Message:
    """A secured multiplexed frame (Mac left 0 by the codec)."""
    return codec.encode(diag_name(2), {"Page": 2, "RejectedDlc": 2, "RejectedRange": 3},
                        counter)


def valid_balance(codec: FrameCodec, counter: int = 3) -> can.Message:
    return codec.encode("ER_Balance", {"Page": 0, "GridPower": -5, "CostRate": 100}, counter)


def valid_sync(codec: FrameCodec) -> can.Message:
    return codec.encode(mc_name(2) + "_Sync", {"Count": 5, "Boot": 1}, 0)


VALID: dict[str, Any] = {"mc": valid_mc, "diag": valid_diag, "balance": valid_balance,
                         "sync": valid_sync}


def test_the_project_dbc_has_no_e2e_frame_left(codec: FrameCodec) -> None:
    """Every frame that reports or accounts is authenticated: no CRC-only frame (the one
    transfer message, ER_PriceSig, is authenticated by the signature it carries)."""
    assert {codec.kind(fid) for fid in codec.frame_ids()} == {"secured", "sync", "transfer"}


def test_codec_refuses_a_dbc_with_an_e2e_only_frame(tmp_path: Path) -> None:
    """A message without Mac (an E2E-only frame: CRC 0|8, Counter 8|4) is neither secured
    nor sync: the codec has no such path and refuses the DBC on load."""
    from cantools.database.can import Message as DbcMessage
    from cantools.database.can import Signal
    db = cantools.database.load_file(DBC_PATH, strict=True)
    assert isinstance(db, cantools.database.can.Database)
    db.messages.append(DbcMessage(0x7FF, "TEST_E2E", 8, [
        Signal("CRC", 0, 8, byte_order="little_endian"),
        Signal("Counter", 8, 4, byte_order="little_endian"),
        Signal("Value", 16, 16, byte_order="little_endian")], senders=["ER"], strict=True))
    path = tmp_path / "e2e.dbc"
    cantools.database.dump_file(db, str(path))
    with pytest.raises(ConfigError, match=r"\[TEST_E2E\] expected the secured frame signal "
                                          r"Mac 0\|24, but got nothing"):
        FrameCodec(path)


@pytest.mark.parametrize("which", ["mc", "diag", "balance", "sync"])
@pytest.mark.parametrize("length", [0, 1, 5, 7])
def test_wrong_dlc(codec: FrameCodec, length: int, which: str) -> None:
    msg = VALID[which](codec)
    with pytest.raises(FrameLengthError, match=f"expected DLC 8, but got {length}") as e:
        codec.decode(frame(msg.arbitration_id, bytes(msg.data[:length])))
    assert e.value.cause == "dlc"


@pytest.mark.parametrize("fid", [0x000, 0x141, 0x2C1, 0x401, 0x430, 0x500, 0x541, 0x600,
                                 0x6C1, 0x700, 0x7FF])
def test_unknown_id(codec: FrameCodec, fid: int) -> None:
    with pytest.raises(UnknownFrameError, match=f"0x{fid:03X}.*unknown ID") as e:
        codec.decode(frame(fid, bytes(8)))
    assert e.value.cause == "unknown_id"


def test_extended_id_is_unknown(codec: FrameCodec) -> None:
    msg = valid_mc(codec)
    ext = can.Message(arbitration_id=0x102, is_extended_id=True, data=msg.data)
    with pytest.raises(UnknownFrameError, match="extended"):
        codec.decode(ext)


@pytest.mark.parametrize("kind", ["remote", "error", "fd"])
def test_malformed_kinds(codec: FrameCodec, kind: str) -> None:
    if kind == "remote":
        msg = can.Message(arbitration_id=0x102, is_extended_id=False, is_remote_frame=True, dlc=8)
    elif kind == "error":
        msg = can.Message(arbitration_id=0x102, is_extended_id=False, is_error_frame=True,
                          data=bytes(8))
    else:
        msg = can.Message(arbitration_id=0x102, is_extended_id=False, is_fd=True,
                          data=valid_mc(codec).data)
    with pytest.raises(FrameError) as e:
        codec.decode(msg)
    assert type(e.value) is FrameError and e.value.cause == "malformed"


@pytest.mark.parametrize(("gain_k", "gain_h"), [(0, 0), (3, 0), (16383, 0), (1, 1), (2, 5)])
def test_a_pin_with_another_gain_is_out_of_range(codec: FrameCodec, gain_k: int,
                                                 gain_h: int) -> None:
    """CMD-7: Command 0 (PIN) takes GainK 1 (pin) or 2 (unpin) and GainH 0; anything else
    is out of range at decode, as Command 0 was before PIN existed."""
    for ok in (PIN_ON, PIN_OFF):
        d = codec.decode(codec.encode("ER_Command", {"Command": int(Command.PIN), "Target": 1,
                                                     "GainK": ok, "GainH": 0}, 0))
        assert d.raw["GainK"] == ok
    msg = codec.encode("ER_Command", {"Command": int(Command.PIN), "Target": 1,
                                      "GainK": gain_k, "GainH": gain_h}, 0)
    with pytest.raises(RangeError, match=r"ER_Command\.GainK: expected 1 \(pin\) or 2") as e:
        codec.decode(msg)
    assert e.value.cause == "range"


def test_every_raw_target_is_an_agent(codec: FrameCodec) -> None:
    """CMD-1: ER_Command.Target's 6 bits address agents 1..64 as raw 0..63 (the DBC's
    offset 1), the same for the codec and cantools; no Target is out of range."""
    db = codec.database.get_message_by_name("ER_Command")
    assert frames.TARGET_OFFSET == 1
    for raw in range(64):
        msg = codec.encode("ER_Command", {"Command": 1, "Target": raw, "GainK": 0,
                                          "GainH": 0}, 0)
        d = codec.decode(msg)
        assert frames.target_agent(d.raw["Target"]) == raw + 1 == d.phys("Target")
        assert db.decode(bytes(msg.data))["Target"] == raw + 1
        assert frames.target_raw(raw + 1) == raw


# All 8 bytes; secured and sync frames carry an arbitrary Mac: the codec does not check it.
@pytest.mark.parametrize(("fid", "hexdata", "signal", "got"), [
    (0x281, "AB CD EF 00 00 00 C9 00", "Soc", 201),          # Soc raw 201 > 200 (100 %)
    (0x281, "00 00 00 00 00 00 FF 00", "Soc", 255),
    (0x410, "12 34 56 01 00 00 00 00", "Boot", 0),           # ER_Price_Sync boot 0
    (0x6A0, "00 00 00 FF FF FF 00 00", "Boot", 0),           # PLANT_32_Status_Sync boot 0
    (0x305, "00 00 00 D0 00 00 00 00", "Page", 13),          # diag page 13 does not exist
    (0x305, "00 00 00 F0 00 00 00 00", "Page", 15),
    (0x305, "00 00 00 10 00 0C 00 00", "State", 12),         # diag page 1 State 12
    (0x305, "00 00 00 B0 00 30 00 00", "SafetyCause", 6),    # diag page 11 cause 6
    (0x3E0, "00 00 00 20 00 00 00 00", "Page", 2),           # balance has pages 0, 1
])
def test_out_of_range_raw_value(codec: FrameCodec, fid: int, hexdata: str, signal: str,
                                got: int) -> None:
    data = bytes.fromhex(hexdata)
    with pytest.raises(RangeError, match=rf"\.{signal}: expected a raw value in .*but got {got}"
                       ) as e:
        codec.decode(frame(fid, data))
    assert e.value.cause == "range"


def test_rejection_order_id_dlc_range(codec: FrameCodec) -> None:
    """Unknown ID before DLC before range (the Mac is NodeIO's, after the codec)."""
    command_0 = bytes.fromhex("FF FF FF 40 00 00 00 00")  # a PIN with GainK 0 (CMD-7)
    with pytest.raises(RangeError, match="ER_Command.GainK"):
        codec.decode(frame(0x020, command_0))
    with pytest.raises(FrameLengthError):
        codec.decode(frame(0x020, command_0[:7]))
    with pytest.raises(UnknownFrameError):
        codec.decode(frame(0x541, command_0[:7]))


# --------------------------------------------------------------------------- Counter


@pytest.mark.parametrize("which", ["mc", "diag"])
def test_codec_counter_sequence_round_trips(codec: FrameCodec, which: str) -> None:
    """The Counter nibble (the freshness value's low bits): byte 3 of a secured frame."""
    for n in range(40):
        msg = VALID[which](codec, n % 16)
        assert msg.data[3] & 0x0F == n % 16
        d = codec.decode(msg)
        assert d.counter == d.raw["Counter"] == n % 16


# --------------------------------------------------------------------------- encode errors


def test_encode_errors_name_message_signal_range_and_value(codec: FrameCodec) -> None:
    good: dict[str, Any] = {"State": 1, "Lambda": 0, "Resets": 0}
    with pytest.raises(EncodeError, match=r"AGENT_1_MC\.State: expected a raw integer in 0\.\.3, "
                                          r"but got 9"):
        codec.encode("AGENT_1_MC", {**good, "State": 9}, 0)
    with pytest.raises(EncodeError, match=r"AGENT_1_MC\.Resets: expected a raw integer in "
                                          r"0\.\.3, but got 4"):  # mod 4 is the caller's
        codec.encode("AGENT_1_MC", {**good, "Resets": 4}, 0)
    with pytest.raises(EncodeError, match=r"AGENT_1_MC\.Lambda: .*-2147483648\.\.2147483647.*"
                                          r"2147483648"):
        codec.encode("AGENT_1_MC", {**good, "Lambda": 2**31}, 0)
    with pytest.raises(EncodeError, match=r"Lambda.*but got 0\.5"):
        codec.encode("AGENT_1_MC", {**good, "Lambda": 0.5}, 0)  # type: ignore[dict-item]  # raw: int
    with pytest.raises(EncodeError, match=r"missing Lambda; not in this frame Lamda"):
        codec.encode("AGENT_1_MC", {**{k: v for k, v in good.items() if k != "Lambda"},
                                    "Lamda": 0}, 0)
    with pytest.raises(EncodeError, match="not in this frame Counter"):
        codec.encode("AGENT_1_MC", {**good, "Counter": 3}, 0)
    with pytest.raises(EncodeError, match="not in this frame Mac"):
        codec.encode("AGENT_1_MC", {**good, "Mac": 0}, 0)  # NodeIO signs
    with pytest.raises(EncodeError, match="not in this frame NeighboursAlive, PriceOk"):
        codec.encode("AGENT_1_MC", {**good, "NeighboursAlive": 1, "PriceOk": 1}, 0)
    with pytest.raises(EncodeError, match=r"Counter: expected an int in 0\.\.15, but got 16"):
        codec.encode("AGENT_1_MC", good, 16)
    with pytest.raises(EncodeError, match="Soc"):
        codec.encode("PLANT_1_Status", {"FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0,
                                        "PowerLimited": 0, "Power": 0, "Soc": 201}, 0)
    with pytest.raises(EncodeError, match=r"ER_Command\.Target: .*0\.\.63, but got 64"):
        codec.encode("ER_Command", {"Command": 1, "Target": 64, "GainK": 0, "GainH": 0}, 0)
    with pytest.raises(EncodeError, match=r"ER_Price_Sync\.Boot: .*1\.\.65535, but got 0"):
        codec.encode("ER_Price_Sync", {"Count": 0, "Boot": 0}, 0)
    with pytest.raises(EncodeError, match=r"ER_Price_Sync\.Count: .*0\.\.16777215, "
                                          r"but got 16777216"):
        codec.encode("ER_Price_Sync", {"Count": 1 << 24, "Boot": 1}, 0)
    with pytest.raises(EncodeError, match="not in this frame Counter"):
        codec.encode("ER_Price_Sync", {"Count": 0, "Boot": 1, "Counter": 0}, 0)
    with pytest.raises(EncodeError, match="not in this frame CRC"):
        codec.encode("ER_Balance", {"Page": 0, "GridPower": 0, "CostRate": 0, "CRC": 0}, 0)
    with pytest.raises(EncodeError, match=r"not in this frame Mac\]"):
        codec.encode("ER_Balance", {"Page": 0, "GridPower": 0, "CostRate": 0, "Mac": 0}, 0)
    with pytest.raises(EncodeError, match="not in this frame OptimalCostRate"):
        codec.encode("ER_Balance", {"Page": 0, "GridPower": 0, "CostRate": 0,
                                    "OptimalCostRate": 0}, 0)
    with pytest.raises(EncodeError, match=r"AGENT_1_Diag\.Page"):
        codec.encode("AGENT_1_Diag", {"Page": 13}, 0)
    with pytest.raises(EncodeError, match="missing RejectedRange"):
        codec.encode("AGENT_1_Diag", {"Page": 2, "RejectedDlc": 0}, 0)
    with pytest.raises(EncodeError, match="not in this frame Resets"):
        codec.encode("AGENT_1_Diag", {"Page": 2, "RejectedDlc": 0, "RejectedRange": 0,
                                      "Resets": 1}, 0)
    with pytest.raises(EncodeError, match="Diag16"):
        codec.encode("AGENT_1_Diag16", {}, 0)
    assert issubclass(EncodeError, ValueError)


# --------------------------------------------------------------------------- properties

MC_RAW = st.fixed_dictionaries({
    "State": st.integers(0, 3),
    "Lambda": st.integers(-(2**31), 2**31 - 1),
    "Resets": st.integers(0, 3),
})


@settings(max_examples=300)
@given(st.integers(1, N_AGENTS_MAX), MC_RAW, st.integers(0, 15))
def test_mc_round_trip(agent: int, raw: dict[str, int], counter: int) -> None:
    codec = FrameCodec()
    name = mc_name(agent)
    msg = codec.encode(name, raw, counter)
    data = bytes(msg.data)
    assert data[0:3] == bytes(3)  # Mac: NodeIO's
    assert data[3] & 0x0F == counter
    d = codec.decode(msg)
    assert d.name == name and d.agent == agent and d.counter == counter
    assert {k: v for k, v in d.raw.items() if k not in ("Mac", "Counter")} == raw
    assert d.phys("Lambda") == raw["Lambda"] / 2**LAMBDA_Q
    # cantools reads the same bytes the same way
    dbc_msg = codec.database.get_message_by_name(name)
    assert dbc_msg.decode(data, scaling=False, decode_choices=False) == d.raw


def draw_raw(draw: st.DrawFn, codec: FrameCodec, msg: Any) -> dict[str, int]:
    """Raw values inside the DBC ranges for every signal the codec's caller supplies."""
    signals = [s for s in msg.signals if s.name not in ("Counter", "Mac")]
    raw: dict[str, int] = {}
    mux = [s for s in signals if s.is_multiplexer]
    if mux:
        pages = sorted({p for s in signals for p in (s.multiplexer_ids or ())})
        raw[mux[0].name] = draw(st.sampled_from(pages))
    for s in signals:
        if s.is_multiplexer or (s.multiplexer_ids and raw["Page"] not in s.multiplexer_ids):
            continue
        lo, hi = codec.raw_range(msg.name, s.name)
        raw[s.name] = draw(st.integers(lo, hi))
    if msg.name == "ER_Command" and raw["Command"] == Command.PIN:  # CMD-7: GainK says which
        raw["GainK"], raw["GainH"] = draw(st.sampled_from((PIN_ON, PIN_OFF))), 0
    return raw


def messages_of_kind(codec: FrameCodec, *kinds: str) -> list[Any]:
    return [m for m in codec.database.messages if expected_kind(m.name) in kinds]


@st.composite
def any_frame(draw: st.DrawFn, kind: str) -> tuple[str, dict[str, int], int]:
    codec = FrameCodec()
    msg = draw(st.sampled_from(messages_of_kind(codec, kind)))
    return msg.name, draw_raw(draw, codec, msg), draw(st.integers(0, 15))


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=300)
@given(data=st.data())
def test_every_frame_matches_cantools_layout(kind: str, data: st.DataObject) -> None:
    codec = FrameCodec()
    name, raw, counter = data.draw(any_frame(kind))
    msg = codec.encode(name, raw, counter)
    fid = msg.arbitration_id
    assert codec.kind(fid) == kind
    wire = bytes(msg.data)
    assert wire[0:3] == bytes(3)  # Mac: NodeIO's
    if kind == "sync":
        counter = 0  # no Counter: the argument is ignored
    prot = protection(kind, wire, counter)
    dbc_msg = codec.database.get_message_by_name(name)
    ct = dbc_msg.encode({**raw, **prot}, scaling=False)
    assert bytes(ct) == wire
    d = codec.decode(msg)
    assert d.raw == {**prot, **raw}
    assert d.counter == counter
    assert dbc_msg.decode(wire, scaling=False, decode_choices=False) == d.raw


# --------------------------------------------------------------------------- SecOC framing

KEY = bytes(range(16))
OTHER_KEY = bytes(range(1, 17))


def received_fv(kind: str, frame_id: int, data: bytes | bytearray, last: int) -> int | None:
    """The freshness value a receiver verifies a (possibly corrupted) frame with, as
    NodeIO does: a sync carries it (Boot ‖ Count); a secured frame's is rebuilt from the
    Counter nibble and the last value accepted from that sender (None: out of the layout,
    rejected too)."""
    if kind == "sync":
        x = int.from_bytes(data, "little")
        return (x >> 48) << contract.FV_COUNT_BITS | (x >> 24) & 0xFFFFFF
    verifier = FreshnessVerifier(tx_bits=contract.FV_TX_BITS, initial={frame_id: last})
    return verifier.candidate(frame_id, data[3] & 0x0F)


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(GOLDEN), st.integers(0, (1 << 24) - 1))
def test_codec_leaves_the_mac_to_nodeio(case: tuple[Any, ...], mac: int) -> None:
    """Secured and sync frames: encode leaves Mac = 0, decode accepts any Mac bytes (the
    MAC is checked by NodeIO with the sender's key, after the codec)."""
    codec = FrameCodec()
    name, counter, raw, hexdata, _ = case
    golden = bytes.fromhex(hexdata)
    assert bytes(codec.encode(name, raw, counter).data[0:3]) == bytes(3)
    data = mac.to_bytes(3, "little") + golden[3:]
    d = codec.decode(frame(codec.frame_id(name), data))
    assert d.raw["Mac"] == mac  # the Intel value: bytes 0..2 read little-endian
    assert frame_mac(data) == int.from_bytes(data[0:3], "big")  # what NodeIO compares
    assert "CRC" not in d.raw
    assert d.raw == {**protection(codec.kind(d.frame_id), data, counter), **raw}


@st.composite
def signed_case(draw: st.DrawFn) -> tuple[str, dict[str, int], int, int]:
    """A secured or sync frame's raw values and the full freshness value it is sent with
    (boot ≥ 1: a sender bumps its boot counter before its first frame)."""
    codec = FrameCodec()
    msg = draw(st.sampled_from(messages_of_kind(codec, "secured", "sync")))
    raw = draw_raw(draw, codec, msg)
    boot = draw(st.integers(1, (1 << contract.FV_BOOT_BITS) - 1))
    count = draw(st.integers(0, (1 << contract.FV_COUNT_BITS) - 1))
    if expected_kind(msg.name) == "sync":
        raw.update(Count=count, Boot=boot)
    return msg.name, raw, boot, count


@settings(max_examples=300, deadline=None, derandomize=True)  # a 2^-24 fluke stays out of CI
@given(signed_case(), st.binary(min_size=16, max_size=16), st.integers(0, 63))
def test_signed_frame_verifies_and_any_single_bit_flip_fails(
        case: tuple[str, dict[str, int], int, int], key: bytes, bit: int) -> None:
    """A frame signed with sign_frame verifies; flipping any one of its 64 bits makes it
    fail under the freshness value a receiver derives from the flipped frame.

    Bytes 0..2 (the MAC itself), the high nibble of byte 3 and bytes 4..7 (the payload)
    fail even under the sender's own freshness value. Bits 24..27 are not in the MAC's
    payload (frame_payload zeroes them): they are the truncated freshness value (or the
    low bits of a sync's Count), authenticated through the freshness value the receiver
    rebuilds from them, which a flip changes.
    """
    codec = FrameCodec()
    name, raw, boot, count = case
    fid = codec.frame_id(name)
    kind = codec.kind(fid)
    fv = boot << contract.FV_COUNT_BITS | count
    msg = codec.encode(name, raw, count % (1 << contract.FV_TX_BITS) if kind == "secured" else 0)
    data = bytearray(msg.data)
    assert data[0:3] == bytes(3)
    sign_frame(key, fid, data, fv)
    assert frame_mac(data) == authenticator(key, fid, frame_payload(data), fv, contract.MAC_BITS)
    assert frame_payload(data) == bytes([data[3] & 0xF0]) + bytes(data[4:8])
    assert frame_verifies(key, fid, data, fv)
    assert received_fv(kind, fid, data, fv - 1) == fv
    d = codec.decode(frame(fid, bytes(data)))  # the codec passes any Mac
    assert d.raw["Mac"] == int.from_bytes(data[0:3], "little")

    flipped = bytearray(data)
    flipped[bit // 8] ^= 1 << (bit % 8)
    fv_rx = received_fv(kind, fid, flipped, fv - 1)
    # the Counter nibble, and every bit of a sync's Count and Boot, move the received FV
    assert (fv_rx != fv) == (24 <= bit < 28 or (kind == "sync" and bit >= 24))
    assert fv_rx is None or not frame_verifies(key, fid, flipped, fv_rx)
    if 24 <= bit < 28:
        assert frame_payload(flipped) == frame_payload(data)
        assert frame_verifies(key, fid, flipped, fv)  # only the freshness value covers it
    else:
        assert not frame_verifies(key, fid, flipped, fv)


def test_mac_binds_data_id_key_and_freshness(codec: FrameCodec) -> None:
    """A signed MC frame replayed under another agent's ID still decodes (no CRC), but
    its MAC fails; so do another key, another freshness value and its sync's ID."""
    fv = 1 << contract.FV_COUNT_BITS | 3
    data = bytearray(valid_mc(codec, 3).data)
    sign_frame(KEY, 0x102, data, fv)
    assert frame_verifies(KEY, 0x102, data, fv)
    assert codec.decode(frame(0x103, bytes(data))).name == "AGENT_3_MC"
    assert not frame_verifies(KEY, 0x103, data, fv)
    assert not frame_verifies(KEY, 0x102 + SYNC_OFFSET, data, fv)
    assert not frame_verifies(OTHER_KEY, 0x102, data, fv)
    assert not frame_verifies(KEY, 0x102, data, fv + 16)  # same nibble, next window
    sync = bytearray(valid_sync(codec).data)
    sync_fv = 1 << contract.FV_COUNT_BITS | 5
    sign_frame(KEY, 0x502, sync, sync_fv)
    assert frame_verifies(KEY, 0x502, sync, sync_fv)
    assert not frame_verifies(KEY, 0x102, sync, sync_fv)


# --------------------------------------------------------------------------- the DBC itself

# Every signal's start|length per message type, the contract the firmware relies on.
LAYOUTS = {
    "ER_Price": {"Mac": (0, 24), "Counter": (24, 4), "PriceValid": (28, 1), "Segment": (29, 3),
                 "Rho": (32, 32)},
    "ER_Command": {"Mac": (0, 24), "Counter": (24, 4), "Command": (28, 2), "Target": (30, 6),
                   "GainK": (36, 14), "GainH": (50, 14)},
    "MC": {"Mac": (0, 24), "Counter": (24, 4), "State": (28, 2), "Resets": (30, 2),
           "Lambda": (32, 32)},
    "Setpoint": {"Mac": (0, 24), "Counter": (24, 4), "Enable": (28, 1),
                 "PowerSetpoint": (32, 16)},
    "Status": {"Mac": (0, 24), "Counter": (24, 4), "FaultOverCurrent": (28, 1),
               "FaultVoltage": (29, 1), "FaultSoc": (30, 1), "PowerLimited": (31, 1),
               "Power": (32, 16), "Soc": (48, 8)},
    "ER_Balance": {"Mac": (0, 24), "Counter": (24, 4), "Page": (28, 4), "GridPower": (32, 16),
                   "CostRate": (48, 16), "OptimalCostRate": (32, 16)},
    **{f"{t}_Sync": {"Mac": (0, 24), "Count": (24, 24), "Boot": (48, 16)}
       for t in SECURED_TYPES},
}


def test_dbc_loads_strict_with_the_contract() -> None:
    db = cantools.database.load_file(DBC_PATH, strict=True)
    assert isinstance(db, cantools.database.can.Database)
    assert {n.name for n in db.nodes} == {"ER", "PLANT", *(f"AGENT_{i}" for i in range(1, 65))}
    assert db.buses[0].baudrate == 500_000
    assert db.dbc is not None and db.dbc.attributes["BusType"].value == "CAN"
    assert len(db.messages) == 521
    cycles = {"ER_Price": 50, "ER_Command": None, "AGENT_7_MC": 10, "AGENT_7_Setpoint": 50,
              "PLANT_7_Status": 50, "AGENT_7_Diag": 100, "ER_Balance": 100,
              "ER_Price_Sync": 1000, "ER_Command_Sync": 1000, "AGENT_7_MC_Sync": 1000,
              "AGENT_7_Setpoint_Sync": 1000, "PLANT_7_Status_Sync": 1000,
              "AGENT_7_Diag_Sync": 1000, "ER_Balance_Sync": 1000}
    for name, cycle in cycles.items():
        assert db.get_message_by_name(name).cycle_time == cycle
    assert db.get_message_by_name("ER_Command").send_type == "Event"
    by_name = {m.name: m for m in db.messages}
    for m in db.messages:
        assert m.length == 8 and not m.is_extended_frame and m.frame_id <= 0x7FF
        assert m.comment
        for s in m.signals:
            assert s.byte_order == "little_endian" and s.comment
        layout = {s.name: (s.start, s.length) for s in m.signals}
        kind = expected_kind(m.name)
        if msg_type(m.name) in LAYOUTS:
            assert layout == LAYOUTS[msg_type(m.name)], m.name
        if kind == "secured":
            assert (layout["Mac"], layout["Counter"]) == ((0, 24), (24, 4))
            assert "CRC" not in layout
            payload = [start for n, (start, _) in layout.items() if n not in ("Mac", "Counter")]
            assert min(payload) == 28
            sync = by_name[m.name + "_Sync"]
            assert sync.frame_id == m.frame_id + SYNC_OFFSET
            assert sync.senders == m.senders
            receivers = {r for s in m.signals for r in s.receivers}
            assert {r for s in sync.signals for r in s.receivers} == receivers
        elif kind == "transfer":  # ER_PriceSig: Page 0..10, no Mac, Counter or sync
            assert layout["Page"] == (0, 4) and "Mac" not in layout and "Counter" not in layout
            assert m.name + "_Sync" not in by_name and m.send_type == "Event"
        else:
            assert set(layout) == {"Mac", "Count", "Boot"}
            assert expected_kind(m.name.removesuffix("_Sync")) == "secured"
            assert by_name[m.name.removesuffix("_Sync")].frame_id == m.frame_id - SYNC_OFFSET
            boot = m.get_signal_by_name("Boot")
            assert (boot.minimum, boot.maximum) == (1, 65535)
    for name, sig in [("ER_Price", "Rho"), ("AGENT_32_MC", "Lambda")]:
        s = db.get_message_by_name(name).get_signal_by_name(sig)
        assert s.scale == 2.0**-24 == 5.9604644775390625e-08
        assert (s.start, s.length, s.is_signed) == (32, 32, True)
        assert s.minimum == -(2**31) * 2.0**-24 and s.maximum == (2**31 - 1) * 2.0**-24
    state = db.get_message_by_name("AGENT_1_MC").get_signal_by_name("State")
    assert state.choices is not None
    assert dict(state.choices) == {0: "INIT", 1: "RUNNING", 2: "ISOLATED", 3: "SAFE"}
    command = db.get_message_by_name("ER_Command").get_signal_by_name("Command")
    assert command.choices is not None
    assert dict(command.choices) == {0: "PIN", 1: "ISOLATE", 2: "RECONNECT", 3: "SET_GAINS"}
    target = db.get_message_by_name("ER_Command").get_signal_by_name("Target")
    assert (target.minimum, target.maximum, target.offset) == (1, 64, 1)
    diag = db.get_message_by_name("AGENT_1_Diag")
    assert diag.is_multiplexed()
    page = diag.get_signal_by_name("Page")
    assert (page.start, page.length, page.minimum, page.maximum) == (28, 4, 0, 12)
    for name in ("Unsynced", "Resyncs"):
        assert diag.get_signal_by_name(name).multiplexer_ids == [12]
    assert "saturat" in str(diag.get_signal_by_name("LostFrames").comment)
    # two 16-bit slots per page; the small signals share one
    for s in diag.signals:
        if s.multiplexer_ids:
            slot = 32 if s.start < 48 else 48
            assert s.start + s.length <= slot + 16, s.name
    balance = db.get_message_by_name("ER_Balance")
    assert balance.frame_id == 0x3E0 and by_name["ER_Balance_Sync"].frame_id == 0x7E0
    assert {s.name: s.multiplexer_ids for s in balance.signals if s.multiplexer_ids} == {
        "GridPower": [0], "CostRate": [0], "OptimalCostRate": [1]}
    soc = db.get_message_by_name("PLANT_1_Status").get_signal_by_name("Soc")
    assert (soc.scale, soc.maximum) == (0.5, 100)


def test_committed_dbc_is_up_to_date_with_generator() -> None:
    gen = runpy.run_path(str(GEN_DBC))  # run_name is not __main__: nothing is written
    assert DBC_PATH.read_bytes() == gen["render"]().encode("ascii"), \
        "dbc/bess_ded.dbc is stale: run python tools/gen_dbc.py"


def test_codec_refuses_a_dbc_with_another_lambda_factor(tmp_path: Path) -> None:
    text = DBC_PATH.read_text(encoding="ascii")
    old = "SG_ Lambda : 32|32@1- (5.960464477539063e-08,0)"
    assert old in text
    bad = tmp_path / "bad.dbc"
    bad.write_text(text.replace(old, "SG_ Lambda : 32|32@1- (1e-06,0)", 1), encoding="ascii")
    with pytest.raises(ValueError, match=r"Lambda.*2\*\*-24"):
        FrameCodec(bad)


@pytest.mark.parametrize(("old", "new", "match"), [
    # ER_Price's Counter (the first secured frame in the file)
    ("SG_ Counter : 24|4@1+ (1,0) [0|15]", "SG_ Counter : 24|3@1+ (1,0) [0|7]",
     r"\[ER_Price\] expected the secured frame signal Counter 24\|4, but got 24\|3"),
    # the first report frame's Counter (PLANT_Totals: receiver ER)
    ('SG_ Counter : 24|4@1+ (1,0) [0|15] ""  ER', 'SG_ Counter : 24|3@1+ (1,0) [0|7] ""  ER',
     r"\[PLANT_Totals\] expected the secured frame signal Counter 24\|4, but got 24\|3"),
    # the first sync frame's Mac (sync receivers are listed sorted: AGENT_1,AGENT_10,...)
    ('SG_ Mac : 0|24@1+ (1,0) [0|16777215] ""  AGENT_1,AGENT_10,',
     'SG_ Mac : 0|16@1+ (1,0) [0|65535] ""  AGENT_1,AGENT_10,',
     r"_Sync\] expected the sync frame signal Mac 0\|24, but got 0\|16"),
])
def test_codec_refuses_a_dbc_whose_protection_layout_moved(
        tmp_path: Path, old: str, new: str, match: str) -> None:
    text = DBC_PATH.read_text(encoding="ascii")
    assert old in text
    bad = tmp_path / "bad.dbc"
    bad.write_text(text.replace(old, new, 1), encoding="ascii")
    with pytest.raises(ConfigError, match=match):
        FrameCodec(bad)


def test_generate_c_source_accepts_the_dbc(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "cantools", "generate_c_source", str(DBC_PATH),
                        "-o", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    c_file, h_file = tmp_path / "bess_ded.c", tmp_path / "bess_ded.h"
    header = h_file.read_text()
    assert c_file.exists() and "BESS_DED_AGENT_32_MC_FRAME_ID (0x120u)" in header
    assert "BESS_DED_AGENT_32_MC_SYNC_FRAME_ID (0x520u)" in header
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler to build the generated code")
    r = subprocess.run([cc, "-std=c99", "-Wall", "-c", str(c_file), "-o",
                        str(tmp_path / "bess_ded.o")], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr


def test_cantools_decode_cli_reads_a_candump_log(codec: FrameCodec, tmp_path: Path) -> None:
    log = tmp_path / "run.log"
    logger = can.Logger(str(log))
    try:
        for i, (name, counter, raw, _hex, _phys) in enumerate(GOLDEN):
            msg = codec.encode(name, raw, counter)
            msg.timestamp = 1000.0 + i * 0.01
            msg.channel = "vcan0"
            logger(msg)
    finally:
        logger.stop()
    text = log.read_text().replace(" ", "")
    assert "103#000000D0000080FE" in text
    assert "410#0000005634120201" in text
    r = subprocess.run([sys.executable, "-m", "cantools", "decode", str(DBC_PATH)],
                       input=log.read_text(), capture_output=True, text=True, timeout=120,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr
    for name, *_ in GOLDEN:
        assert name in r.stdout
    assert "RUNNING" in r.stdout and "SET_GAINS" in r.stdout


# --------------------------------------------------------------------------- speed


@pytest.mark.parametrize("which", ["mc", "diag"])
def test_codec_is_fast_enough_for_the_receive_loop(codec: FrameCodec, which: str) -> None:
    """Guard against falling back to a generic per-frame path (tens of µs), for a secured
    frame and a multiplexed one."""
    msg = VALID[which](codec, 1)
    n = 2000
    dec = min(timeit.repeat(lambda: codec.decode(msg), number=n, repeat=3)) / n
    enc = min(timeit.repeat(lambda: VALID[which](codec, 1), number=n, repeat=3)) / n
    assert dec < 100e-6 and enc < 100e-6, f"decode {dec * 1e6:.1f} µs, encode {enc * 1e6:.1f} µs"
    assert math.isfinite(dec)


def test_compiled_dbc_is_cached_and_a_corrupt_cache_compiles_afresh(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled DBC is pickled under $XDG_CACHE_HOME/bess-ded (node start-up); a
    cache file that does not unpickle is ignored and rewritten, never trusted."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    path = str(DBC_PATH.resolve())
    frames._compile.cache_clear()
    try:
        fresh = frames._compile(path, 0)
        (cache,) = (tmp_path / "bess-ded").iterdir()
        assert pickle.loads(cache.read_bytes()).by_name == fresh.by_name
        frames._compile.cache_clear()
        assert frames._compile(path, 0).by_name == fresh.by_name  # from the cache
        cache.write_bytes(b"not a pickle")
        frames._compile.cache_clear()
        assert frames._compile(path, 0).by_name == fresh.by_name
        assert pickle.loads(cache.read_bytes()).by_name == fresh.by_name  # rewritten
    finally:
        frames._compile.cache_clear()
