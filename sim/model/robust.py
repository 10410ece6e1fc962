"""The graph condition of the resilient (W-MSR) update: r-robustness and (r, s)-robustness.

LeBlanc, Zhang, Koutsoukos & Sundaram, "Resilient asymptotic consensus in robust networks"
(IEEE JSAC 31(4), 2013). A set S of agents is *r-reachable* when some agent of S has at
least r neighbours outside S. Let X_S = the agents of S with at least r neighbours outside
S. The graph is (r, s)-robust when, for every pair of disjoint nonempty sets S1, S2, at
least one of |X_S1| = |S1|, |X_S2| = |S2|, |X_S1| + |X_S2| ≥ s holds; r-robust is
(r, 1)-robust. W-MSR with parameter F reaches consensus among the honest agents, within
the range of their own values, when

* at most F agents in all lie (F-total) and the graph is (F+1, F+1)-robust;
* at most F of every honest agent's neighbours lie (F-local) and the graph is (2F+1)-robust.

Deciding robustness is coNP-complete. The check here is exact: with x(S) = |X_S| and the
"deficient" sets D = {S : x(S) < |S|}, the graph fails (r, s) iff two disjoint sets of D
have x(S1) + x(S2) < s. g(T) = min {x(S) : S ∈ D, ∅ ≠ S ⊆ T} is a subset-minimum, taken for
every T by one sum-over-subsets pass, so the test is x(S) + g(V \\ S) ≥ s for every S ∈ D:
O(n·2^n) time and O(2^n) memory instead of the 3^n pairs. Graphs of more than
``EXACT_MAX_AGENTS`` agents are not checked (2^20 sets take ~1 s and 10 MB here).
Neighbours are counted, not weighted: W-MSR discards values by rank, whatever their weight.

Those conditions are for consensus on *some* value. Here the honest agents must agree on
the price ρ, which only the pinned agents hear (its term is never trimmed): ``price_robust``
checks that no set of honest agents can hold a common value off ρ, whichever F agents lie
(it needs at least 2F + 1 pinned agents). Both are the first-order theory's conditions;
the reset-PI loop is checked by measurement (tests/test_resilient.py, docs/security.md).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from itertools import combinations
from math import comb

import numpy as np

EXACT_MAX_AGENTS = 20
# price_robust's work: (liar sets) × 2^(unpinned agents) sets; 2^24 take ~5 s here
PRICE_CHECK_MAX_SETS = 1 << 24


def _masks(n: int, edges: Iterable[Sequence[float]]) -> list[int]:
    """Each agent's neighbours as a bit mask (0-based bits, 1-based agents in ``edges``)."""
    nbr = [0] * n
    for e in edges:
        i, j = int(e[0]) - 1, int(e[1]) - 1
        nbr[i] |= 1 << j
        nbr[j] |= 1 << i
    return nbr


def is_robust(n: int, edges: Iterable[Sequence[float]], r: int, s: int = 1) -> bool:
    """Is the undirected graph of ``n`` agents and ``edges`` (r, s)-robust (exact)?
    ValueError above EXACT_MAX_AGENTS agents, or for r < 1 or s < 1."""
    if n > EXACT_MAX_AGENTS:
        raise ValueError(f"the exact robustness check takes at most {EXACT_MAX_AGENTS} "
                         f"agents (O(n·2^n)), but got {n}")
    if r < 1 or s < 1:
        raise ValueError(f"expected r ≥ 1 and s ≥ 1, but got r = {r}, s = {s}")
    if n < 2:
        return True  # no two disjoint nonempty sets
    full = (1 << n) - 1
    sets = np.arange(1 << n, dtype=np.int64)
    size = np.bitwise_count(sets).astype(np.int64)
    x = np.zeros(1 << n, dtype=np.int64)          # x(S): agents of S reaching ≥ r outside
    for i, nb in enumerate(_masks(n, edges)):
        outside = np.bitwise_count(np.int64(nb) & (full ^ sets))
        x += ((sets >> i) & 1) * (outside >= r)
    big = np.int64(n + 1)
    g = np.where((x < size) & (sets != 0), x, big)  # D's x, "none" elsewhere
    for i in range(n):  # sum over subsets: g(T) = min over D's subsets of T
        bit = np.int64(1 << i)
        with_bit = (sets & bit) != 0
        g[with_bit] = np.minimum(g[with_bit], g[sets[with_bit] ^ bit])
    deficient = (x < size) & (sets != 0)
    return not bool(np.any(x[deficient] + g[full ^ sets[deficient]] < s))


def max_robustness(n: int, edges: Sequence[Sequence[float]]) -> int:
    """The largest r for which the graph is r-robust (0 if it is not even 1-robust, that
    is, disconnected); ValueError above EXACT_MAX_AGENTS agents."""
    r = 0
    while r < n and is_robust(n, edges, r + 1):
        r += 1
    return r


def _stuck_free(n: int, nbr: Sequence[int], pinned: int, liars: int, need: int) -> bool:
    """No nonempty set C of agents outside ``pinned`` | ``liars`` (bit masks) in which
    every agent has fewer than ``need`` neighbours outside C and the liars."""
    free = [i for i in range(n) if not (pinned | liars) >> i & 1]
    idx = np.arange(1 << len(free), dtype=np.int64)
    sets = np.zeros_like(idx)
    for k, i in enumerate(free):   # the subsets of the free agents, as masks over all n
        sets |= ((idx >> k) & 1) << i
    reached = np.zeros(len(idx), dtype=bool)
    for i in free:
        outside = np.bitwise_count(np.int64(nbr[i]) & ~(sets | np.int64(liars)))
        reached |= (((sets >> i) & 1) == 1) & (outside >= need)
    return bool(np.all(reached[1:]))


def price_robust(n: int, edges: Iterable[Sequence[float]], pinned: Iterable[int],
                 f: int) -> bool:
    """Does the price reach every honest agent through the trimming, whichever ``f``
    agents lie? Exact: for every set L of at most f agents and every nonempty set C of
    agents neither pinned nor in L, some agent of C has at least f + 1 neighbours outside
    C and L. Otherwise the honest agents of such a C can hold one value off ρ for good:
    each drops its only (≤ f) neighbours on ρ's side as extremes, and none hears ρ itself
    (W-MSR's max-set argument with the price as a trusted input that is never trimmed).
    ValueError above EXACT_MAX_AGENTS agents."""
    if n > EXACT_MAX_AGENTS:
        raise ValueError(f"the exact check takes at most {EXACT_MAX_AGENTS} agents, but got {n}")
    nbr = _masks(n, edges)
    pin = sum(1 << (p - 1) for p in pinned)
    return all(_stuck_free(n, nbr, pin, sum(1 << i for i in liars), f + 1)
               for size in range(f + 1) for liars in combinations(range(n), size))


@dataclass(frozen=True)
class ResilienceReport:
    """W-MSR's graph conditions for ``f`` liars; None where not checked (too large)."""

    f: int
    n: int
    f_total: bool | None     # (F+1, F+1)-robust: honest agents agree, F liars in all
    f_local: bool | None     # (2F+1)-robust: F liars per neighbourhood
    price: bool | None       # price_robust: that agreement is ρ, whichever F lie

    @property
    def tolerates(self) -> bool | None:
        """Both conditions of an F-total liar set: the honest λ converge to ρ."""
        if self.f_total is None or self.price is None:
            return None
        return self.f_total and self.price

    def describe(self) -> list[str]:
        """The lines `bess-ded case` prints."""
        f, s = self.f, "s" if self.f > 1 else ""
        head = f"resilient update (W-MSR, F = {f}): "
        if self.f_total is None:
            return [head + f"graph condition not checked ({self.n} agents; the exact check "
                    f"is O(n·2^n), done up to {EXACT_MAX_AGENTS})"]

        def yn(x: bool | None) -> str:
            return "not checked (too many sets)" if x is None else "yes" if x else "no"
        return [head + f"tolerates {f} lying agent{s}: {yn(self.tolerates)}",
                f"  {f} liar{s} in all (F-total) needs ({f + 1}, {f + 1})-robust: "
                f"{yn(self.f_total)}; {f} per neighbourhood (F-local) needs "
                f"{2 * f + 1}-robust: {yn(self.f_local)}",
                f"  the price reaches every honest agent whichever {f} lie{'' if s else 's'} "
                f"(needs at least {2 * f + 1} pinned agents): {yn(self.price)}"]


def resilience(n: int, edges: Sequence[Sequence[float]], pinned: Sequence[int],
               f: int) -> ResilienceReport:
    """W-MSR's graph conditions for ``f`` liars (f ≥ 1) on this graph."""
    if n > EXACT_MAX_AGENTS:
        return ResilienceReport(f, n, None, None, None)
    work = sum(comb(n, size) for size in range(f + 1)) << (n - len(set(pinned)))
    price = price_robust(n, edges, pinned, f) if work <= PRICE_CHECK_MAX_SETS else None
    return ResilienceReport(f, n, is_robust(n, edges, f + 1, f + 1),
                            is_robust(n, edges, 2 * f + 1), price)
