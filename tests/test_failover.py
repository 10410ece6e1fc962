"""Pinned-agent failover (issue 23.5, docs/faults.md): the choice rule and the lockstep's
model of it. The bus run (the router's detection, the PIN commands, the report) is
tests/test_faults.py::test_pinned_agent_killed_failover_simulated_clock; the command
itself (CMD-7) tests/test_runtime.py::test_pin_and_unpin_commands and the node vector pin.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from firmware_py.frames import target_agent
from sim.model.graph import failover_choice
from sim.model.lockstep import run_lockstep
from sim.model.scenario import Event, load_case, load_scenario

FAILOVER = Path(__file__).resolve().parent.parent / "examples" / "failover_case1.toml"
STAR = [(1, 2), (1, 3), (1, 4)]


def test_the_star_without_its_centre_pins_every_leaf() -> None:
    # each leaf is a component of its own: degree 0 each
    assert failover_choice(4, STAR, {1}, [2, 3, 4]) == [2, 3, 4]
    # a leaf lost instead: the centre still hears the price, nothing to do
    assert failover_choice(4, STAR, {1}, [1, 2, 3]) == []


def test_the_highest_degree_then_the_lowest_id() -> None:
    # a path 1-2-3-4-5, pinned 1 lost: 2..5 one component; 3 and 4 have degree 2 (2 has 1
    # live neighbour once 1 is gone): 3, the lower id
    path = [(1, 2), (2, 3), (3, 4), (4, 5)]
    assert failover_choice(5, path, {1}, [2, 3, 4, 5]) == [3]
    # case 7's ring of 12 with both pinned agents (1, 7) lost: two arcs, 2..6 and 8..12;
    # the inner agents of each have 2 live neighbours, the lowest id wins
    ring = [(i, i % 12 + 1) for i in range(1, 13)]
    live = [i for i in range(1, 13) if i not in (1, 7)]
    assert failover_choice(12, ring, {1, 7}, live) == [3, 9]
    # one pinned agent left alive: the ring minus agent 1 is one arc that holds agent 7
    assert failover_choice(12, ring, {1, 7}, [i for i in range(2, 13)]) == []
    # weighted edges (a third element) are edges all the same
    assert failover_choice(3, [(1, 2, 0.5), (2, 3, 2.0)], {3}, [1, 2]) == [1]  # a tie


def test_lockstep_failover_after_the_pinned_centre_is_isolated() -> None:
    """The lockstep models the kill as an isolate of agent 1 at 5 s; with the failover the
    leaves follow the price step at 10 s, without it they stay at the old price."""
    sc = replace(load_scenario(FAILOVER), events=(Event(5.0, 1, "isolate"),))
    with_failover = run_lockstep(sc, failover=True)
    assert np.abs(with_failover.lam[-1, 1:] - 0.9).max() < 1e-3
    without = run_lockstep(sc)
    assert np.abs(without.lam[-1, 1:] - 0.9).max() > 0.09  # cut off: ρ = 0.8 still


def test_lockstep_failover_changes_nothing_without_a_lost_pinned_agent() -> None:
    sc = load_case(4)   # agent 2 (not pinned) isolated and reconnected
    a, b = run_lockstep(sc), run_lockstep(sc, failover=True, impl="py")
    assert np.array_equal(a.lam, b.lam)


def _router_run(kill_at: float | None = None, isolate_at: float | None = None,
                seconds: float = 1.0) -> tuple[Any, list[tuple[float, dict[str, int]]]]:
    """The router of case 1 (--insecure keys) fed every agent's MC frames each Ts (agent 1
    silent from ``kill_at``, or reporting ISOLATED from ``isolate_at``): the router and
    the ER_Command frames it sent, decoded."""
    from firmware_py.frames import FrameCodec, mc_name
    from firmware_py.nodeio import FleetSender
    from sim.nodes.router import RouterNode

    codec = FrameCodec()
    sender = FleetSender(codec)
    router = RouterNode(load_case(1))
    commands = []
    for k in range(round(seconds / 0.01)):
        t = k * 0.01
        for i in range(1, 5):
            state = 1
            if i == 1 and kill_at is not None and t >= kill_at:
                continue
            if i == 1 and isolate_at is not None and t >= isolate_at:
                state = 2
            router.on_frame(sender.frame(mc_name(i), {"Lambda": 0, "State": state,
                                                      "Resets": 0}, k % 16), t)
        for msg in router.tick(t):
            if msg.arbitration_id == codec.frame_id("ER_Command"):
                commands.append((t, codec.decode(msg).raw))
    return router, commands


def test_the_router_pins_the_leaves_when_the_centre_goes_silent() -> None:
    router, commands = _router_run(kill_at=0.5)
    # last frame at 0.49 s; timed out after 3 Ts: noticed at the tick of 0.53 s
    assert [(round(t, 2), c["Command"], target_agent(c["Target"]), c["GainK"])
             for t, c in commands] == [
        (round(0.53 + d, 2), 0, i, 1) for d in (0.0, 0.01, 0.02) for i in (2, 3, 4)]
    assert router.counters["failovers"] == 3
    assert [(e.lost, e.pinned) for e in router.failover_log] == [((1,), (2, 3, 4))]
    assert "failover t=0.53 s: pinned agents lost 1; pinned 2, 3, 4" in router.summary()


def test_the_router_fails_over_for_an_isolated_pinned_agent_and_not_without_a_loss() -> None:
    _, commands = _router_run(isolate_at=0.5)
    assert {target_agent(c["Target"]) for _, c in commands} == {2, 3, 4} and commands[0][0] == 0.5
    router, commands = _router_run()
    assert commands == [] and router.counters["failovers"] == 0
