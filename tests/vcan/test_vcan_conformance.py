"""`bess-ded conformance` on a real SocketCAN vcan0 (issue 10's acceptance): firmware_py's
agent and firmware_c's node program, started from the command line the tool prints, pass
every requirement; an agent
whose reset band re-arms at the reset sample fails, and the failure names BAND-2.

In the QEMU guest the tool and the device run at --time-scale 5 (VCAN_RUN_GUEST=1), both
under SCHED_FIFO as on a HIL rig.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from conformance_run import DEVIANT, FIRMWARE_PY, run_conformance

from sim.cagent import node_program

pytestmark = pytest.mark.vcan

BUS = ["--interface", "socketcan"]


def test_firmware_py_agent_passes_on_vcan0(vcan_channel: str, tmp_path: Path) -> None:
    code, log = run_conformance(tmp_path, FIRMWARE_PY, [*BUS, "--channel", vcan_channel])
    assert code == 0, log
    assert "bess-ded conformance: PASS" in log and "  FAIL  " not in log
    assert "interface': 'socketcan'" in log


def test_c_agent_passes_on_vcan0(vcan_channel: str, tmp_path: Path) -> None:
    """Issue 11: firmware_c's node program, started with the arguments the tool prints
    for `bess-ded agent` (it takes the same configuration, key and bus flags)."""
    code, log = run_conformance(tmp_path, [str(node_program())],
                                [*BUS, "--channel", vcan_channel])
    assert code == 0, log
    assert "bess-ded conformance: PASS" in log and "  FAIL  " not in log


def test_band_re_armed_at_the_reset_sample_fails_band_2_on_vcan0(vcan_channel: str,
                                                                  tmp_path: Path) -> None:
    code, log = run_conformance(tmp_path, DEVIANT, [*BUS, "--channel", vcan_channel])
    assert code == 1, log
    assert re.findall(r"^  FAIL  (\S+)", log, re.M) == ["BAND-2"], log
