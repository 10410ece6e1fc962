"""Smoke tests of real SocketCAN on vcan0: python-can to python-can, and can-utils interop.

Kept small: in the QEMU guest (TCG) Python runs ~15x slower than on the host.
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

pytestmark = pytest.mark.vcan

# Test traffic lives in its own ID blocks, and receivers filter on them, so other traffic
# on a shared vcan0 (a developer's host) cannot disturb the tests.
STD_BASE = 0x500  # 0x500..0x57F
EXT_BASE = 0x1ABC0000  # 0x1ABC0000..0x1ABC00FF
FILTERS = [
    {"can_id": STD_BASE, "can_mask": 0x780, "extended": False},
    {"can_id": EXT_BASE, "can_mask": 0x1FFFFF00, "extended": True},
]


@pytest.fixture
def bus_pair(vcan_channel: str) -> Iterator[tuple[can.BusABC, can.BusABC]]:
    tx = can.Bus(interface="socketcan", channel=vcan_channel)
    rx = can.Bus(interface="socketcan", channel=vcan_channel, can_filters=FILTERS)
    try:
        yield tx, rx
    finally:
        tx.shutdown()
        rx.shutdown()


def _frame(i: int) -> can.Message:
    """Frame i of the 200: alternating 11/29-bit IDs, every DLC 0..8, payload from i."""
    extended = i % 2 == 1
    arb = EXT_BASE + (i % 256) if extended else STD_BASE + (i % 128)
    dlc = i % 9
    data = bytes((i * 7 + k) & 0xFF for k in range(dlc))
    return can.Message(arbitration_id=arb, is_extended_id=extended, data=data)


def test_socketcan_200_frames_between_two_buses(
    vcan_channel: str, bus_pair: tuple[can.BusABC, can.BusABC]
) -> None:
    tx, rx = bus_pair
    sent = [_frame(i) for i in range(200)]
    received: list[can.Message] = []
    # Batches of 25 keep the receive socket far below its buffer limit, so nothing is
    # dropped even when the guest is slow to read.
    for start in range(0, len(sent), 25):
        for msg in sent[start : start + 25]:
            tx.send(msg)
        for _ in range(25):
            msg = rx.recv(timeout=5.0)
            assert msg is not None, f"timed out after {len(received)} frames"
            received.append(msg)
    assert rx.recv(timeout=0.05) is None, "more frames than were sent"

    for want, got in zip(sent, received, strict=True):
        assert (got.arbitration_id, got.is_extended_id, bytes(got.data), got.dlc) == (
            want.arbitration_id,
            want.is_extended_id,
            want.data,
            len(want.data),
        )
        assert got.channel == vcan_channel


def test_cansend_is_received_by_python_can(vcan_channel: str, can_utils: None) -> None:
    with can.Bus(
        interface="socketcan",
        channel=vcan_channel,
        can_filters=[{"can_id": 0x123, "can_mask": 0x7FF, "extended": False}],
    ) as bus:
        subprocess.run(["cansend", vcan_channel, "123#DEADBEEF"], check=True, timeout=30)
        msg = bus.recv(timeout=10.0)
    assert msg is not None, "cansend's frame never arrived"
    assert msg.arbitration_id == 0x123
    assert not msg.is_extended_id
    assert bytes(msg.data) == bytes.fromhex("DEADBEEF")


@pytest.mark.parametrize(
    ("arb", "extended", "data"),
    [(0x321, False, bytes.fromhex("CAFEBABE0102")), (EXT_BASE + 0x42, True, b"\x00\xff")],
    ids=["std11", "ext29"],
)
def test_python_can_frame_is_captured_by_candump(
    vcan_channel: str, can_utils: None, tmp_path: Path, arb: int, extended: bool, data: bytes
) -> None:
    # Filter exactly this ID (the EFF bit in the mask tells 11-bit and 29-bit apart).
    cid = f"{arb:08X}" if extended else f"{arb:03X}"
    mask = "DFFFFFFF" if extended else "C00007FF"
    log = tmp_path / "dump.log"
    with log.open("w") as out:
        dump = subprocess.Popen(
            ["candump", "-L", "-n", "1", "-T", "20000", f"{vcan_channel},{cid}:{mask}"],
            stdout=out,
        )
        msg = can.Message(arbitration_id=arb, is_extended_id=extended, data=data)
        with can.Bus(interface="socketcan", channel=vcan_channel) as bus:
            # candump may not have bound its socket yet (slow guest): resend until it has
            # taken its one frame (-n 1) and exited.
            deadline = time.monotonic() + 20
            while dump.poll() is None and time.monotonic() < deadline:
                bus.send(msg)
                try:
                    dump.wait(timeout=0.2)
                except subprocess.TimeoutExpired:
                    pass
        if dump.poll() is None:
            dump.kill()
            dump.wait()
            pytest.fail("candump captured nothing")
    assert dump.returncode == 0

    line = log.read_text()
    assert line.count("\n") == 1, line
    frames = list(can.LogReader(log))  # .log = candump -L format
    assert len(frames) == 1, line
    got = frames[0]
    assert got.channel == vcan_channel
    assert got.arbitration_id == arb
    assert got.is_extended_id == extended
    assert bytes(got.data) == data
    assert got.timestamp == pytest.approx(time.time(), abs=120)
