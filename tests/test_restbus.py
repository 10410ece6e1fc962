"""`bess-ded restbus`: the fleet but one node, with a device under test in its place.

The device here is firmware_py's own agent, started by hand from what restbus prints
(its configuration and key file, the bus), as an operator would start a device on
can0: restbus must wait for it, then run and judge the whole fleet, the device's
frames included, as `bess-ded up` does.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest
from conformance_run import with_device

from sim.cli import main

DEVICE_HINT = re.compile(r"device under test: \S+, waited for up to .*?; e\.g\. (.*)$")


@pytest.mark.realtime
def test_restbus_with_a_hand_started_agent_converges_like_up(tmp_path: Path) -> None:
    """Expected (any load): `restbus --case 1 --dut 3` prints how to start agent 3 (its
    config and key file from this run), waits for it, and the whole fleet converges
    (< 1e-3) with agent 3 dispatching: exit 0 or 3 (deadline misses and the like on a
    loaded host), never 1; the device's MC frames are in the recording and its frames
    verify with the run's keys (no auth_failed)."""
    out = tmp_path / "rb"
    code, log = with_device(["restbus", "--case", "1", "--dut", "3", "--duration", "8",
                             "--no-plot", "--out", str(out)], DEVICE_HINT,
                            [sys.executable, "-m", "firmware_py"])
    assert re.search(r"device under test: agent_3,", log), log
    assert code in (0, 3), log
    m = json.loads((out / "metrics.json").read_text())
    assert m["final_error"] < 1e-3, log
    assert m["verdict"]["converged"], m["verdict"]
    assert "agent_3" not in m["exit_codes"]  # not a node of restbus's own
    assert "auth_failed" not in {a["kind"] for a in m["anomalies"]}, m["anomalies"]
    assert m["node_ticks"]["agent_3"] > 500  # its frames were recorded and counted


def test_restbus_without_a_device_gives_up_naming_the_missing_frames(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["restbus", "--case", "1", "--dut", "2", "--duration", "2", "--no-plot",
                 "--wait", "3", "--out", str(tmp_path / "rb")]) == 2
    out, err = capsys.readouterr()
    assert "bess-ded: error: the device under test sent no 0x102, 0x202 within 3 s" in err
    # the device's command line has the fleet's real-time priority (busrun.RT_PRIORITY)
    (hint,) = [m.group(1) for m in map(DEVICE_HINT.search, out.splitlines()) if m]
    assert hint.startswith("bess-ded agent --config ") and "--key " in hint
    assert " --rt-priority 10 " in hint, hint


@pytest.mark.parametrize("dut", ["5", "0", "x", "agent_3"])
def test_restbus_rejects_a_device_outside_the_fleet(
        dut: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["restbus", "--case", "1", "--dut", dut, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"--dut: expected an agent number in 1..4 or 'plant', but got '{dut}'" in err


def test_restbus_giving_up_leaves_the_previous_run_intact(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A restbus that gives up waiting for the device (exit 2) wrote its keys, configs
    and log into OUT first: the earlier run there is put back as it was, this attempt's
    files go beside it (OUT.failed), and a leftover OUT.previous is never overwritten."""
    out = tmp_path / "rb"
    (out / "keys").mkdir(parents=True)
    earlier = {"run.log": "(1.0) vcan0 010#00\n", "metrics.json": '{"earlier": true}\n',
               "keys/agent_2.key": "earlier key\n"}
    for name, text in earlier.items():
        (out / name).write_text(text)
    argv = ["restbus", "--case", "1", "--dut", "2", "--duration", "2", "--no-plot",
            "--wait", "1", "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"({out} still holds the previous run; this attempt's logs are in " \
           f"{out}.failed)" in err, err
    assert {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()} == set(earlier)
    assert all((out / name).read_text() == text for name, text in earlier.items())
    assert (tmp_path / "rb.failed" / "agents" / "agent_2.toml").is_file()
    assert not (tmp_path / "rb.previous").exists()
    (tmp_path / "rb.previous").mkdir()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"bess-ded: error: {out}.previous exists" in err and "delete it" in err, err
    assert (out / "metrics.json").read_text() == earlier["metrics.json"]
