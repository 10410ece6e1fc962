"""Micro-benchmarks of the control core, the simulator, the codec, the authentication and
the bus: what ``bess-ded bench`` prints (docs/performance.md). Not a test (nothing passes
or fails): numbers, with the machine they were measured on (``machine_info``). Each
section is one function in BENCHES (``quick`` → ``Table``); ``run_benches`` runs them
with the garbage collector off while timing; the timings are medians over repetitions.

Over 500 lines: one function per bench section (BENCHES), independent of each
other; one file keeps the table of sections next to what they measure.
"""

from __future__ import annotations

import gc
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from firmware_py.controllers import Controller, ControllerState, consensus_error

if TYPE_CHECKING:
    from sim.bench.realtime import CapacityPlan


@dataclass
class Table:
    """One section of the bench output."""

    title: str
    headers: list[str]
    rows: list[list[str]]
    note: str = ""
    data: dict[str, Any] = field(default_factory=dict)  # machine-readable, for --json
    align: str | None = None  # one 'l' or 'r' per column (textfmt.table's default: None)


# A bench section: quick flag → Table. Keep `--quick` sections to a few seconds each.
Bench = Callable[[bool], Table]


# --------------------------------------------------------------------------- sections


def controller_step(quick: bool) -> Table:
    """µs per agent step: consensus_error + controller.step, every kind, fixed and float.

    The input is realistic: the hub of case 1 (agent 1 of the star: three neighbours
    plus the price, the most work any agent there does), fed the λ its neighbours
    held in a lockstep run, sample by sample: the transient, the resets and the
    settled tail, so branches are taken as in a real run.
    """
    from firmware_py.controllers import KINDS, ControllerConfig, make_controller
    from sim.model.lockstep import run_lockstep
    from sim.model.scenario import load_case

    sc = load_case(1)
    tr = run_lockstep(sc, fixed=False)
    samples = tr.t.size
    reps = 7 if quick else 41
    hub = 0
    others = [j for j in range(sc.n) if j != hub]
    rho = float(tr.rho[0])

    cells = []  # (kind, arithmetic, timing arguments)
    for kind in KINDS:
        cfg = ControllerConfig(kind=kind, k=sc.controller.k, h=sc.controller.h, ts=sc.ts,
                               dwell=1.0 if kind == "dwell" else 0.0)
        for fixed in (True, False):
            ctrl = make_controller(cfg, fixed)
            q = ctrl.quantise
            w = q(1.0, "weight")
            inputs = [(q(float(tr.lam[k, hub])),
                       [(w, q(float(tr.lam[k, j]))) for j in others]) for k in range(samples)]
            args = (ctrl, inputs, q(1.0, "pin"), q(rho, "rho"),
                    ctrl.initial_state(sc.lambda0[hub]))
            _time_steps(*args)  # warm up
            cells.append((kind, "fixed" if fixed else "float", args))

    # Repetitions round-robin over the cells, so a burst of load from another process
    # hits every cell alike instead of skewing one; the median drops the outliers.
    times: dict[tuple[str, str], list[float]] = {(k, a): [] for k, a, _ in cells}
    for _ in range(reps):
        for kind, arith, args in cells:
            times[kind, arith].append(_time_steps(*args) / samples / 1e3)
    results: dict[str, dict[str, float]] = {}
    for (kind, arith), us in times.items():
        results.setdefault(kind, {})[arith] = statistics.median(us)

    rows = [[kind, f"{r['fixed']:.2f}", f"{r['float']:.2f}", f"{r['fixed'] / r['float']:.2f}"]
            for kind, r in results.items()]
    return Table("Agent step (consensus_error + step), µs, median",
                 ["controller", "fixed", "float", "fixed/float"], rows,
                 note=f"hub of case 1 (3 neighbours + price), {samples} samples × {reps} "
                 "repetitions per cell",
                 data={"us_per_step": results, "samples": samples, "repetitions": reps})


def _time_steps(ctrl: Controller, inputs: list[tuple[Any, list[tuple[Any, Any]]]], pin: Any,
                price: Any, state0: ControllerState) -> int:
    """ns for one agent to run ξ + step over every input sample, as the runtime does."""
    ar, step = ctrl.ar, ctrl.step
    s = state0
    t0 = time.perf_counter_ns()
    for lam_i, nbrs in inputs:
        x, _ = consensus_error(ar, lam_i, nbrs, pin, price)
        s, _ = step(s, x)
    return time.perf_counter_ns() - t0


def lockstep_speed(quick: bool) -> Table:
    """Simulated seconds per wall-clock second of the lockstep runner (fixed point)."""
    from sim.model.lockstep import run_lockstep
    from sim.model.scenario import load_case

    reps = 1 if quick else 5
    rows, data = [], {}
    for case in (1, 7):
        sc = load_case(case)
        walls = []
        for _ in range(reps):
            t0 = time.perf_counter()
            run_lockstep(sc, fixed=True)
            walls.append(time.perf_counter() - t0)
        wall = statistics.median(walls)
        agent_steps = sc.n * (sc.steps + 1)
        rows.append([sc.name, str(sc.n), f"{sc.duration:g}", f"{wall:.3f}",
                     f"{sc.duration / wall:.0f}", f"{wall / agent_steps * 1e6:.1f}"])
        data[sc.name] = {"agents": sc.n, "simulated_s": sc.duration, "wall_s": wall,
                         "sim_s_per_wall_s": sc.duration / wall,
                         "us_per_agent_step": wall / agent_steps * 1e6}
    return Table("Lockstep simulator, fixed point, Ts = 10 ms",
                 ["case", "agents", "simulated [s]", "wall [s]", "sim s / wall s",
                  "µs / agent step"], rows,
                 note=f"median of {reps} run(s); includes recording the trajectory",
                 data=data)


def lockstep_scaling(quick: bool) -> Table:
    """ms of wall time per lockstep tick against the fleet size, on random 3-regular graphs
    (sim.model.generate), for the per-agent loop and the arrays (sim.model.vlockstep);
    and the issue's yardstick: 1,000 agents, 60 s of case time at Ts = 10 ms."""
    from sim.model.generate import random_scenario
    from sim.model.lockstep import run_lockstep

    sizes = (4, 32, 256, 1000) if quick else (4, 8, 16, 32, 64, 128, 256, 512, 1000)
    case_s = 0.5 if quick else 2.0
    rows: list[list[str]] = []
    data: dict[str, Any] = {}
    for n in sizes:
        sc = random_scenario(n, 3, seed=0, duration=case_s)
        per_tick: dict[str, float] = {}
        # --quick leaves out the loop's 1,000 agents (100 ms a tick)
        for impl in ("py", "vec") if not quick or n <= 256 else ("vec",):
            t0 = time.perf_counter()
            run_lockstep(sc, impl=impl)
            per_tick[impl] = (time.perf_counter() - t0) / (sc.steps + 1) * 1e3
        loop = per_tick.get("py")
        rows.append([str(n), "–" if loop is None else f"{loop:.3f}", f"{per_tick['vec']:.3f}",
                     "–" if loop is None else f"{loop / per_tick['vec']:.1f}"])
        data[str(n)] = {"ms_per_tick_py": loop, "ms_per_tick_vec": per_tick["vec"]}
    note = f"{case_s:g} s of case time per run (set-up included), one run each"
    if not quick:
        sc = random_scenario(1000, 3, seed=0, duration=60.0)
        t0 = time.perf_counter()
        run_lockstep(sc, impl="vec")
        wall = time.perf_counter() - t0
        data["1000_agents_60s_wall_s"] = wall
        note += f"; 1,000 agents × 60 s of case time (6,001 ticks), arrays: {wall:.1f} s"
    return Table("Lockstep scaling: ms per tick, fixed point, random 3-regular graphs",
                 ["agents", "per-agent loop", "arrays", "speed-up"], rows, note=note,
                 data=data)


def codec_speed(quick: bool) -> Table:
    """µs to encode and to decode (length and range checks included) one frame of each
    kind (the MAC is NodeIO's: secoc_cost)."""
    from firmware_py.contract import State
    from firmware_py.frames import FrameCodec

    codec = FrameCodec()
    samples = {
        "AGENT_1_MC": {"State": int(State.RUNNING), "Lambda": 13421773, "Resets": 3},
        "ER_Price": {"PriceValid": 1, "Rho": 13421773, "Segment": 0},
        "AGENT_1_Setpoint": {"Enable": 1, "PowerSetpoint": 6592},
    }
    n = 2000 if quick else 20000
    rows, data = [], {}
    for name, raw in samples.items():
        msg = codec.encode(name, raw, 5)
        t_enc = _median_us(partial(codec.encode, name, raw, 5), n)
        t_dec = _median_us(partial(codec.decode, msg), n)
        rows.append([name, f"{t_enc:.2f}", f"{t_dec:.2f}"])
        data[name] = {"encode_us": t_enc, "decode_us": t_dec}
    return Table("Frame codec (firmware_py.frames), µs per frame, median",
                 ["message", "encode", "decode (length + range checks)"], rows, data=data)


def _median_us(fn: Callable[[], object], n: int, reps: int = 5) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        times.append((time.perf_counter() - t0) / n * 1e6)
    return statistics.median(times)


def bus_load(quick: bool) -> Table:
    """Frames/s and worst-case bus load of today's protocol, from the DBC: every secured
    message and sync of the fleet (sim.bench.auth's ``fleet_messages``, scheme "a": one
    MAC under the sender's key), each cycle at the scenario's Ts as the firmware
    stretches it; classic 8-byte frames, 135 bits worst case (sim.bench.canframe)."""
    from dataclasses import replace

    from sim.bench import auth
    from sim.model.scenario import load_case

    today = auth.SCHEMES[0]
    ring = auth.ring_scenario()
    rows, data = [], {}
    for label, sc in (("cases 1-6", load_case(1)), ("case 7", load_case(7)),
                      ("32-agent ring", ring), ("32-agent ring", replace(ring, ts=0.04))):
        msgs = auth.fleet_messages(sc)
        plain = auth.bus_load(today, sc, msgs=[m for m in msgs
                                                if not m.name.endswith("_Sync")])
        secured = auth.bus_load(today, sc, msgs=msgs)
        ts_ms = round(sc.ts * 1000)
        rows.append([label, str(sc.n), str(ts_ms), f"{plain['frames_per_s']:.0f}",
                     f"{100 * plain['load']:.1f} %", f"{secured['frames_per_s']:.0f}",
                     f"{100 * secured['load']:.1f} %"])
        data[f"{label} Ts={ts_ms}ms"] = {
            "agents": sc.n, "ts_ms": ts_ms, "frames_per_s": plain["frames_per_s"],
            "load": plain["load"], "frames_per_s_auth": secured["frames_per_s"],
            "load_auth": secured["load"]}
    return Table("CAN bus load (the DBC's frames and cycles at Ts, 135-bit worst-case "
                 "frames, the DBC's bit rate)",
                 ["scenario", "agents", "Ts [ms]", "frames/s", "bus load",
                  "frames/s, authenticated", "bus load, authenticated"], rows,
                 note="32 agents do not fit at Ts = 10 ms on classic CAN; at Ts = 40 ms "
                 "every cycle is 4x longer. Authenticated: + one <name>_Sync per secured "
                 "ID per sync period (no frame grew: the MAC is inside DLC 8); "
                 "bench --fleet-load: CAN FD and larger fleets", data=data)


def secoc_cost(quick: bool) -> Table:
    """µs to send (encode + sign) and to receive (decode + verify) one frame through
    NodeIO: a secured AGENT_2_MC and a secured, multiplexed AGENT_2_Diag page."""
    from firmware_py import secoc
    from firmware_py.frames import FrameCodec, diag_name, mc_name
    from firmware_py.nodeio import NodeIO

    codec = FrameCodec()
    rings = secoc.Keyring.fleet(bytes(16), ["agent_1", "agent_2", "router"])
    n = 2000 if quick else 20000
    mc = {"State": 1, "Resets": 0, "Lambda": 13421773}
    diag = {"Page": 0, "Resets": 3, "DeadlineMisses": 0}
    rows, data = [], {}
    for label, name, raw, receiver in (
            ("AGENT_2_MC (secured: CMAC-AES-128/24, FV 4/40 bits)", mc_name(2), mc,
             ("agent_1", [mc_name(1)])),
            (f"AGENT_2_Diag (secured, page 0 of {len(codec.pages(diag_name(2)))})",
             diag_name(2), diag,
             ("router", ["ER_Price"]))):
        tx = NodeIO(codec, "agent 2", own=[mc_name(2), diag_name(2)], wanted=[],
                    keys=rings["agent_2"])
        frames = [tx.send(name, raw) for _ in range(n)]
        t_send = _median_us(partial(tx.send, name, raw), n)
        rx_times = []
        for _ in range(5):
            rx = NodeIO(codec, receiver[0], own=receiver[1], wanted=[codec.frame_id(name)],
                        keys=rings[receiver[0]], untrusted_after=10**9)
            # the freshness state a sync would give
            rx.assume_synced(codec.frame_id(name), tx.boot)
            t0 = time.perf_counter()
            for msg in frames:
                rx.receive(msg, 0.0)
            rx_times.append((time.perf_counter() - t0) / n * 1e6)
            assert rx.counters.total() == 0, rx.counters  # every frame accepted
        t_recv = statistics.median(rx_times)
        rows.append([label, f"{t_send:.2f}", f"{t_recv:.2f}"])
        data[name] = {"send_us": t_send, "receive_us": t_recv}
    return Table("Frame authentication in firmware_py (NodeIO), µs per frame, median",
                 ["frame", "send (encode + sign)", "receive (decode + verify)"], rows,
                 note="Python → OpenSSL (cryptography) per CMAC; one AES block per MAC input",
                 data=data)


def secoc_settling(quick: bool) -> Table:
    """Settling of cases 1 and 7 on the deterministic in-process bus (simulated clock)
    with authentication, next to the lockstep simulator (no bus): what signing and
    verifying, the syncs and the start-up change in the dispatch."""
    import tempfile

    from sim.model.lockstep import run_lockstep
    from sim.model.metrics import compute
    from sim.model.scenario import load_case
    from sim.run.busrun import run_in_process

    rows, data = [], {}
    for case in (1,) if quick else (1, 7):
        sc = load_case(case)
        with tempfile.TemporaryDirectory() as tmp:
            bus = run_in_process(sc, Path(tmp), sc.duration)
        ref = compute(sc, run_lockstep(sc, fixed=True))
        st_bus, st_ref = bus["settling_time_s"], ref["settling_time_s"]
        rows.append([f"case {case}", "never" if st_ref is None else f"{st_ref:.2f}",
                     "never" if st_bus is None else f"{st_bus:.2f}",
                     f"{bus['final_error']:.1e}", str(bus["verdict"]["exit_code"])])
        data[f"case{case}"] = {"lockstep_settling_s": st_ref, "bus_settling_s": st_bus,
                               "bus_final_error": bus["final_error"],
                               "exit_code": bus["verdict"]["exit_code"]}
    return Table("Settling with authentication on the in-process virtual bus",
                 ["case", "lockstep (no bus) [s]", "bus, authenticated [s]", "final error",
                  "exit"], rows,
                 note="the bus adds one sample of transport delay per hop; real-time "
                 "figures: bess-ded bench --realtime", data=data)


def realtime_bus(quick: bool) -> Table:
    """Cases 1 and 7 as node processes on udp_multicast (``bess-ded up``'s path): what only
    a wall clock can tell, and what the tests therefore never assert: frame and price
    rates, the worst node's deadline misses, bus silences, recorder misses, settling."""
    from sim.bench.realtime import realtime_run

    rows, data = [], {}
    for case in (1, 7):
        r = realtime_run(case, 8.0 if quick else 20.0)
        data[f"case{case}"] = r
        st = r["settling_time_s"]
        rows.append([f"case {case}", str(r["agents"]), f"{r['seconds']:g}",
                     f"{r['frames_per_s']:.0f}", f"{r['price_frames_per_s']:.1f}",
                     f"{r['deadline_miss_pct_max']:.2f} %", str(r["bus_silences"]),
                     str(r["frames_missed_by_recorder"]),
                     "never" if st is None else f"{st:.2f}", f"{r['final_error']:.1e}",
                     str(r["exit_code"])])
    return Table("Real-time bus runs (node processes on udp_multicast, SCHED_FIFO where allowed)",
                 ["run", "agents", "s", "frames/s", "ER_Price/s", "worst misses",
                  "silences", "rec. missed", "settling [s]", "final error", "exit"], rows,
                 note="deadline miss: a tick released > Ts/2 late; silences: gaps > 3 Ts; "
                 "exit as `bess-ded up` (3: converged with anomalies)", data=data)


def c_controller_step(quick: bool) -> Table:
    """µs per controller step, firmware_c's core against firmware_py's fixed controller,
    every kind, on the ξ of case 1's hub: C in one ``bd_ctrl_run`` call per repetition
    (no binding overhead per step), Python one ``step`` per sample."""
    import ctypes

    from firmware_py.controllers import KINDS, ControllerConfig, make_controller
    from sim.cbind.cimpl import CController, record_buffer
    from sim.model.lockstep import run_lockstep
    from sim.model.scenario import load_case

    sc = load_case(1)
    tr = run_lockstep(sc)
    q = make_controller(sc.controller).quantise
    assert tr.xi is not None
    xis = [int(q(float(x))) for x in tr.xi[:, 0]] * (1 if quick else 10)
    reps = 3 if quick else 9
    rows, data = [], {}
    for kind in KINDS:
        cfg = ControllerConfig(kind=kind, k=sc.controller.k, h=sc.controller.h, ts=sc.ts,
                               dwell=1.0 if kind == "dwell" else 0.0)
        py, c = make_controller(cfg), CController.from_config(cfg)
        s0 = py.initial_state(sc.lambda0[0])

        def run_py(py: Controller = py, s0: ControllerState = s0) -> None:
            s = s0
            for x in xis:
                s, _ = py.step(s, x)

        arr = (ctypes.c_int32 * len(xis))(*xis)
        rec = record_buffer(len(xis))

        def run_c(c: CController = c, s0: ControllerState = s0, arr: Any = arr,
                  rec: Any = rec) -> None:
            c.run_into(s0, arr, rec)

        us_py = _median_us(run_py, 1, reps) / len(xis)
        us_c = _median_us(run_c, 1, reps) / len(xis)
        data[kind] = {"python_us": us_py, "c_us": us_c}
        rows.append([kind, f"{us_py:.2f}", f"{us_c * 1000:.1f}", f"{us_py / us_c:.0f}×"])
    return Table("Controller step, firmware_c against firmware_py (fixed point), median",
                 ["controller", "Python [µs]", "C [ns]", "C faster by"], rows,
                 note=f"{len(xis)} steps of case 1's hub ξ × {reps}; C through one "
                 "bd_ctrl_run call (its per-call binding cost included, spread over the "
                 "steps)", data=data)


def _tick_traffic(n_nbrs: int, ticks: int) -> tuple[str, list[tuple[str, float, Any]]]:
    """An agent with ``n_nbrs`` RUNNING neighbours at Ts = 10 ms, insecure: its TOML and
    its inputs, every tick: each neighbour's MC, and the price and its plant status every
    5 ticks (their cycles), all authentic (the MAC checked on every frame)."""
    from firmware_py.config import AgentConfig, DispatchParams, Neighbour
    from firmware_py.controllers import ControllerConfig
    from firmware_py.nodeio import FleetSender

    cfg = AgentConfig(id=1, lambda0=0.8, pinned=True, controller=ControllerConfig(),
                      neighbours=tuple(Neighbour(j, 1.0) for j in range(2, n_nbrs + 2)),
                      battery=DispatchParams(0.005, 0.18, 0.08, -100.0, 100.0),
                      fleet_size=32)
    tx = FleetSender()
    events: list[tuple[str, float, Any]] = []
    for k in range(ticks):
        t = k * 0.01
        events.append(("tick", t, None))
        rx = t + 0.004
        for j in range(2, n_nbrs + 2):
            lam = 13_421_773 + ((k * 7 + j * 13) % 41 - 20) * 200
            events.append(("rx", rx, tx.frame(f"AGENT_{j}_MC", {"State": 1, "Resets": 0,
                                                                "Lambda": lam})))
        if k % 5 == 0:
            events.append(("rx", rx, tx.frame("ER_Price", {"PriceValid": 1, "Segment": 0,
                                                           "Rho": 13_421_773})))
            events.append(("rx", rx, tx.frame("PLANT_1_Status", {
                "FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
                "Power": 100, "Soc": 100})))
    return cfg.to_toml(), events


def agent_tick(quick: bool) -> Table:
    """µs of work per tick of one agent (the frames received since the last tick, each
    authenticated, and the tick: ξ, the step, the frames it signs), C against Python,
    for 2, 8 and 31 neighbours. C natively (firmware_c/tools/node_runner.c --bench: the
    clock read around each tick's work), Python through AgentRuntime (no bus, no loop)."""
    import logging
    import subprocess
    import tempfile

    import can

    from firmware_py.config import parse_agent_config
    from firmware_py.runtime import AgentRuntime
    from firmware_py.secoc import Keyring
    from sim.cbind.cagent import RUNNER_NAME, built, ns

    runner = built(RUNNER_NAME)
    ticks = 300 if quick else 2000
    logging.disable(logging.WARNING)   # the insecure agents' warning, once per agent
    rows, data = [], {}
    for n_nbrs in (2, 8, 31):
        toml, events = _tick_traffic(n_nbrs, ticks)
        cfg = parse_agent_config(__import__("tomllib").loads(toml), "bench")
        py_ns: list[int] = []
        agent = AgentRuntime(cfg, keys=Keyring.insecure_for("agent_1"))
        start = time.perf_counter_ns()
        for kind, t, msg in events:
            if kind == "rx":
                agent.on_frame(msg, t)
            else:
                agent.tick(t)
                end = time.perf_counter_ns()
                py_ns.append(end - start)
                start = time.perf_counter_ns()
        lines = [f"V bench {toml.encode().hex()}",
                 f"K agent_1 1 {Keyring.insecure_for('agent_1').key.hex()} 0 0 0"]
        for kind, t, msg in events:
            if kind == "rx":
                assert isinstance(msg, can.Message)
                lines.append(f"R {ns(t)} {msg.arbitration_id} 0 {bytes(msg.data).hex()}")
            else:
                lines.append(f"T {ns(t)}")
        lines.append("E")
        with tempfile.TemporaryFile("w+") as dump:
            dump.write("\n".join(lines) + "\n")
            dump.seek(0)
            out = subprocess.run([str(runner), "--bench"], stdin=dump, capture_output=True,
                                 text=True, check=True, timeout=300).stdout.split()
        n, total, worst = int(out[1]), int(out[2]), int(out[3])
        us_py = statistics.mean(py_ns) / 1e3
        us_c = total / n / 1e3
        data[str(n_nbrs)] = {"python_us": us_py, "python_worst_us": max(py_ns) / 1e3,
                             "c_us": us_c, "c_worst_us": worst / 1e3, "ticks": n}
        rows.append([str(n_nbrs), f"{us_py:.1f}", f"{max(py_ns) / 1e3:.0f}", f"{us_c:.2f}",
                     f"{worst / 1e3:.1f}", f"{us_py / us_c:.0f}×"])
    logging.disable(logging.NOTSET)
    return Table("Agent tick, firmware_c against firmware_py: µs of work per tick (mean)",
                 ["neighbours", "Python", "Python worst", "C", "C worst", "C faster by"],
                 rows, note=f"{ticks} ticks at Ts = 10 ms: every neighbour's MC each tick, "
                 "price and status every 5th, each frame's MAC verified; no bus, no loop",
                 data=data)


# Sections in print order. To add one (bus load, frame codec, ...): write a
# `def name(quick: bool) -> Table` above and append it here.
def input_checks(quick: bool) -> Table:
    """µs per input of the checks issue 19 added on the receive paths: the transport
    guard (``frame_fault``, every input of every node), the freshness look-back that
    tells a late genuine frame (``stale``) from a forgery (only on frames the window
    already refused), and the plant's setpoint-consistency check (per MC frame and per
    setpoint it hears). A genuine frame's acceptance is given for scale."""
    import logging

    import can

    from firmware_py import secoc
    from firmware_py.config import agent_configs_from_scenario
    from firmware_py.frames import FrameCodec, mc_name
    from firmware_py.node import frame_fault
    from firmware_py.nodeio import NodeIO
    from sim.model.scenario import load_case
    from sim.nodes.consistency import Setpoint, SetpointCheck

    n = 2000 if quick else 20000
    codec = FrameCodec()
    rings = secoc.Keyring.fleet(bytes(16), ["agent_1", "agent_2", "router"])
    tx = NodeIO(codec, "agent 2", own=[mc_name(2)], wanted=[], keys=rings["agent_2"])
    mc = {"State": 1, "Resets": 0, "Lambda": 13421773}
    fid = codec.frame_id(mc_name(2))
    genuine = [tx.send(mc_name(2), mc) for _ in range(n)]
    forged = [can.Message(arbitration_id=fid, is_extended_id=False, data=bytes(8))
              for _ in range(n)]

    def receiver() -> NodeIO:
        rx = NodeIO(codec, "agent_1", own=[mc_name(1)], wanted=[fid], keys=rings["agent_1"],
                    untrusted_after=10**9)
        rx.assume_synced(fid, tx.boot)  # the freshness state a sync would give
        return rx

    def per_frame(frames: list[can.Message], cause: str | None) -> float:
        """Median over 5 receivers of µs per frame; every frame counted under ``cause``
        (None: every frame accepted)."""
        times = []
        for _ in range(5):
            rx = receiver()
            t0 = time.perf_counter()
            for msg in frames:
                rx.receive(msg, 0.0)
            times.append((time.perf_counter() - t0) / len(frames) * 1e6)
            counted = 0 if cause is None else rx.counters[cause]
            assert rx.counters.total() == counted == (0 if cause is None else len(frames))
        return statistics.median(times)

    def per_late_frame() -> float:
        """µs per frame held back behind the one after it (which the receiver took)."""
        times = []
        for _ in range(5):
            rx, t = receiver(), 0.0
            for early, late in zip(genuine[1::2], genuine[0::2], strict=True):
                rx.receive(early, 0.0)
                t0 = time.perf_counter()
                rx.receive(late, 0.0)
                t += time.perf_counter() - t0
            # each early frame first counts its held-back predecessor lost (AUTH-15)
            assert rx.counters["stale"] == rx.counters["lost_frames"] == n // 2, rx.counters
            times.append(t / (n // 2) * 1e6)
        return statistics.median(times)

    check = SetpointCheck(agent_configs_from_scenario(load_case(1))[1].battery)
    sp_raw = check.expected(1, mc["Lambda"])[1]

    def mc_then_setpoint() -> None:
        check.mc(1, mc["Lambda"])
        check.setpoint(Setpoint(True, sp_raw, 0.0))

    logging.disable(logging.WARNING)  # the receivers log their first rejections
    try:
        rows = [
            ["frame_fault (every input of every node)",
             f"{_median_us(partial(frame_fault, genuine[0]), n):.2f}"],
            ["a genuine AGENT_2_MC accepted (for scale)", f"{per_frame(genuine, None):.2f}"],
            ["a forged AGENT_2_MC refused (window, then one look-back CMAC)",
             f"{per_frame(forged, 'auth'):.2f}"],
            ["a late genuine AGENT_2_MC counted stale", f"{per_late_frame():.2f}"],
            ["setpoint consistency at the plant: one MC frame and one setpoint",
             f"{_median_us(mc_then_setpoint, n):.2f}"]]
    finally:
        logging.disable(logging.NOTSET)
    return Table("Input checks (issue 19), firmware_py and the plant, µs per input, median",
                 ["check", "µs"], rows,
                 note="the look-back costs one CMAC, spent only on a frame the window refused",
                 data={r[0]: float(r[1]) for r in rows})


def event_transmit(quick: bool) -> Table:
    """Event-triggered λ against periodic on the paper cases (sim.bench.event): MC frames
    over the run and once settled, settling time, final error; deterministic lockstep
    figures (docs/performance.md). --quick: each case's own controller, no variants."""
    from firmware_py.config import Transmit
    from sim.bench.event import HEADERS, paper_cases, rows

    tx = Transmit("event")
    results = paper_cases(tx, variants=not quick)
    ok = all(c.accepted for c in results)
    note = (f"threshold {tx.threshold:g} cu/kWh, heartbeat {tx.heartbeat} ticks; issue 23's "
            f"acceptance (≥ 50 % fewer, ≥ 90 % fewer once settled, settling ≤ 1.1×, final "
            f"error ≤ 1e-3): {'met' if ok else 'NOT met'}")
    data = {f"case{c.case}/{c.label}": {"frames": c.frames, "settled_frames": c.settled_frames,
                                        "settling_s": c.settling, "final_error": c.final_error}
            for c in results}
    return Table("Event-triggered λ against periodic (lockstep, MC frames of all agents)",
                 HEADERS, rows(results), note=note, data=data)


def auth_schemes(quick: bool) -> Table:
    """Every authentication scheme of issue 25 (sim.bench.auth): sign/verify µs measured
    here, bus load of case 1, case 7 and a 32-agent ring at Ts = 10 ms from the DBC,
    added latency, and what an insider with agent 3's key file still forges."""
    from sim.bench.auth import HEADERS, run

    rows, data = run(quick)
    return Table("Authentication schemes (issue 25): cost, bus load at Ts = 10 ms, insider",
                 HEADERS, rows, data=data, align="l" + "r" * (len(HEADERS) - 2) + "l",
                 note=f"bus {data['nominal_bps'] / 1e3:.0f} kbit/s (DBC), FD data phase "
                 f"{data['fd_data_bps'] / 1e6:g} Mbit/s; worst-case stuffing; sign/verify: "
                 "the costliest operation per message (λ: "
                 f"{data['lambda_tags_measured']} tags); +price latency of a signature: "
                 "its frames, plus its verify on the node (M4 figures cited, ms)")


def fleet_load(quick: bool) -> Table:
    """Bus load per fleet size at Ts = 10 ms (sim.bench.fleetload, issue 23 item 4):
    classic and CAN FD, periodic and event-triggered λ, rings of 4..64 agents and cases
    1 and 7, computed from the DBC; the largest N at ≤ 60 %. --quick: the event ratios
    of rings above 32 agents are ring-32's."""
    from sim.bench.fleetload import note, run, title

    headers, rows, data = run(quick)
    return Table(title(), headers, rows, note=note(data), data=data)


def measured_load(runs: list[Path]) -> Bench:
    """`bench --fleet-load --measured DIR`: the bus load of `bess-ded up` runs measured from
    their recordings beside the computed figure (sim.bench.fleetload.measured_run)."""
    def bench(quick: bool) -> Table:
        from sim.bench.fleetload import MEASURED_HEADERS, measured_rows, measured_run

        data = [measured_run(r) for r in runs]
        return Table("Bus load measured on the bus (recorded frames) against the computed "
                     "figure", MEASURED_HEADERS, measured_rows(data), data={"runs": data},
                     note="measured: each recorded frame's worst-case time at the DBC's bit "
                     "rates (its own format, length, bit-rate switch) over the recorded span; "
                     "computed: the scenario's frames from the DBC, event-triggered MC "
                     "frames × the lockstep's ratio over the same span; a run at Ts = "
                     "10 ms·F is × F at Ts = 10 ms")
    return bench


def scenario_loads(specs: list[str]) -> Bench:
    """`bench --fleet-load --case CASE`: the computed bus load of each scenario's fleet at
    its Ts, classic and FD (sim.bench.fleetload.scenario_load)."""
    def bench(quick: bool) -> Table:
        from sim.bench.fleetload import SCENARIO_HEADERS, scenario_load, scenario_rows
        from sim.model.scenario_select import resolve_scenario

        data = [scenario_load(resolve_scenario(s)) for s in specs]
        return Table("Bus load of the scenarios' fleets, computed from the DBC",
                     SCENARIO_HEADERS, scenario_rows(data), data={"scenarios": data},
                     note="each scenario at its own Ts: every frame of the DBC at its "
                     "cycle; event-triggered MC frames × the lockstep's ratio event/periodic "
                     "over the scenario's run; * over 60 % (issue 23's limit); its bus: "
                     "[bus] fd")
    return bench


BENCHES: list[Bench] = [
    controller_step,
    c_controller_step,
    agent_tick,
    lockstep_speed,
    lockstep_scaling,
    codec_speed,
    secoc_cost,
    input_checks,
    bus_load,
    auth_schemes,
    fleet_load,
    secoc_settling,
    event_transmit,
]


def machine_info() -> dict[str, Any]:
    """The machine the numbers are from: Python, platform, CPU, numpy, load average."""
    import numpy

    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        cpu = platform.processor() or "unknown"
    try:
        load = round(os.getloadavg()[0], 2)
    except OSError:
        load = None
    return {"python": f"{platform.python_version()} ({platform.python_implementation()})",
            "platform": platform.platform(), "cpu": cpu, "logical_cpus": os.cpu_count(),
            "numpy": numpy.__version__, "load_average_1min": load}


def fleet_capacity(plan: CapacityPlan | None = None) -> Bench:
    """The fleet-capacity section for ``plan`` (sim.bench.realtime; None: its default):
    missed ticks by fleet size and agents per process, each run repeated."""
    def fleets(quick: bool) -> Table:
        from sim.bench.realtime import capacity_table, print_run

        return capacity_table(quick, plan, print_run)
    return fleets


def run_benches(quick: bool = False, realtime: bool = False,
                on_table: Callable[[Table], None] | None = None,
                only: list[Bench] | None = None,
                capacity: CapacityPlan | None = None) -> list[Table]:
    """Every section of BENCHES (and ``realtime_bus`` and the fleet capacity with
    ``realtime``: ``capacity`` a sim.bench.realtime.CapacityPlan, None: its default), or
    ``only`` those given, in order, with the garbage collector off while each runs;
    ``on_table`` gets each table as it is done."""
    realtime_parts = [realtime_bus, fleet_capacity(capacity)] if realtime else []
    tables = []
    for bench in only if only is not None else BENCHES + realtime_parts:
        was_enabled = gc.isenabled()
        gc.collect()
        gc.disable()
        try:
            tab = bench(quick)
        finally:
            if was_enabled:
                gc.enable()
        tables.append(tab)
        if on_table is not None:
            on_table(tab)
    return tables
