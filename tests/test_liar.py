"""A compromised agent holding only its own key, and one verdict per log (issue 19:
deliverables 3, 6, 7; issue 20: host overload).

The liar signs what it sends, so no MAC gives it away: only what it says does. The plant
and the verdict check each setpoint against the agent's own dispatch rule at the λ it
publishes (sim/nodes/consistency.py: ``setpoint_inconsistent``); the verdict wants every final λ
within the tolerance of ρ and names an agent whose told λ stays off the others'
(``lambda_outlier``). Runs are case 1 on the deterministic in-process bus
(``run_in_process``, ~2 s each); every run's directory is then judged again by
``bess-ded analyze DIR``, which must give the same verdict and anomalies.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from deviant_agent import LIE_SETPOINT_KW, lying
from test_attacks import spoofed_mc

from firmware_py.config import agent_configs_from_scenario
from firmware_py.frames import FrameCodec, mc_name, setpoint_name
from firmware_py.nodeio import FleetSender
from firmware_py.runtime import SetpointMap
from sim.cli import main
from sim.model.scenario import load_case
from sim.nodes.consistency import Check, Setpoint, SetpointCheck
from sim.nodes.plant import PlantNode
from sim.run import busrun
from sim.run.buslog import LogContents, SequenceStats
from sim.run.verdict import EXIT_ANOMALIES, EXIT_NOT_CONVERGED, Anomaly, RunFacts, _host_overload

CASE = replace(load_case(1), duration=6.5)  # the fleet dispatches from ~0.21 s (join window)
DURATION_S = 6.5
CODEC = FrameCodec()
BATTERY_3 = agent_configs_from_scenario(CASE)[2].battery
Q24 = 1 << 24


# --------------------------------------------------------------------------- the check


def test_a_setpoint_is_checked_against_the_lambda_its_agent_publishes() -> None:
    check = SetpointCheck(BATTERY_3)
    lam = round(0.8 * Q24)
    honest = SetpointMap(BATTERY_3)(lam)[0]
    assert check.mc(1, lam) is None                       # RUNNING at λ = 0.8
    sp = Setpoint(True, honest, 0.0)
    assert check.setpoint(sp) == [(Check.CONSISTENT, sp)]
    rounded = Setpoint(True, honest + 1, 0.0)             # the wire's rounding
    assert check.setpoint(rounded) == [(Check.CONSISTENT, rounded)]
    lie = Setpoint(True, round(LIE_SETPOINT_KW * 100), 0.1)
    assert check.setpoint(lie) == []                      # may have overtaken its MC frame
    assert check.mc(1, lam) == (Check.INCONSISTENT, lie)  # the next one does not explain it
    assert check.setpoint(Setpoint(True, honest, 0.2))[0][0] is Check.CONSISTENT
    off = Setpoint(False, 0, 0.3)                         # disabled while RUNNING:
    assert check.setpoint(off) == [(Check.CONSISTENT, off)]   # the safe direction


def test_a_setpoint_ahead_of_its_mc_frame_waits_for_it_and_one_without_is_unverified() -> None:
    check = SetpointCheck(BATTERY_3)
    check.mc(1, round(0.8 * Q24))
    ahead = Setpoint(True, SetpointMap(BATTERY_3)(round(0.9 * Q24))[0], 0.0)
    assert check.setpoint(ahead) == []
    assert check.mc(1, round(0.9 * Q24)) == (Check.CONSISTENT, ahead)
    # its own tick's MC frame lost: between the ones before and after it
    lost = Setpoint(True, SetpointMap(BATTERY_3)(round(0.95 * Q24))[0], 0.1)
    assert check.setpoint(lost) == []
    assert check.mc(1, round(1.0 * Q24)) == (Check.CONSISTENT, lost)
    # a checker (a plant) started between a tick's MC frame and its setpoint: unverified
    fresh, early = SetpointCheck(BATTERY_3), Setpoint(True, 1234, 0.0)
    assert fresh.setpoint(early) == []
    assert fresh.mc(1, round(0.8 * Q24)) == (Check.UNVERIFIED, early)
    first, second = Setpoint(True, 1, 0.0), Setpoint(True, 2, 0.1)
    assert check.setpoint(first) == []
    assert check.setpoint(second) == [(Check.UNVERIFIED, first)]   # MC frames not getting
    # more than one MC frame lost around a setpoint: λ may have turned there, unverified
    timed = SetpointCheck(BATTERY_3, period=0.01)
    timed.mc(1, round(0.8 * Q24), 0.0)
    odd = Setpoint(True, SetpointMap(BATTERY_3)(round(0.7 * Q24))[0], 0.01)
    assert timed.setpoint(odd) == []
    assert timed.mc(1, round(0.9 * Q24), 0.03) == (Check.UNVERIFIED, odd)   # 2 lost
    assert timed.setpoint(odd) == []
    assert timed.mc(1, round(0.95 * Q24), 0.04) == (Check.INCONSISTENT, odd)  # 1 lost
    # the clipping at the battery's limits is the firmware's own
    assert check.expected(1, 10 * Q24) == (True, round(100 * BATTERY_3.p_max))
    assert check.expected(0, 10 * Q24) == (False, 0)                 # INIT: disabled


@pytest.mark.parametrize("obey", [False, True])
def test_the_plant_holds_the_last_consistent_setpoint_unless_told_to_obey(obey: bool) -> None:
    plant = PlantNode(CASE, obey_inconsistent=obey)
    agent = FleetSender(CODEC)   # agent 3, --insecure: boot 1, no sync needed
    lam = round(0.8 * Q24)
    honest = SetpointMap(BATTERY_3)(lam)[0]
    plant.on_frame(agent.frame(mc_name(3), {"State": 1, "Lambda": lam, "Resets": 0}), 0.04)
    plant.on_frame(agent.frame(setpoint_name(3), {"Enable": 1, "PowerSetpoint": honest}), 0.04)
    assert plant.unit(3).p_set == pytest.approx(honest / 100)
    lie = round(LIE_SETPOINT_KW * 100)
    plant.on_frame(agent.frame(setpoint_name(3), {"Enable": 1, "PowerSetpoint": lie}), 0.05)
    plant.on_frame(agent.frame(mc_name(3), {"State": 1, "Lambda": lam, "Resets": 0}), 0.06)
    assert plant.counters["setpoint_inconsistent"] == 1
    assert plant.counters["setpoint_inconsistent_agent_3"] == 1
    assert plant.unit(3).p_set == pytest.approx((lie if obey else honest) / 100)
    assert plant.unit(3).setpoint_rx == 0.05   # the agent is alive: no setpoint timeout


# --------------------------------------------------------------------------- the runs


def _liar(kind: str, agent: int = 3) -> Callable[[Path], dict[str, Any]]:
    def run(out: Path) -> dict[str, Any]:
        with lying(kind, agent):
            return busrun.run_in_process(CASE, out, DURATION_S, channel=f"liar-{out.name}")
    return run


def _plain(**kw: Any) -> Callable[[Path], dict[str, Any]]:
    return lambda out: busrun.run_in_process(CASE, out, DURATION_S,
                                             channel=f"liar-{out.name}", **kw)


RUNS: dict[str, Callable[[Path], dict[str, Any]]] = {
    "honest": _plain(),
    "lie-setpoint": _liar("LIE-SETPOINT"),
    "lie-lambda": _liar("LIE-LAMBDA"),
    "lie-ramp": _liar("LIE-RAMP"),
    "lie-lambda-hub": _liar("LIE-LAMBDA", 1),   # the star's hub, the agent pinned to ρ
    "insecure": _plain(insecure=True),
    "router-outage": _plain(router_silent=((4.0, 4.6),)),
    "forged-mc": _plain(inject=spoofed_mc(1)),
    "plant-faults": _plain(plant_faults=((2, "overcurrent", 3.0, 3.5),
                                         (4, "power_limit", 4.5, 6.5))),
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], tuple[Path, dict]]:
    done: dict[str, tuple[Path, dict]] = {}

    def get(name: str) -> tuple[Path, dict]:
        if name not in done:
            out = tmp_path_factory.mktemp(name)
            done[name] = out, RUNS[name](out)
        return done[name]
    return get


def _final(out: Path) -> tuple[np.ndarray, np.ndarray, float]:
    last = np.genfromtxt(out / "trajectory.csv", delimiter=",", names=True)[-1]
    lam = np.array([last[f"lam_{i}"] for i in range(1, 5)])
    return lam, np.array([last[f"p_{i}"] for i in range(1, 5)]), float(last["rho"])


def _named(m: dict) -> set[tuple[str, str]]:
    return {(a["kind"], a["node"]) for a in m["anomalies"]}


def test_an_agent_commanding_its_plant_off_its_lambda_is_named_and_not_obeyed(runs) -> None:
    """Agent 3 publishes its honest λ but commands its plant 89 kW (41.2 kW honest)."""
    out, m = runs("lie-setpoint")
    assert m["verdict"]["exit_code"] != 0
    assert ("setpoint_inconsistent", "agent_3") in _named(m)
    assert [n for k, n in _named(m) if k == "setpoint_inconsistent"] == ["agent_3"]
    _, p, _ = _final(out)
    assert abs(p[2] - LIE_SETPOINT_KW) > 10, p   # the plant held its last consistent one
    assert m["node_counters"]["plant"]["counters"]["setpoint_inconsistent_agent_3"] > 100


@pytest.mark.parametrize("run, liar", [("lie-lambda", "agent_3"), ("lie-ramp", "agent_3"),
                                       ("lie-lambda-hub", "agent_1")])
def test_an_agent_telling_a_lambda_off_the_others_is_named(run: str, liar: str,
                                                          runs) -> None:
    """0.3 % of ρ above its λ, with setpoints consistent with the lie (LIE-LAMBDA), or a
    lie growing by 0.002 cu/kWh per s (LIE-RAMP): not converged, the liar named as the
    most likely cause. A leaf's lie leaves it apart from the others; the hub's (pinned to
    ρ) drags every λ along, and the fleet agreeing off ρ names the pinned agent."""
    out, m = runs(run)
    assert m["verdict"]["exit_code"] == EXIT_NOT_CONVERGED
    assert [n for k, n in _named(m) if k == "lambda_outlier"] == [liar]
    assert m["verdict"]["cause"].startswith(f"lambda_outlier [{liar}]")


@pytest.mark.parametrize("seed", range(3))
def test_an_honest_agent_s_setpoints_stay_consistent_through_loss_and_reordering(
        seed: int, runs) -> None:
    """The honest run's agents' frames as a lossy, reordering bus would deliver them: 30 %
    of the MC frames lost, one setpoint in four ahead of its tick's MC frame. No honest
    setpoint is called inconsistent (the plant would hold a genuine one)."""
    import random

    from sim.run.buslog import read_log

    out, _ = runs("honest")
    log = read_log(out / "run.log", n=CASE.n, ts=CASE.ts)
    rng = random.Random(seed)
    for cfg in agent_configs_from_scenario(CASE):
        events = [e for e in log.dispatch[cfg.id] if e[1] != "mc" or rng.random() > 0.3]
        for k in range(1, len(events)):
            if (events[k][1] == "setpoint" and events[k - 1][1] == "mc"
                    and events[k][0] == events[k - 1][0] and rng.random() < .25):
                events[k - 1], events[k] = events[k], events[k - 1]
        check, outcomes = SetpointCheck(cfg.battery, period=CASE.ts), []
        for t, what, a, b in events:
            if what == "mc":
                done = check.mc(a, b, t)
                outcomes += [done[0]] if done else []
            else:
                outcomes += [c for c, _ in check.setpoint(Setpoint(bool(a), b, t))]
        assert Check.INCONSISTENT not in outcomes, cfg.id
        assert outcomes.count(Check.CONSISTENT) > 0.9 * len(outcomes)


def test_the_honest_run_is_clean_and_within_the_tolerance(runs) -> None:
    out, m = runs("honest")
    assert m["verdict"]["exit_code"] == 0, m["anomalies"]
    lam, _, rho = _final(out)
    assert np.max(np.abs(lam - rho)) < 1e-3


def test_a_tighter_tolerance_than_the_run_reached_is_not_converged(runs, tmp_path) -> None:
    out, m = runs("honest")
    rc = main(["analyze", str(out), "--tolerance", f"{m['final_error'] / 2:g}", "--no-plot",
               "--out", str(tmp_path)])
    again = json.loads((tmp_path / "metrics.json").read_text())
    assert rc == EXIT_NOT_CONVERGED and "tolerance" in again["verdict"]["reasons"][0]


def test_an_insecure_run_is_an_anomaly_and_exits_3_at_best(runs, tmp_path) -> None:
    out, m = runs("insecure")
    assert ("insecure_keys", "run") in _named(m) and m["insecure"] is True
    assert m["verdict"]["converged"] and m["verdict"]["exit_code"] == EXIT_ANOMALIES
    # its log alone (no run facts, no keys): the frames verify with the public demo key
    shutil.copy(out / "run.log", tmp_path / "capture.log")
    rc = main(["analyze", str(tmp_path / "capture.log"), "--case", "1", "--no-plot"])
    assert rc == EXIT_ANOMALIES
    again = json.loads((tmp_path / "capture-analysis" / "metrics.json").read_text())
    assert again["anomalies"] == m["anomalies"]


# --------------------------------------------------------------------------- one verdict


@pytest.mark.parametrize("run, kinds", [
    ("honest", set()),
    ("lie-setpoint", {"setpoint_inconsistent"}),
    ("lie-lambda", {"lambda_outlier"}),
    ("insecure", {"insecure_keys"}),
    ("forged-mc", {"auth_failed"}),
    ("router-outage", {"price_timeout", "agent_safe"}),
    ("plant-faults", {"plant_fault", "agent_safe", "power_limit"}),
])
def test_analyze_of_a_run_directory_gives_the_run_s_verdict(run: str, kinds: set[str],
                                                            runs, tmp_path: Path) -> None:
    """`analyze DIR` finds the run's scenario, keys, counters and facts there."""
    out, m = runs(run)
    assert kinds <= {a["kind"] for a in m["anomalies"]}, m["anomalies"]
    rc = main(["analyze", str(out), "--no-plot", "--out", str(tmp_path)])
    again = json.loads((tmp_path / "metrics.json").read_text())
    assert rc == m["verdict"]["exit_code"]
    assert again["verdict"] == m["verdict"]
    assert again["anomalies"] == m["anomalies"]


def test_analyze_reads_what_up_knew_beyond_the_log(runs, tmp_path: Path) -> None:
    """A node's death and a starved plant and router, as `up` leaves them in DIR/logs."""
    src, _ = runs("honest")
    out = tmp_path / "run"
    shutil.copytree(src, out)
    facts = json.loads((out / "logs" / "run_facts.json").read_text())
    facts.update(deaths=[["agent_2", 3.0, -9]], exit_codes={"agent_2": -9, "plant": 0})
    (out / "logs" / "run_facts.json").write_text(json.dumps(facts))
    rc = main(["analyze", str(out / "run.log"), "--case", "1", "--no-plot"])
    m = json.loads((out / "run-analysis" / "metrics.json").read_text())
    assert rc == EXIT_NOT_CONVERGED
    assert ("node_died", "agent_2") in _named(m)
    assert m["verdict"]["cause"].startswith("node_died [agent_2]")
    restored = RunFacts.from_json(facts, None)
    assert restored.deaths == [("agent_2", 3.0, -9)]
    assert RunFacts.from_json(restored.as_json(), None) == restored


# --------------------------------------------------------------------------- host overload


def _log_with_misses(agent_misses: list[int], ticks: int = 1000) -> LogContents:
    log = LogContents()
    for a, misses in enumerate(agent_misses, start=1):
        log.diag[a] = {"DeadlineMisses": misses}
        log.sequences[f"AGENT_{a}_MC"] = SequenceStats(frames=ticks - misses)
    return log


def _per_node(log: LogContents, counters: dict) -> list[Anomaly]:
    out = [Anomaly("deadline_misses", n, "…") for n in (*map("agent_{}".format, log.diag),
                                                        *counters)]
    return out + [Anomaly("price_timeout", "agent_1", "…"), Anomaly("agent_safe", "agent_1",
                                                                     "…")]


def test_every_node_late_at_once_is_one_host_overload() -> None:
    log = _log_with_misses([80, 120, 60, 90])
    counters = {"plant": {"ticks": 1000, "counters": {"deadline_miss": 70}},
                "router": {"ticks": 1000, "counters": {"deadline_miss": 50}}}
    out = _host_overload(log, RunFacts(node_counters=counters), _per_node(log, counters))
    assert [a.kind for a in out] == ["agent_safe", "host_overloaded"]
    host = out[-1]
    assert host.node == "host" and "6 of 6 nodes" in host.detail
    assert "worst 12.0 % at agent_2" in host.detail and "price_timeout ×1" in host.detail


def test_a_node_late_alone_is_still_named() -> None:
    log = _log_with_misses([0, 300, 0, 0])
    counters = {"plant": {"ticks": 1000, "counters": {"deadline_miss": 0}},
                "router": {"ticks": 1000, "counters": {"deadline_miss": 0}}}
    before = _per_node(log, counters)
    assert _host_overload(log, RunFacts(node_counters=counters), before) == before


def test_analyze_names_bad_run_facts(runs, tmp_path: Path, capsys) -> None:
    src, _ = runs("honest")
    out = tmp_path / "run"
    shutil.copytree(src, out)
    for bad in ('{"deaths": 7}', '{"time_scale": -1}', '[1, 2]', '{"boot_floors": [1]}'):
        (out / "logs" / "run_facts.json").write_text(bad)
        assert main(["analyze", str(out), "--no-plot"]) == 2, bad
        err = capsys.readouterr().err
        assert err.startswith("bess-ded: error:") and "run_facts.json" in err, (bad, err)


@pytest.mark.slow
@pytest.mark.realtime
def test_a_lying_device_on_restbus_is_named(tmp_path: Path) -> None:
    """The same liar as a device under test of `bess-ded restbus` (node processes on the
    wall clock, the operator's way to bring a device): started with the key file restbus
    made for agent 3 and nothing else. Expected at any load: exit ≠ 0, agent 3 named,
    the plant holding its last consistent setpoint."""
    import re
    import sys

    from conformance_run import with_device

    hint = re.compile(r"device under test: \S+, waited for up to .*?; e\.g\. (.*)$")
    out = tmp_path / "rb"
    code, log = with_device(["restbus", "--case", "1", "--dut", "3", "--duration", "6",
                             "--no-plot", "--out", str(out)], hint,
                            [sys.executable, str(Path(__file__).parent / "deviant_agent.py"),
                             "LIE-SETPOINT"])
    assert code != 0, log
    m = json.loads((out / "metrics.json").read_text())
    assert ("setpoint_inconsistent", "agent_3") in _named(m), log
    assert m["node_counters"]["plant"]["counters"]["setpoint_inconsistent_agent_3"] > 0
