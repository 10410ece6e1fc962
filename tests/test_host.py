"""Several agents in one process (firmware_py.host, node.run_nodes): what each agent sends
is what it sends alone, deadlines stay per agent, and `up --agents-per-process` runs a
case with every agent accounted for. Nothing here asserts a wall-clock rate: the
capacity figures are `bess-ded bench --realtime`'s (docs/performance.md)."""

from __future__ import annotations

import copy
from pathlib import Path

import can
import pytest
from test_spec_coverage import CODEC, SENDER, Clock, FakeBus, Recorder, T, msg, price_frame

from firmware_py import fixedpoint as fx
from firmware_py.config import agent_configs_from_scenario
from firmware_py.frames import mc_name, status_name
from firmware_py.host import AcceptedOnly, Routes, host_bus
from firmware_py.node import NodesOnOneBus, run_node, run_nodes, spread_phases
from firmware_py.runtime import AgentRuntime
from sim.model.scenario import load_case
from sim.run import busrun

TS = 0.01


def script(seconds: float) -> list[tuple[float, can.Message]]:
    """What the rest of case 1's fleet sends, on a fixed clock: the price and every
    plant's status at their 50 ms cycle, every agent's MC each Ts (λ drifting), some of
    them on the host's own agents' IDs (impersonations, counted alike)."""
    frames = []
    for k in range(round(seconds / TS)):
        t = k * TS + 0.003
        if k % 5 == 0:
            frames.append((t, price_frame(0.8)))
            frames += [(t, SENDER.frame(status_name(i), {
                "FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
                "Power": 0.0, "Soc": 50.0}, phys=True)) for i in range(1, 5)]
        frames += [(t + 0.001 * i, SENDER.frame(mc_name(i), {
            "State": 1, "Lambda": fx.to_fixed(0.5 + 0.1 * i + 0.001 * k), "Resets": 0}))
            for i in range(1, 5)]
    return frames


def agents() -> list[AgentRuntime]:
    return [AgentRuntime(cfg, CODEC) for cfg in agent_configs_from_scenario(load_case(1))]


def sent_by(bus: FakeBus, agent: AgentRuntime) -> list[tuple[float, int, bytes]]:
    own = set(agent.io._sent)  # the IDs it sends, syncs included
    return [(t, m.arbitration_id, bytes(m.data)) for t, m in bus.sent
            if m.arbitration_id in own]


def test_an_agent_in_a_host_sends_what_it_sends_alone() -> None:
    """Case 1's four agents on one loop and one (scripted) bus send, frame for frame and
    at the same instants, what each sends driven alone by run_node on the same frames
    and clock, with the same counters: only the scheduling is shared, never state, and
    the frames a host does not hand an agent (Routes) are ones it would have ignored."""
    frames = script(1.5)
    clock = Clock()
    host = FakeBus(clock, [(t, copy.copy(m)) for t, m in frames])
    together = agents()
    routes = Routes(together, [a.io for a in together])
    run_nodes(together, host, duration=1.5, clock=clock, route=routes)
    assert any(len(nodes) < len(together) for nodes in routes._by_id.values())
    for i, agent in enumerate(together):
        clock = Clock()
        alone = FakeBus(clock, [(t, copy.copy(m)) for t, m in frames])
        solo = agents()[i]
        run_node(solo, alone, duration=1.5, clock=clock)
        assert sent_by(host, agent) == sent_by(alone, solo) and sent_by(alone, solo)
        assert agent.counters == solo.counters and solo.state == agent.state
    assert together[0].counters["impersonation"] > 0  # the script's own-ID frames


def test_agents_started_apart_in_a_host_send_what_each_sends_alone_from_its_start() -> None:
    """Case 1's agents started a quarter of their sync period apart in one host
    (spread_phases, as the agents' command line does) send, frame for frame and at the
    same instants, what each sends alone started at its own phase: each ticks at its own
    release, sends its syncs at its own first tick, and hears nothing before its start."""
    frames = script(1.5)
    together = agents()
    phases = spread_phases(len(together), together[0].io.sync_s)
    assert phases == pytest.approx([0.0, 0.25, 0.5, 0.75])
    clock = Clock()
    host = FakeBus(clock, [(t, copy.copy(m)) for t, m in frames])
    run_nodes(together, host, duration=1.5, clock=clock,
              route=Routes(together, [a.io for a in together]), phases=phases)
    for i, agent in enumerate(together):
        clock = Clock()
        alone = FakeBus(clock, [(t, copy.copy(m)) for t, m in frames])
        solo = agents()[i]
        run_node(solo, alone, duration=1.5, clock=clock, phase=phases[i])
        sent = sent_by(host, agent)
        assert sent == sent_by(alone, solo) and sent[0][0] == pytest.approx(phases[i])
        assert agent.counters == solo.counters and solo.state == agent.state
    # started later, heard less: the last agent missed the first 0.75 s of the script
    assert together[3].counters["impersonation"] < together[0].counters["impersonation"]


def test_a_node_hears_the_bus_from_its_first_release_on() -> None:
    """A node whose phase puts its start after a frame does not get that frame; one
    started already does; a phase that is not a non-negative number per node is
    refused."""
    clock = Clock()
    early, late = Recorder(clock), Recorder(clock)
    run_nodes([early, late], FakeBus(clock, [(1.5 * T, msg()), (3.5 * T, msg())]),
              duration=6 * T, clock=clock, phases=[0.0, 2.5 * T])
    assert [t for e, t in early.events if e == "rx"] == [1.5 * T, 3.5 * T]
    assert [t for e, t in late.events if e == "rx"] == [3.5 * T]
    assert late.ticks() == pytest.approx([2.5 * T, 3.5 * T, 4.5 * T, 5.5 * T])
    assert early.counters == late.counters == {}
    for bad in ([0.0], [0.0, -T]):
        with pytest.raises(NodesOnOneBus):
            run_nodes([early, late], FakeBus(clock), duration=T, clock=clock, phases=bad)


def test_what_is_queued_only_for_agents_not_due_waits_until_the_due_ones_ticked() -> None:
    """A frame queued at a release for an agent that is not due then is its input
    after the due agent's tick, not before it: a burst of other agents' frames (the
    plant's syncs) never holds a tick. The agent it is for still hears it before its
    own next tick; a frame for the due agent is handed over before that agent ticks."""
    clock = Clock()
    a, b = Recorder(clock, {2: 0.1}), Recorder(clock, {1: 0.6})  # b's 1.5T tick overruns
    for_b, for_a = msg(), can.Message(arbitration_id=0x011, data=bytes(8),
                                      is_extended_id=False)
    frames = [(2.05 * T, for_b), (2.06 * T, for_a)]
    run_nodes([a, b], FakeBus(clock, frames), duration=3 * T, clock=clock,
              route=lambda m: [b] if m.arbitration_id == 0x010 else [a],
              phases=[0.0, 0.5 * T])
    # b's tick at 1.5T ran to 2.1T; a is due at 2T, b at 2.5T: a hears its frame at
    # once and ticks at 2.1T (0.1T of work), and only then does b hear its own
    assert a.ticks() == pytest.approx([0, T, 2.1 * T])
    assert [t for e, t in a.events if e == "rx"] == pytest.approx([2.1 * T])
    assert [t for e, t in b.events if e == "rx"] == pytest.approx([2.2 * T])
    assert b.ticks() == pytest.approx([0.5 * T, 1.5 * T, 2.5 * T])


def test_deadlines_are_per_node_in_a_host() -> None:
    """Each node of a host keeps run_node's accounting of its own releases: a node whose
    turn comes > Ts/2 late (delayed by the node before it) counts 1 + floor(late/Ts)
    misses and skips what it missed; the node that overran counts its own; both hear
    every frame at the same instant and tick together again afterwards."""
    clock = Clock()
    first = Recorder(clock, {2: 0.6, 5: 2.2})  # tick 2 delays the second node by 0.6 T
    second = Recorder(clock)
    run_nodes([first, second], FakeBus(clock, [(1.5 * T, msg())]), duration=10 * T,
              clock=clock)
    # release 6T comes at 7.2T for the first: 1 + 1 misses, ticks there for 7T
    assert first.counters == {"deadline_miss": 2}
    assert first.ticks() == pytest.approx([0, T, 2 * T, 3 * T, 4 * T, 5 * T, 7.2 * T,
                                           8 * T, 9 * T])
    # the second: 0.6 T late at 2T (1 miss), 2.2 T late at 5T (3 misses: 5T, 6T, 7T)
    assert second.counters == {"deadline_miss": 1 + 3}
    assert second.ticks() == pytest.approx([0, T, 2.6 * T, 3 * T, 4 * T, 7.2 * T, 8 * T,
                                            9 * T])
    assert [e for e in first.events if e[0] == "rx"] == [("rx", 1.5 * T)]
    assert [e for e in second.events if e[0] == "rx"] == [("rx", 1.5 * T)]
    with pytest.raises(NodesOnOneBus):
        other = Recorder(clock)
        other.period = 2 * T
        run_nodes([first, other], FakeBus(clock), duration=T, clock=clock)


def test_a_host_bus_filters_for_each_agent_and_hears_its_own() -> None:
    """The kernel passes the union of the agents' IDs, each agent gets only its own; on
    interfaces that do not loop sends back, the host's socket asks for them."""
    a, b = agents()[:2]
    kw, own = host_bus({"interface": "socketcan", "channel": "vcan0"},
                       [a.io.accepted_ids(), b.io.accepted_ids()])
    assert own and kw["receive_own_messages"]
    assert {f["can_id"] for f in kw["can_filters"]} == \
        set(a.io.accepted_ids()) | set(b.io.accepted_ids())
    kw, own = host_bus({"interface": "udp_multicast"}, [a.io.accepted_ids()] * 2)
    assert not own and "receive_own_messages" not in kw and "can_filters" not in kw
    seen: list[int] = []
    a.on_frame = lambda m, t: seen.append(m.arbitration_id)  # type: ignore[method-assign]
    node = AcceptedOnly(a, a.io.accepted_ids())
    for i in (2, 3, 4, 9):
        node.on_frame(mc_name_frame(i), 0.0)
    mcs = [CODEC.frame_id(mc_name(i)) for i in (2, 3, 4, 9)]
    assert seen == [i for i in mcs if i in a.io.accepted_ids()] and seen and seen != mcs


def test_what_an_agent_ignores_changes_nothing_in_it() -> None:
    """NodeIO.ignores (what Routes leaves out) names only IDs whose frames ``receive``
    drops uncounted, once joined: every DBC ID and a few beyond, with any payload."""
    agent = agents()[0]
    agent.tick(0.0)                      # its hello: the join window opens ...
    agent.on_frame(price_frame(0.8), 1.0)  # ... and a frame after it closes it
    assert not agent.io.joining
    before = copy.deepcopy(agent.io.counters)
    ignored = [fid for fid in range(0x800) if agent.io.ignores(fid)]
    for fid in ignored:
        frame = can.Message(arbitration_id=fid, data=bytes(range(8)), is_extended_id=False)
        assert agent.io.receive(frame, 1.0) is None
    assert agent.io.counters == before
    near = {n.id for n in agent.cfg.neighbours} | {agent.cfg.id}
    mcs = {i: CODEC.frame_id(mc_name(i)) for i in range(1, 10)}
    # the MC of a fleet agent that is no neighbour is ignored; its own, a neighbour's and
    # one of an agent beyond the fleet (foreign_id) are not
    assert {mcs[i] for i in range(1, 5) if i not in near} <= set(ignored) != set()
    assert not {mcs[i] for i in near | {9}} & set(ignored)


def mc_name_frame(i: int) -> can.Message:
    return SENDER.frame(mc_name(i), {"State": 1, "Lambda": fx.to_fixed(0.8), "Resets": 0})


@pytest.mark.realtime
def test_up_with_agents_per_process_converges_every_agent_accounted(
        tmp_path: Path, udp_port: int) -> None:
    """Case 1's four agents in two host processes on udp_multicast: it converges, every
    agent has its exit code and its ticks in the verdict by name, and the log names the
    host processes. At any load: deadline misses are `bench --realtime`'s."""
    sc = load_case(1)
    bus = busrun.BusOptions("udp_multicast", None, f'{{"port": {udp_port}}}')
    m = busrun.run(sc, tmp_path, bus, duration=10.0, quiet=True, plot=False,
                   agents_per_process=2)
    agents_ = {f"agent_{i}" for i in range(1, 5)}
    assert set(m["exit_codes"]) == agents_ | {"plant", "router"}
    assert all(code == 0 for code in m["exit_codes"].values()), m["exit_codes"]
    assert agents_ <= set(m["node_ticks"]) and min(m["node_ticks"][a] for a in agents_) > 0
    assert m["final_error"] < 1e-3, m
    assert m["verdict"]["exit_code"] in (0, 3), m["verdict"]
    assert sorted(p.name for p in (tmp_path / "logs").glob("host_*.log")) == \
        ["host_1.log", "host_2.log"]
    log = (tmp_path / "logs" / "host_1.log").read_text()
    assert "agent 1: state=RUNNING" in log and "agent 2: state=RUNNING" in log


def test_a_host_refuses_keys_not_one_per_config_one_agent_twice_and_fault_flags(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`python -m firmware_py` with two --config: one --key each, distinct agents, and no
    fault injection (it is per socket); usage errors, exit 2, before any bus is opened."""
    from firmware_py import __main__ as agent_main

    paths = []
    for cfg in agent_configs_from_scenario(load_case(1))[:2]:
        paths += ["--config", str(tmp_path / f"agent_{cfg.id}.toml")]
        (tmp_path / f"agent_{cfg.id}.toml").write_text(cfg.to_toml())
    assert agent_main.main(paths + ["--key", str(tmp_path / "agent_1.key"),
                                    "--interface", "virtual"]) == 2
    assert "one key file per --config (2)" in capsys.readouterr().err
    assert agent_main.main(paths + ["--insecure", "--inject-rx-loss", "0.1",
                                    "--interface", "virtual"]) == 2
    assert "faults are injected per agent" in capsys.readouterr().err
    assert agent_main.main(paths[:2] * 2 + ["--insecure", "--interface", "virtual"]) == 2
    assert "the files of distinct agents, but got [1, 1]" in capsys.readouterr().err


def test_node_specs_put_the_python_agents_k_to_a_host(tmp_path: Path) -> None:
    """`up --agents-per-process 5` on case 7 (12 agents): hosts of 5, 5 and 2 agents in
    agent order, each agent's --config with its own --key, the plant and router alone;
    an agent's fault flags are refused (they are per socket)."""
    from sim.model.scenario import to_toml
    from sim.run.busopts import BusRunError
    from sim.run.nodeprocs import node_specs

    sc = load_case(7)
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(to_toml(sc))
    bus = busrun.BusOptions("udp_multicast", None, '{"port": 43299}')
    specs = node_specs(sc, scenario, tmp_path, bus, keys=tmp_path / "keys",
                       agents_per_process=5)
    assert [s.name for s in specs] == ["host_1", "host_2", "host_3", "plant", "router"]
    assert [len(s.members) for s in specs[:3]] == [5, 5, 2]
    assert specs[1].members == tuple(f"agent_{i}" for i in range(6, 11))
    argv = specs[1].argv
    configs = [argv[i + 1] for i, a in enumerate(argv) if a == "--config"]
    keys = [argv[i + 1] for i, a in enumerate(argv) if a == "--key"]
    assert [Path(c).stem for c in configs] == [Path(k).stem for k in keys] == \
        list(specs[1].members)
    assert specs[3].nodes == ("plant",) and specs[0].nodes == specs[0].members
    # a host one SCHED_FIFO priority above the rig's plant and router; alone, an agent
    # at theirs (a process each above the rig starved it)
    priority = {s.name: s.argv[s.argv.index("--rt-priority") + 1] for s in specs}
    assert priority == {"host_1": "11", "host_2": "11", "host_3": "11", "plant": "10",
                        "router": "10"}
    alone = node_specs(sc, scenario, tmp_path, bus, keys=tmp_path / "keys")
    assert {s.argv[s.argv.index("--rt-priority") + 1] for s in alone} == {"10"}
    with pytest.raises(BusRunError, match="takes no fault-injection flags"):
        node_specs(sc, scenario, tmp_path, bus, extra={"agent_2": ["--inject-rx-loss", "0.1"]},
                   agents_per_process=2)
