"""Real-time figures of multi-process bus runs, for `bess-ded bench --realtime`.

What depends on how busy the machine is — deadline misses, frame rates, bus silences,
settling measured on the wall clock — is measured here and written to the docs with the
machine it ran on, never asserted by a test (the tests assert what holds at any load:
docs/runs.md). Each run is `bess-ded up`'s own path (``busrun.record``) on a private
udp_multicast port, or on the bus the caller names.

``capacity``: how many agents run in real time on this host, a process per agent or K
to a process (firmware_py.host), each fleet size repeated: the median and the worst of
its missed ticks (issue 24).
"""

from __future__ import annotations

import itertools
import json
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sim.model.scenario import load_case
from sim.run import busrun

if TYPE_CHECKING:
    from sim.bench.micro import Table


def realtime_run(case: int, seconds: float, bus: busrun.BusOptions | None = None
                 ) -> dict[str, Any]:
    """One case for ``seconds`` as node processes; the figures of its recording."""
    sc = load_case(case)
    sc = replace(sc, duration=seconds) if not sc.variants else sc.runs()[0][1]
    bus, _ = busrun.private_port(bus or busrun.BusOptions("udp_multicast"))
    with tempfile.TemporaryDirectory(prefix=f"bess-ded-bench-case{case}-") as tmp:
        rec = busrun.record(sc, Path(tmp), bus, duration=seconds, quiet=True, plot=False)
    m, log = rec.metrics, rec.log
    t0 = log.t_first_price or 0.0
    span = max(log.t_end - t0, 1e-9)
    price = log.sequences.get("ER_Price")
    miss_pct = {k: 100.0 * m["deadline_misses"][k] / max(t, 1)
                for k, t in m["node_ticks"].items()}
    return {
        "case": case, "agents": sc.n, "seconds": seconds,
        "frames_per_s": log.frames / span,
        "price_frames_per_s": (price.frames if price else 0) / span,
        "deadline_miss_pct_max": max(miss_pct.values()) if miss_pct else 0.0,
        "deadline_miss_pct": miss_pct,
        "bus_silences": m["bus_silences"],
        "frames_missed_by_recorder": m["frames_missed_by_recorder"],
        "settling_time_s": m.get("settling_time_s"),
        "final_error": m.get("final_error"),
        "anomalies": [a["kind"] for a in m["anomalies"]],
        "exit_code": m["verdict"]["exit_code"],
    }


# --------------------------------------------------------------------------- fleet capacity

MISS_LIMIT_PCT = 0.1  # issue 24: a fleet "runs in real time" below this share of missed ticks
WARMUP_S = 2.0        # after the first price: processes still starting, not counted


@dataclass(frozen=True)
class CapacityPlan:
    """Which fleets `bench --realtime` sizes up: ``sizes`` agents (``fleet_scenario``),
    each run with the Python agents ``per_process`` to a process (1: a process each) and
    each ``transmit`` mode of the MC frames, ``repeats`` times, ``seconds`` of price
    time at Ts = 10 ms, on a private udp_multicast port, or on SocketCAN ``channel``.
    ``impl`` "c": firmware_c's node program, a process per agent."""

    sizes: tuple[int, ...] = (16, 32)
    per_process: tuple[int, ...] = (1, 16)
    repeats: int = 3
    seconds: float = 14.0
    impl: str = "py"
    channel: str | None = None
    transmit: tuple[str, ...] = ("periodic", "event")


def steady_misses(log_path: Path, n: int, t_first_price: float, ts: float = 0.01,
                  fd: bool = False) -> dict[int, tuple[int, int]]:
    """Per agent, (deadline misses, ticks) from WARMUP_S after the first price to the end,
    read from the recording: the growth of AGENT_i_Diag page 0's DeadlineMisses between
    the agent's first and last such page, over the periods of ``ts`` between them (so an
    event-triggered fleet, which sends no MC frame on most ticks, is counted alike)."""
    import can

    from dbc import dbc_path
    from firmware_py.frames import FrameCodec, diag_name

    codec = FrameCodec(dbc_path(fd))
    diag = {codec.frame_id(diag_name(i)): i for i in range(1, n + 1)}
    start = t_first_price + WARMUP_S
    first: dict[int, tuple[float, int]] = {}
    last: dict[int, tuple[float, int]] = {}
    for msg in can.LogReader(str(log_path)):
        if msg.timestamp < start or msg.is_error_frame or msg.is_fd != fd:
            continue
        i = diag.get(msg.arbitration_id)
        if i is not None:
            f = codec.decode(msg)
            if f.raw["Page"] == 0:
                first.setdefault(i, (msg.timestamp, f.raw["DeadlineMisses"]))
                last[i] = (msg.timestamp, f.raw["DeadlineMisses"])
    out = {}
    for i in range(1, n + 1):
        (t0, m0), (t1, m1) = first.get(i, (0.0, 0)), last.get(i, (0.0, 0))
        out[i] = (m1 - m0, round((t1 - t0) / ts))
    return out


def fleet_scenario(n: int, transmit: str, seconds: float, seed: int = 0) -> Any:
    """The capacity runs' fleet: ``n`` agents on a random 4-regular graph (fewer for
    n < 5), one in four pinned (so that 32 event-triggered agents settle within 14 s: one
    in eight did not, even in the lockstep), its MC frames
    ``transmit``ted (periodic or event), on classic CAN if its computed load fits there,
    else on CAN FD (32 periodic agents: 134 % of classic CAN at Ts = 10 ms), with λ tags
    (AUTH-34) if they fit too, else without (32 periodic agents: 101.5 % with the tags)."""
    from sim.bench.fleetload import BUS_LOAD_MAX, run_bus_load
    from sim.model.generate import random_fleet
    from sim.model.scenario import parse_scenario

    data = random_fleet(n, degree=max(1, min(4, n - 1)), seed=seed, pinned=max(1, n // 4),
                        duration=seconds)
    data["transmit"] = transmit
    sc = parse_scenario(data, f"<{data['name']}>")
    for fd in ({"bus": {"fd": True}},
               {"bus": {"fd": True}, "security": {"lambda_tags": False}}):
        if run_bus_load(sc)[0] <= BUS_LOAD_MAX:
            break
        sc = parse_scenario({**data, **fd}, f"<{data['name']}>")
    return sc


def capacity_run(n: int, per_process: int, plan: CapacityPlan, seed: int = 0,
                 transmit: str = "periodic") -> dict[str, Any]:
    """One fleet of ``n`` agents for ``plan.seconds``: its agents' missed ticks in steady
    state (all of them together, and the worst agent's), the plant's and router's over
    the whole run, the final error and the exit code; ``did_not_run`` if it never
    started (a router starved before its first price counts as 100 % missed)."""
    sc = fleet_scenario(n, transmit, plan.seconds, seed)
    c = plan.impl == "c"
    if c:
        from sim.cbind.cagent import node_program
    if plan.channel is not None:
        bus = busrun.BusOptions("socketcan", plan.channel)
    else:
        bus, _ = busrun.private_port(busrun.BusOptions("udp_multicast"))
    out: dict[str, Any] = {"impl": plan.impl, "agents": n, "per_process": per_process,
                           "seconds": plan.seconds, "transmit": transmit,
                           "bus": "FD" if sc.fd else "classic"}
    with tempfile.TemporaryDirectory(prefix=f"bess-ded-capacity-{plan.impl}{n}x") as tmp, \
            _StallProbe() as probe:
        try:
            rec = busrun.record(sc, Path(tmp), bus, duration=plan.seconds, quiet=True,
                                plot=False, agents_per_process=per_process,
                                c_agents=frozenset(range(1, n + 1)) if c else frozenset(),
                                c_node=node_program() if c else None)
        except busrun.BusRunError as e:
            return {**out, "fleet_miss_pct": 100.0, "worst_agent_miss_pct": 100.0,
                    "did_not_run": " ".join(str(e).split())[:300]}
        steady = steady_misses(Path(tmp) / "run.log", n, rec.log.t_first_price or 0.0,
                               sc.ts, sc.fd)
    m = rec.metrics
    misses, ticks = sum(x for x, _ in steady.values()), sum(t for _, t in steady.values())
    whole = {k: 100.0 * m["deadline_misses"][k] / max(t, 1)
             for k, t in m["node_ticks"].items()}
    return {**out, "fleet_miss_pct": 100.0 * misses / max(ticks, 1),
            "steady_misses": misses, "steady_ticks": ticks,
            "worst_agent_miss_pct": max(100.0 * x / max(t, 1) for x, t in steady.values()),
            "plant_miss_pct": whole.get("plant"), "router_miss_pct": whole.get("router"),
            "final_error": m.get("final_error"), "exit_code": m["verdict"]["exit_code"],
            "machine_stalls": probe.result}


class _StallProbe:
    """sim.bench.stallprobe beside a run (a process above the nodes' priority): what
    the machine itself took away while the run ran. ``result``: its JSON, or None if it
    could not run."""

    def __init__(self) -> None:
        self.result: dict[str, Any] | None = None

    def __enter__(self) -> _StallProbe:
        self.proc = subprocess.Popen([sys.executable, "-m", "sim.bench.stallprobe", "3600"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True)
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            out, _ = self.proc.communicate(input="", timeout=10)  # closes its stdin
            self.result = json.loads(out) if self.proc.returncode == 0 else None
        except (subprocess.TimeoutExpired, ValueError):
            self.proc.kill()
            self.proc.wait()


def capacity(plan: CapacityPlan, on_run: Callable[[dict[str, Any]], None] | None = None
             ) -> list[dict[str, Any]]:
    """Every fleet size of ``plan`` with each agents-per-process and transmit mode,
    ``plan.repeats`` times: per (size, K, mode) the runs, the median and the worst of the
    fleet's missed-tick share."""
    out = []
    for n, k, mode in itertools.product(
            plan.sizes, (1,) if plan.impl == "c" else plan.per_process, plan.transmit):
        runs = []
        for r in range(plan.repeats):
            runs.append(capacity_run(n, k, plan, seed=r, transmit=mode))
            if on_run is not None:
                on_run(runs[-1])
        pct = [x["fleet_miss_pct"] for x in runs]
        out.append({"impl": plan.impl, "agents": n, "per_process": k, "transmit": mode,
                    "bus": runs[0]["bus"], "runs": runs,
                    "median_miss_pct": statistics.median(pct), "worst_miss_pct": max(pct),
                    "worst_agent_miss_pct": max(x["worst_agent_miss_pct"] for x in runs),
                    "real_time": statistics.median(pct) < MISS_LIMIT_PCT})
    return out


def capacity_table(quick: bool, plan: CapacityPlan | None = None,
                   on_run: Callable[[dict[str, Any]], None] | None = None) -> Table:
    """``capacity`` as a bench section (``--quick``: one run of 8 s per fleet)."""
    from sim.bench.micro import Table

    plan = plan or CapacityPlan()
    if quick:
        plan = replace(plan, repeats=1, seconds=8.0)
    rows, data = [], []
    for r in capacity(plan, on_run):
        data.append(r)
        exits = sorted({str(x.get("exit_code", "-")) for x in r["runs"]})
        rows.append([r["impl"], str(r["agents"]), str(r["per_process"]), r["transmit"],
                     r["bus"],
                     str(len(r["runs"])), f"{r['median_miss_pct']:.3f} %",
                     f"{r['worst_miss_pct']:.3f} %", f"{r['worst_agent_miss_pct']:.2f} %",
                     "yes" if r["real_time"] else "no", ",".join(exits), _stalls(r["runs"])])
    return Table(f"Fleet capacity at Ts = 10 ms ({plan.seconds:g} s per run, "
                 f"{'udp_multicast' if plan.channel is None else plan.channel})",
                 ["impl", "agents", "per process", "MC frames", "bus", "runs",
                  "missed (median)",
                  "missed (worst run)", "worst agent", f"< {MISS_LIMIT_PCT} %", "exit",
                  "machine stalls"],
                 rows, note=f"missed: the fleet's agents' deadline misses over their ticks "
                 f"from {WARMUP_S:g} s after the first price (AGENT_i_Diag page 0); "
                 "a did-not-start run counts 100 %; machine stalls: per run, the wake-ups a "
                 "real-time probe above the nodes got more than 3 ms late, and the longest "
                 "(sim.bench.stallprobe): the machine's, not the fleet's", data={"fleets": data})


def _stalls(runs: list[dict[str, Any]]) -> str:
    """The stall probe's counts of ``runs`` ("-" where it did not run)."""
    seen = [r.get("machine_stalls") for r in runs]
    return ",".join("-" if s is None else f"{s['stalls']} ({1e3 * s['worst_s']:.0f} ms)"
                    for s in seen)


def print_run(r: dict[str, Any]) -> None:
    """One capacity run as a progress line."""
    what = (f"  {r['impl']} {r['agents']} agents, {r['per_process']} per process, "
            f"{r['transmit']} on {r['bus']}: ")
    if "did_not_run" in r:
        print(what + f"did not run: {r['did_not_run']}", flush=True)
        return
    print(what + f"{r['fleet_miss_pct']:.3f} % missed ({r['steady_misses']} of "
          f"{r['steady_ticks']} ticks), worst agent {r['worst_agent_miss_pct']:.2f} %, "
          f"plant {r['plant_miss_pct']:.2f} %, router {r['router_miss_pct']:.2f} %, "
          f"final error {r['final_error']:.1e}, exit {r['exit_code']}", flush=True)
