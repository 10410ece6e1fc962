"""docs/deployment.md, "One node per host on real CAN", followed step by step with the
commands it gives (on a private udp_multicast port instead of can0, `bess-ded record`
instead of candump): configurations and the fleet's keys from `bess-ded deploy` at the
time scale, the agents and the plant first, the recorder, the router last, every node
under --rt-priority 10; then `bess-ded analyze` with the key set judges the run.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest

from firmware_py.frames import FrameCodec, mc_name, status_name

SCALE = "2"       # the recipe's time scale F: Ts = 20 ms
RUN_TICKS = 700   # each agent's MC frames after the first price: 14 s at Ts = 20 ms (7 s of
                  # price time at ×2), counted in its ticks, which load stretches, not drops
LOAD_TOLERANT_S = 600.0  # waiting for processes: a deadline, not a duration


def bess_ded(*argv: str) -> list[str]:
    return [sys.executable, "-m", "sim.cli", *argv]


@pytest.mark.realtime
def test_the_by_hand_recipe_converges(tmp_path: Path, udp_port: int) -> None:
    """Expected (any load): the hand-started fleet converges (analyze exits 0 or 3, never
    1; final max|λ−ρ| < 1e-3), every agent's frames verify with the key set (no
    auth_failed), and every node stops cleanly on SIGTERM (exit 0)."""
    bus = ["--interface", "udp_multicast", "--bus-config", json.dumps({"port": udp_port})]
    rt = ["--rt-priority", "10"]
    # 2. the stretched agent configurations and the fleet's keys, nothing run (exit 0)
    subprocess.run(bess_ded("deploy", "--case", "1", "--time-scale", SCALE, "--out",
                            str(tmp_path / "plan")), check=True, capture_output=True,
                   timeout=120)
    cfg = tmp_path / "plan" / "agents"
    assert sorted(p.name for p in cfg.glob("*.toml")) == [f"agent_{i}.toml" for i in range(1, 5)]
    # 3. each node's own key file, from the key set deploy wrote
    keys = tmp_path / "plan" / "keys"
    logs = tmp_path / "logs"
    logs.mkdir()
    procs: dict[str, subprocess.Popen[bytes]] = {}

    def start(name: str, argv: list[str]) -> None:
        with open(logs / f"{name}.log", "wb") as out:
            procs[name] = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT,
                                           env={**os.environ, "PYTHONUNBUFFERED": "1"})

    # as an operator watching the bus: each step waits until the nodes it started are
    # heard, however long a loaded host takes to start them (imports, DBC), not a fixed time
    codec = FrameCodec()
    watch = can.Bus(interface="udp_multicast", port=udp_port, receive_own_messages=False)

    def heard(names: list[str], timeout_s: float = 180.0) -> None:
        want = {codec.frame_id(n) for n in names}
        end = time.monotonic() + timeout_s
        while want and time.monotonic() < end:
            msg = watch.recv(timeout=0.2)
            if msg is not None:
                want.discard(msg.arbitration_id)
        assert not want, f"not heard within {timeout_s:g} s: {[codec.name_of(i) for i in want]}"

    def ran(names: list[str], frames: int, timeout_s: float = LOAD_TOLERANT_S) -> None:
        """Block until ``frames`` more frames of each of ``names`` were heard: the run's
        length in the nodes' own ticks, not in wall seconds."""
        left = {codec.frame_id(n): frames for n in names}
        end = time.monotonic() + timeout_s
        while max(left.values()) > 0 and time.monotonic() < end:
            msg = watch.recv(timeout=0.2)
            if msg is not None and msg.arbitration_id in left:
                left[msg.arbitration_id] -= 1
        got = {codec.name_of(i): frames - n for i, n in left.items()}
        assert max(left.values()) <= 0, f"heard within {timeout_s:g} s: {got}, not {frames} each"

    def said(name: str, text: str, timeout_s: float = 180.0) -> None:
        end = time.monotonic() + timeout_s
        while text not in (logs / f"{name}.log").read_text() and time.monotonic() < end:
            time.sleep(0.2)  # a poll of a real process's log, with a deadline
        assert text in (logs / f"{name}.log").read_text(), f"{name} never said {text!r}"

    try:
        # 4. the agents, and 5. the plant (simulated batteries): first, in any order
        for i in range(1, 5):
            start(f"agent_{i}", bess_ded("agent", "--config", str(cfg / f"agent_{i}.toml"),
                                         "--key", str(keys / f"agent_{i}.key"), *bus, *rt))
        start("plant", bess_ded("plant", "--case", "1", "--time-scale", SCALE, "--key",
                                str(keys / "plant.key"), *bus, *rt))
        # 6. record everything (before the router: its first price is t = 0)
        start("record", bess_ded("record", "--out", str(tmp_path / "run.log"), *bus))
        heard([mc_name(i) for i in range(1, 5)] + [status_name(i) for i in range(1, 5)])
        said("record", "bess-ded record: ")  # its bus is open
        start("router", bess_ded("router", "--case", "1", "--time-scale", SCALE, "--key",
                                 str(keys / "router.key"), *bus, *rt))
        heard(["ER_Price"])
        ran([mc_name(i) for i in range(1, 5)], RUN_TICKS)
    finally:
        watch.shutdown()
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        codes = {name: p.wait(timeout=60) for name, p in procs.items()}
    assert codes == dict.fromkeys(procs, 0), {n: (logs / f"{n}.log").read_text()[-500:]
                                              for n, c in codes.items() if c}
    # 6. analyse it with the key set
    done = subprocess.run(bess_ded("analyze", str(tmp_path / "run.log"), "--case", "1",
                                   "--time-scale", SCALE, "--keys", str(keys), "--no-plot",
                                   "--out", str(tmp_path / "an")),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode in (0, 3), done.stdout + done.stderr
    m = json.loads((tmp_path / "an" / "metrics.json").read_text())
    assert m["final_error"] < 1e-3, done.stdout
    assert "auth_failed" not in {a["kind"] for a in m["anomalies"]}, m["anomalies"]
    assert all(m["node_ticks"][f"agent_{i}"] > 300 for i in range(1, 5)), m["node_ticks"]
