#!/usr/bin/env python3
"""The largest fleet that runs in real time at Ts = 10 ms, C agents against Python agents.

Each run is `bess-ded up`'s own path (``busrun.record``) on SocketCAN: a random regular
graph of n agents (tools/fidelity.py's, two price steps), every agent a process running
firmware_c's node program or firmware_py, with the plant and the router (Python) beside
them, for ``--seconds`` of price time at Ts = 10 ms (no time scale). Reported per run:
each agent's deadline misses (AGENT_i_Diag.DeadlineMisses over its ticks) over the whole
run and in steady state (from WARMUP_S after the first price on: the guest is still
starting the other processes before), the plant's and the router's, the final error and
the verdict. A fleet "runs in real time" when no agent misses more than 0.1 % of its
deadlines in steady state. Writes JSON and a PNG. (`bess-ded bench --realtime` sizes
fleets up the same way on the host, with repeats and several agents per process.)

Made for the vcan tier's QEMU guest (the issue asks for the numbers there):

    tools/vcan-run python3 tools/fleet_capacity.py --json runs/fleet.json --png runs/fleet.png
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from fidelity import graph_scenario  # noqa: E402

from sim.bench.realtime import MISS_LIMIT_PCT, steady_misses  # noqa: E402
from sim.cbind.cagent import node_program  # noqa: E402
from sim.model.scenario import PriceStep  # noqa: E402
from sim.run import busrun  # noqa: E402


def run(n: int, impl: str, seconds: float, channel: str) -> dict[str, Any]:
    sc = replace(graph_scenario(n, 0.01), duration=seconds,
                 prices=(PriceStep(0.0, 0.8), PriceStep(seconds / 2, 1.0)))
    c_agents = frozenset(range(1, n + 1)) if impl == "c" else frozenset()
    with tempfile.TemporaryDirectory(prefix=f"bess-ded-fleet-{impl}{n}-") as tmp:
        rec = busrun.record(sc, Path(tmp), busrun.BusOptions("socketcan", channel),
                            quiet=True, plot=False, c_agents=c_agents,
                            c_node=node_program() if c_agents else None)
        steady = steady_misses(Path(tmp) / "run.log", n, rec.log.t_first_price or 0.0)
    m = rec.metrics
    steady_pct = [100.0 * miss / max(t, 1) for miss, t in steady.values()]
    pct = {k: 100.0 * m["deadline_misses"][k] / max(t, 1) for k, t in m["node_ticks"].items()}
    agents = [v for k, v in pct.items() if k.startswith("agent_")]
    return {"impl": impl, "agents": n, "seconds": seconds,
            "steady_agent_miss_pct_max": max(steady_pct),
            "steady_agent_misses": sum(miss for miss, _ in steady.values()),
            "steady_agent_ticks": sum(t for _, t in steady.values()),
            "agent_miss_pct_max": max(agents) if agents else None,
            "agent_miss_pct_mean": sum(agents) / len(agents) if agents else None,
            "plant_miss_pct": pct.get("plant"), "router_miss_pct": pct.get("router"),
            "final_error": m.get("final_error"), "exit_code": m["verdict"]["exit_code"],
            "anomalies": sorted({a["kind"] for a in m["anomalies"]})}


def plot(results: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for impl, label in (("c", "firmware_c (bessded-agent)"), ("py", "firmware_py")):
        rs = [r for r in results if r["impl"] == impl]
        if rs:
            ax.plot([r["agents"] for r in rs],
                    [max(r["steady_agent_miss_pct_max"], 1e-3) for r in rs], "o-", label=label)
    ax.axhline(MISS_LIMIT_PCT, color="k", ls="--", lw=1, label="0.1 % (real time)")
    ax.set_yscale("log")
    ax.set_xlabel("agents (processes) at Ts = 10 ms")
    ax.set_ylabel("worst agent's deadline misses, steady state [%]")
    ax.set_title("Fleet size against deadline misses, vcan0")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--c-sizes", default="4,8,16,32", help="C fleets (default: %(default)s)")
    p.add_argument("--py-sizes", default="2,4,8", help="Python fleets (default: %(default)s)")
    p.add_argument("--seconds", type=float, default=10.0, help="price time per run")
    p.add_argument("--channel", default="vcan0")
    p.add_argument("--json", type=Path)
    p.add_argument("--png", type=Path)
    args = p.parse_args(argv)
    results = []
    plan = [("c", int(n)) for n in args.c_sizes.split(",") if n] + \
        [("py", int(n)) for n in args.py_sizes.split(",") if n]
    for k, (impl, n) in enumerate(plan, 1):
        print(f"[{k}/{len(plan)}] {n} agents, {impl} ...", flush=True)
        try:
            r = run(n, impl, args.seconds, args.channel)
        except busrun.BusRunError as e:   # e.g. a router starved before its first price
            print(f"  did not run: {e}", flush=True)
            results.append({"impl": impl, "agents": n, "seconds": args.seconds,
                            "steady_agent_miss_pct_max": 100.0, "did_not_run": str(e)})
            continue
        results.append(r)
        print(f"  steady state: worst agent {r['steady_agent_miss_pct_max']:.3f} % missed "
              f"({r['steady_agent_misses']} of {r['steady_agent_ticks']} ticks); whole run: "
              f"worst agent {r['agent_miss_pct_max']:.3f} % (mean "
              f"{r['agent_miss_pct_mean']:.3f} %), plant {r['plant_miss_pct']:.2f} %, router "
              f"{r['router_miss_pct']:.2f} %, final error {r['final_error']:.1e}, exit "
              f"{r['exit_code']} {r['anomalies']}", flush=True)
    for impl in ("c", "py"):
        ok = [r["agents"] for r in results if r["impl"] == impl
              and r["steady_agent_miss_pct_max"] < MISS_LIMIT_PCT]
        print(f"largest {impl} fleet under {MISS_LIMIT_PCT} % misses: "
              f"{max(ok) if ok else 'none of those tried'}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1))
    if args.png:
        args.png.parent.mkdir(parents=True, exist_ok=True)
        plot(results, args.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
