#!/usr/bin/env python3
"""Fixed point against float: how far the firmware's λ strays from its float twin.

Runs the lockstep simulator (sim/model/lockstep.py) twice per scenario, once with the
fixed-point core (``fixed=True``, what the firmware runs) and once with its float twin
(``fixed=False``, same algorithm in binary64), and reports, per scenario and Ts:

* ``max``   max over time and agents of |λ_fixed − λ_float| (cu/kWh), λ_fixed being the
  λ the agent sends (Q24);
* ``tail``  the same over the last 5 s of the run (after settling);
* ``final`` the same at the last sample;
* ``cycle`` how far the float twin's own λ still moves over the last 5 s (peak to peak,
  max over agents): a slow tail still converging, or the amplitude of a discrete limit
  cycle (finite-time: both twins end on the same cycle, out of phase, so ``tail`` ≈
  ``cycle``);
* ``resets`` resets of the fixed core / of the float twin, and ``moved``: how many reset
  instants are not common to both (per agent, counted in samples); ``first`` the time
  of the first reset that differs (a reset is a sign test on ξ, so two runs whose ξ
  differ by an LSB can reset a sample apart and then follow different transients);
* ``stable`` whether forward Euler at this Ts is stable for the case's gains
  (sim.model.graph.analyse); an unstable combination is reported but not judged.

Scenarios: every paper case (sim/scenarios/case1..7.toml, every variant) at
Ts = 1, 2.5, 5, 10, 50 ms (the case's duration, events and prices unchanged; only Ts),
and random connected regular graphs (seeded; degree 3, or 4 for an odd number of agents)
of 4, 8, 16, 31 and 32 agents at Ts = 10 ms and 1 ms, reset-PI k = 1, h = 2, every 8th
agent pinned, λ(0) uniform in [0.3, 1.2], ρ = 0.8 then 1.0 at 15 s, 30 s long.

Usage::

    python tools/fidelity.py                       # everything, table on stdout
    python tools/fidelity.py --json out.json --png out.png
    python tools/fidelity.py --cases 1 2 --ts 0.01 --no-graphs

Deterministic: the same code gives the same numbers on any machine.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from sim.model.lockstep import run_lockstep
from sim.model.scenario import PriceStep, Scenario, load_case

CASE_TS = (0.001, 0.0025, 0.005, 0.01, 0.05)
GRAPH_SIZES = (4, 8, 16, 31, 32)
GRAPH_TS = (0.01, 0.001)
GRAPH_SEED = 2026
TAIL_S = 5.0


@dataclass(frozen=True)
class Result:
    name: str
    ts: float
    agents: int
    stable: bool
    max: float
    tail: float
    final: float
    cycle: float
    resets_fixed: int
    resets_float: int
    moved: int
    first: float | None
    saturations: int
    seconds: float


def with_ts(sc: Scenario, ts: float) -> Scenario:
    """The same case (duration, prices, events, gains) sampled at another Ts."""
    return replace(sc, ts=ts, controller=replace(sc.controller, ts=ts))


def _moved(a: list[float], b: list[float], ts: float) -> tuple[int, float | None]:
    sa, sb = {round(t / ts) for t in a}, {round(t / ts) for t in b}
    diff = sa ^ sb
    return len(diff), (min(diff) * ts if diff else None)


def compare(name: str, sc: Scenario) -> Result:
    t0 = time.perf_counter()
    fx_tr = run_lockstep(sc, fixed=True)
    fl_tr = run_lockstep(sc, fixed=False)
    d = np.abs(fx_tr.lam - fl_tr.lam).max(axis=1)
    tail = fx_tr.t >= fx_tr.t[-1] - TAIL_S - 1e-9
    moved, first = 0, None
    for ra, rb in zip(fx_tr.resets, fl_tr.resets, strict=True):
        m, f = _moved(ra, rb, sc.ts)
        moved += m
        if f is not None and (first is None or f < first):
            first = f
    return Result(name=name, ts=sc.ts, agents=sc.n, stable=bool(sc.analysis().discrete_stable),
                  max=float(d.max()), tail=float(d[tail].max()), final=float(d[-1]),
                  cycle=float((fl_tr.lam[tail].max(axis=0) - fl_tr.lam[tail].min(axis=0)).max()),
                  resets_fixed=sum(map(len, fx_tr.resets)),
                  resets_float=sum(map(len, fl_tr.resets)), moved=moved, first=first,
                  saturations=int(fx_tr.saturations), seconds=time.perf_counter() - t0)


# --------------------------------------------------------------------------- scenarios


def paper_runs(cases: list[int], ts_list: list[float]) -> list[tuple[str, Scenario]]:
    out = []
    for case in cases:
        base = load_case(case)
        for label, sc in base.runs():
            name = f"case{case}" + (f" {label}" if base.variants else "")
            out.extend((name, with_ts(sc, ts)) for ts in ts_list)
    return out


def random_regular_edges(n: int, degree: int, rng: random.Random) -> list[tuple[int, int]]:
    """A connected simple d-regular graph on agents 1..n (pairing model, rejection)."""
    if n <= degree:
        return [(i, j) for i in range(1, n + 1) for j in range(i + 1, n + 1)]
    for _ in range(10_000):
        stubs = [v for v in range(1, n + 1) for _ in range(degree)]
        rng.shuffle(stubs)
        pairs = {tuple(sorted(stubs[k:k + 2])) for k in range(0, len(stubs), 2)}
        if len(pairs) != len(stubs) // 2 or any(a == b for a, b in pairs):
            continue
        seen, todo = {1}, [1]
        while todo:
            v = todo.pop()
            for a, b in pairs:
                for x, y in ((a, b), (b, a)):
                    if x == v and y not in seen:
                        seen.add(y)
                        todo.append(y)
        if len(seen) == n:
            return sorted(pairs)  # type: ignore[arg-type]
    raise RuntimeError(f"no connected {degree}-regular graph on {n} agents found")


def graph_scenario(n: int, ts: float, seed: int = GRAPH_SEED) -> Scenario:
    rng = random.Random(seed * 1000 + n)
    degree = 4 if n % 2 else 3
    base = load_case(7)                       # batteries and the reset-PI defaults
    edges = tuple((float(a), float(b)) for a, b in random_regular_edges(n, degree, rng))
    bats = tuple(base.batteries[i % base.n] for i in range(n))
    return replace(
        base, name=f"regular{n}", title=f"random {degree}-regular graph, {n} agents",
        ts=ts, duration=30.0, controller=replace(base.controller, kind="reset", k=1.0, h=2.0,
                                                 ts=ts),
        n=n, edges=edges, pinned=tuple(range(1, n + 1, 8)), batteries=bats,
        lambda0=tuple(round(rng.uniform(0.3, 1.2), 6) for _ in range(n)),
        prices=(PriceStep(0.0, 0.8), PriceStep(15.0, 1.0)), events=(),
        variants=())


def graph_runs(sizes: list[int], ts_list: list[float]) -> list[tuple[str, Scenario]]:
    return [(f"regular{n}", graph_scenario(n, ts)) for ts in ts_list for n in sizes]


# --------------------------------------------------------------------------- output


def _e(x: float) -> str:
    return f"{x:.2e}"


def table(results: list[Result]) -> str:
    head = (f"{'scenario':<22} {'Ts ms':>6} {'N':>3} {'stable':>6} {'max':>9} {'tail':>9} "
            f"{'final':>9} {'cycle':>9} {'resets fx/fl':>13} {'moved':>6} {'first s':>8} "
            f"{'sats':>5}")
    rows = [head, "-" * len(head)]
    for r in results:
        first = "-" if r.first is None else f"{r.first:.3f}"
        rows.append(f"{r.name:<22} {r.ts * 1e3:>6g} {r.agents:>3} {str(r.stable):>6} "
                    f"{_e(r.max):>9} {_e(r.tail):>9} {_e(r.final):>9} {_e(r.cycle):>9} "
                    f"{f'{r.resets_fixed}/{r.resets_float}':>13} {r.moved:>6} {first:>8} "
                    f"{r.saturations:>5}")
    return "\n".join(rows)


def plot(results: list[Result], path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r.name for r in results))
    ts_vals = sorted({r.ts for r in results})
    fig, ax = plt.subplots(figsize=(max(8.0, 0.55 * len(names) + 3), 5))
    width = 0.8 / len(ts_vals)
    for k, ts in enumerate(ts_vals):
        xs, ys = [], []
        for i, name in enumerate(names):
            for r in results:
                if r.name == name and r.ts == ts:
                    xs.append(i + (k - (len(ts_vals) - 1) / 2) * width)
                    ys.append(max(r.max, 1e-12) if r.stable else np.nan)
        ax.bar(xs, ys, width=width, label=f"Ts = {ts * 1e3:g} ms")
    ax.set_yscale("log")
    ax.axhline(1e-5, color="k", lw=0.8, ls="--")
    ax.text(len(names) - 0.5, 1e-5, " 1e-5", va="bottom", ha="right", fontsize=8)
    ax.set_xticks(range(len(names)))
    ax.set_xticklabels(names, rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("max |λ_fixed − λ_float| [cu/kWh]")
    ax.set_title(title)
    ax.legend(fontsize=8, ncol=3)
    ax.grid(axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", type=int, nargs="*", default=list(range(1, 8)), metavar="N")
    p.add_argument("--ts", type=float, nargs="*", default=list(CASE_TS), metavar="S",
                   help="sample times of the paper cases, s (default: %(default)s)")
    p.add_argument("--graphs", type=int, nargs="*", default=list(GRAPH_SIZES), metavar="N",
                   help="agents of the random regular graphs (default: %(default)s)")
    p.add_argument("--graph-ts", type=float, nargs="*", default=list(GRAPH_TS), metavar="S")
    p.add_argument("--no-graphs", action="store_true")
    p.add_argument("--json", metavar="FILE", help="write the results as JSON")
    p.add_argument("--png", metavar="FILE", help="plot max |Δλ| per scenario and Ts")
    p.add_argument("--title", default="fixed point against its float twin")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    a = p.parse_args(argv)

    runs = paper_runs(a.cases, a.ts)
    if not a.no_graphs:
        runs += graph_runs(a.graphs, a.graph_ts)
    results: list[Result] = []
    t0 = time.perf_counter()
    for i, (name, sc) in enumerate(runs):
        r = compare(name, sc)
        results.append(r)
        if not a.quiet:
            print(f"[{i + 1}/{len(runs)}] {name} Ts = {sc.ts * 1e3:g} ms: max {_e(r.max)} "
                  f"({r.seconds:.1f} s, {time.perf_counter() - t0:.0f} s so far)",
                  file=sys.stderr, flush=True)
    print(table(results))
    paper = [r for r in results if r.name.startswith("case") and r.stable]
    if paper:
        worst = max(paper, key=lambda r: r.max)
        print(f"\npaper cases (Euler-stable): worst max {_e(worst.max)} ({worst.name}, "
              f"Ts = {worst.ts * 1e3:g} ms)")
    print(f"total {time.perf_counter() - t0:.1f} s")
    if a.json:
        with open(a.json, "w") as f:
            doc: dict[str, Any] = {"results": [asdict(r) for r in results]}
            json.dump(doc, f, indent=1, default=lambda x: None if x != x else x)
    if a.png:
        plot(results, a.png, a.title)
    return 0 if all(math.isfinite(r.max) for r in results) else 1


if __name__ == "__main__":
    raise SystemExit(main())
