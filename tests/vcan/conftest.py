"""The vcan tier: tests that need a real SocketCAN ``vcan0``.

On a host without CAN (this project's CI machines) run them through the QEMU guest:

    tools/vcan-run python3 -m pytest -m vcan tests/vcan

Without vcan0 they are skipped, except under CI (env ``CI`` set), where they fail: the tier
must never pass by silently skipping.
"""

from __future__ import annotations

import os
import shutil
import socket
from pathlib import Path

import pytest

CHANNEL = "vcan0"
FD_CHANNEL = "vcan1"   # CAN FD: mtu 72 (tools/vcan-run brings it up beside vcan0)
CANFD_MTU = 72


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def _vcan_problem(channel: str) -> str | None:
    """Why a CAN_RAW socket cannot be bound to ``channel``, or None if it can."""
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no AF_CAN"
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        return f"the kernel has no CAN_RAW sockets ({exc.strerror})"
    with sock:
        try:
            sock.bind((channel,))
        except OSError as exc:
            return f"cannot bind to {channel} ({exc.strerror})"
    return None


def _unavailable(reason: str) -> None:
    if _in_ci():
        pytest.fail(f"{reason}; CI must run the vcan tier through tools/vcan-run", pytrace=False)
    pytest.skip(f"{reason}: run through tools/vcan-run")


@pytest.fixture(scope="session")
def vcan_channel() -> str:
    """The SocketCAN channel of the tier; fails (CI) or skips when it is not usable."""
    problem = _vcan_problem(CHANNEL)
    if problem:
        _unavailable(problem)
    return CHANNEL


@pytest.fixture(scope="session")
def vcan_fd_channel() -> str:
    """The tier's CAN FD channel (a vcan with mtu 72); fails (CI) or skips like vcan0."""
    problem = _vcan_problem(FD_CHANNEL)
    if problem is None:
        mtu = int(Path(f"/sys/class/net/{FD_CHANNEL}/mtu").read_text())
        if mtu < CANFD_MTU:
            problem = f"{FD_CHANNEL} carries no CAN FD frames (mtu {mtu}, expected {CANFD_MTU})"
    if problem:
        _unavailable(problem)
    return FD_CHANNEL


@pytest.fixture(autouse=True)
def _require_vcan(vcan_channel: str) -> None:
    """Every test in this directory needs vcan0, whether or not it asks for it."""


@pytest.fixture(scope="session")
def can_utils() -> None:
    """can-utils (cansend, candump) on PATH; fails (CI) or skips otherwise."""
    missing = [tool for tool in ("cansend", "candump") if shutil.which(tool) is None]
    if missing:
        _unavailable(f"can-utils missing ({', '.join(missing)}; tools/install-vcan-deps)")
