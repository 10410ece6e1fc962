"""Deterministic lockstep runner: N firmware controllers stepped at Ts on a simulated clock.

Every sample, each agent computes ξ from the λ its neighbours held at the same
sample (what a synchronous bus exchange delivers), then steps its controller.
Plug-and-play events and price changes apply at their scheduled sample. No wall
clock is involved, so runs are bit-for-bit repeatable and much faster than real time.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace

import numpy as np

from firmware_py.controllers import consensus_error, make_controller
from sim.model.graph import failover_choice
from sim.model.links import Links, Transmitter
from sim.model.scenario import Event, Scenario
from sim.model.trajectory import Trajectory
from sim.model.vlockstep import run_vectorised, vectorisable

# below this many agents numpy's per-call cost outweighs the loop it replaces (bess-ded bench)
VEC_MIN_AGENTS = 8
# the failover's delay beyond the neighbour timeout, in samples: the router hears the
# timeout a sample late and its PIN reaches the agent a sample later (sim.nodes.router)
FAILOVER_DELAY_TS = 2


def run_lockstep(sc: Scenario, fixed: bool = True,
                 progress: Callable[[int, int], None] | None = None,
                 impl: str = "auto", start_tick: int = 0, loss: float = 0.0,
                 loss_seed: int = 0,
                 lies: Mapping[int, Callable[[int, int], int]] | None = None,
                 failover: bool = False) -> Trajectory:
    """``impl``: "py" steps firmware_py's controllers agent by agent, "vec" the same
    fixed-point step over numpy arrays (sim.model.vlockstep: all agents at once), "c" the
    C core (firmware_c, through sim.cbind.cimpl: its controller step and its ξ), fixed
    point only; "auto" (the default) is "vec" where it applies (``vectorisable``) and
    pays (``VEC_MIN_AGENTS``), else "py". All give the same trajectory bit for bit.
    ``start_tick``: the first sample the agents step (before it they hold λ(0), as nodes
    in INIT: a bus run's start, whose nodes take no frame in their join window,
    firmware-spec AUTH-26). ``loss``: each neighbour's MC frame lost with this probability
    (seeded by ``loss_seed``; sim.model.links: the receiver holds the last λ and times
    the neighbour out), the same frames on every ``impl``. ``lies``: agent (1-based) →
    ``told(k, λ)``, the λ (a Q24 int) that agent sends its neighbours at sample k instead
    of its own (a compromised agent with its own key, tests/deviant_agent.py's LIE-*); its
    trajectory holds the told λ (its setpoints follow what it tells). ``sc.resilient_f``
    > 0 runs every agent's ξ through the W-MSR trimming (controllers.resilient_trim);
    both run on the scalar loop ("vec" falls back to "py"). ``failover``: the router's
    pinned-agent failover (sim.nodes.router, docs/faults.md): when a pinned agent is
    isolated (the lockstep's model of a dead agent), ``FAILOVER_DELAY_TS`` samples later
    (the router's detection: the agents' neighbour timeout, a sample to hear it, one for
    the PIN to arrive) the agents ``graph.failover_choice`` names are pinned (scalar loop
    only, "vec" falls back to "py")."""
    if impl == "vec" and (lies or sc.resilient_f or failover):
        impl = "py"  # the resilient update or a liar: the per-agent loop, same results
    if impl == "auto":
        impl = ("vec" if fixed and sc.n >= VEC_MIN_AGENTS and vectorisable(sc) and not lies
                and not failover else "py")
    if impl == "vec":
        if not fixed:
            raise ValueError("the vectorised step is fixed point only (impl='vec' with "
                             "fixed=False)")
        return run_vectorised(sc, progress, start_tick, loss, loss_seed)
    ctrl = make_controller(sc.controller, fixed)
    step, initial, wire = ctrl.step, ctrl.initial_state, ctrl.wire_lambda

    trim = sc.resilient_f

    def xi_of(lam: int, nbrs: list[tuple[int, int]], pin: int, rho: int) -> tuple[int, bool]:
        return consensus_error(ctrl.ar, lam, nbrs, pin, rho, trim)  # type: ignore[return-value]

    if impl == "c":
        from sim.cbind.cimpl import CController

        if not fixed:
            raise ValueError("the C core is fixed point only (impl='c' with fixed=False)")
        c = CController.from_config(sc.controller)
        step, initial, wire = c.step, c.initial_state, c.wire_lambda  # type: ignore[assignment]

        def xi_of(lam: int, nbrs: list[tuple[int, int]], pin: int, rho: int
                  ) -> tuple[int, bool]:
            return c.core.xi(lam, pin, rho, nbrs, trim)
    elif impl != "py":
        raise ValueError(f"impl: expected 'auto', 'py', 'vec' or 'c', but got {impl!r}")
    q = ctrl.quantise
    n, steps, ts = sc.n, sc.steps + 1, sc.ts
    neighbours = [[(j - 1, q(w, "weight")) for j, w in sc.neighbours(i)] for i in range(1, n + 1)]
    senders = np.array([j for nb in neighbours for j, _ in nb], dtype=np.int64)
    first_link = np.cumsum([0] + [len(nb) for nb in neighbours])  # agent i's links from here
    links = Links(len(senders), loss, loss_seed, sc.transmit.neighbour_periods)
    tx = Transmitter(n, sc.transmit, q(sc.transmit.threshold, "threshold"))
    pin = [q(1.0, "pin") if i in sc.pinned else 0 for i in range(1, n + 1)]
    states = [initial(l0) for l0 in sc.lambda0]
    active = [True] * n
    events: dict[int, list[Event]] = {round(e.t / ts): [] for e in sc.events}
    for e in sc.events:
        events[round(e.t / ts)].append(e)

    shape = (steps, n)
    lam, u, xi, nu = (np.zeros(shape) for _ in range(4))
    act, sent = np.zeros(shape, dtype=bool), np.zeros(shape, dtype=bool)
    rho_arr, seg_arr = np.zeros(steps), np.zeros(steps, dtype=int)
    resets: list[list[float]] = [[] for _ in range(n)]
    real, real_state = ctrl.real, ctrl.real_state
    pinned = set(sc.pinned)                 # whom the failover counts as pinned
    failover_due: int | None = None         # the sample its PINs take effect
    delay = sc.transmit.neighbour_periods + FAILOVER_DELAY_TS

    for k in range(steps):
        t = k * ts
        # a State change is sent at once (TX-7): the start and plug-and-play events
        force = np.full(n, k == start_tick)
        for e in events.get(k, ()):
            i = e.agent - 1
            active[i] = e.action == "reconnect"
            force[i] = True
            if e.action == "isolate":  # off the network: P = 0, λ at its idle MC
                states[i] = initial(sc.batteries[i].idle_lambda)
                if failover and e.agent in pinned:
                    failover_due = k + delay
        if failover_due == k:
            live = [i + 1 for i in range(n) if active[i]]
            if any(not active[p - 1] for p in pinned):
                for p in failover_choice(n, sc.edges, pinned, live):
                    pinned.add(p)
                    pin[p - 1] = q(1.0, "pin")
            failover_due = None
        rho, seg = sc.price_at(t)
        rho_q = q(rho, "rho")
        rho_arr[k], seg_arr[k] = rho, seg
        lams = [wire(s) for s in states]     # each agent's λ at this sample
        told = [lies[i + 1](k, int(v)) if lies and i + 1 in lies and active[i] else v
                for i, v in enumerate(lams)]  # what a liar sends instead (tests, tools)
        pub, sent[k] = tx.publish(np.array(told), force)  # the λ last sent (TX-7)
        if k >= start_tick:
            held, alive = links.exchange(pub[senders], sent[k][senders])  # Q24 ints or floats
        for i, s in enumerate(states):
            lam[k, i] = real(told[i])
            act[k, i] = active[i]
            if not active[i] or k < start_tick:
                continue
            nbrs = [(w, held[e].item()) for e, (j, w) in enumerate(neighbours[i], first_link[i])
                    if active[j] and alive[e]]
            x, sat = xi_of(lams[i], nbrs, pin[i], rho_q)  # type: ignore[arg-type]
            new, out = step(s, x)
            if sat:
                new = replace(new, saturations=new.saturations + 1)
            xi[k, i] = real(x)
            nu[k, i] = 0.0 if out.reset else real_state(s.nu)
            u[k, i] = real_state(out.dlam) / ts
            if out.reset:
                resets[i].append(t)
            states[i] = new
        if progress is not None and k % 500 == 0:
            progress(k, steps)

    return Trajectory.sampled(sc.batteries, ts, lam, act, rho=rho_arr, segment=seg_arr, u=u,
                              xi=xi, nu=nu, resets=resets,
                              saturations=sum(s.saturations for s in states),
                              label=sc.controller.kind, mc_sent=sent)
