"""Issue 22, acceptance: a healthy device passes `bess-ded conformance` on a real
SocketCAN vcan0 at any load — firmware_py's agent process and firmware_c's node program,
each three times in a row with `stress-ng --cpu 2` running in the guest beside them.
Marked `soak` and `long` (37 min of the guest on 2026-11-28): by hand,
`tools/vcan-run python3 -m pytest -m soak tests/vcan/test_vcan_soak.py -q`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from conformance_run import FIRMWARE_PY, assert_passed, run_conformance, stress_hog

from sim.cbind.cagent import node_program

pytestmark = [pytest.mark.vcan, pytest.mark.soak, pytest.mark.long]
RUNS = 3
BUS = ["--interface", "socketcan"]


@pytest.fixture(scope="module")
def hog() -> Iterator[None]:
    """`stress-ng --cpu 2` beside every run of the module."""
    with stress_hog():
        yield


@pytest.mark.parametrize("run", range(1, RUNS + 1))
@pytest.mark.parametrize("kind", ["firmware_py", "firmware_c"])
def test_a_healthy_device_passes_on_vcan0_beside_stress_ng(
        kind: str, run: int, hog: None, vcan_channel: str, tmp_path: Path) -> None:
    dev = [*FIRMWARE_PY] if kind == "firmware_py" else [str(node_program())]
    code, log = run_conformance(tmp_path, dev, [*BUS, "--channel", vcan_channel])
    assert_passed(code, log)
