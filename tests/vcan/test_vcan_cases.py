"""Scenarios on the kernel's vcan0, every node (agents, plant, router) its own process.

The runs are shortened (dataclasses.replace, stated per run below) and, in the QEMU
guest, stretched by vcanrun.TIME_SCALE (Ts = 50 ms instead of 10 ms: the same discrete
system per sample, see docs/vcan.md); case 7, with 14 node processes, by
vcanrun.HEAVY_TIME_SCALE (Ts = 100 ms): its Python plant takes 12 agents' setpoints.
Case 1 runs a mixed
fleet (agent 3 on firmware_c) and case 7 every agent on firmware_c (issue 11). Each
scenario runs once per session (module fixtures); the tests then check its recording.
Case 5 (price steps) is not here: its segments are exact on the virtual bus
(tests/test_bus.py::test_virtual_bus_follows_lockstep_through_events[5]) and the tier
must fit CI's 35 min (it cost 154 s of the guest, and once ended at 1.01e-3):

* convergence: max|λ−ρ| < 1e-3 at the end;
* plug-and-play (case 4): AGENT_2_MC.State is ISOLATED during the isolation window and
  RUNNING again after the reconnect;
* the router's power balance: ER_Balance.GridPower = load − Σ PLANT_i_Status.Power
  within 1 kW at the end;
* the whole candump log decodes against the DBC with our codec (frames_undecodable);
  the cantools CLI pass runs on test_vcan_interop.py's candump capture;
* every node exits with code 0 on SIGTERM.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import replace

import can
import pytest
from vcanrun import (
    FINAL_TOL,
    HEAVY_TIME_SCALE,
    TIME_SCALE,
    Run,
    assert_clean_exit,
    assert_power_balance,
    run_on_vcan,
)

from dbc import FD_DBC_PATH
from firmware_py.contract import State
from firmware_py.frames import FrameCodec
from sim.cbind.cagent import node_program
from sim.model.lockstep import run_lockstep
from sim.model.metrics import worst_error
from sim.model.scenario import Event, load_case

pytestmark = pytest.mark.vcan

ISOLATED, RUNNING = State.ISOLATED, State.RUNNING
# the verdict's anomaly kinds that mean a node rejected frames as bad (sim/run/verdict.py).
# Not stale_frames: genuine frames that arrived out of order (AUTH-25), which vcan in a
# 2-CPU guest does to one sender's frames (docs/vcan.md), are a load anomaly, not bad.
REJECTIONS = {"rejected_frames", "foreign_traffic", "implausible_frames",
              "untrusted_source", "auth_failed"}


@pytest.fixture(scope="module")
def case1(vcan_fd_channel: str, tmp_path_factory: pytest.TempPathFactory) -> Run:
    """Case 1 (4 agents, star, ρ = 0.8), 8 s instead of 20 s (lockstep settles in 2.54 s
    and is at 1.4e-4 at 8 s), a mixed fleet: agent 3 runs firmware_c's node program, the
    others firmware_py; on CAN FD (``[bus] fd``, vcan1 with mtu 72: issue 23.3), so the
    C and the Python agents both send and take FD frames on SocketCAN. The classic
    SocketCAN path runs in the other cases and in the interop, attack and fuzz runs."""
    sc = replace(load_case(1), duration=8.0, fd=True)
    return run_on_vcan(sc, tmp_path_factory.mktemp("case1"), vcan_fd_channel,
                       c_agents=frozenset({3}), c_node=node_program())


@pytest.fixture(scope="module")
def case4(vcan_channel: str, tmp_path_factory: pytest.TempPathFactory) -> Run:
    """Case 4 (plug-and-play), compressed: agent 2 isolated at 3 s instead of 10 s,
    reconnected at 6 s instead of 20 s, 13 s instead of 35 s (lockstep: 1.7e-4 at 13 s)."""
    sc = replace(load_case(4), duration=13.0,
                 events=(Event(3.0, 2, "isolate"), Event(6.0, 2, "reconnect")))
    return run_on_vcan(sc, tmp_path_factory.mktemp("case4"), vcan_channel)


@pytest.fixture(scope="module")
def case7(vcan_channel: str, tmp_path_factory: pytest.TempPathFactory) -> Run:
    """Case 7 (12 agents on a ring: 14 processes), 10 s instead of 30 s (lockstep settles
    in 4.3 s and is at 2.2e-4 at 10 s), every agent on firmware_c's node program, at
    HEAVY_TIME_SCALE: the C agents would afford TIME_SCALE, but the Python plant that
    takes their 12 setpoints does not (at TIME_SCALE it missed 43 % of its deadlines in
    the guest, and vcan0 then handed it one agent's setpoints out of order: 30 late within
    a freshness window, and once in CI one beyond it, rejected as unauthentic)."""
    sc = replace(load_case(7), duration=10.0)
    return run_on_vcan(sc, tmp_path_factory.mktemp("case7"), vcan_channel,
                       scale=HEAVY_TIME_SCALE, c_agents=frozenset(range(1, 13)),
                       c_node=node_program())


CASES = ["case1", "case4", "case7"]


@pytest.fixture(params=CASES)
def run(request: pytest.FixtureRequest) -> Run:
    return request.getfixturevalue(request.param)


def test_converges_to_the_price(run: Run) -> None:
    assert run.m["final_error"] < FINAL_TOL, {k: run.m[k] for k in (
        "final_error", "settling_times_s", "deadline_misses")}
    assert all(st is not None for st in run.m["settling_times_s"]), run.m["settling_times_s"]


def test_router_power_balance(run: Run) -> None:
    assert_power_balance(run)


def test_log_decodes_against_the_dbc(run: Run) -> None:
    """Every recorded frame decodes with our codec (built from the DBC, checking DLC
    and ranges too). The `python3 -m cantools decode` pass over a whole log runs once,
    on test_vcan_interop.py's candump capture of a case-1 fleet (the logs hold the same
    frames, and each CLI pass costs 40-50 s in the guest)."""
    assert run.m["frames_undecodable"] == {}
    assert run.m["frames_recorded"] > 0
    # the recorder kept up (16 MiB socket buffer, drained after the stop): a run once
    # lost 16 frames of one agent at a neighbour too; without the buffer case 7 lost 75 %
    assert run.m["frames_missed_by_recorder"] <= 0.005 * run.m["frames_recorded"], \
        run.m["frames_missed_by_recorder"]


def test_nodes_exit_cleanly(run: Run) -> None:
    assert_clean_exit(run)


def test_case1_on_can_fd_sends_fd_frames_only(case1: Run) -> None:
    """Every frame of the FD run (the C agent's too) is CAN FD with the bit-rate switch,
    and each sender was heard: the format is the scenario's, end to end (issue 23.3)."""
    frames = list(can.LogReader(str(case1.out / "run.log")))
    assert frames and all(f.is_fd and f.bitrate_switch for f in frames), \
        Counter((f.is_fd, f.bitrate_switch) for f in frames)
    codec = FrameCodec(FD_DBC_PATH)
    heard = {codec.name_of(f.arbitration_id) for f in frames}
    assert {"AGENT_3_MC", "AGENT_3_Setpoint", "AGENT_1_MC", "ER_Price"} <= heard, heard


@pytest.mark.parametrize("name", ["case1", "case7"])
def test_c_agents_run_clean_like_the_lockstep(name: str, request: pytest.FixtureRequest
                                              ) -> None:
    """Issue 11: the runs with C agents converge like the lockstep run, and the verdict
    finds no rejection at any node (no rejected, stale, foreign, implausible, untrusted
    or unauthentic frame); the C agents really ran (their summary line)."""
    run = request.getfixturevalue(name)
    assert run.m["verdict"]["converged"], run.m["verdict"]
    rejections = [a for a in run.m["anomalies"] if a["kind"] in REJECTIONS]
    assert not rejections, rejections
    assert run.m["final_error"] < FINAL_TOL
    assert float(worst_error(run_lockstep(run.sc))[-1]) < FINAL_TOL
    c_ids = [3] if name == "case1" else list(range(1, 13))
    for i in c_ids:
        log = (run.out / "logs" / f"agent_{i}.log").read_text()
        assert f"agent {i} (C): state=RUNNING" in log, log[-500:]


def test_case4_agent2_leaves_and_rejoins(case4: Run) -> None:
    """From AGENT_2_MC.State in the log: ISOLATED between the isolate and reconnect
    commands (0.5 s margin each side for the command frame's delivery), RUNNING again
    from 0.5 s after the reconnect to the end; the other agents never leave."""
    f = TIME_SCALE
    t0 = case4.log.t_first_price
    assert t0 is not None
    states = [(t - t0, v) for t, v in case4.log.series[("AGENT_2_MC", "State")]]
    inside = [v for t, v in states if 3.5 * f < t < 5.5 * f]
    after = [v for t, v in states if t > 6.5 * f]
    assert inside and all(v == ISOLATED for v in inside), sorted(set(inside))
    assert after and all(v == RUNNING for v in after), sorted(set(after))
    for agent in (1, 3, 4):
        late = [v for t, v in case4.log.series[(f"AGENT_{agent}_MC", "State")]
                if t - t0 > 1.0 * f]
        assert late and all(v == RUNNING for v in late), (agent, sorted(set(late)))
    # and the isolated agent is left out of the final error, which still converges
    assert case4.tr.active[case4.tr.t > 6.5 * f, 1].all()
