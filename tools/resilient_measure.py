#!/usr/bin/env python3
"""Measure the resilient (W-MSR) update against one lying agent, in the lockstep.

For every agent of the scenario as the liar and every lie (tests/test_resilient.py's
LIES: tests/deviant_agent.py's LIE-LAMBDA and LIE-RAMP, and a constant +0.5 / −0.3
cu/kWh), the largest final |ΔP| of an honest battery against the honest run (the default
update, no liar), with the trimming off (F = 0) and on (the scenario's F, else 1). The
graph condition is printed first (sim.model.robust). docs/security.md quotes the output.

Usage: ``python tools/resilient_measure.py [SCENARIO]`` (default
examples/resilient_ring7.toml).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))  # this worktree's firmware_py and sim

from firmware_py import fixedpoint as fx  # noqa: E402
from sim.model.lockstep import run_lockstep  # noqa: E402
from sim.model.robust import resilience  # noqa: E402
from sim.model.scenario import load_scenario  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenario", nargs="?", default=str(ROOT / "examples" /
                                                      "resilient_ring7.toml"))
    args = p.parse_args(argv)
    sc = load_scenario(args.scenario)
    f = sc.resilient_f or 1
    ts = sc.ts
    lies = {
        "LIE-LAMBDA (+0.0024)": lambda k, lam: lam + fx.to_fixed(0.0024),
        "LIE-RAMP (+0.002/s)": lambda k, lam: lam + fx.to_fixed(0.002 * k * ts),
        "+0.5": lambda k, lam: lam + fx.to_fixed(0.5),
        "-0.3": lambda k, lam: lam - fx.to_fixed(0.3),
    }
    print(f"{sc.name}: {sc.n} agents, pinned {list(sc.pinned)}, {sc.duration:g} s")
    for line in resilience(sc.n, sc.edges, sc.pinned, f).describe():
        print(line)
    ref = np.array(run_lockstep(replace(sc, resilient_f=0)).p)[-1]
    print(f"largest final |ΔP| of an honest battery against the honest run, kW "
          f"(F = 0 | F = {f}); the liar in rows")
    print(f"{'liar':>4}  " + "  ".join(f"{name:>22}" for name in lies))
    worst = {0: 0.0, f: 0.0}
    for liar in range(1, sc.n + 1):
        honest = [i for i in range(sc.n) if i != liar - 1]
        cells = []
        for lie in lies.values():
            moved = []
            for trim in (0, f):
                p_end = np.array(run_lockstep(replace(sc, resilient_f=trim),
                                              lies={liar: lie}).p)[-1]
                moved.append(float(np.max(np.abs(p_end[honest] - ref[honest]))))
                worst[trim] = max(worst[trim], moved[-1])
            cells.append(f"{moved[0]:9.3f} | {moved[1]:9.3f}")
        print(f"{liar:>4}  " + "  ".join(f"{c:>22}" for c in cells))
    print(f"worst: F = 0 {worst[0]:.3f} kW, F = {f} {worst[f]:.3f} kW")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
