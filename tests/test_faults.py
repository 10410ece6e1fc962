"""Fault injection on the host buses (docs/faults.md has the table and the measured numbers).

Most tests run case 1 (4 agents, star, pinned agent 1) with every node an OS process on
udp_multicast (``busrun.run``) and read the outcome back from the recording (run.log) and
the agents' own diagnostics frames. udp_multicast on loopback may lose a few frames in
bursts, so counts from the bus carry a stated tolerance; FaultyBus itself is tested
deterministically on the virtual bus with a fake clock at the end.

Times in run.log are the recorder's receive times; t = 0 is the first ER_Price frame.
"""

from __future__ import annotations

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

from firmware_py.config import agent_configs_from_scenario
from firmware_py.errors import FrameError
from firmware_py.faultinject import FaultyBus, RxFaults
from firmware_py.frames import FrameCodec
from sim import busrun, inject
from sim.scenario import load_case

pytestmark = pytest.mark.slow

CASE = load_case(1)
TS = CASE.ts                     # 10 ms
N = CASE.n                       # 4 agents
RHO = 0.8
FINAL_TOL = 1e-3                 # max|λ−ρ| at the end of a run
LOCKSTEP_SETTLING_S = 2.54       # case 1, lockstep simulation (tests/test_bus.py)
PRICE_PERIOD = 0.05              # ER_Price cycle (DBC GenMsgCycleTime)
PRICE_TIMEOUT = 25 * TS          # 0.25 s
SCHED_SLACK = 0.010              # one more Ts of OS scheduling / recorder latency on 2 cores
UDP_LOSS_TOL = 0.10              # udp_multicast on loopback loses at most this share of a burst
SAFE, RUNNING = 3, 1

CODEC = FrameCodec()
STATUS_CYCLE = CODEC.database.get_message_by_name("PLANT_3_Status").cycle_time / 1000
SETPOINT_CYCLE = CODEC.database.get_message_by_name("AGENT_3_Setpoint").cycle_time / 1000


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
    return [(r.t, r.raw[sig]) for r in recs if r.name == name]


def lam_error_at(recs: list[Rec], t: float, agents: range | list[int]) -> float:
    """max over ``agents`` of |λ_i − ρ| from the last MC frame at or before t."""
    worst = 0.0
    for i in agents:
        lam = [r.raw["Lambda"] for r in recs if r.name == f"AGENT_{i}_MC" and r.t <= t]
        assert lam, f"agent {i} sent no MC frame before t = {t}"
        worst = max(worst, abs(lam[-1] / 2**24 - RHO))
    return worst


def run_case(tmp: Path, port: int, duration: float, **kw: Any) -> dict[str, Any]:
    m = busrun.run(CASE, tmp, bus_opts(port), duration=duration, quiet=True, **kw)
    assert all(code == 0 for code in m["exit_codes"].values()), m["exit_codes"]
    # settling is measured from the first recorded price: a recording that missed the
    # start would make every timing below meaningless
    assert m["start_recorded"], "the recorder missed the start of the run"
    return m


def injected_losses(out: Path, agent: int) -> int:
    """FaultyBus's own count, printed by the agent at exit."""
    for line in (out / "logs" / f"agent_{agent}.log").read_text().splitlines():
        if line.startswith(f"agent {agent}: injected "):
            return int(line.split()[3])
    raise AssertionError(f"agent {agent} printed no injection summary")


NEIGHBOURS = {1: [2, 3, 4], 2: [1], 3: [1], 4: [1]}   # case 1's star


# --------------------------------------------------------------------------- 1. loss


@pytest.fixture(scope="module")
def lossless(tmp_path_factory: pytest.TempPathFactory,
             udp_ports: Callable[[], int]) -> dict[str, Any]:
    """The fault-free reference run (0 % injected loss), 10 s."""
    out = tmp_path_factory.mktemp("lossless")
    return run_case(out, udp_ports(), 10.0)


def test_lossless_reference_converges(lossless: dict[str, Any]) -> None:
    """Expected: the reference run settles (2 % band) within 2× the lockstep 2.54 s and
    ends below 1e-3; no agent counts a lost frame beyond udp's own few."""
    assert lossless["final_error"] < FINAL_TOL
    assert lossless["frames_missed_by_recorder"] == 0
    st = lossless["settling_time_s"]
    assert st is not None and st < 2 * LOCKSTEP_SETTLING_S
    print(f"lossless settling {st:.2f} s, final {lossless['final_error']:.1e}")


@pytest.mark.parametrize("loss", [0.05, 0.20])
def test_random_mc_loss(tmp_path: Path, udp_port: int, loss: float,
                        lossless: dict[str, Any]) -> None:
    """Expected: with loss P of the MC frames at every agent the system still converges
    (final max|λ−ρ| < 1e-3) and settles within 2× the lossless settling time; each agent's
    LostFrames (diag) is within ±50 % of P × the neighbour MC frames recorded (the rest
    of the difference is udp's own loss and the diag's last page being ≤ 0.4 s old)."""
    extra = {f"agent_{i}": ["--inject-rx-loss", str(loss), "--inject-seed", str(i)]
             for i in range(1, N + 1)}
    m = run_case(tmp_path, udp_port, 10.0, extra=extra)
    recs = decode_log(tmp_path)
    st, st0 = m["settling_time_s"], lossless["settling_time_s"]
    print(f"loss {loss:.0%}: settling {st} s (lossless {st0:.2f} s), "
          f"final {m['final_error']:.1e}, diag {m['node_diagnostics']}")
    assert m["final_error"] < FINAL_TOL
    assert st is not None and st <= 2 * st0
    assert m["frames_missed_by_recorder"] == 0  # the loss is at the agents, not the bus
    mc_count = Counter(r.name for r in recs if r.name.endswith("_MC"))
    for i in range(1, N + 1):
        lost = m["node_diagnostics"][f"agent_{i}"]["LostFrames"]
        heard = sum(mc_count[f"AGENT_{j}_MC"] for j in NEIGHBOURS[i])
        assert 0.5 * loss * heard <= lost <= 1.5 * loss * heard, (i, lost, heard)
        # every injected loss of a neighbour frame is noticed: the firmware's count
        # cannot be far below what FaultyBus dropped on the neighbours' IDs
        assert injected_losses(tmp_path, i) > 0


# --------------------------------------------------------------------------- 2. delay/jitter


def test_delay_and_jitter_up_to_three_samples(tmp_path: Path, udp_port: int,
                                              lossless: dict[str, Any]) -> None:
    """Expected: MC frames delayed by 10 ms plus uniform 0–20 ms jitter (1–3 samples) at
    every agent: still converges (< 1e-3) and settles within 2× the lossless time; no
    agent mistakes its own delayed echo for an impersonation, and since the delay keeps
    each sender's order, LostFrames stays at udp's own few (< 2 % of what it hears)."""
    extra = {f"agent_{i}": ["--inject-rx-delay", "0.01", "--inject-rx-jitter", "0.02",
                            "--inject-seed", str(i)] for i in range(1, N + 1)}
    m = run_case(tmp_path, udp_port, 10.0, extra=extra)
    st = m["settling_time_s"]
    print(f"delay 10 ms + jitter 20 ms: settling {st} s (lossless "
          f"{lossless['settling_time_s']:.2f} s), final {m['final_error']:.1e}, "
          f"diag {m['node_diagnostics']}")
    assert m["final_error"] < FINAL_TOL
    assert st is not None and st <= 2 * lossless["settling_time_s"]
    assert m["frames_missed_by_recorder"] == 0
    recs = decode_log(tmp_path)
    mc_count = Counter(r.name for r in recs if r.name.endswith("_MC"))
    for i in range(1, N + 1):
        d = m["node_diagnostics"][f"agent_{i}"]
        assert d["RejectedImpersonation"] == 0
        heard = sum(mc_count[f"AGENT_{j}_MC"] for j in NEIGHBOURS[i])
        assert d["LostFrames"] < 0.02 * heard, (i, d["LostFrames"], heard)


# --------------------------------------------------------------------------- 4. kill/restart


def test_agent_killed_and_restarted(tmp_path: Path, udp_port: int) -> None:
    """Expected: agent_4 SIGKILLed at 5 s: agent 1 drops it (NeighboursAlive 3 → 2) within
    3·Ts + one period (+ 10 ms scheduling slack) of agent 4's last MC frame; agents 1–3
    stay converged. Restarted at 7.5 s with the same argv, it rejoins (NeighboursAlive
    back to 3) and the whole system reconverges (< 1e-3 at 15 s)."""
    def kill(specs: list[busrun.NodeSpec], _logdir: Path) -> None:
        spec = next(s for s in specs if s.name == "agent_4")
        assert spec.proc is not None
        spec.proc.send_signal(signal.SIGKILL)
        spec.proc.wait()

    def restart(specs: list[busrun.NodeSpec], logdir: Path) -> None:
        busrun.start(next(s for s in specs if s.name == "agent_4"), logdir)

    m = run_case(tmp_path, udp_port, 15.0, actions=[(5.0, kill), (7.5, restart)])
    recs = decode_log(tmp_path)
    a4 = [r.t for r in recs if r.name == "AGENT_4_MC"]
    last_before = max(t for t in a4 if t < 7.5)
    alive1 = series(recs, "AGENT_1_MC", "NeighboursAlive")
    t_drop = next(t for t, v in alive1 if t > last_before and v < 3)
    latency = t_drop - last_before
    t_back = next(t for t, v in alive1 if t > t_drop and v == 3)
    first_after = min(t for t in a4 if t > 7.5)
    err_gap = lam_error_at(recs, 7.4, [1, 2, 3])
    print(f"drop-out detected {1000 * latency:.1f} ms after agent 4's last frame; "
          f"rejoined {1000 * (t_back - first_after):.1f} ms after its first new frame "
          f"(t = {t_back:.2f} s); agents 1–3 at 7.4 s: {err_gap:.1e}; "
          f"final {m['final_error']:.1e}")
    assert 4.9 < last_before < 5.3
    assert latency <= 3 * TS + TS + SCHED_SLACK
    assert err_gap < FINAL_TOL
    assert t_back < 10.0
    assert m["final_error"] < FINAL_TOL
    assert m["node_diagnostics"]["agent_1"]["NeighbourTimeouts"] >= 1


# --------------------------------------------------------------------------- 5. router silent


def test_router_silent_sends_agents_safe(tmp_path: Path, udp_port: int) -> None:
    """Expected: the router silent from 5 to 7 s: every agent enters SAFE (State = 3)
    within 0.25 s + one price period (50 ms) after the last price frame, returns to
    RUNNING within one price period (+ slack) of the first price frame after the gap,
    and the system reconverges (< 1e-3 at 10 s)."""
    m = run_case(tmp_path, udp_port, 10.0, extra={"router": ["--silent", "5:7"]})
    recs = decode_log(tmp_path)
    price_t = [r.t for r in recs if r.name == "ER_Price"]
    last = max(t for t in price_t if t < 6.0)
    back = min(t for t in price_t if t > 6.0)
    assert 1.9 < back - last < 2.1
    entry, resume = [], []
    for i in range(1, N + 1):
        st = series(recs, f"AGENT_{i}_MC", "State")
        t_safe = next(t for t, v in st if t > last and v == SAFE)
        assert all(v == RUNNING for t, v in st if 1.0 < t <= last)
        t_run = next(t for t, v in st if t > t_safe and v == RUNNING)
        assert all(v == SAFE for t, v in st if t_safe <= t < back)
        entry.append(t_safe - last)
        resume.append(t_run - back)
    print(f"SAFE entry {[round(1000 * x, 1) for x in entry]} ms after the last price; "
          f"RUNNING again {[round(1000 * x, 1) for x in resume]} ms after it came back; "
          f"final {m['final_error']:.1e}; final diag State "
          f"{[d['State'] for d in m['node_diagnostics'].values()]}")
    assert all(PRICE_TIMEOUT < x <= PRICE_TIMEOUT + PRICE_PERIOD for x in entry)
    assert all(0 <= x <= PRICE_PERIOD + SCHED_SLACK for x in resume)
    assert m["final_error"] < FINAL_TOL


# --------------------------------------------------------------------------- 3. crafted frames

INJECT_COUNT = 100
CRAFTED = [  # kind, inject flags, diag signal that must count it, agents that must count it
    ("crc", [], "RejectedCrc", [1, 2, 3, 4]),
    ("dlc", [], "RejectedDlc", [1, 2, 3, 4]),
    ("range", [], "RejectedRange", [1, 2, 3, 4]),
    ("repeat", [], "RepeatedCounter", [1, 2, 3, 4]),
    ("unknown", [], "RejectedUnknownId", [1, 2, 3, 4]),
    ("impersonate", ["--target", "2"], "RejectedImpersonation", [2]),
]


def inject_cmd(port: int, kind: str, count: int, rate: float, *flags: str) -> list[str]:
    return [sys.executable, "-m", "sim.cli", "inject", kind, "--count", str(count),
            "--rate", str(rate), "--interface", "udp_multicast",
            "--bus-config", f'{{"port": {port}}}', *flags]


def test_crafted_frames_counted_by_cause(tmp_path: Path, udp_port: int) -> None:
    """Expected: 100 frames each of bad CRC, DLC 5, ρ = 127 (out of range), one repeated
    counter, unknown IDs (all ER_Price-shaped, so every agent sees them) and AGENT_2_MC
    impersonation, sent by `bess-ded inject` processes from t = 2 s: every agent counts
    each kind under its cause, ≥ 90 % of the injected count (udp loses a few % of a
    burst; for `repeat` also minus the ≤ 2 real price frames that interleave and make the
    next injected one new data), and never more than injected (for `repeat`, plus the one
    real price frame that may carry the same counter 3 right after an injected one: the
    router cycles its 16 counters every 0.8 s and the burst lasts 0.2 s, and that frame is
    rightly no new data); only agent 2 counts the impersonation; the system still ends
    below 1e-3 at 12 s."""
    chain = " && ".join(subprocess.list2cmdline(
        inject_cmd(udp_port, kind, INJECT_COUNT, 500, *flags)) for kind, flags, _, _ in CRAFTED)
    procs: list[subprocess.Popen[bytes]] = []

    def start_injector(_specs: list[busrun.NodeSpec], _logdir: Path) -> None:
        procs.append(subprocess.Popen(["sh", "-c", chain], stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT))

    try:
        m = run_case(tmp_path, udp_port, 12.0, actions=[(2.0, start_injector)])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            out = p.communicate()[0].decode()
    assert procs and procs[0].returncode == 0, out
    assert out.count("bess-ded inject: sent 100") == len(CRAFTED), out
    diag = m["node_diagnostics"]
    print(f"crafted frames: diag {diag}")
    floor = int((1 - UDP_LOSS_TOL) * INJECT_COUNT)
    for _kind, _flags, sig, agents in CRAFTED:
        for i in range(1, N + 1):
            got = diag[f"agent_{i}"][sig]
            if i in agents:
                repeat = sig == "RepeatedCounter"
                lo, hi = (floor - 2, INJECT_COUNT + 1) if repeat else (floor, INJECT_COUNT)
                assert lo <= got <= hi, (sig, i, got)
            elif sig == "RejectedImpersonation":
                assert got == 0, (sig, i, got)
    assert m["final_error"] < FINAL_TOL


# As root the recorder's socket buffer is forced to 16 MiB (busrun), which holds the whole
# flood (~10 MB of socket buffers) even if the recorder did not run at all: every flood
# frame must then be in run.log (measured: 10,000 of 10,000). Without root the buffer
# stays at the ~208 KiB default and udp_multicast drops what it cannot hold (measured
# 90-96 % before the buffer was enlarged).
FLOOD_SEEN_MIN = 1.0 if os.geteuid() == 0 else 0.80


def normal_rate() -> float:
    """Frames/s the nodes send in case 1, from the DBC's cycle times."""
    cyc = {name: CODEC.database.get_message_by_name(name).cycle_time / 1000
           for name in ("AGENT_1_Setpoint", "AGENT_1_Diag", "PLANT_1_Status", "ER_Price",
                        "ER_Balance")}
    return (N * (1 / TS + 1 / cyc["AGENT_1_Setpoint"] + 1 / cyc["AGENT_1_Diag"]
                 + 1 / cyc["PLANT_1_Status"]) + 1 / cyc["ER_Price"] + 1 / cyc["ER_Balance"])


def test_flood_of_random_frames(tmp_path: Path, udp_port: int) -> None:
    """Expected: 10,000 random frames (random 11-bit IDs, DLCs, payloads) at 5000/s from
    t = 2 s: no node crashes (all exit 0), nothing hangs (the run ends on time), the
    system still converges (< 1e-3 at 12 s), and the recorder logged every flood frame
    (matched by ID and payload; ≥ 80 % without root, see FLOOD_SEEN_MIN) on top of ≥ 90 %
    of the nominal normal traffic for the 12 s."""
    procs: list[subprocess.Popen[bytes]] = []

    def start_flood(_specs: list[busrun.NodeSpec], _logdir: Path) -> None:
        procs.append(subprocess.Popen(inject_cmd(udp_port, "flood", 10_000, 5000),
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT))

    t_start = time.monotonic()
    try:
        m = run_case(tmp_path, udp_port, 12.0, actions=[(2.0, start_flood)])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            out = p.communicate()[0].decode()
    wall = time.monotonic() - t_start
    assert "sent 10000 flood frames" in out, out
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
    assert flood_seen >= FLOOD_SEEN_MIN * 10_000
    assert normal >= 0.9 * normal_rate() * 12.0
    assert m["final_error"] < FINAL_TOL
    assert wall < 12.0 + 20.0


# --------------------------------------------------------------------------- 6. plant faults


@pytest.fixture(scope="module")
def plant_faults(tmp_path_factory: pytest.TempPathFactory,
                 udp_ports: Callable[[], int]) -> tuple[dict[str, Any], list[Rec]]:
    """One 13 s run with both plant faults: over-current on BESS 3 (5–7 s) and a power
    limit on BESS 2 (4–10 s), times from the plant's first tick."""
    out = tmp_path_factory.mktemp("plant")
    m = run_case(out, udp_ports(), 13.0, extra={
        "plant": ["--fault", "3:overcurrent:5:7", "--fault", "2:power_limit:4:10"]})
    return m, decode_log(out)


def _window(s: list[tuple[float, int]]) -> tuple[float, float]:
    """First and last time a flag was set."""
    on = [t for t, v in s if v]
    assert on, "flag never set"
    return on[0], on[-1]


def test_overcurrent_sends_agent_safe(plant_faults: tuple[dict[str, Any], list[Rec]]) -> None:
    """Expected: while PLANT_3_Status has FaultOverCurrent (2 s), agent 3 is SAFE
    (State = 3, setpoint Enable = 0) — Enable = 0 within one setpoint period (50 ms, + Ts
    slack) of the first faulty status — and enabled again within one status + one setpoint
    period (50 + 50 ms, + slack) of the last faulty status (the clear is only seen with
    the next status frame); the other agents stay RUNNING; the system reconverges."""
    m, recs = plant_faults
    f0, f1 = _window(series(recs, "PLANT_3_Status", "FaultOverCurrent"))
    assert 1.9 < f1 - f0 < 2.1
    en = series(recs, "AGENT_3_Setpoint", "Enable")
    off0 = next(t for t, v in en if t >= f0 and v == 0)
    on1 = next(t for t, v in en if t > f1 and v == 1)
    st3 = series(recs, "AGENT_3_MC", "State")
    assert all(v == SAFE for t, v in st3 if off0 + 0.02 < t < f1)
    assert all(v == 0 for t, v in en if off0 <= t <= f1)
    for i in (1, 2, 4):
        assert all(v == RUNNING for t, v in series(recs, f"AGENT_{i}_MC", "State") if t > 1.0)
    print(f"over-current: Enable=0 {1000 * (off0 - f0):.1f} ms after the fault flag, "
          f"Enable=1 {1000 * (on1 - f1):.1f} ms after it cleared; final {m['final_error']:.1e}")
    assert off0 - f0 <= SETPOINT_CYCLE + SCHED_SLACK
    assert on1 - f1 <= STATUS_CYCLE + SETPOINT_CYCLE + SCHED_SLACK
    assert m["final_error"] < FINAL_TOL


def test_power_limit_keeps_agent_running(plant_faults: tuple[dict[str, Any], list[Rec]]
                                         ) -> None:
    """Expected: PowerLimited set in PLANT_2_Status for the 6 s power-limit window, agent 2
    stays RUNNING throughout, BESS 2's power is clamped to 50 kW (of the ≈ 56 kW it is
    dispatched at ρ = 0.8), and ER_Balance's grid power is ≈ 6 kW higher while clamped
    than after the clamp is released (± 1 kW)."""
    m, recs = plant_faults
    f0, f1 = _window(series(recs, "PLANT_2_Status", "PowerLimited"))
    assert 5.8 < f1 - f0 < 6.2
    assert all(v == RUNNING for t, v in series(recs, "AGENT_2_MC", "State") if t > 1.0)
    power_scale = CODEC.database.get_message_by_name("PLANT_2_Status").get_signal_by_name(
        "Power").scale
    clamped = [v * power_scale for t, v in series(recs, "PLANT_2_Status", "Power")
               if f0 + 0.5 < t < f1]
    assert clamped and max(clamped) <= 50.0 + 0.5
    grid_scale = CODEC.database.get_message_by_name("ER_Balance").get_signal_by_name(
        "GridPower").scale
    grid = series(recs, "ER_Balance", "GridPower")

    def mean(a: float, b: float) -> float:
        v = [x * grid_scale for t, x in grid if a < t < b]
        assert v, (a, b)
        return sum(v) / len(v)

    during, after = mean(f1 - 1.5, f1 - 0.1), mean(f1 + 1.0, f1 + 2.5)
    print(f"power limit: P2 ≤ {max(clamped):.2f} kW, grid {during:.2f} kW clamped vs "
          f"{after:.2f} kW after")
    assert during - after == pytest.approx(56.07 - 50.0, abs=1.0)
    assert m["final_error"] < FINAL_TOL


# --------------------------------------------------------------------------- 7. shutdown


def _wait_for_frames(port: int, ids: set[int], timeout: float = 30.0) -> None:
    """Block until a frame of each ID was heard on the bus (the nodes are up)."""
    missing = set(ids)
    with can.Bus(interface="udp_multicast", port=port, fd=False) as bus:
        end = time.monotonic() + timeout
        while missing and time.monotonic() < end:
            msg = bus.recv(timeout=0.2)
            if msg is not None:
                missing.discard(msg.arbitration_id)
    assert not missing, f"no frames from {sorted(missing)} within {timeout} s"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_agent_and_router_stop_cleanly(tmp_path: Path, udp_port: int, sig: int) -> None:
    """Expected: `bess-ded agent` and `bess-ded router` receiving SIGINT/SIGTERM stop
    within 2 s with exit code 0 and print their summary line."""
    cfg = agent_configs_from_scenario(CASE)[0]
    (tmp_path / "agent_1.toml").write_text(cfg.to_toml())
    bus = ["--interface", "udp_multicast", "--bus-config", f'{{"port": {udp_port}}}']
    cmds = {"agent": [sys.executable, "-m", "sim.cli", "agent", "--config",
                      str(tmp_path / "agent_1.toml"), *bus],
            "router": [sys.executable, "-m", "sim.cli", "router", "--case", "1", *bus]}
    procs = {k: subprocess.Popen(v, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for k, v in cmds.items()}
    try:
        _wait_for_frames(udp_port, {0x101, 0x010})
        for p in procs.values():
            p.send_signal(sig)
        t0 = time.monotonic()
        results = {}
        for k, p in procs.items():
            out, err = p.communicate(timeout=2.0)
            results[k] = (p.returncode, time.monotonic() - t0, err.decode())
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
    print({k: (rc, round(dt, 2)) for k, (rc, dt, _) in results.items()})
    for k, (rc, dt, err) in results.items():
        assert rc == 0, (k, err)
        assert dt < 2.0
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


def test_up_interrupted_stops_every_node(tmp_path: Path, udp_port: int) -> None:
    """Expected: `bess-ded up` interrupted with SIGINT once the run is under way stops
    every node (no process with the run's port in its command line remains), exits
    within STOP_GRACE_S + 2 s with 130 ("interrupted"), and run.log holds the frames
    recorded until then."""
    port_text = f'"port": {udp_port}'   # in up's argv and in every node's --bus-config
    p = subprocess.Popen([sys.executable, "-m", "sim.cli", "up", "--case", "1",
                          "--duration", "60", "--out", str(tmp_path), "--interface",
                          "udp_multicast", "--bus-config", f"{{{port_text}}}"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        _wait_for_frames(udp_port, {0x101, 0x102, 0x103, 0x104, 0x010})
        time.sleep(1.0)
        assert len(_procs_with(port_text)) == 1 + N + 2, _procs_with(port_text)
        p.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        out, err = p.communicate(timeout=busrun.STOP_GRACE_S + 2.0)
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
