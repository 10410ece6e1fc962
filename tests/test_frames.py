"""The DBC and the firmware's frame codec: golden byte traces, E2E checks, rejections.

The expected bytes below were written by hand from the layout in tools/gen_dbc.py
(Intel order, byte 0 = CRC, low nibble of byte 1 = counter); the CRC bytes come
from the bitwise reference CRC in this file, not from the codec under test.
"""

from __future__ import annotations

import math
import pickle
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
from crccheck.crc import Crc8SaeJ1850
from hypothesis import given, settings
from hypothesis import strategies as st

from dbc import DBC_PATH
from firmware_py import frames
from firmware_py.errors import (
    CrcError,
    EncodeError,
    FrameError,
    FrameLengthError,
    RangeError,
    UnknownFrameError,
)
from firmware_py.frames import (
    LAMBDA_Q,
    N_AGENTS_MAX,
    CounterTracker,
    FrameCodec,
    agent_of,
    diag_name,
    e2e_crc,
    mc_name,
    setpoint_name,
    status_name,
)
from firmware_py.runtime import AgentRuntime

ROOT = Path(__file__).resolve().parent.parent
GEN_DBC = ROOT / "tools" / "gen_dbc.py"


def ref_crc8_j1850(data: bytes) -> int:
    """Bitwise CRC-8 SAE J1850 (poly 0x1D, init 0xFF, xorout 0xFF): the test's own oracle."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def ref_frame_crc(frame_id: int, payload_1_7: bytes) -> int:
    return ref_crc8_j1850(frame_id.to_bytes(2, "little") + payload_1_7)


def with_crc(frame_id: int, payload_1_7: bytes) -> bytes:
    assert len(payload_1_7) == 7
    return bytes([ref_frame_crc(frame_id, payload_1_7)]) + payload_1_7


def frame(frame_id: int, data: bytes, **kw: Any) -> can.Message:
    return can.Message(arbitration_id=frame_id, is_extended_id=False, data=data, **kw)


@pytest.fixture(scope="module")
def codec() -> FrameCodec:
    return FrameCodec()


# --------------------------------------------------------------------------- CRC


def test_crc_check_value() -> None:
    assert ref_crc8_j1850(b"123456789") == 0x4B
    assert Crc8SaeJ1850.calc(b"123456789") == 0x4B


@given(st.integers(0, 0x7FF), st.binary(min_size=8, max_size=8))
def test_e2e_crc_matches_crccheck_and_reference(frame_id: int, data: bytes) -> None:
    expected = Crc8SaeJ1850.calc(frame_id.to_bytes(2, "little") + data[1:])
    assert e2e_crc(frame_id, data) == expected == ref_frame_crc(frame_id, data[1:])


# --------------------------------------------------------------------------- golden traces

# (message, counter, raw signals, expected 8 bytes (hex, CRC first), physical checks)
GOLDEN = [
    # byte1 = 0x15: counter 5 | PriceValid<<4; Rho = round(0.8·2^24) = 0x00CCCCCD; Segment 2
    ("ER_Price", 5, {"PriceValid": 1, "Rho": 13421773, "Segment": 2},
     "C3 15 CD CC CC 00 02 00", {"Rho": 13421773 / 2**24, "Segment": 2}),
    # byte1 = 0x3F: counter 15 | SET_GAINS(3)<<4; Target 2; GainK 1000 = 0x03E8; GainH 0x07D0
    ("ER_Command", 15, {"Command": 3, "Target": 2, "GainK": 1000, "GainH": 2000},
     "B7 3F 02 E8 03 D0 07 00", {"GainK": 1.0, "GainH": 2.0}),
    # byte1 = 0x10: counter 0 | RUNNING<<4; λ = -1.5 → int32 0xFE800000; Resets 7;
    # byte7 = PriceOk<<6 | NeighboursAlive 3 = 0x43
    ("AGENT_3_MC", 0, {"State": 1, "Lambda": -25165824, "Resets": 7, "NeighboursAlive": 3,
                       "PriceOk": 1},
     "4C 10 00 00 80 FE 07 43", {"Lambda": -1.5}),
    # byte1 = 0x19: counter 9 | Enable<<4; -12.34 kW → -1234 = 0xFB2E
    ("AGENT_1_Setpoint", 9, {"Enable": 1, "PowerSetpoint": -1234},
     "60 19 2E FB 00 00 00 00", {"PowerSetpoint": -12.34}),
    # byte1 = 0xAC: counter 12 | (PowerLimited<<3 | FaultVoltage<<1)<<4; Power 50 kW = 0x1388;
    # Current -20.5 A → -41 → 12-bit 0xFD7, Voltage 400 V → 1600 = 0x640: bits 32..55 = 0x640FD7;
    # Soc 75.5 % → 151 = 0x97
    ("PLANT_4_Status", 12, {"FaultOverCurrent": 0, "FaultVoltage": 1, "FaultSoc": 0,
                            "PowerLimited": 1, "Power": 5000, "Current": -41, "Voltage": 1600,
                            "Soc": 151},
     "C8 AC 88 13 D7 0F 64 97",
     {"Power": 50.0, "Current": -20.5, "Voltage": 400.0, "Soc": 75.5}),
    # diag page 0: byte1 = 0x01; Resets 300 = 0x012C; DeadlineMisses 2; NeighboursAlive 4;
    # State SAFE (3) in bits 56..59
    ("AGENT_5_Diag", 1, {"Page": 0, "Resets": 300, "DeadlineMisses": 2, "NeighboursAlive": 4,
                         "State": 3},
     "4C 01 2C 01 02 00 04 03", {"Resets": 300, "State": 3}),
    # page 1: byte1 = 0x12; RejectedCrc saturated 0xFFFF; RejectedDlc 1; RejectedRange 0x1234
    ("AGENT_5_Diag", 2, {"Page": 1, "RejectedCrc": 65535, "RejectedDlc": 1,
                         "RejectedRange": 0x1234},
     "12 12 FF FF 01 00 34 12", {"RejectedCrc": 65535}),
    # page 2: byte1 = 0x23; RejectedUnknownId 10; RejectedImpersonation 0; RepeatedCounter 0x0201
    ("AGENT_5_Diag", 3, {"Page": 2, "RejectedUnknownId": 10, "RejectedImpersonation": 0,
                         "RepeatedCounter": 513},
     "09 23 0A 00 00 00 01 02", {"RepeatedCounter": 513}),
    # page 3: byte1 = 0x34; LostFrames 7; Saturations 0x0100; NeighbourTimeouts 0xFFFE
    ("AGENT_5_Diag", 4, {"Page": 3, "LostFrames": 7, "Saturations": 256,
                         "NeighbourTimeouts": 65534},
     "47 34 07 00 00 01 FE FF", {"Saturations": 256}),
    # page 4: byte1 = 0x45; PriceTimeouts 1; StatusTimeouts 2; PlantFaults 0x0300
    ("AGENT_5_Diag", 5, {"Page": 4, "PriceTimeouts": 1, "StatusTimeouts": 2,
                         "PlantFaults": 0x0300},
     "DD 45 01 00 02 00 00 03", {"StatusTimeouts": 2}),
    # page 5: byte1 = 0x56; ForeignFrames saturated 0xFFFF; ForeignIds 0x10; Interleaved 0x0102
    ("AGENT_5_Diag", 6, {"Page": 5, "ForeignFrames": 65535, "ForeignIds": 16,
                         "InterleavedCounters": 0x0102},
     "83 56 FF FF 10 00 02 01", {"ForeignFrames": 65535}),
    # page 6: byte1 = 0x67; Untrusted 95; ImplausiblePrice 2; ImplausibleLambda 0x0400
    ("AGENT_5_Diag", 7, {"Page": 6, "Untrusted": 95, "ImplausiblePrice": 2,
                         "ImplausibleLambda": 0x0400},
     "9C 67 5F 00 02 00 00 04", {"Untrusted": 95}),
    # page 7: byte1 = 0x78; ImplausibleGains 1; SafetySender 0x101 (11 bits at 32);
    # SafetyCause IMPLAUSIBLE_LAMBDA (3) in bits 48..51
    ("AGENT_5_Diag", 8, {"Page": 7, "ImplausibleGains": 1, "SafetySender": 0x101,
                         "SafetyCause": 3},
     "2B 78 01 00 01 01 03 00", {"SafetySender": 257, "SafetyCause": 3}),
    # byte1 = 0x06; GridPower -123.4 kW → 0xFB2E; CostRate 56.7 → 0x0237; Optimal -0.1 → 0xFFFF
    ("ER_Balance", 6, {"GridPower": -1234, "CostRate": 567, "OptimalCostRate": -1},
     "22 06 2E FB 37 02 FF FF",
     {"GridPower": -123.4, "CostRate": 56.7, "OptimalCostRate": -0.1}),
]


def test_golden_covers_every_message_type(codec: FrameCodec) -> None:
    kinds = {name.split("_", 2)[-1] if name.startswith(("AGENT_", "PLANT_")) else name
             for name, *_ in GOLDEN}
    assert kinds == {"ER_Price", "ER_Command", "MC", "Setpoint", "Status", "Diag", "ER_Balance"}
    db_kinds = {m.name.split("_", 2)[-1] if m.name.startswith(("AGENT_", "PLANT_")) else m.name
                for m in codec.database.messages}
    assert db_kinds == kinds
    assert {raw["Page"] for name, _, raw, *_ in GOLDEN if name.endswith("_Diag")} == set(
        range(len(AgentRuntime.DIAG_PAGES)))


@pytest.mark.parametrize(("name", "counter", "raw", "hexdata", "phys"), GOLDEN,
                         ids=[f"{g[0]}-{g[1]}" for g in GOLDEN])
def test_golden_trace(codec: FrameCodec, name: str, counter: int, raw: dict[str, int],
                      hexdata: str, phys: dict[str, float]) -> None:
    expected = bytes.fromhex(hexdata)
    fid = codec.frame_id(name)
    assert expected[0] == ref_frame_crc(fid, expected[1:]), "golden CRC byte"

    msg = codec.encode(name, raw, counter)
    assert msg.arbitration_id == fid
    assert not msg.is_extended_id and not msg.is_fd and not msg.is_remote_frame
    assert msg.dlc == 8
    assert bytes(msg.data) == expected

    # cantools agrees on the layout (it does not know the CRC: we pass the golden byte)
    dbc_msg = codec.database.get_message_by_name(name)
    ct = dbc_msg.encode({**raw, "CRC": expected[0], "Counter": counter}, scaling=False)
    assert bytes(ct) == expected

    d = codec.decode(frame(fid, expected))
    assert (d.name, d.frame_id, d.counter) == (name, fid, counter)
    assert d.agent == agent_of(fid)
    assert d.raw == {"CRC": expected[0], "Counter": counter, **raw}
    for sig, value in phys.items():
        assert d.phys(sig) == pytest.approx(value, abs=1e-12)


def test_golden_lambda_is_exact_q24(codec: FrameCodec) -> None:
    d = codec.decode(frame(0x103, bytes.fromhex("4C 10 00 00 80 FE 07 43")))
    assert d.phys("Lambda") == -1.5  # exact: the factor is a power of two
    assert d.label("State") == "RUNNING"
    assert d.label("Lambda") is None
    with pytest.raises(KeyError, match="Lamda"):
        d.phys("Lamda")


def test_diag_page_carries_only_its_signals(codec: FrameCodec) -> None:
    d = codec.decode(frame(0x305, bytes.fromhex("12 12 FF FF 01 00 34 12")))
    assert set(d.raw) == {"CRC", "Counter", "Page", "RejectedCrc", "RejectedDlc",
                          "RejectedRange"}
    assert d.agent == 5


def test_encode_phys_matches_raw_encoding(codec: FrameCodec) -> None:
    phys = codec.encode_phys("PLANT_4_Status", {
        "FaultOverCurrent": 0, "FaultVoltage": 1, "FaultSoc": 0, "PowerLimited": 1,
        "Power": 50.0, "Current": -20.5, "Voltage": 400.0, "Soc": 75.5}, 12)
    assert bytes(phys.data) == bytes.fromhex("C8 AC 88 13 D7 0F 64 97")
    mc = codec.encode_phys("AGENT_2_MC", {"State": "RUNNING", "Lambda": 0.8, "Resets": 0,
                                          "NeighboursAlive": 1, "PriceOk": 1}, 1)
    assert codec.decode(mc).raw["Lambda"] == round(0.8 * 2**24)
    with pytest.raises(EncodeError, match=r"PLANT_1_Status.*Soc.*100"):
        codec.encode_phys("PLANT_1_Status", {
            "FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
            "Power": 0.0, "Current": 0.0, "Voltage": 400.0, "Soc": 100.5}, 0)
    with pytest.raises(EncodeError, match="Enabel"):
        codec.encode_phys("AGENT_1_Setpoint", {"Enabel": 1, "PowerSetpoint": 0.0}, 0)


# --------------------------------------------------------------------------- ID plan


def test_names_ids_and_agent_of(codec: FrameCodec) -> None:
    assert N_AGENTS_MAX == 32
    assert codec.frame_id("ER_Price") == 0x010
    assert codec.frame_id("ER_Command") == 0x020
    assert codec.frame_id("ER_Balance") == 0x400
    for i in (1, 17, 32):
        assert codec.frame_id(mc_name(i)) == 0x100 + i
        assert codec.frame_id(setpoint_name(i)) == 0x200 + i
        assert codec.frame_id(status_name(i)) == 0x280 + i
        assert codec.frame_id(diag_name(i)) == 0x300 + i
        for base in (0x100, 0x200, 0x280, 0x300):
            assert agent_of(base + i) == i
    for fid in (0x010, 0x020, 0x400, 0x100, 0x121, 0x2A1, 0x321, 0x7FF):
        assert agent_of(fid) is None
    assert len(codec.frame_ids()) == 3 + 4 * 32
    assert codec.name_of(0x120) == "AGENT_32_MC"
    for bad in (0, 33, -1, True, 1.0):
        with pytest.raises(EncodeError, match="agent index"):
            mc_name(bad)  # type: ignore[arg-type]
    with pytest.raises(EncodeError, match="AGENT_33_MC"):
        codec.frame_id("AGENT_33_MC")


# --------------------------------------------------------------------------- receive rejections


def valid_mc(codec: FrameCodec, counter: int = 3) -> can.Message:
    return codec.encode(mc_name(2), {"State": 1, "Lambda": 1 << 24, "Resets": 0,
                                     "NeighboursAlive": 1, "PriceOk": 1}, counter)


@given(st.integers(0, 63))
def test_any_single_bit_error_fails_the_crc(bit: int) -> None:
    codec = FrameCodec()
    msg = valid_mc(codec)
    msg.data[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(CrcError) as e:
        codec.decode(msg)
    assert e.value.cause == "crc"
    assert "expected CRC 0x" in str(e.value) and "but got 0x" in str(e.value)


def test_frame_under_another_id_fails_the_crc(codec: FrameCodec) -> None:
    """The data ID is in the CRC: agent 2's payload replayed as agent 3's is rejected."""
    msg = valid_mc(codec)
    with pytest.raises(CrcError, match="AGENT_3_MC"):
        codec.decode(frame(0x103, bytes(msg.data)))


@pytest.mark.parametrize("length", [0, 1, 5, 7])
def test_wrong_dlc(codec: FrameCodec, length: int) -> None:
    msg = valid_mc(codec)
    with pytest.raises(FrameLengthError, match=f"expected DLC 8, but got {length}") as e:
        codec.decode(frame(msg.arbitration_id, bytes(msg.data[:length])))
    assert e.value.cause == "dlc"


@pytest.mark.parametrize("fid", [0x000, 0x121, 0x2A1, 0x500, 0x7FF])
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


@pytest.mark.parametrize(("fid", "payload", "signal", "got"), [
    (0x102, "90 00 00 00 01 00 01", "State", 9),            # AGENT_2_MC State 9
    (0x281, "00 00 00 00 00 00 C9", "Soc", 201),             # Soc raw 201 > 200 (100 %)
    (0x281, "00 00 00 00 00 00 FF", "Soc", 255),
    (0x020, "00 01 00 00 00 00 00", "Command", 0),           # no command 0
    (0x020, "10 21 00 00 00 00 00", "Target", 33),           # no agent 33
    (0x305, "80 00 00 00 00 00 00", "Page", 8),              # diag page 8 does not exist
    (0x305, "00 00 00 00 00 00 0C", "State", 12),            # diag page 0 State 12
])
def test_out_of_range_raw_value(codec: FrameCodec, fid: int, payload: str, signal: str,
                                got: int) -> None:
    data = with_crc(fid, bytes.fromhex(payload))
    with pytest.raises(RangeError, match=rf"\.{signal}: expected a raw value in .*but got {got}"
                       ) as e:
        codec.decode(frame(fid, data))
    assert e.value.cause == "range"


def test_rejection_order_dlc_before_crc_before_range(codec: FrameCodec) -> None:
    bad_range_bad_crc = bytes.fromhex("00 90 00 00 00 01 00 01")
    with pytest.raises(CrcError):
        codec.decode(frame(0x102, bad_range_bad_crc))
    with pytest.raises(FrameLengthError):
        codec.decode(frame(0x102, bad_range_bad_crc[:7]))


# --------------------------------------------------------------------------- E2E counter


def test_counter_first_frame_then_in_sequence() -> None:
    t = CounterTracker()
    assert t.last is None
    s = t.update(7)
    assert (s.new_data, s.lost) == (True, 0)
    s = t.update(8)
    assert (s.new_data, s.lost) == (True, 0)
    assert t.last == 8


def test_counter_repeated_is_no_new_data() -> None:
    t = CounterTracker()
    t.update(4)
    s = t.update(4)
    assert (s.new_data, s.lost) == (False, 0)
    assert t.update(5).lost == 0  # the repeat did not move the reference


def test_counter_skips_are_counted_as_lost() -> None:
    t = CounterTracker()
    t.update(2)
    assert t.update(5).lost == 2
    assert t.update(4).lost == 14  # (4 - 5 - 1) mod 16: a step back reads as 14 lost
    t.reset()
    assert t.update(11).lost == 0


def test_counter_wrap_15_to_0_is_not_a_loss() -> None:
    t = CounterTracker()
    t.update(15)
    s = t.update(0)
    assert (s.new_data, s.lost) == (True, 0)
    t.update(14)
    assert t.update(1).lost == 2  # 14 → (15, 0 lost) → 1


@given(st.integers(0, 15), st.lists(st.integers(1, 15), max_size=40))
def test_counter_loss_accounting(start: int, steps: list[int]) -> None:
    t = CounterTracker()
    t.update(start)
    c, lost = start, 0
    for step in steps:
        c = (c + step) % 16
        lost += t.update(c).lost
    assert lost == sum(steps) - len(steps)


def test_counter_rejects_values_outside_4_bits() -> None:
    with pytest.raises(ValueError):
        CounterTracker().update(16)


def test_codec_counter_sequence_round_trips(codec: FrameCodec) -> None:
    t = CounterTracker()
    for n in range(40):
        d = codec.decode(valid_mc(codec, n % 16))
        assert d.counter == n % 16
        assert t.update(d.counter).lost == 0


# --------------------------------------------------------------------------- encode errors


def test_encode_errors_name_message_signal_range_and_value(codec: FrameCodec) -> None:
    good: dict[str, Any] = {"State": 1, "Lambda": 0, "Resets": 0, "NeighboursAlive": 0,
                            "PriceOk": 0}
    with pytest.raises(EncodeError, match=r"AGENT_1_MC\.State: expected a raw integer in 0\.\.3, "
                                          r"but got 9"):
        codec.encode("AGENT_1_MC", {**good, "State": 9}, 0)
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
    with pytest.raises(EncodeError, match=r"Counter: expected an int in 0\.\.15, but got 16"):
        codec.encode("AGENT_1_MC", good, 16)
    with pytest.raises(EncodeError, match="Soc"):
        codec.encode("PLANT_1_Status", {"FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0,
                                        "PowerLimited": 0, "Power": 0, "Current": 0,
                                        "Voltage": 0, "Soc": 201}, 0)
    with pytest.raises(EncodeError, match=r"AGENT_1_Diag\.Page"):
        codec.encode("AGENT_1_Diag", {"Page": 8}, 0)
    with pytest.raises(EncodeError, match="missing RejectedDlc, RejectedRange"):
        codec.encode("AGENT_1_Diag", {"Page": 1, "RejectedCrc": 0}, 0)
    with pytest.raises(EncodeError, match="not in this frame Resets"):
        codec.encode("AGENT_1_Diag", {"Page": 1, "RejectedCrc": 0, "RejectedDlc": 0,
                                      "RejectedRange": 0, "Resets": 1}, 0)
    with pytest.raises(EncodeError, match="Diag16"):
        codec.encode("AGENT_1_Diag16", {}, 0)
    assert issubclass(EncodeError, ValueError)


# --------------------------------------------------------------------------- properties

MC_RAW = st.fixed_dictionaries({
    "State": st.integers(0, 3),
    "Lambda": st.integers(-(2**31), 2**31 - 1),
    "Resets": st.integers(0, 255),
    "NeighboursAlive": st.integers(0, 63),
    "PriceOk": st.integers(0, 1),
})


@settings(max_examples=300)
@given(st.integers(1, N_AGENTS_MAX), MC_RAW, st.integers(0, 15))
def test_mc_round_trip(agent: int, raw: dict[str, int], counter: int) -> None:
    codec = FrameCodec()
    name = mc_name(agent)
    msg = codec.encode(name, raw, counter)
    data = bytes(msg.data)
    assert data[0] == ref_frame_crc(0x100 + agent, data[1:])
    d = codec.decode(msg)
    assert d.name == name and d.agent == agent and d.counter == counter
    assert {k: v for k, v in d.raw.items() if k not in ("CRC", "Counter")} == raw
    assert d.phys("Lambda") == raw["Lambda"] / 2**LAMBDA_Q
    # cantools reads the same bytes the same way
    dbc_msg = codec.database.get_message_by_name(name)
    assert dbc_msg.decode(data, scaling=False, decode_choices=False) == d.raw


@st.composite
def any_frame(draw: st.DrawFn) -> tuple[str, dict[str, int], int]:
    codec = FrameCodec()
    msg = draw(st.sampled_from(codec.database.messages))
    signals = [s for s in msg.signals if s.name not in ("CRC", "Counter")]
    raw: dict[str, int] = {}
    mux = [s for s in signals if s.is_multiplexer]
    if mux:
        raw["Page"] = draw(st.integers(0, 3))
    for s in signals:
        if s.is_multiplexer or (s.multiplexer_ids and raw["Page"] not in s.multiplexer_ids):
            continue
        lo, hi = codec.raw_range(msg.name, s.name)
        raw[s.name] = draw(st.integers(lo, hi))
    return msg.name, raw, draw(st.integers(0, 15))


@settings(max_examples=300)
@given(any_frame())
def test_every_frame_matches_cantools_layout(case: tuple[str, dict[str, int], int]) -> None:
    codec = FrameCodec()
    name, raw, counter = case
    msg = codec.encode(name, raw, counter)
    dbc_msg = codec.database.get_message_by_name(name)
    ct = dbc_msg.encode({**raw, "CRC": msg.data[0], "Counter": counter}, scaling=False)
    assert bytes(ct) == bytes(msg.data)
    assert codec.decode(msg).raw == {"CRC": msg.data[0], "Counter": counter, **raw}


# --------------------------------------------------------------------------- the DBC itself


def test_dbc_loads_strict_with_the_contract() -> None:
    db = cantools.database.load_file(DBC_PATH, strict=True)
    assert isinstance(db, cantools.database.can.Database)
    assert {n.name for n in db.nodes} == {"ER", "PLANT", *(f"AGENT_{i}" for i in range(1, 33))}
    assert db.buses[0].baudrate == 500_000
    assert db.dbc is not None and db.dbc.attributes["BusType"].value == "CAN"
    cycles = {"ER_Price": 50, "ER_Command": None, "AGENT_7_MC": 10, "AGENT_7_Setpoint": 50,
              "PLANT_7_Status": 50, "AGENT_7_Diag": 100, "ER_Balance": 100}
    for name, cycle in cycles.items():
        assert db.get_message_by_name(name).cycle_time == cycle
    assert db.get_message_by_name("ER_Command").send_type == "Event"
    for m in db.messages:
        assert m.length == 8 and not m.is_extended_frame and m.frame_id <= 0x7FF
        assert m.comment
        crc, ctr = m.get_signal_by_name("CRC"), m.get_signal_by_name("Counter")
        assert (crc.start, crc.length, ctr.start, ctr.length) == (0, 8, 8, 4)
        for s in m.signals:
            assert s.byte_order == "little_endian" and s.comment
    for name, sig in [("ER_Price", "Rho"), ("AGENT_32_MC", "Lambda")]:
        s = db.get_message_by_name(name).get_signal_by_name(sig)
        assert s.scale == 2.0**-24 == 5.9604644775390625e-08
        assert (s.length, s.is_signed) == (32, True)
        assert s.minimum == -(2**31) * 2.0**-24 and s.maximum == (2**31 - 1) * 2.0**-24
    state = db.get_message_by_name("AGENT_1_MC").get_signal_by_name("State")
    assert state.choices is not None
    assert dict(state.choices) == {0: "INIT", 1: "RUNNING", 2: "ISOLATED", 3: "SAFE"}
    command = db.get_message_by_name("ER_Command").get_signal_by_name("Command")
    assert command.choices is not None
    assert dict(command.choices) == {1: "ISOLATE", 2: "RECONNECT", 3: "SET_GAINS"}
    diag = db.get_message_by_name("AGENT_1_Diag")
    assert diag.is_multiplexed()
    assert "saturat" in str(diag.get_signal_by_name("LostFrames").comment)
    soc = db.get_message_by_name("PLANT_1_Status").get_signal_by_name("Soc")
    assert (soc.scale, soc.maximum) == (0.5, 100)


def test_committed_dbc_is_up_to_date_with_generator() -> None:
    gen = runpy.run_path(str(GEN_DBC))  # run_name is not __main__: nothing is written
    assert DBC_PATH.read_bytes() == gen["render"]().encode("ascii"), \
        "dbc/bess_ded.dbc is stale: run python tools/gen_dbc.py"


def test_codec_refuses_a_dbc_with_another_lambda_factor(tmp_path: Path) -> None:
    text = DBC_PATH.read_text(encoding="ascii")
    old = "SG_ Lambda : 16|32@1- (5.960464477539063e-08,0)"
    assert old in text
    bad = tmp_path / "bad.dbc"
    bad.write_text(text.replace(old, "SG_ Lambda : 16|32@1- (1e-06,0)", 1), encoding="ascii")
    with pytest.raises(ValueError, match=r"Lambda.*2\*\*-24"):
        FrameCodec(bad)


def test_generate_c_source_accepts_the_dbc(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "cantools", "generate_c_source", str(DBC_PATH),
                        "-o", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    c_file, h_file = tmp_path / "bess_ded.c", tmp_path / "bess_ded.h"
    assert c_file.exists() and "BESS_DED_AGENT_32_MC_FRAME_ID (0x120u)" in h_file.read_text()
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
    text = log.read_text()
    assert "103#4C10000080FE0743" in text.replace(" ", "")
    r = subprocess.run([sys.executable, "-m", "cantools", "decode", str(DBC_PATH)],
                       input=text, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    for name in ("ER_Price", "ER_Command", "AGENT_3_MC", "AGENT_1_Setpoint", "PLANT_4_Status",
                 "AGENT_5_Diag", "ER_Balance"):
        assert name in r.stdout
    assert "RUNNING" in r.stdout and "SET_GAINS" in r.stdout


# --------------------------------------------------------------------------- speed


def test_codec_is_fast_enough_for_the_receive_loop(codec: FrameCodec) -> None:
    """Guard against falling back to a generic per-frame path (tens of µs)."""
    raw = {"State": 1, "Lambda": 123456, "Resets": 3, "NeighboursAlive": 2, "PriceOk": 1}
    msg = codec.encode("AGENT_4_MC", raw, 1)
    n = 2000
    dec = min(timeit.repeat(lambda: codec.decode(msg), number=n, repeat=3)) / n
    enc = min(timeit.repeat(lambda: codec.encode("AGENT_4_MC", raw, 1), number=n,
                            repeat=3)) / n
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
