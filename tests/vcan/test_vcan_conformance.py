"""`bess-ded conformance` on a real SocketCAN vcan0: firmware_c's node program (its own
SocketCAN driver), started from the command line the tool prints, passes every
requirement. firmware_py's agent and the BAND-2 deviant are judged by the same tool on
udp_multicast beside stress-ng in the real-time tier (tests/test_conformance.py): the
tool's bus seam is python-can's either way, and firmware_py's nodes run on vcan0 in
test_vcan_cases.py; each of those two runs cost 2-3.5 min of the guest (docs/vcan.md).

In the QEMU guest the tool and the device run at --time-scale 5 (VCAN_RUN_GUEST=1), both
under SCHED_FIFO as on a HIL rig.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from conformance_run import assert_passed, run_conformance

from sim.cbind.cagent import node_program

pytestmark = pytest.mark.vcan

BUS = ["--interface", "socketcan"]


def test_c_agent_passes_on_vcan0(vcan_channel: str, tmp_path: Path) -> None:
    """Issue 11: firmware_c's node program, started with the arguments the tool prints
    for `bess-ded agent` (it takes the same configuration, key and bus flags)."""
    code, log = run_conformance(tmp_path, [str(node_program())],
                                [*BUS, "--channel", vcan_channel])
    assert_passed(code, log)

