"""Scenarios made, not written: a fleet of any size on a random regular graph.

For the simulator's scale (up to SIM_MAX_AGENTS agents: the lockstep, ``bess-ded bench``,
sweeps) and for studies over many graphs. The scenario is built as the TOML data a user
would write and parsed by ``parse_scenario``, so it passes every check a file does. The
batteries are case 1's four, cycled, each with its α scaled by a seeded factor in
[1, 1.5) so that no two agents are alike; λ(0) is drawn in [0.2, 1.4] cu/kWh.
"""

from __future__ import annotations

from typing import Any

import networkx as nx
import numpy as np

from firmware_py.errors import ParameterError
from sim.model.scenario import SIM_MAX_AGENTS, Scenario, load_case, parse_scenario

# networkx builds a random regular graph by pairing; a disconnected draw is redrawn
_DRAWS = 100


def random_regular_edges(n: int, degree: int, seed: int) -> list[list[int]]:
    """The edges (1-based, each once) of a connected random ``degree``-regular graph on
    ``n`` agents; ParameterError if there is none (n·degree odd, degree ≥ n)."""
    if not 1 <= degree < n or (n * degree) % 2:
        raise ParameterError("degree", f"an integer in [1, {n - 1}] with n·degree even "
                             f"(n = {n})", degree)
    rng = np.random.default_rng(seed)
    for _ in range(_DRAWS):
        g = nx.random_regular_graph(degree, n, seed=int(rng.integers(1 << 31)))
        if nx.is_connected(g):
            return sorted([min(a, b) + 1, max(a, b) + 1] for a, b in g.edges())
    raise ParameterError("degree", f"a degree whose random regular graphs on {n} agents "
                         f"are connected ({_DRAWS} draws were not)", degree)


def random_fleet(n: int, degree: int = 3, seed: int = 0, pinned: int = 1,
                 duration: float = 30.0, ts: float = 0.01, rho: float = 0.8,
                 controller: dict[str, Any] | None = None) -> dict[str, Any]:
    """The scenario data (as in a TOML file, docs/scenarios.md) of ``n`` agents on a
    random ``degree``-regular graph, the first ``pinned`` of a seeded permutation
    hearing the price ``rho``."""
    if not 1 <= n <= SIM_MAX_AGENTS:
        raise ParameterError("n", f"a number of agents in [1, {SIM_MAX_AGENTS}]", n)
    if not 1 <= pinned <= n:
        raise ParameterError("pinned", f"a number of pinned agents in [1, {n}]", pinned)
    rng = np.random.default_rng(seed)
    edges = random_regular_edges(n, degree, seed) if n > 1 else []
    base = load_case(1).batteries
    batteries = []
    for i in range(n):
        b = base[i % len(base)]
        batteries.append({
            "lambda0": round(float(rng.uniform(0.2, 1.4)), 4),
            "alpha": round(b.alpha * float(rng.uniform(1.0, 1.5)), 6), "beta": b.beta,
            "m": b.m, "p_min": b.p_min, "p_max": b.p_max, "capacity_kwh": b.capacity_kwh,
            "soc0": b.soc0})
    return {
        "name": f"random-{n}x{degree}-s{seed}",
        "title": f"{n} BESSs on a random {degree}-regular graph (seed {seed})",
        "ts": ts, "duration": duration, "load_kw": 75.0 * n,
        "graph": {"agents": n, "edges": edges,
                  "pinned": sorted(int(a) + 1 for a in rng.permutation(n)[:pinned])},
        "controller": controller or {"kind": "reset", "k": 1.0, "h": 2.0},
        "price": [{"t": 0.0, "rho": rho}],
        "battery": batteries,
    }


def random_scenario(n: int, degree: int = 3, seed: int = 0, **kw: Any) -> Scenario:
    """``random_fleet``'s data as a validated Scenario."""
    data = random_fleet(n, degree, seed, **kw)
    return parse_scenario(data, f"<{data['name']}>")
