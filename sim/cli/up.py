"""`bess-ded up`: run a case with every node a separate process on a CAN bus."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from firmware_py.__main__ import add_bus_arguments

# In tools/vcan-run's QEMU TCG guest (VCAN_RUN_GUEST=1) Python runs ~20x slower: at
# Ts = 10 ms the agents miss most deadlines and starve the router, which then never
# starts (docs/vcan.md, "The vcan tier"). Ts = 50 ms keeps every deadline there.
GUEST_TIME_SCALE = 5.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="run router, plant and every agent as processes on a bus",
                       description=__doc__)
    p.add_argument("--case", required=True, help="case number or path to a scenario .toml")
    add_bus_arguments(p)
    p.add_argument("--duration", type=float, help="seconds of price time (default: the "
                   "scenario's duration)")
    p.add_argument("--out", type=Path, help="output directory (default: runs/up-caseN)")
    p.add_argument("--time-scale", type=float, metavar="F",
                   help="stretch the time axis by F (Ts·F, k/F, h/F²: the same discrete "
                   "system) for hosts too slow for Ts = 10 ms, e.g. an emulated guest "
                   f"(default: 1, or {GUEST_TIME_SCALE:g} under tools/vcan-run)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .. import busrun
    from ..scenario import case_path, load_scenario, scaled

    path = Path(args.case) if args.case.endswith(".toml") else case_path(args.case)
    sc = load_scenario(path)
    if sc.variants:
        sc = sc.variant(sc.variants[0].label)
    out = args.out or Path("runs") / f"up-{sc.name}"
    scale = args.time_scale
    if scale is None and os.environ.get("VCAN_RUN_GUEST") == "1":
        scale = GUEST_TIME_SCALE
        print(f"bess-ded up: --time-scale {scale:g} (VCAN_RUN_GUEST=1: the emulated guest is "
              f"too slow for Ts = {sc.ts * 1000:g} ms; give --time-scale 1 to insist)")
    sc = scaled(sc, scale or 1.0)
    duration = args.duration or sc.duration
    bus = busrun.BusOptions(args.interface, args.channel, args.bus_config)
    print(f"bess-ded up: {sc.title or sc.name}: {sc.n} agents + plant + router on "
          f"{bus.resolved()} for {duration:g} s")
    m = busrun.run(sc, out, bus, duration=duration)
    st = m["settling_time_s"]
    settled = "never" if st is None else f"{st:.2f} s"
    if st is not None and scale not in (None, 1.0):
        settled += f" ({st / scale:.2f} s on the unscaled time axis)"
    print(f"  settled (2 %) after {settled}, final max|λ−ρ| = "
          f"{m['final_error']:.2e}, resets per agent {m['resets']}")
    print(f"  frames recorded {m['frames_recorded']}, undecodable "
          f"{sum(m['frames_undecodable'].values())}, missed by the recorder "
          f"{m['frames_missed_by_recorder']}, deadline misses "
          f"{json.dumps(m['deadline_misses'])}")
    if not m["start_recorded"]:
        print("  warning: the recorder missed the start of the run (an agent's first recorded "
              "MC frame is not INIT), so t = 0 is late and the settling time too short")
    print(f"  wrote {out}/run.log, {out}/metrics.json, {out}/bus_run.png")
    return 0
