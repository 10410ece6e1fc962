"""Issue 22, acceptance: a healthy device passes `bess-ded conformance` at any load —
firmware_py's agent process three times in a row on udp_multicast beside `stress-ng --cpu
2` (started here, stopped at the end). firmware_c's node program speaks SocketCAN only:
its soak, and firmware_py's, on vcan0 is tests/vcan/test_vcan_soak.py. Marked `soak`
(with `long` and `realtime`): run by hand, `python3 -m pytest -m soak
tests/test_conformance_soak.py` (about 2 min); CI runs each device once a run
(tests/test_conformance.py, tests/vcan/test_vcan_conformance.py).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from conformance_run import FIRMWARE_PY, run_conformance, stress_hog

pytestmark = [pytest.mark.soak, pytest.mark.long, pytest.mark.realtime]
RUNS = 3


@pytest.fixture(scope="module")
def hog() -> Iterator[None]:
    """`stress-ng --cpu 2` beside every run of the module."""
    with stress_hog():
        yield


@pytest.mark.parametrize("run", range(1, RUNS + 1))
def test_firmware_py_passes_beside_stress_ng(run: int, hog: None, tmp_path: Path) -> None:
    code, log = run_conformance(tmp_path, FIRMWARE_PY)
    assert code == 0, log
    assert "bess-ded conformance: PASS" in log and "  FAIL  " not in log
