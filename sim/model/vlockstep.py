"""The lockstep, vectorised over agents: firmware_py's fixed-point step on numpy int64 arrays.

The same sample as sim.model.lockstep's per-agent loop, bit for bit (tests/test_vlockstep.py
checks every paper case and the controller vectors): every agent computes ξ from the wire λ
its active neighbours hold at the sample, then steps its controller. The arithmetic is
firmware_py/fixedpoint.py's, written once over arrays instead of once per agent:

* ξ_i = sat32(Σ_j mul(a_ij, Λ_i − Λ_j) + mul(b_i, Λ_i − ρ)), each product rounded to
  nearest, ties toward +∞ (``(a·d + 2^23) >> 24``; numpy's ``>>`` on int64 is arithmetic,
  a floor, as Python's);
* the PI family (pi, reset, dwell) and PC: Δλ = sat54(−(k·Ts·ξ + h·Ts·narrow(ν))),
  ν' = sat54(ν + Ts·ξ), λ' = sat54(λ + Δλ), the reset at an armed zero crossing.

Every intermediate fits int64 when the weights are below 64 (|a·(Λ_i − Λ_j)| < 2^30·2^32):
``vectorisable`` says so, and the finite-time controller (integer square roots) and the float
twin stay on the per-agent loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from firmware_py import fixedpoint as fx
from firmware_py.controllers import Controller, make_controller
from sim.model.links import Links, Transmitter
from sim.model.scenario import Event, Scenario
from sim.model.trajectory import Trajectory

KINDS = ("pc", "pi", "reset", "dwell")
# a weight (or pin) below 2^30 raw (64.0) keeps a·(Λ_i − Λ_j) and its rounding in int64
WEIGHT_RAW_MAX = 1 << 30
_HALF = np.int64(1 << (fx.Q - 1))
_HALF_GUARD = np.int64(1 << (fx.GUARD - 1))


def vectorisable(sc: Scenario) -> bool:
    """True if the vectorised step gives firmware_py's results for ``sc``: a PI-family or
    PC controller in Q24 with every weight and pin below 64 (no int64 overflow), without
    the resilient update (its per-agent sort runs on the scalar loop)."""
    c = sc.controller
    if c.kind not in KINDS or c.q != fx.Q or sc.resilient_f:  # W-MSR sorts: the scalar loop
        return False
    return float(np.max(sc.adjacency, initial=0.0)) < WEIGHT_RAW_MAX / fx.ONE


_I32 = (np.int64(fx.INT32_MIN), np.int64(fx.INT32_MAX))
_S54 = (np.int64(fx.STATE_MIN), np.int64(fx.STATE_MAX))


def _sat(x: np.ndarray, bounds: tuple[np.int64, np.int64]) -> tuple[np.ndarray, np.ndarray]:
    """x clamped to [lo, hi] and where it was clamped."""
    lo, hi = bounds
    return np.minimum(np.maximum(x, lo), hi), (x > hi) | (x < lo)


@dataclass(frozen=True)
class FleetState:
    """Every agent's ControllerState, one array per field (index i: agent i + 1)."""

    lam: np.ndarray          # int64 Q54
    nu: np.ndarray           # int64 Q54
    xi_prev: np.ndarray      # int64 (int32 Q24 values)
    armed: np.ndarray        # bool
    since_reset: np.ndarray  # int64
    resets: np.ndarray       # int64
    saturations: np.ndarray  # int64

    @classmethod
    def initial(cls, lam0_q24: np.ndarray) -> FleetState:
        """ControllerState(lam=widen(λ(0))) for every agent: λ(0) given as Q24 words."""
        n = len(lam0_q24)
        zeros = np.zeros(n, dtype=np.int64)
        return cls(lam=np.asarray(lam0_q24, dtype=np.int64) << fx.GUARD, nu=zeros,
                   xi_prev=zeros, armed=np.ones(n, dtype=bool), since_reset=zeros,
                   resets=zeros, saturations=zeros)

    def wire(self) -> np.ndarray:
        """The λ every agent sends: the state rounded to Q24 (fixedpoint.narrow)."""
        return (self.lam + _HALF_GUARD) >> fx.GUARD


def step(ctrl: Controller, s: FleetState, xi: np.ndarray
         ) -> tuple[FleetState, np.ndarray, np.ndarray]:
    """``ctrl.step`` for every agent at once: (the states after ξ = ``xi``, Δλ, reset?).
    ``ctrl``: a fixed-point controller of a kind in KINDS (its constants are used)."""
    kind = ctrl.config.kind
    n = len(xi)
    if kind == "pc":
        reset = np.zeros(n, dtype=bool)
        dlam, s1 = _sat(-(np.int64(ctrl.kts) * xi), _S54)
        nu_next, s2 = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=bool)
        armed = s.armed
    else:
        crossed = ((s.xi_prev > 0) & (xi <= 0)) | ((s.xi_prev < 0) & (xi >= 0))
        reset = crossed & s.armed if kind != "pi" else np.zeros(n, dtype=bool)
        if kind == "dwell":
            reset &= s.since_reset >= ctrl.dwell_samples
        nu = np.where(reset, 0, s.nu)
        # re-armed once |ξ| leaves the band after the reset sample, not at it (BAND-2)
        armed = ~reset & (s.armed | (np.abs(xi) > np.int64(ctrl.band)))
        nu_word = (nu + _HALF_GUARD) >> fx.GUARD
        dlam, s1 = _sat(-(np.int64(ctrl.kts) * xi + np.int64(ctrl.hts) * nu_word), _S54)
        nu_next, s2 = _sat(nu + np.int64(ctrl.ts_q) * xi, _S54)
    lam, s3 = _sat(s.lam + dlam, _S54)
    return (FleetState(lam=lam, nu=nu_next, xi_prev=np.asarray(xi, dtype=np.int64),
                       armed=armed, since_reset=np.where(reset, 1, s.since_reset + 1),
                       resets=s.resets + reset, saturations=s.saturations + s1 + s2 + s3),
            dlam, reset)


def _keep(off: np.ndarray, old: FleetState, new: FleetState) -> FleetState:
    """``new``, but ``old`` for the agents ``off`` the network (they do not step)."""
    return FleetState(*(np.where(off, a, b) for a, b in
                        zip(old.__dict__.values(), new.__dict__.values(), strict=True)))


def run_vectorised(sc: Scenario, progress: Callable[[int, int], None] | None = None,
                   start_tick: int = 0, loss: float = 0.0, loss_seed: int = 0) -> Trajectory:
    """``sim.model.lockstep.run_lockstep(sc, fixed=True, ...)`` on arrays (see the module
    doc); ValueError if ``sc`` is not ``vectorisable``."""
    if not vectorisable(sc):
        raise ValueError(f"the vectorised lockstep runs {', '.join(KINDS)} in Q24 with "
                         f"weights below 64, but got {sc.controller.kind!r} (q = "
                         f"{sc.controller.q}, largest weight {np.max(sc.adjacency):g})")
    ctrl = make_controller(sc.controller, True)
    q = ctrl.quantise
    n, steps, ts = sc.n, sc.steps + 1, sc.ts

    rows, cols = np.nonzero(sc.adjacency)       # edge i ← j, in row order
    weights = np.array([q(float(w), "weight") for w in sc.adjacency[rows, cols]],
                       dtype=np.int64)
    bounds = np.searchsorted(rows, np.arange(n + 1))  # agent i's edges: bounds[i]:bounds[i+1]
    starts, lonely = bounds[:-1], bounds[:-1] == bounds[1:]  # lonely: agents without an edge
    prod = np.zeros(len(rows) + 1, dtype=np.int64)   # one product per edge, then a 0 to end on
    links = Links(len(rows), loss, loss_seed, sc.transmit.neighbour_periods)
    tx = Transmitter(n, sc.transmit, q(sc.transmit.threshold, "threshold"))
    pinned = np.zeros(n, dtype=bool)
    pinned[[p - 1 for p in sc.pinned]] = True
    pin = np.where(pinned, np.int64(q(1.0, "pin")), np.int64(0))

    def q24(values: list[float]) -> np.ndarray:
        return np.array([q(x, "lambda0") for x in values], dtype=np.int64)

    state = FleetState.initial(q24(list(sc.lambda0)))
    idle = FleetState.initial(q24([b.idle_lambda for b in sc.batteries]))
    active = np.ones(n, dtype=bool)
    events: dict[int, list[Event]] = {}
    for e in sc.events:
        events.setdefault(round(e.t / ts), []).append(e)

    shape = (steps, n)
    lam, u, xi_rec, nu_rec = (np.zeros(shape) for _ in range(4))
    act, sent = np.zeros(shape, dtype=bool), np.zeros(shape, dtype=bool)
    rho_arr, seg_arr = np.zeros(steps), np.zeros(steps, dtype=int)
    reset_at: list[list[float]] = [[] for _ in range(n)]
    lam_scale, state_scale = float(fx.ONE), float(1 << (fx.Q + fx.GUARD))

    for k in range(steps):
        t = k * ts
        force = np.full(n, k == start_tick)  # State changes are sent at once (TX-7)
        for e in events.get(k, ()):
            i = e.agent - 1
            active[i] = e.action == "reconnect"
            force[i] = True
            if e.action == "isolate":  # off the network: P = 0, λ at its idle MC (a new state)
                state = _keep(np.arange(n) == i, idle, state)
        all_active = bool(active.all())
        rho, seg = sc.price_at(t)
        rho_q = np.int64(q(rho, "rho"))
        rho_arr[k], seg_arr[k] = rho, seg
        wire = state.wire()
        lam[k] = wire / lam_scale
        act[k] = active
        pub, sent[k] = tx.publish(wire, force)   # the λ each agent last sent
        if k < start_tick:
            continue
        # ξ: one rounded product per edge from an active neighbour, summed per agent
        held, alive = links.exchange(pub[cols], sent[k][cols])
        prod[:-1] = (weights * (wire[rows] - held) + _HALF) >> fx.Q
        if not all_active or loss:
            prod[:-1][~(active[cols] & alive)] = 0
        acc = np.add.reduceat(prod, starts)
        acc[lonely] = 0                         # reduceat gives them the next edge's product
        acc += (pin * (wire - rho_q) + _HALF) >> fx.Q
        x, xi_sat = _sat(acc, _I32)
        new, dlam, reset = step(ctrl, state, x)
        new = replace(new, saturations=new.saturations + xi_sat)
        if not all_active:  # an isolated agent neither steps nor records
            off = ~active
            new = _keep(off, state, new)
            x, dlam, reset = np.where(off, 0, x), np.where(off, 0, dlam), reset & active
        xi_rec[k] = x / lam_scale
        nu_rec[k] = np.where(reset, 0.0, state.nu / state_scale)
        u[k] = dlam / state_scale / ts
        if reset.any():
            for agent in np.flatnonzero(reset):
                reset_at[agent].append(t)
        state = new
        if progress is not None and k % 500 == 0:
            progress(k, steps)

    return Trajectory.sampled(sc.batteries, ts, lam, act, rho=rho_arr, segment=seg_arr, u=u,
                              xi=xi_rec, nu=nu_rec, resets=reset_at,
                              saturations=int(state.saturations.sum()), label=sc.controller.kind,
                              mc_sent=sent)
