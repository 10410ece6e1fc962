"""Continuous-time hybrid reference: the paper's consensus integrated exactly, resets located.

The discrete firmware (sim/model/lockstep.py) runs forward Euler at Ts in Q24; this module
is the continuous-time system it approximates, so the two can be compared and the
discretisation error measured (tests/test_reference.py).

Between events the base system is linear with a constant input. With x = [λ; ν],

    ξ = M λ + d,         M = H restricted to the agents on the network, d = −ρ·b
    λ̇ = −k ξ − h ν,      ν̇ = ξ          (PC: λ̇ = −k ξ, ν ≡ 0)

so z = [x; 1] obeys ż = G z with G = [[A, c], [0, 0]] and z(t+τ) = expm(G τ) z(t):
the flow is exact, there is no integrator tolerance to trust. Inactive (isolated)
agents have zero rows in M and d, so their λ stays where the isolate event put it.

The hybrid part mirrors firmware_py/controllers.py, in continuous time:

* a reset happens when ξ_i changes sign (reset and dwell kinds) and
  - the agent is *armed*: |ξ_i| has exceeded ``band`` since its last reset (band 0:
    always armed, plain Clegg). The start and a reconnection count as armed;
  - for kind "dwell", t − t_last ≥ Δ, with t_last = 0 at the start (the start counts
    as a reset, ν(0) = 0) and t_last = t_reconnect after a plug-in (the firmware does
    not step while isolated, so its dwell clock restarts there);
* a reset sets ν_i := 0; λ is continuous, so ξ is too;
* a price step or plug event makes ξ jump; a jump across zero is a crossing at the
  event instant (the firmware sees it as a sign change between two samples). An
  isolated agent's λ is set to its idle MC (1+m)β and held; its neighbours drop it.

Crossings are bracketed on a fine grid (Ts/10 by default) of the exact solution and
located with brentq on the exact solution to ``xtol`` (1e-12 s). Arming is decided
exactly too: |ξ_i| on a grid step is checked at the ends and at an interior extremum
(a sign change of ξ̇_i, itself linear in z). A crossing back right after a reset (ν_i := 0
can turn ξ̇_i round) is found the same way, past the turn. Limitation: a ξ_i that dips
across zero and back within one fine step, away from a reset, is missed; that needs
|μ|·Ts/10 ≳ 1, and the paper's cases have |μ| ≤ 48 s⁻¹ (case 3, k = 10) against 1 ms.

The finite-time baseline (kind "ft", u = −k sign(ξ)|ξ|^a) is not supported: its
right-hand side is not Lipschitz at ξ = 0 and has no closed-form flow, so an
"exact" reference would only be an ODE solver's chattering at its tolerance.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm  # type: ignore[import-untyped]
from scipy.optimize import brentq  # type: ignore[import-untyped]

from sim.model import graph
from sim.model.scenario import Scenario
from sim.model.trajectory import Trajectory

SUPPORTED = ("pc", "pi", "reset", "dwell")


@dataclass(frozen=True)
class BaseSystem:
    """The affine flow of one mode (active set, price): ż = G z, ξ = C z, ξ̇ = Cd z."""

    g: np.ndarray    # (2N+1, 2N+1) augmented generator
    c: np.ndarray    # (N, 2N+1) ξ = c @ z
    cd: np.ndarray   # (N, 2N+1) ξ̇ = cd @ z

    def flow(self, tau: float) -> np.ndarray:
        """exp(G·tau): the mode's state transition over ``tau`` s."""
        return expm(self.g * tau)


def base_system(sc: Scenario, active: np.ndarray, rho: float) -> BaseSystem:
    """G, C and Ċ for the agents in ``active`` at price ρ (the graph rebuilt over them)."""
    n, ctl = sc.n, sc.controller
    on = np.asarray(active, dtype=bool)
    a = sc.adjacency * np.outer(on, on)          # edges to isolated agents dropped
    b = np.array([1.0 if i + 1 in sc.pinned else 0.0 for i in range(n)]) * on
    m = graph.laplacian(a) + np.diag(b)
    d = -rho * b
    integral = ctl.kind != "pc"
    gen = np.zeros((2 * n + 1, 2 * n + 1))
    gen[:n, :n] = -ctl.k * m
    gen[:n, 2 * n] = -ctl.k * d
    if integral:
        gen[:n, n:2 * n] = -ctl.h * np.diag(on.astype(float))
        gen[n:2 * n, :n] = m
        gen[n:2 * n, 2 * n] = d
    c = np.zeros((n, 2 * n + 1))
    c[:, :n] = m
    c[:, 2 * n] = d
    return BaseSystem(gen, c, c @ gen)


class _Hybrid:
    """Reset bookkeeping and the exact flow between grid points for one run."""

    def __init__(self, sc: Scenario, xtol: float) -> None:
        ctl = sc.controller
        self.sc, self.n, self.xtol = sc, sc.n, xtol
        self.resetting = ctl.kind in ("reset", "dwell")
        self.dwell = ctl.dwell if ctl.kind == "dwell" else 0.0
        self.band = ctl.band
        self.z = np.concatenate([np.asarray(sc.lambda0, float), np.zeros(sc.n), [1.0]])
        self.active = np.ones(sc.n, dtype=bool)
        self.side = np.zeros(sc.n)            # sign of ξ_i since its last crossing (0: unknown)
        self.armed = np.ones(sc.n, dtype=bool)
        self.t_last = np.zeros(sc.n)
        self.resets: list[list[float]] = [[] for _ in range(sc.n)]
        self.sys: BaseSystem
        self.step_flow: np.ndarray
        self.fine = 0.0

    # ---- modes and events

    def set_mode(self, t: float, rho: float, fine: float) -> None:
        """Enter a new mode at an event; a jump of ξ across zero is a crossing at t."""
        self.sys = base_system(self.sc, self.active, rho)
        self.fine = fine
        self.step_flow = self.sys.flow(fine)
        xi = self.xi(self.z)
        if self.resetting:
            crossed = self.active & (((self.side > 0) & (xi <= 0)) | ((self.side < 0) & (xi >= 0)))
            for i in np.flatnonzero(crossed).tolist():
                if self._crossing(i, t):
                    self.z[self.n + i] = 0.0
            self.armed |= np.abs(xi) > self.band
        self.side = np.where(self.active & (xi != 0), np.sign(xi), self.side)

    def isolate(self, i: int) -> None:
        self.active[i] = False
        self.z[i] = self.sc.batteries[i].idle_lambda
        self.z[self.n + i] = 0.0
        self.side[i] = 0.0

    def reconnect(self, i: int, t: float) -> None:
        self.active[i] = True
        self.armed[i] = True
        self.t_last[i] = t
        self.side[i] = 0.0   # no crossing at the plug-in itself

    def xi(self, z: np.ndarray) -> np.ndarray:
        return self.sys.c @ z

    # ---- exact flow with located crossings

    def advance(self, a: float, b: float) -> None:
        """Flow from a to b (at most one fine step), resetting at every crossing on the way."""
        z, just = self.z, set[int]()
        while True:
            span = b - a
            zb = (self.step_flow if abs(span - self.fine) < 1e-12 else self.sys.flow(span)) @ z
            if not self.resetting:
                self.z = zb
                return
            xb = self.xi(zb)
            cand = self.active & (self.side != 0) & (self.side * xb <= 0)
            roots = [(r, i) for i in np.flatnonzero(cand).tolist()
                     if (r := self._root(i, z, zb, span, i in just)) is not None]
            if not roots:
                self._arm(z, zb, span)
                self.side = np.where(self.active & (xb != 0), np.sign(xb), self.side)
                self.z = zb
                return
            tau, i = min(roots)
            zt = self.sys.flow(tau) @ z
            self._arm(z, zt, tau)
            if self._crossing(i, a + tau):
                zt[self.n + i] = 0.0
            self.side[i] = -self.side[i]
            just = (just if tau == 0 else set()) | {i}
            z, a = zt, a + tau

    def _crossing(self, i: int, t: float) -> bool:
        """ξ_i changed sign at t: reset (the caller zeroes ν_i) if armed and Δ has elapsed."""
        if not (self.armed[i] and t - self.t_last[i] >= self.dwell):
            return False
        self.t_last[i] = t
        self.armed[i] = False
        self.resets[i].append(t)
        return True

    def _at(self, row: np.ndarray, z: np.ndarray, tau: float) -> float:
        """row · z(τ), exactly (used inside the root finders)."""
        return float(row @ (self.sys.flow(tau) @ z))

    def _extremum(self, i: int, z: np.ndarray, zb: np.ndarray, span: float) -> float | None:
        """Where ξ̇_i changes sign inside (0, span), if it does."""
        cd = self.sys.cd[i]
        if (cd @ z) * (cd @ zb) >= 0:
            return None
        return brentq(lambda s: self._at(cd, z, s), 0.0, span, xtol=self.xtol)

    def _root(self, i: int, z: np.ndarray, zb: np.ndarray, span: float,
              just_crossed: bool) -> float | None:
        """First τ in [0, span] where ξ_i leaves its side (None: no real crossing)."""
        s, c = self.side[i], self.sys.c[i]
        lo = 0.0
        if s * (c @ z) <= 0:
            if not just_crossed:
                return 0.0        # on the line already: a tie with the crossing just handled
            turn = self._extremum(i, z, zb, span)   # ξ_i must turn before it can cross back
            if turn is None or s * self._at(c, z, turn) <= 0:
                return None
            lo = turn
        return brentq(lambda tau: s * self._at(c, z, tau), lo, span, xtol=self.xtol)

    def _arm(self, z: np.ndarray, zb: np.ndarray, span: float) -> None:
        """Arm every disarmed agent whose |ξ_i| exceeded the band on [0, span]."""
        for i in np.flatnonzero(self.active & ~self.armed).tolist():
            c = self.sys.c[i]
            peak = max(abs(c @ z), abs(c @ zb))
            if peak <= self.band and (tau := self._extremum(i, z, zb, span)) is not None:
                peak = abs(self._at(c, z, tau))
            self.armed[i] = peak > self.band


def run_reference(sc: Scenario, progress: Callable[[int, int], None] | None = None,
                  substeps: int = 10, xtol: float = 1e-12) -> Trajectory:
    """The exact hybrid trajectory of ``sc``, sampled at t_k = k·Ts like run_lockstep.

    ``substeps`` fine steps per Ts bracket the zero crossings; ``xtol`` (s) is the
    precision of the located reset instants in ``Trajectory.resets``.
    """
    ctl = sc.controller
    if ctl.kind not in SUPPORTED:
        raise NotImplementedError(
            f"run_reference supports kinds {', '.join(SUPPORTED)}, not {ctl.kind!r}: the "
            "finite-time law is not Lipschitz at ξ = 0 and has no exact flow")
    ts, n, steps = sc.ts, sc.n, sc.steps + 1
    fine = ts / substeps
    hy = _Hybrid(sc, xtol)

    lam, u, xi, nu, p = (np.zeros((steps, n)) for _ in range(5))
    act = np.zeros((steps, n), dtype=bool)
    rho_arr, seg_arr = np.zeros(steps), np.zeros(steps, dtype=int)

    def record(k: int, t: float) -> None:
        z, x = hy.z, hy.xi(hy.z)
        lam[k], nu[k], xi[k], act[k] = z[:n], z[n:2 * n], x, hy.active
        u[k] = np.where(hy.active, -ctl.k * x - (ctl.h * z[n:2 * n] if ctl.kind != "pc" else 0), 0)
        rho_arr[k], seg_arr[k] = sc.price_at(t)
        if progress is not None and k % 500 == 0:
            progress(k, steps)

    def sample_index(t: float) -> int | None:
        k = round(t / ts)
        return k if abs(t - k * ts) < 1e-9 and k < steps else None

    end = (steps - 1) * ts
    breaks = sorted({0.0, end} | {s.t for s in sc.prices if s.t < end}
                    | {e.t for e in sc.events if e.t <= end})
    for s0, s1 in zip(breaks, breaks[1:] + [math.inf], strict=True):
        for e in sc.events:
            if e.t == s0 and e.action == "isolate":
                hy.isolate(e.agent - 1)
            elif e.t == s0:
                hy.reconnect(e.agent - 1, s0)
        hy.set_mode(s0, sc.price_at(s0)[0], fine)
        if (k := sample_index(s0)) is not None:
            record(k, s0)
        if s1 == math.inf:
            break
        j = math.floor(s0 / fine + 1e-9) + 1          # first fine grid point after s0
        a = s0
        while a < s1:
            b = j * fine
            if b >= s1 - 1e-9:
                b = s1
            hy.advance(a, b)
            if b < s1 and j % substeps == 0:
                record(j // substeps, b)
            a, j = b, j + 1

    for i, bat in enumerate(sc.batteries):
        p[:, i] = np.where(act[:, i], bat.power(lam[:, i]), 0.0)
    return Trajectory(t=np.arange(steps) * ts, lam=lam, rho=rho_arr, segment=seg_arr,
                      active=act, p=p, u=u, xi=xi, nu=nu, resets=hy.resets,
                      saturations=0, label=f"{ctl.kind} (continuous reference)")
