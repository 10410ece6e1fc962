"""Fault injection on the host buses (docs/faults.md has the table and the measured numbers).

Most tests run case 1 (4 agents, star, pinned agent 1) with every node an OS process on
udp_multicast (``busrun.run``) and read the outcome back from the recording (run.log) and
the agents' own diagnostics frames. udp_multicast on loopback may lose a few frames in
bursts, so counts from the bus carry a stated tolerance; FaultyBus itself is tested
deterministically on the virtual bus with a fake clock at the end.

Those real-time runs (marked ``realtime``) assert only what holds at any load of the
host: outcomes, orderings, counters by cause, every tick accounted for, and latencies
counted in the nodes' own ticks or frames. Every timing window (SAFE entry after the
price timeout, the drop-out latency of a killed agent, the setpoint reaction to a plant
fault, the power-limit delta...) is asserted exactly on the simulated clock
(``busrun.run_in_process``, the ``*_simulated_clock`` tests).

Times in run.log are the recorder's receive times; t = 0 is the first ER_Price frame.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from conftest import assert_every_tick_accounted, lockstep_settling_ticks, settling_ticks

from firmware_py import contract
from firmware_py.config import agent_configs_from_scenario
from firmware_py.errors import FrameError
from firmware_py.faultinject import FaultyBus, RxFaults, neighbour_mc
from firmware_py.frames import FrameCodec, agent_of
from firmware_py.nodeio import JOIN_FRACTION, SYNC_S
from firmware_py.runtime import DIAG_EVERY, AgentRuntime
from sim.model.scenario import load_case, load_scenario
from sim.nodes import inject
from sim.run import busrun

pytestmark = pytest.mark.slow

CASE = load_case(1)
TS = CASE.ts                     # 10 ms
N = CASE.n                       # 4 agents
RHO = 0.8
FINAL_TOL = 1e-3                 # max|λ−ρ| at the end of a run
LOCKSTEP_SETTLING_S = 2.54       # case 1, lockstep simulation (tests/test_bus.py)
PRICE_PERIOD = contract.cycle_s("ER_Price", TS)      # 50 ms (DBC GenMsgCycleTime)
PRICE_TIMEOUT = contract.timeout_s("ER_Price", TS)   # 0.25 s
EPS = 1e-9                       # float slack of the simulated clock's k·Ts
LOAD_TOLERANT_S = 300.0          # waiting for a process: a deadline, not a duration
# every Diag page once: a count reaches the report on the agents' Diag pages
DIAG_ROUND_S = len(AgentRuntime.DIAG_PAGES) * DIAG_EVERY * TS
UDP_LOSS_TOL = 0.10              # udp_multicast on loopback loses at most this share of a burst
SAFE, RUNNING = contract.State.SAFE, contract.State.RUNNING

CODEC = FrameCodec()
STATUS_CYCLE = contract.cycle_s("PLANT_3_Status", TS)
SETPOINT_CYCLE = contract.cycle_s("AGENT_3_Setpoint", TS)


# --------------------------------------------------------------------------- helpers


def bus_opts(port: int) -> busrun.BusOptions:
    return busrun.BusOptions("udp_multicast", None, f'{{"port": {port}}}')


@dataclass
class Rec:
    t: float          # s after the first ER_Price frame
    name: str
    raw: dict[str, int]


def decode_log(out: Path) -> list[Rec]:
    """Every decodable frame of DIR/run.log with its raw signals, t = 0 at the first price."""
    recs: list[Rec] = []
    t0 = None
    for msg in can.LogReader(str(out / "run.log")):
        try:
            f = CODEC.decode(msg)
        except FrameError:
            continue
        if t0 is None:
            if f.name != "ER_Price":
                continue
            t0 = msg.timestamp
        recs.append(Rec(msg.timestamp - t0, f.name, dict(f.raw)))
    assert t0 is not None, "no ER_Price frame in run.log"
    return recs


def series(recs: list[Rec], name: str, sig: str) -> list[tuple[float, int]]:
    """``sig`` from every ``name`` frame that carries it (a multiplexed frame: its page)."""
    return [(r.t, r.raw[sig]) for r in recs if r.name == name and sig in r.raw]


def lam_error_at(recs: list[Rec], t: float, agents: range | list[int]) -> float:
    """max over ``agents`` of |λ_i − ρ| from the last MC frame at or before t."""
    worst = 0.0
    for i in agents:
        lam = [r.raw["Lambda"] for r in recs if r.name == f"AGENT_{i}_MC" and r.t <= t]
        assert lam, f"agent {i} sent no MC frame before t = {t}"
        worst = max(worst, abs(lam[-1] / 2**24 - RHO))
    return worst


def run_case(tmp: Path, port: int, duration: float, account: bool = True,
             **kw: Any) -> dict[str, Any]:
    """A real-time run of case 1. ``account``: check that every tick of every node is a
    frame or a counted deadline miss (not where the test forges frames with real IDs or
    restarts a node, which breaks the counter arithmetic by design)."""
    m = busrun.run(CASE, tmp, bus_opts(port), duration=duration, quiet=True, plot=False,
                   **kw)
    assert all(code == 0 for code in m["exit_codes"].values()), m["exit_codes"]
    # settling is measured from the first recorded price: a recording that missed the
    # start would make every timing below meaningless
    assert m["start_recorded"], "the recorder missed the start of the run"
    if account:
        assert_every_tick_accounted(tmp, m, TS)
    return m


_sim_channels = iter(range(1_000_000))


def run_simulated(tmp: Path, duration: float, **kw: Any) -> tuple[dict[str, Any], list[Rec]]:
    """Case 1 on the virtual bus, stepped on the simulated clock (busrun.run_in_process):
    the same nodes and frames, deterministic, t exact multiples of Ts."""
    m = busrun.run_in_process(CASE, tmp, duration, channel=f"faults-sim-{next(_sim_channels)}",
                              **kw)
    assert m["start_recorded"]
    return m, decode_log(tmp)


def frames_between(recs: list[Rec], name: str, t0: float, t1: float) -> int:
    """How many ``name`` frames were recorded with t0 < t < t1: a latency counted in a
    node's own frames (ticks), which a loaded host stretches in seconds but not in count."""
    return sum(1 for r in recs if r.name == name and t0 < r.t < t1)


def injected_losses(out: Path, agent: int) -> int:
    """FaultyBus's own count, printed by the agent at exit."""
    for line in (out / "logs" / f"agent_{agent}.log").read_text().splitlines():
        if line.startswith(f"agent {agent}: injected "):
            return int(line.split()[3])
    raise AssertionError(f"agent {agent} printed no injection summary")


def others_mc_while_running(out: Path, agent: int) -> int:
    """The other agents' MC frames in DIR/run.log (from the recorder's start, not t = 0)
    between ``agent``'s own first and last MC frame: what its receive path, and its
    injector, could see, however far apart a loaded host started the nodes."""
    own = contract.MC_BASE + agent
    others = {contract.MC_BASE + j for j in range(1, N + 1) if j != agent}
    frames = [(m.arbitration_id, m.timestamp) for m in can.LogReader(str(out / "run.log"))]
    t_own = [t for fid, t in frames if fid == own]
    return sum(1 for fid, t in frames if fid in others and t_own[0] <= t <= t_own[-1])


NEIGHBOURS = {1: [2, 3, 4], 2: [1], 3: [1], 4: [1]}   # case 1's star


# --------------------------------------------------------------------------- 1. loss


@pytest.fixture(scope="module")
def lossless(tmp_path_factory: pytest.TempPathFactory,
             udp_ports: Callable[[], int]) -> dict[str, Any]:
    """The fault-free reference run (0 % injected loss), 10 s."""
    out = tmp_path_factory.mktemp("lossless")
    m = run_case(out, udp_ports(), 10.0)
    m["settling_ticks"] = settling_ticks(out, m)
    return m


@pytest.mark.realtime
def test_lossless_reference_converges(lossless: dict[str, Any]) -> None:
    """Expected: the reference run settles (2 % band) within 2× the lockstep 2.54 s,
    counted in agent 1's own ticks, and ends below 1e-3; the recorder missed nothing."""
    assert lossless["final_error"] < FINAL_TOL
    assert lossless["frames_missed_by_recorder"] == 0
    assert round(LOCKSTEP_SETTLING_S / TS) == lockstep_settling_ticks(CASE)
    assert lossless["settling_ticks"] <= 2 * lockstep_settling_ticks(CASE)
    print(f"lossless settling {lossless['settling_time_s']:.2f} s "
          f"({lossless['settling_ticks']} ticks), final {lossless['final_error']:.1e}")


@pytest.mark.realtime
@pytest.mark.parametrize("loss", [0.05, 0.20])
def test_random_mc_loss(tmp_path: Path, udp_port: int, loss: float,
                        lossless: dict[str, Any]) -> None:
    """Expected: with loss P of the MC frames at every agent the system still converges
    (final max|λ−ρ| < 1e-3) and settles within 2× the lossless settling time (both
    counted in agent 1's ticks); each agent's
    LostFrames (diag) is within 0.5–2 × P × the neighbour MC frames recorded (the rest
    of the difference is udp's own loss and the diag's last page being ≤ 0.4 s old), and
    FaultyBus's own count of dropped frames within ±50 % of P × the MC frames of every
    other agent recorded while it ran (on udp_multicast the agent has no acceptance filter:
    its injector sees them all). The counts depend on how many frames the host let
    through, hence the bounds (the binomial spread alone is under 10 % of the mean)."""
    extra = {f"agent_{i}": ["--inject-rx-loss", str(loss), "--inject-seed", str(i)]
             for i in range(1, N + 1)}
    m = run_case(tmp_path, udp_port, 10.0, extra=extra)
    recs = decode_log(tmp_path)
    st, st0 = settling_ticks(tmp_path, m), lossless["settling_ticks"]
    print(f"loss {loss:.0%}: settling {st} ticks (lossless {st0}), "
          f"final {m['final_error']:.1e}, diag {m['node_diagnostics']}")
    assert m["final_error"] < FINAL_TOL
    assert st <= 2 * st0
    assert m["frames_missed_by_recorder"] == 0  # the loss is at the agents, not the bus
    mc_count = Counter(r.name for r in recs if r.name.endswith("_MC"))
    for i in range(1, N + 1):
        lost = m["node_diagnostics"][f"agent_{i}"]["LostFrames"]
        heard = sum(mc_count[f"AGENT_{j}_MC"] for j in NEIGHBOURS[i])
        # above: a starved host's own udp loss adds to the injected (2× leaves room for it:
        # 76 of 1003 heard at 5 % once, beside a QEMU guest and two scoring processes)
        assert 0.5 * loss * heard <= lost <= 2.0 * loss * heard, (i, lost, heard)
        others = others_mc_while_running(tmp_path, i)
        injected = injected_losses(tmp_path, i)
        assert 0.5 * loss * others <= injected <= 1.5 * loss * others, (i, injected, others)


# --------------------------------------------------------------------------- 2. delay/jitter


@pytest.mark.realtime
def test_delay_and_jitter_up_to_three_samples(tmp_path: Path, udp_port: int,
                                              lossless: dict[str, Any]) -> None:
    """Expected: MC frames delayed by 10 ms plus uniform 0–20 ms jitter (1–3 samples) at
    every agent: still converges (< 1e-3) and settles within 2× the lossless time
    (counted in agent 1's ticks); no agent counts an impersonation (the injector delays
    neighbours' frames only: an agent's own echo is its loopback, not a network path, and
    a delayed echo would only measure the host's starvation against RX-3's 4 payloads),
    and since the delay keeps each sender's order, LostFrames stays at udp's own few
    (< 2 % of what it hears)."""
    extra = {f"agent_{i}": ["--inject-rx-delay", "0.01", "--inject-rx-jitter", "0.02",
                            "--inject-seed", str(i)] for i in range(1, N + 1)}
    m = run_case(tmp_path, udp_port, 10.0, extra=extra)
    st = settling_ticks(tmp_path, m)
    print(f"delay 10 ms + jitter 20 ms: settling {st} ticks (lossless "
          f"{lossless['settling_ticks']}), final {m['final_error']:.1e}, "
          f"diag {m['node_diagnostics']}")
    assert m["final_error"] < FINAL_TOL
    assert st <= 2 * lossless["settling_ticks"]
    assert m["frames_missed_by_recorder"] == 0
    recs = decode_log(tmp_path)
    mc_count = Counter(r.name for r in recs if r.name.endswith("_MC"))
    for i in range(1, N + 1):
        d = m["node_diagnostics"][f"agent_{i}"]
        assert d["RejectedImpersonation"] == 0
        heard = sum(mc_count[f"AGENT_{j}_MC"] for j in NEIGHBOURS[i])
        assert d["LostFrames"] < 0.02 * heard, (i, d["LostFrames"], heard)


# --------------------------------------------------------------------------- 4. kill/restart


def _kill_restart_times(recs: list[Rec], alive1: list[tuple[float, int]]
                        ) -> tuple[float, float, float, float]:
    """(agent 4's last MC frame before the restart, agent 1's first tick counting fewer
    than 3 neighbours alive after it, restarted agent 4's first MC frame in RUNNING (only
    a RUNNING neighbour counts), agent 1's first tick counting 3 again after that)."""
    a4 = series(recs, "AGENT_4_MC", "State")
    last_before = max(t for t, _ in a4 if t < 7.5 - EPS)
    t_drop = next(t for t, v in alive1 if t > last_before and v < 3)
    first_after = min(t for t, v in a4 if t > t_drop and v == RUNNING)
    t_back = next(t for t, v in alive1 if t > first_after and v == 3)
    return last_before, t_drop, first_after, t_back


def run_kill_restart_simulated(tmp: Path) -> tuple[dict[str, Any], list[Rec],
                                                   list[tuple[float, int]]]:
    """agent_4 gone at 5 s, a fresh one from 7.5 s, on the simulated clock; with agent
    1's neighbours alive at every tick (the MC frame no longer carries the count: the
    DBC gave its bits to the MAC)."""
    alive1: list[tuple[float, int]] = []

    def observe(t: float, nodes: dict[str, Any]) -> None:
        alive1.append((t, nodes["agent_1"].neighbours_alive))

    m, recs = run_simulated(tmp, 15.0, restarts=[("agent_4", 5.0, 7.5)], observe=observe)
    return m, recs, alive1


def test_agent_killed_and_restarted_simulated_clock(tmp_path: Path) -> None:
    """Expected (exact, simulated clock): agent_4 gone at 5 s and a fresh agent_4 from
    7.5 s (busrun.run_in_process(restarts=...)). Agent 1 drops it (neighbours alive 3 → 2)
    no earlier than the 3·Ts neighbour timeout and within 3·Ts + Ts + one sample of
    transport after agent 4's last MC frame; agents 1–3 stay converged meanwhile (< 1e-3
    at 7.4 s); the restarted agent starts in INIT with a new boot counter (its syncs
    first: no frame of it is rejected), is RUNNING once it heard a price and counted by
    agent 1 one sample after its first RUNNING frame, and the whole system reconverges
    (< 1e-3 at 15 s)."""
    m, recs, alive1 = run_kill_restart_simulated(tmp_path)
    last_before, t_drop, first_after, t_back = _kill_restart_times(recs, alive1)
    assert last_before == pytest.approx(5.0 - TS)
    assert 3 * TS - EPS <= t_drop - last_before <= 3 * TS + TS + TS + EPS
    restarted = [t for t, _ in series(recs, "AGENT_4_MC", "State") if t > t_drop]
    assert restarted[0] == pytest.approx(7.5)  # as INIT: a fresh agent
    assert dict(series(recs, "AGENT_4_MC", "State"))[restarted[0]] == 0
    # RUNNING once it heard a price it can verify: its syncs at 7.5 s make the router
    # re-announce the price's at 7.51 s (heard at 7.52 s); it takes that sync at the end
    # of its join window (AUTH-26: 0.2 s after its syncs), then the next price frame
    price_cycle = contract.cycle_s("ER_Price", TS)
    join_s = JOIN_FRACTION * SYNC_S
    assert 7.5 + join_s < first_after <= 7.5 + join_s + price_cycle + TS + EPS
    assert t_back - first_after == pytest.approx(TS)
    assert lam_error_at(recs, 7.4, [1, 2, 3]) < FINAL_TOL
    assert m["final_error"] < FINAL_TOL
    d1 = m["node_diagnostics"]["agent_1"]
    assert d1["NeighbourTimeouts"] == 1 and d1["RejectedAuth"] == 0 and d1["Unsynced"] == 0
    assert "auth_failed" not in {a["kind"] for a in m["anomalies"]}, m["anomalies"]


FAILOVER = Path(__file__).resolve().parent.parent / "examples" / "failover_case1.toml"


def test_pinned_agent_killed_failover_simulated_clock(tmp_path: Path) -> None:
    """Issue 23.5 (exact, simulated clock): examples/failover_case1.toml is case 1 with ρ
    stepping 0.8 → 0.9 at 10 s. Agent 1, the star's centre and its only pinned agent, is
    killed at 5 s for good: the three leaves are cut off from each other and the price.
    The router hears agent 1's MC frames stop, and after the agents' neighbour timeout
    (3·Ts) plus a sample pins each leaf (a component of its own: the highest degree, 0,
    ties by id) with one ER_Command PIN each, repeated 3 times; the leaves follow the step
    (max|λ−ρ| ≤ 1e-3 over agents 2–4 at the end). The run's metrics list the three pins
    as events and one failover; the router's summary names it; the verdict judges agents
    2–4 only from agent 1's last frame on (buslog.failed_over): converged, with the kill's
    anomalies."""
    sc = load_scenario(FAILOVER)
    m = busrun.run_in_process(sc, tmp_path, sc.duration,
                              channel=f"faults-sim-{next(_sim_channels)}",
                              restarts=[("agent_1", 5.0, math.inf)])
    recs = decode_log(tmp_path)
    assert m["failovers"] == [{"t": pytest.approx(5.04), "pinned": [2, 3, 4]}]
    assert [(e["command"], e["target"]) for e in m["events"]] == [("pin", 2), ("pin", 3),
                                                                   ("pin", 4)]
    router = m["node_counters"]["router"]["counters"]
    assert router["failovers"] == 3 and router["command_frames"] == 9
    assert "failover t=5.04 s: pinned agents lost 1; pinned 2, 3, 4" in m["node_summaries"][-1]
    final = {i: series(recs, f"AGENT_{i}_MC", "Lambda")[-1][1] / 2**24 for i in (2, 3, 4)}
    assert max(abs(lam - 0.9) for lam in final.values()) <= FINAL_TOL, final
    assert all(series(recs, f"AGENT_{i}_MC", "State")[-1][1] == RUNNING for i in (2, 3, 4))
    # the failover is no anomaly, the kill is (agent 1 silent; its plant's setpoints stop);
    # the dead agent failed over from is judged no more: converged, with anomalies
    assert {(a["kind"], a["node"]) for a in m["anomalies"]} == {
        ("node_silent", "agent_1"), ("setpoint_timeout", "plant")}, m["anomalies"]
    assert m["verdict"]["converged"] and m["verdict"]["exit_code"] == 3
    assert m["final_error"] <= FINAL_TOL and m["settling_times_s"][-1] < 1.0


@pytest.mark.realtime
def test_agent_killed_and_restarted(tmp_path: Path, udp_port: int) -> None:
    """Expected (real processes, any load): agent_4 SIGKILLed at 5 s and restarted at
    7.5 s with the same argv and key file (its start-up takes as long as the host lets
    it; its boot counter moves on, so its frames are fresh): agent 1 counts one
    neighbour timeout, agents 1–3 stay converged while it is away, no frame is rejected
    as forged (the restarted agent's syncs come first), agent 4 comes back RUNNING, and
    the whole system reconverges (< 1e-3) by the end of the 20 s run if that leaves 2×
    the time the simulated-clock twin needs from agent 4's return (≈ 4.5 s), else agent
    4 is at least back in the consensus. The drop-out and rejoin latencies in ticks are
    asserted on the simulated clock (the MC frame does not carry agent 1's count of
    neighbours alive)."""
    def kill(specs: list[busrun.NodeSpec], _logdir: Path) -> None:
        spec = next(s for s in specs if s.name == "agent_4")
        assert spec.proc is not None
        spec.proc.send_signal(signal.SIGKILL)
        spec.proc.wait()

    def restart(specs: list[busrun.NodeSpec], logdir: Path) -> None:
        busrun.start(next(s for s in specs if s.name == "agent_4"), logdir)

    _, sim, alive1 = run_kill_restart_simulated(tmp_path / "simulated")
    _, _, sim_back, _ = _kill_restart_times(sim, alive1)
    need = next(t for t in (sim_back + 0.1 * k for k in range(100))
                if lam_error_at(sim, t, range(1, N + 1)) < FINAL_TOL) - sim_back
    m = run_case(tmp_path, udp_port, 20.0, account=False,
                 actions=[(5.0, kill), (7.5, restart)])
    recs = decode_log(tmp_path)
    a4 = series(recs, "AGENT_4_MC", "State")
    last_before = max(t for t, _ in a4 if t < 7.5 - EPS)
    first_after = min(t for t, v in a4 if t > 7.5 - EPS and v == RUNNING)
    err_gap = lam_error_at(recs, first_after - 0.1, [1, 2, 3])
    print(f"agent 4 silent from {last_before:.2f} s, RUNNING again at {first_after:.2f} s; "
          f"agents 1–3 before it: {err_gap:.1e}; final {m['final_error']:.1e}")
    assert 5.0 - TS <= last_before < first_after
    assert err_gap < FINAL_TOL
    t_end = max(r.t for r in recs)
    print(f"reconvergence budget {2 * need:.1f} s, had {t_end - first_after:.1f} s")
    if t_end - first_after >= 2 * need:
        assert m["final_error"] < FINAL_TOL
    else:  # the restart took the run's time: agent 4 must be back in the consensus
        assert series(recs, "AGENT_4_MC", "State")[-1][1] == RUNNING
    d1 = m["node_diagnostics"]["agent_1"]
    assert d1["NeighbourTimeouts"] >= 1 and d1["RejectedAuth"] == 0, d1
    assert "auth_failed" not in {a["kind"] for a in m["anomalies"]}, m["anomalies"]


# --------------------------------------------------------------------------- 5. router silent


def _silent_times(recs: list[Rec], throughout: bool = True
                  ) -> tuple[float, float, list[tuple[float, float]]]:
    """(last price before the gap, first after it, per agent (SAFE entry, RUNNING again))
    with the ordering every run must show: RUNNING before the gap (``throughout``: from
    1 s on; else within its last second, since a loaded host may delay a price past the
    timeout before the gap), SAFE from the entry until prices come back."""
    price_t = [r.t for r in recs if r.name == "ER_Price"]
    last = max(t for t in price_t if t < 6.0)
    back = min(t for t in price_t if t > 6.0)
    out = []
    for i in range(1, N + 1):
        st = series(recs, f"AGENT_{i}_MC", "State")
        t_safe = next(t for t, v in st if t > last and v == SAFE)
        before = [v for t, v in st if (1.0 if throughout else last - 1.0) < t <= last]
        assert (all if throughout else any)(v == RUNNING for v in before), i
        t_run = next(t for t, v in st if t > t_safe and v == RUNNING)
        assert all(v == SAFE for t, v in st if t_safe <= t < back), i
        out.append((t_safe, t_run))
    return last, back, out


def test_router_silent_sends_agents_safe_simulated_clock(tmp_path: Path) -> None:
    """Expected (exact, simulated clock): the router silent from 5 to 7 s: the gap in
    prices is 2 s + one price period; every agent enters SAFE (State = 3) after the
    0.25 s price timeout and within it + one sample of transport + one tick (the timeout
    is strict) of the last price frame, returns to RUNNING one sample after the first
    price frame after the gap, and the system reconverges (< 1e-3 at 10 s)."""
    m, recs = run_simulated(tmp_path, 10.0, router_silent=[(5.0, 7.0)])
    last, back, times = _silent_times(recs)
    assert back - last == pytest.approx(2.0 + PRICE_PERIOD)
    for t_safe, t_run in times:
        assert PRICE_TIMEOUT < t_safe - last <= PRICE_TIMEOUT + 2 * TS + EPS
        assert 0 < t_run - back <= TS + EPS
    assert m["final_error"] < FINAL_TOL


@pytest.mark.realtime
def test_router_silent_sends_agents_safe(tmp_path: Path, udp_port: int) -> None:
    """Expected (real processes, any load): the router silent from 5 to 7 s: every agent
    enters SAFE (State = 3) more than the 0.25 s price timeout after the last price frame
    (its own clock can only be later than the recorder's) and within the timeout's 25
    ticks + 2 of its own, stays SAFE until prices come back, returns to RUNNING with its
    first or second tick after the first price frame after the gap, and the system
    reconverges (< 1e-3 at 10 s)."""
    m = run_case(tmp_path, udp_port, 10.0, extra={"router": ["--silent", "5:7"]})
    recs = decode_log(tmp_path)
    last, back, times = _silent_times(recs, throughout=False)
    entry = [frames_between(recs, f"AGENT_{i}_MC", last, t_safe) + 1
             for i, (t_safe, _) in enumerate(times, start=1)]
    resume = [frames_between(recs, f"AGENT_{i}_MC", back, t_run) + 1
              for i, (_, t_run) in enumerate(times, start=1)]
    print(f"SAFE entry {[round(1000 * (t - last), 1) for t, _ in times]} ms, {entry} ticks "
          f"after the last price; RUNNING again {[round(1000 * (t - back), 1) for _, t in times]}"
          f" ms, {resume} ticks after it came back; final {m['final_error']:.1e}")
    assert back - last > 2.0 - PRICE_PERIOD
    for (t_safe, t_run), n_entry, n_resume in zip(times, entry, resume, strict=True):
        assert t_safe - last > PRICE_TIMEOUT
        assert n_entry <= round(PRICE_TIMEOUT / TS) + 2
        assert t_run > back and n_resume <= 2
    assert m["final_error"] < FINAL_TOL


# --------------------------------------------------------------------------- 3. crafted frames

INJECT_COUNT = 100
CRAFTED = [  # kind, inject flags, diag signal that must count it, agents that must count it
    ("forge", [], "RejectedAuth", [1, 2, 3, 4]),
    ("corrupt", [], "RejectedAuth", [1, 2, 3, 4]),
    ("dlc", [], "RejectedDlc", [1, 2, 3, 4]),
    ("range", [], "RejectedRange", [1, 2, 3, 4]),
    ("unknown", [], "RejectedUnknownId", [1, 2, 3, 4]),
    ("impersonate", ["--target", "2"], "RejectedImpersonation", [2]),
]


def inject_cmd(port: int, kind: str, count: int, rate: float, *flags: str) -> list[str]:
    return [sys.executable, "-m", "sim.cli", "inject", kind, "--count", str(count),
            "--rate", str(rate), "--interface", "udp_multicast",
            "--bus-config", f'{{"port": {port}}}', *flags]


@pytest.mark.realtime
def test_crafted_frames_counted_by_cause(tmp_path: Path, udp_port: int) -> None:
    """Expected: 100 frames each of forged ER_Price (a guessed MAC), corrupted ER_Price,
    DLC 5, an ER_Command for agent 40 (out of range), unknown IDs and AGENT_2_MC
    impersonation, sent by `bess-ded inject` processes from t = 2 s: every agent counts
    each kind under its cause, ≥ 90 % of the injected count (udp loses a few % of a
    burst) and never more than injected (agent 2's neighbours also verify, and reject,
    the frames impersonating it). Secured frames prove themselves one by one, so
    the untrusted-source alarm the forgeries raise on ER_Price does not stop the genuine
    prices (docs/safety-model.md); only agent 2 counts the impersonation; the system
    still ends below 1e-3 at 12 s (or when the injectors are done, if that is later)."""
    chain = " && ".join(subprocess.list2cmdline(
        inject_cmd(udp_port, kind, INJECT_COUNT, 500, *flags)) for kind, flags, _, _ in CRAFTED)
    procs: list[subprocess.Popen[bytes]] = []

    def inject_and_wait(_specs: list[busrun.NodeSpec], _logdir: Path) -> None:
        """Runs the six injectors to their end while the nodes run (the run's clock goes
        on meanwhile): on a loaded host their start-up alone can outlast the run."""
        procs.append(subprocess.Popen(["sh", "-c", chain], stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT))
        with contextlib.suppress(subprocess.TimeoutExpired):
            procs[0].wait(timeout=LOAD_TOLERANT_S)
        # let one whole round of Diag pages go out after the last injection, however late
        # the injectors ended on a loaded host (the run's clock went on meanwhile)
        time.sleep(DIAG_ROUND_S + 0.5)

    out = ""
    try:
        m = run_case(tmp_path, udp_port, 12.0, account=False,
                     actions=[(2.0, inject_and_wait)])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            out = p.communicate()[0].decode()
    assert procs and procs[0].returncode == 0, out
    assert out.count("bess-ded inject: sent 100") == len(CRAFTED), out
    diag = m["node_diagnostics"]
    print(f"crafted frames: diag {diag}")
    expected: dict[tuple[str, int], int] = {}
    for _kind, _flags, sig, agents in CRAFTED:
        for i in agents:
            expected[(sig, i)] = expected.get((sig, i), 0) + INJECT_COUNT
    for j in NEIGHBOURS[2]:  # agent 2's neighbours verify the impersonating frames too
        expected[("RejectedAuth", j)] += INJECT_COUNT
    for (sig, i), n in sorted(expected.items()):
        got = diag[f"agent_{i}"][sig]
        assert int((1 - UDP_LOSS_TOL) * n) <= got <= n, (sig, i, got)
    for i in range(1, N + 1):
        if i != 2:
            assert diag[f"agent_{i}"]["RejectedImpersonation"] == 0, (i, diag)
    assert m["final_error"] < FINAL_TOL


# As root the recorder's socket buffer is forced to 16 MiB (busrun), which holds the whole
# flood (~10 MB of socket buffers) even if the recorder did not run at all: every flood
# frame must then be in run.log (measured: 10,000 of 10,000). Without root the buffer
# stays at the ~208 KiB default and udp_multicast drops what it cannot hold (measured
# 90-96 % before the buffer was enlarged).
FLOOD_SEEN_MIN = 1.0 if os.geteuid() == 0 else 0.80


def normal_rate() -> float:
    """Frames/s the nodes send in case 1, from the DBC's cycle times: every ER_Balance
    page each balance cycle, and a sync per secured ID every sync cycle."""
    cyc = {name: CODEC.database.get_message_by_name(name).cycle_time / 1000
           for name in ("AGENT_1_Setpoint", "AGENT_1_Diag", "PLANT_1_Status", "ER_Price",
                        "ER_Balance", "ER_Price_Sync")}
    secured = [fid for fid in contract.SECURED_IDS if (agent_of(fid) or 0) <= N]
    syncs = len(secured) / cyc["ER_Price_Sync"]
    return (N * (1 / TS + 1 / cyc["AGENT_1_Setpoint"] + 1 / cyc["AGENT_1_Diag"]
                 + 1 / cyc["PLANT_1_Status"]) + 1 / cyc["ER_Price"]
            + len(CODEC.pages("ER_Balance")) / cyc["ER_Balance"] + syncs)


ALIVE_NAMES = {*(f"AGENT_{i}_MC" for i in range(1, N + 1)), "PLANT_1_Status", "ER_Price"}
ALIVE_IDS = {CODEC.frame_id(n) for n in ALIVE_NAMES}


@pytest.mark.realtime
def test_flood_of_random_frames(tmp_path: Path, udp_port: int) -> None:
    """Expected: 10,000 random frames (random 11-bit IDs, DLCs, payloads) at 5000/s from
    t = 2 s: no node crashes (all exit 0), nothing hangs (the run, less the wait for the
    flood, ends within a generous deadline), every node still sends after the flood, the
    system still converges (< 1e-3 at the end), and the recorder logged every flood frame
    (matched by ID and payload; ≥ 80 % without root, see FLOOD_SEEN_MIN). How much of
    the nominal traffic got through on a loaded host is `bess-ded bench`'s figure."""
    procs: list[subprocess.Popen[bytes]] = []
    waited = [0.0]

    def flood_and_wait(_specs: list[busrun.NodeSpec], _logdir: Path) -> None:
        """The flood runs to its end while the nodes run (see test_crafted_frames...)."""
        t = time.monotonic()
        procs.append(subprocess.Popen(inject_cmd(udp_port, "flood", 10_000, 5000),
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT))
        with contextlib.suppress(subprocess.TimeoutExpired):
            procs[0].wait(timeout=LOAD_TOLERANT_S)
        waited[0] = time.monotonic() - t

    out = ""
    t_start = time.monotonic()
    try:
        m = run_case(tmp_path, udp_port, 12.0, account=False,
                     actions=[(2.0, flood_and_wait)])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            out = p.communicate()[0].decode()
    wall = time.monotonic() - t_start - waited[0]
    # the injector ran to its end (not killed at the deadline) and said so, once
    assert len(procs) == 1 and procs[0].returncode == 0, out
    assert out.splitlines().count("bess-ded inject: sent 10000 flood frames") == 1, out
    flood = Counter((f.arbitration_id, bytes(f.data)) for f in inject.frames("flood", 10_000))
    seen: Counter[tuple[int, bytes]] = Counter()
    t_first = t_last = None
    for msg in can.LogReader(str(tmp_path / "run.log")):
        key = (msg.arbitration_id, bytes(msg.data))
        if seen[key] < flood[key]:
            seen[key] += 1
            t_first = msg.timestamp if t_first is None else t_first
            t_last = msg.timestamp
    flood_seen = sum(seen.values())
    normal = m["frames_recorded"] - flood_seen
    assert t_first is not None and t_last is not None
    rate = flood_seen / (t_last - t_first)
    print(f"flood: recorded {flood_seen}/10000 flood frames at {rate:.0f} frames/s, "
          f"{normal} normal frames, total {m['frames_recorded']}, wall {wall:.1f} s, "
          f"final {m['final_error']:.1e}, diag {m['node_diagnostics']}")
    # a bound, not a count: without root how much udp_multicast drops depends on the load
    assert FLOOD_SEEN_MIN * 10_000 <= flood_seen <= 10_000
    print(f"normal traffic {normal / (normal_rate() * 12.0):.0%} of nominal")
    after = {CODEC.decode(msg).name for msg in can.LogReader(str(tmp_path / "run.log"))
             if msg.timestamp > t_last and msg.arbitration_id in ALIVE_IDS
             and (msg.arbitration_id, bytes(msg.data)) not in flood}
    assert after == ALIVE_NAMES, after
    assert m["final_error"] < FINAL_TOL
    assert wall < 12.0 + busrun.STOP_GRACE_S + LOAD_TOLERANT_S / 5


# --------------------------------------------------------------------------- 6. plant faults


PLANT_FAULTS = ("3:overcurrent:5:7", "2:power_limit:4:10")


@pytest.fixture(scope="module")
def plant_faults(tmp_path_factory: pytest.TempPathFactory,
                 udp_ports: Callable[[], int]) -> tuple[dict[str, Any], list[Rec]]:
    """One real-time 13 s run with both plant faults: over-current on BESS 3 (5–7 s) and a
    power limit on BESS 2 (4–10 s), times from the plant's first tick."""
    out = tmp_path_factory.mktemp("plant")
    extra = [a for f in PLANT_FAULTS for a in ("--fault", f)]
    m = run_case(out, udp_ports(), 13.0, extra={"plant": extra})
    return m, decode_log(out)


@pytest.fixture(scope="module")
def plant_faults_simulated(tmp_path_factory: pytest.TempPathFactory
                           ) -> tuple[dict[str, Any], list[Rec]]:
    """The same run on the simulated clock (busrun.run_in_process(plant_faults=...))."""
    return run_simulated(tmp_path_factory.mktemp("plant-sim"), 13.0, plant_faults=PLANT_FAULTS)


def _window(s: list[tuple[float, int]]) -> tuple[float, float]:
    """First and last time a flag was set."""
    on = [t for t, v in s if v]
    assert on, "flag never set"
    return on[0], on[-1]


def _overcurrent(recs: list[Rec]) -> tuple[float, float, float, float]:
    """(first and last status with FaultOverCurrent on BESS 3, agent 3's first setpoint
    with Enable = 0 from the first, its first with Enable = 1 after the last), with the
    behaviour every run must show: agent 3 SAFE and disabled in between, the others
    RUNNING."""
    f0, f1 = _window(series(recs, "PLANT_3_Status", "FaultOverCurrent"))
    en = series(recs, "AGENT_3_Setpoint", "Enable")
    off0 = next(t for t, v in en if t >= f0 and v == 0)
    on1 = next(t for t, v in en if t > f1 and v == 1)
    st3 = series(recs, "AGENT_3_MC", "State")
    assert all(v == SAFE for t, v in st3 if off0 < t < f1)
    assert all(v == 0 for t, v in en if off0 <= t <= f1)
    for i in (1, 2, 4):
        assert all(v == RUNNING for t, v in series(recs, f"AGENT_{i}_MC", "State") if t > 1.0)
    return f0, f1, off0, on1


def test_overcurrent_sends_agent_safe_simulated_clock(
        plant_faults_simulated: tuple[dict[str, Any], list[Rec]]) -> None:
    """Expected (exact, simulated clock): PLANT_3_Status has FaultOverCurrent from 5 s to
    its last status before 7 s; agent 3 is SAFE (State = 3, setpoint Enable = 0) meanwhile
    — Enable = 0 within one setpoint period of the first faulty status — and enabled again
    within one status + one setpoint period of the last faulty status (the clear is only
    seen with the next status frame); the other agents stay RUNNING; the system
    reconverges."""
    m, recs = plant_faults_simulated
    f0, f1, off0, on1 = _overcurrent(recs)
    assert f0 == pytest.approx(5.0) and f1 == pytest.approx(7.0 - STATUS_CYCLE)
    assert 0 < off0 - f0 <= SETPOINT_CYCLE + EPS
    assert 0 < on1 - f1 <= STATUS_CYCLE + SETPOINT_CYCLE + EPS
    assert m["final_error"] < FINAL_TOL


@pytest.mark.realtime
def test_overcurrent_sends_agent_safe(plant_faults: tuple[dict[str, Any], list[Rec]]) -> None:
    """Expected (real processes, any load): agent 3 goes SAFE (Enable = 0) while
    PLANT_3_Status flags FaultOverCurrent, the others stay RUNNING; counted in frames,
    at most one of agent 3's setpoints (one in flight as the status arrived) is still
    enabled after the first faulty status, and it is enabled again no later than its
    second setpoint after the status that clears the flag; the system reconverges."""
    m, recs = plant_faults
    f0, f1, off0, on1 = _overcurrent(recs)
    late_off = frames_between(recs, "AGENT_3_Setpoint", f0, off0)
    t_clear = min(r.t for r in recs if r.name == "PLANT_3_Status" and r.t > f1)
    late_on = frames_between(recs, "AGENT_3_Setpoint", t_clear, on1)
    print(f"over-current: Enable=0 {1000 * (off0 - f0):.1f} ms ({late_off} setpoints) after "
          f"the fault flag, Enable=1 {1000 * (on1 - f1):.1f} ms ({late_on} setpoints after "
          f"the clear); final {m['final_error']:.1e}")
    assert late_off <= 1 and on1 > t_clear and late_on <= 1
    assert m["final_error"] < FINAL_TOL


def _power_limit(recs: list[Rec]) -> tuple[float, float, list[float]]:
    """(first and last status with PowerLimited on BESS 2, BESS 2's power from 0.5 s into
    the window), with agent 2 RUNNING throughout."""
    f0, f1 = _window(series(recs, "PLANT_2_Status", "PowerLimited"))
    assert all(v == RUNNING for t, v in series(recs, "AGENT_2_MC", "State") if t > 1.0)
    power_scale = CODEC.database.get_message_by_name("PLANT_2_Status").get_signal_by_name(
        "Power").scale
    clamped = [v * power_scale for t, v in series(recs, "PLANT_2_Status", "Power")
               if f0 + 0.5 < t < f1]
    assert clamped and max(clamped) <= 50.0 + 0.5
    return f0, f1, clamped


def test_power_limit_keeps_agent_running_simulated_clock(
        plant_faults_simulated: tuple[dict[str, Any], list[Rec]]) -> None:
    """Expected (exact, simulated clock): PowerLimited set in PLANT_2_Status for the 6 s
    power-limit window, agent 2 stays RUNNING throughout, BESS 2's power is clamped to
    50 kW (of the ≈ 56 kW it is dispatched at ρ = 0.8), and ER_Balance's grid power is
    ≈ 6 kW higher while clamped than after the clamp is released (± 1 kW)."""
    m, recs = plant_faults_simulated
    f0, f1, _ = _power_limit(recs)
    assert f0 == pytest.approx(4.0) and f1 == pytest.approx(10.0 - STATUS_CYCLE)
    grid_scale = CODEC.database.get_message_by_name("ER_Balance").get_signal_by_name(
        "GridPower").scale
    grid = series(recs, "ER_Balance", "GridPower")

    def mean(a: float, b: float) -> float:
        v = [x * grid_scale for t, x in grid if a < t < b]
        assert v, (a, b)
        return sum(v) / len(v)

    during, after = mean(f1 - 1.5, f1 - 0.1), mean(f1 + 1.0, f1 + 2.5)
    assert during - after == pytest.approx(56.07 - 50.0, abs=1.0)
    assert m["final_error"] < FINAL_TOL


@pytest.mark.realtime
def test_power_limit_keeps_agent_running(plant_faults: tuple[dict[str, Any], list[Rec]]
                                         ) -> None:
    """Expected (real processes, any load): PowerLimited is set in PLANT_2_Status for a
    window, agent 2 stays RUNNING throughout, BESS 2's power is clamped to 50 kW while
    it lasts, and the system reconverges after it. (The grid-power delta is asserted on
    the simulated clock: on a loaded host the averaging windows are not comparable.)"""
    m, recs = plant_faults
    f0, f1, clamped = _power_limit(recs)
    print(f"power limit {f1 - f0:.2f} s: P2 ≤ {max(clamped):.2f} kW")
    assert f1 > f0
    assert m["final_error"] < FINAL_TOL


# --------------------------------------------------------------------------- 7. shutdown


def _wait_for_frames(port: int, names: list[str], timeout: float = LOAD_TOLERANT_S,
                     keys: Path | None = None) -> None:
    """Block until a frame of each message was heard on the bus and verified (the test
    kit's Tester: decoded with the CRC and range checks, its MAC and freshness checked
    with the run's key set ``keys``, which `up` writes before it starts any node, or the
    public --insecure keys): the nodes are up and signing."""
    from sim.testkit import Tester

    end = time.monotonic() + timeout
    if keys is not None:  # the router's key file is the last one `up` writes
        while not (keys / "router.key").exists():
            assert time.monotonic() < end, f"no key set in {keys} within {timeout} s"
            time.sleep(0.05)
    with can.Bus(interface="udp_multicast", port=port, fd=False) as bus, \
            Tester(bus, keys) as tester:
        for name in names:
            tester.expect(name, max(0.0, end - time.monotonic()), since=float("-inf"))
        assert tester.rejected["auth"] == 0, tester.summary()


@pytest.mark.realtime
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_agent_and_router_stop_cleanly(tmp_path: Path, udp_port: int, sig: int) -> None:
    """Expected: `bess-ded agent` and `bess-ded router` receiving SIGINT/SIGTERM stop by
    themselves (no kill: a generous deadline, since how fast is the host's load's) with
    exit code 0 and print their summary line. (Idle they take ~0.1 s: printed.)"""
    cfg = agent_configs_from_scenario(CASE)[0]
    (tmp_path / "agent_1.toml").write_text(cfg.to_toml())
    bus = ["--interface", "udp_multicast", "--bus-config", f'{{"port": {udp_port}}}']
    cmds = {"agent": [sys.executable, "-m", "sim.cli", "agent", "--config",
                      str(tmp_path / "agent_1.toml"), "--insecure", *bus],
            "router": [sys.executable, "-m", "sim.cli", "router", "--case", "1", "--insecure",
                       *bus]}
    procs = {k: subprocess.Popen(v, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for k, v in cmds.items()}
    try:
        _wait_for_frames(udp_port, ["AGENT_1_MC", "ER_Price"])
        for p in procs.values():
            p.send_signal(sig)
        t0 = time.monotonic()
        results = {}
        for k, p in procs.items():
            out, err = p.communicate(timeout=LOAD_TOLERANT_S)
            results[k] = (p.returncode, time.monotonic() - t0, err.decode())
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
    print({k: (rc, round(dt, 2)) for k, (rc, dt, _) in results.items()})
    for k, (rc, _dt, err) in results.items():
        assert rc == 0, (k, err)
    assert "agent 1: state=" in results["agent"][2]
    assert "router: t=" in results["router"][2]


def _procs_with(text: str) -> list[int]:
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if text in cmdline.read_bytes().decode(errors="replace"):
                found.append(int(cmdline.parent.name))
        except OSError:
            continue
    return found


@pytest.mark.realtime
def test_up_interrupted_stops_every_node(tmp_path: Path, udp_port: int) -> None:
    """Expected: `bess-ded up` interrupted with SIGINT once the run is under way stops
    every node (no process with the run's port in its command line remains), exits by
    itself (a generous deadline; idle: < STOP_GRACE_S + 2 s, printed) with 130
    ("interrupted"), and run.log holds the frames recorded until then, with the metrics,
    trajectory and plot of what was recorded, and a verdict that says it was interrupted."""
    port_text = f'"port": {udp_port}'   # in up's argv and in every node's --bus-config
    p = subprocess.Popen([sys.executable, "-m", "sim.cli", "up", "--case", "1",
                          "--duration", "60", "--out", str(tmp_path), "--interface",
                          "udp_multicast", "--bus-config", f"{{{port_text}}}"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        _wait_for_frames(udp_port, [*(f"AGENT_{i}_MC" for i in range(1, N + 1)), "ER_Price"],
                         keys=tmp_path / "keys")
        # the recording's receive times are wall-clock ones (the processes' own clocks,
        # nothing to inject): a second of them before the interrupt, for recs[-1].t > 0.5
        time.sleep(1.0)
        assert len(_procs_with(port_text)) == 1 + N + 2, _procs_with(port_text)
        p.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        out, err = p.communicate(timeout=LOAD_TOLERANT_S)
        dt = time.monotonic() - t0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    print(f"up stopped {dt:.2f} s after SIGINT, rc {p.returncode}")
    assert p.returncode == 130, err.decode()
    assert "interrupted" in err.decode()
    assert _procs_with(port_text) == []
    recs = decode_log(tmp_path)
    assert {r.name for r in recs} >= {f"AGENT_{i}_MC" for i in range(1, N + 1)}
    assert recs[-1].t > 0.5
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["verdict"]["interrupted"] and m["verdict"]["exit_code"] == 130
    assert ("interrupted", "run") in {(a["kind"], a["node"]) for a in m["anomalies"]}
    assert (tmp_path / "trajectory.csv").is_file() and (tmp_path / "bus_run.png").is_file()
    assert "verdict: INTERRUPTED" in out.decode()


# --------------------------------------------------------------------------- FaultyBus units


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def vbus(request: pytest.FixtureRequest):
    """A sender and a receiver on a virtual channel of their own."""
    ch = f"faultinject-{request.node.name}"
    tx = can.Bus(interface="virtual", channel=ch, receive_own_messages=False)
    rx = can.Bus(interface="virtual", channel=ch, receive_own_messages=False)
    yield tx, rx
    tx.shutdown()
    rx.shutdown()


def _mc(k: int, fid: int = 0x101) -> can.Message:
    return can.Message(arbitration_id=fid, is_extended_id=False, data=k.to_bytes(4, "little"))


def _drain(fb: FaultyBus) -> list[can.Message]:
    out = []
    while (m := fb.recv(timeout=0)) is not None:
        out.append(m)
    return out


def test_faultybus_loss_rate_and_counts(vbus) -> None:
    """Expected: loss 0.2 on 5000 MC frames drops 20 % ± 1.5 %, counted in ``dropped``;
    the 500 non-MC frames (ER_Price) all pass; nothing is duplicated or invented."""
    tx, rx = vbus
    fb = FaultyBus(rx, RxFaults(loss=0.2, seed=1), clock=FakeClock())
    for k in range(5000):
        tx.send(_mc(k))
        if k % 10 == 0:
            tx.send(_mc(k, fid=0x010))
    got = _drain(fb)
    mc = [m for m in got if m.arbitration_id == 0x101]
    assert len(got) - len(mc) == 500
    assert fb.dropped + len(mc) == 5000
    assert fb.dropped == pytest.approx(1000, abs=75)
    ks = [int.from_bytes(m.data, "little") for m in mc]
    assert ks == sorted(set(ks))


def test_faultybus_same_seed_same_losses(vbus) -> None:
    """Expected: the loss pattern is a function of the seed (reproducible runs)."""
    tx, rx = vbus
    patterns = []
    for _ in range(2):
        fb = FaultyBus(rx, RxFaults(loss=0.3, seed=7), clock=FakeClock())
        for k in range(200):
            tx.send(_mc(k))
        patterns.append([int.from_bytes(m.data, "little") for m in _drain(fb)])
    assert patterns[0] == patterns[1] and len(patterns[0]) < 200


def test_faultybus_fixed_delay_keeps_order(vbus) -> None:
    """Expected: a fixed 50 ms delay holds every MC frame until t + 50 ms (fake clock),
    releases them in arrival order, counts each in ``delayed``; others pass at once."""
    tx, rx = vbus
    clock = FakeClock()
    fb = FaultyBus(rx, RxFaults(delay=0.05), clock=clock)
    for k in range(20):
        tx.send(_mc(k))
    tx.send(_mc(99, fid=0x010))
    first = _drain(fb)
    assert [m.arbitration_id for m in first] == [0x010]
    assert fb.delayed == 20
    clock.t = 0.049
    assert _drain(fb) == []
    clock.t = 0.05
    assert [int.from_bytes(m.data, "little") for m in _drain(fb)] == list(range(20))


def test_faultybus_jitter_bound(vbus) -> None:
    """Expected: delay 10 ms + jitter 20 ms: each frame (one per 10 ms, polled every 1 ms
    of fake time) comes out between 10 and 30 ms after it arrived (+ the 1 ms polling
    step), never earlier, and frames of one ID come out in the order they arrived."""
    tx, rx = vbus
    clock = FakeClock()
    fb = FaultyBus(rx, RxFaults(delay=0.01, jitter=0.02, seed=3), clock=clock)
    arrived: dict[int, float] = {}
    released: dict[int, float] = {}
    for step in range(5100):
        clock.t = step * 1e-3
        if step < 5000 and step % 10 == 0:      # one MC frame per Ts, like a neighbour
            tx.send(_mc(step // 10))
            arrived[step // 10] = clock.t
        for m in _drain(fb):
            released[int.from_bytes(m.data, "little")] = clock.t
    assert sorted(released) == list(range(500))
    order = sorted(released, key=lambda k: (released[k], k))
    assert order == list(range(500))        # held, never reordered (CAN keeps one ID's order)
    holds = [released[k] - arrived[k] for k in arrived]
    assert min(holds) >= 0.01 - 1e-9
    assert max(holds) <= 0.03 + 1e-3 + 1e-9
    assert max(holds) > 0.025 and min(holds) < 0.015   # the jitter really spreads


def test_faultybus_rejects_bad_parameters(vbus) -> None:
    """Expected: loss outside [0, 1) or a negative delay/jitter is refused."""
    _, rx = vbus
    for faults in (RxFaults(loss=1.0), RxFaults(loss=-0.1), RxFaults(delay=-1),
                   RxFaults(jitter=-0.01)):
        with pytest.raises(ValueError):
            FaultyBus(rx, faults)


def test_an_agent_injects_faults_on_its_neighbours_frames_only() -> None:
    """Expected: the agent's injector (`neighbour_mc`) matches every other agent's MC
    frame and neither its own (its echo) nor any other frame."""
    own = neighbour_mc(3)
    mc = [can.Message(arbitration_id=contract.MC_BASE + i, is_extended_id=False)
          for i in range(1, contract.N_AGENTS_MAX + 1)]
    assert [m.arbitration_id - contract.MC_BASE for m in mc if own(m)] == [
        i for i in range(1, contract.N_AGENTS_MAX + 1) if i != 3]
    assert all(neighbour_mc(None)(m) for m in mc)
    assert not own(can.Message(arbitration_id=contract.MC_BASE, is_extended_id=False))
