"""Issue 22, acceptance: a healthy device passes `bess-ded conformance` at any load —
firmware_py's agent process and firmware_c's node program (started from the command line
the tool prints for it), each three times in a row on udp_multicast beside `stress-ng
--cpu 2` (started here, stopped at the end). Both on vcan0: tests/vcan/test_vcan_soak.py.
Marked `soak` (with `long` and `realtime`): run by hand, `python3 -m pytest -m soak
tests/test_conformance_soak.py` (about 3 min); CI runs each device once a run
(tests/test_conformance.py, tests/vcan/test_vcan_conformance.py).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from conformance_run import C_DEVICE_HINT, FIRMWARE_PY, assert_passed, run_conformance, stress_hog

from sim.cbind.cagent import node_program

pytestmark = [pytest.mark.soak, pytest.mark.long, pytest.mark.realtime]
RUNS = 3


@pytest.fixture(scope="module")
def hog() -> Iterator[None]:
    """`stress-ng --cpu 2` beside every run of the module."""
    with stress_hog():
        yield


@pytest.mark.parametrize("run", range(1, RUNS + 1))
@pytest.mark.parametrize("kind", ["firmware_py", "firmware_c"])
def test_a_healthy_device_passes_beside_stress_ng(kind: str, run: int, hog: None,
                                                 tmp_path: Path) -> None:
    if kind == "firmware_py":
        code, log = run_conformance(tmp_path, FIRMWARE_PY)
    else:
        code, log = run_conformance(tmp_path, [str(node_program())], hint=C_DEVICE_HINT)
    assert_passed(code, log)
