"""Communication-graph analysis: Laplacian, pinning, H = L + B and the stability tests.

Agents are numbered 1..N in scenarios and in the DBC; arrays here are 0-based.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np


def adjacency(n: int, edges: Iterable[Sequence[float]]) -> np.ndarray:
    """Symmetric adjacency from 1-based (i, j) or (i, j, weight) edges."""
    a = np.zeros((n, n))
    for edge in edges:
        i, j = int(edge[0]) - 1, int(edge[1]) - 1
        w = float(edge[2]) if len(edge) > 2 else 1.0
        a[i, j] = a[j, i] = w
    return a


def laplacian(a: np.ndarray) -> np.ndarray:
    """The graph Laplacian D − A of adjacency ``a``."""
    return np.diag(a.sum(axis=1)) - a


def pinning(n: int, pinned: Iterable[int], weight: float = 1.0) -> np.ndarray:
    """The n×n pinning matrix B: ``weight`` on the diagonal of each pinned agent
    (1-based), 0 elsewhere."""
    b = np.zeros((n, n))
    for i in pinned:
        b[i - 1, i - 1] = weight
    return b


def h_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """H = L + B, whose eigenvalues decide regularity and discrete stability."""
    return laplacian(a) + b


def eigenvalues(h: np.ndarray) -> np.ndarray:
    """Eigenvalues of the symmetric H, ascending."""
    return np.linalg.eigvalsh(h)


def base_eigenvalues(h: np.ndarray, k: float, hgain: float) -> np.ndarray:
    """μ = (−kη ± √(k²η² − 4hη))/2 for every η of H: the PI base system's spectrum."""
    eta = eigenvalues(h).astype(complex)
    root = np.sqrt(k * k * eta * eta - 4 * hgain * eta)
    return np.concatenate([(-k * eta + root) / 2, (-k * eta - root) / 2])


def unpinned_components(n: int, edges: Iterable[Sequence[float]],
                        pinned: Iterable[int]) -> list[list[int]]:
    """The connected components (1-based agents, sorted) that hold no pinned agent.

    Such agents never hear the price, directly or through a neighbour: H = L + B is
    then singular and their λ cannot converge to ρ.
    """
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for edge in edges:
        a, b = root(int(edge[0]) - 1), root(int(edge[1]) - 1)
        parent[a] = b
    reached = {root(p - 1) for p in pinned}
    comps: dict[int, list[int]] = {}
    for i in range(n):
        if root(i) not in reached:
            comps.setdefault(root(i), []).append(i + 1)
    return sorted(comps.values())


@dataclass(frozen=True)
class GraphReport:
    """A graph's analysis for a controller: H's eigenvalues, regularity
    (Theorem 1), discrete-time stability at Ts, and the numbers behind them."""

    eta: tuple[float, ...]
    eta_max: float
    eta_min: float
    regular: bool          # Theorem 1: k > 0 and 4h > η_max k²
    discrete_stable: bool  # forward Euler at Ts: |1 + Ts μ| < 1 for every μ
    spectral_radius: float  # max |1 + Ts μ|
    # what the verdicts were computed from, so describe() can show the numbers
    k: float = math.nan
    h: float = math.nan
    ts: float = math.nan
    kind: str = "reset"

    @property
    def uses_theorem_1(self) -> bool:
        """Theorem 1 is about the PI base system; PC and finite-time have no h."""
        return self.kind not in ("pc", "ft")

    def regular_line(self) -> str:
        """'regular (Theorem 1): yes, 4h = 8 > η_max·k² = 4.79' or why not."""
        if not self.uses_theorem_1:
            return f"regular (Theorem 1): n/a for {self.kind} (no integral gain h)"
        rhs = self.eta_max * self.k * self.k
        lhs = f"4h = {_g(4 * self.h)}"
        if self.regular:
            return f"regular (Theorem 1): yes, {lhs} > η_max·k² = {_g(rhs)}"
        if not self.k > 0:
            return f"regular (Theorem 1): no: k = {_g(self.k)} (Theorem 1 needs k > 0)"
        return (f"regular (Theorem 1): no: {lhs} ≤ η_max·k² = {_g(rhs)} "
                "(Theorem 1 needs 4h > η_max·k²)")

    def stability_line(self) -> str:
        """'discrete-time stable at Ts = 10 ms: yes, max|1 + Ts·μ| = 0.9952' or why not."""
        what = "max|1 + Ts·μ|" if self.uses_theorem_1 else "max|1 − Ts·k·η|"
        head = f"discrete-time stable at Ts = {self.ts * 1e3:g} ms:"
        r = _radius(self.spectral_radius)
        if self.discrete_stable:
            return f"{head} yes, {what} = {r}"
        return f"{head} no: {what} = {r} ≥ 1: lower Ts or the gains"

    def describe(self) -> list[str]:
        """Human lines for the CLI: η_max(H), regularity and discrete stability, each
        with the numbers that decide it."""
        return [f"η_max(H) = {self.eta_max:.4f}, η_min(H) = {self.eta_min:.4f}",
                self.regular_line(), self.stability_line()]

    def verdict(self) -> str:
        """A short cell for tables: 'yes', 'no', 'yes, unstable at Ts'."""
        reg = "n/a" if not self.uses_theorem_1 else ("yes" if self.regular else "no")
        return reg if self.discrete_stable else f"{reg}; unstable at Ts"


def _radius(r: float) -> str:
    """4 decimals, more when that would print a radius ≠ 1 as 1.0000 (the verdict hinges
    on < 1); exactly 1 (marginal) prints as 1."""
    if r == 1:
        return "1"
    digits = 4
    while round(r, digits) == 1 and digits < 12:
        digits += 1
    return f"{r:.{digits}f}"


def _g(x: float) -> str:
    """3-4 significant digits, no trailing zeros: 8, 4.79, 119.8."""
    return f"{x:.4g}" if abs(x) >= 100 else f"{x:.3g}"


def analyse(h: np.ndarray, k: float, hgain: float, ts: float, kind: str = "reset") -> GraphReport:
    """Regularity (continuous) and forward-Euler stability (discrete) of the base system.

    For PC the base system is λ̇ = −kHλ, so the check is |1 − Ts k η| < 1.
    """
    eta = eigenvalues(h)
    if kind in ("pc", "ft"):
        mus = -k * eta.astype(complex)
    else:
        mus = base_eigenvalues(h, k, hgain)
    radius = float(np.max(np.abs(1 + ts * mus)))
    return GraphReport(eta=tuple(float(e) for e in eta), eta_max=float(eta[-1]),
                       eta_min=float(eta[0]), regular=bool(k > 0 and 4 * hgain > eta[-1] * k * k),
                       discrete_stable=radius < 1, spectral_radius=radius, k=float(k),
                       h=float(hgain), ts=float(ts), kind=kind)


def describe(h: np.ndarray, k: float, hgain: float, ts: float, kind: str = "reset") -> list[str]:
    """``analyse(...).describe()``: the lines `case`, `compare` and `up` print."""
    return analyse(h, k, hgain, ts, kind).describe()


def failover_choice(n: int, edges: Iterable[Sequence[float]], pinned: Iterable[int],
                    live: Iterable[int]) -> list[int]:
    """The pinned-agent failover's choice (docs/faults.md): the agents to pin so that the
    price reaches every ``live`` agent again. The graph of the live agents (the edges
    between two of them) falls into connected components; each that holds no live
    ``pinned`` agent gets one: its agent with the most live neighbours, ties by the
    lowest id. Sorted; empty if every live agent already hears the price."""
    up = set(live)
    kept = [e for e in edges if int(e[0]) in up and int(e[1]) in up]
    degree = dict.fromkeys(up, 0)
    for e in kept:
        degree[int(e[0])] += 1
        degree[int(e[1])] += 1
    chosen = []
    for comp in unpinned_components(n, kept, set(pinned) & up):
        members = [i for i in comp if i in up]  # an agent not live is a component alone
        if members:
            chosen.append(min(members, key=lambda i: (-degree[i], i)))
    return sorted(chosen)
