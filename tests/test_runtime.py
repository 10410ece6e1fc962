"""The agent runtime, pure: frames in through on_frame, frames out of tick, fixed timestamps."""

from __future__ import annotations

from dataclasses import replace

import can
import numpy as np
import pytest

from firmware_py import fixedpoint as fx
from firmware_py.config import agent_configs_from_scenario
from firmware_py.contract import COUNTER_MODULO, Command, every_ticks, timeout_s
from firmware_py.frames import (
    PIN_OFF,
    PIN_ON,
    FrameCodec,
    mc_name,
    setpoint_name,
    status_name,
    target_raw,
)
from firmware_py.node import bus_kwargs, run_node, with_acceptance_filter
from firmware_py.nodeio import FleetSender
from firmware_py.runtime import DIAG_EVERY, AgentRuntime, SetpointMap, State
from sim.model.lockstep import run_lockstep
from sim.model.scenario import PriceStep, load_case, scaled

CODEC = FrameCodec()
TS = 0.01


SENDER = FleetSender(CODEC)  # the other nodes, --insecure: boot 1, no sync needed


@pytest.fixture(autouse=True)
def _fresh_senders() -> None:
    """Every test starts with senders that just booted, as its fresh agents expect."""
    SENDER.reset_counts()
    SENDER.boot = 1


def status_frame(agent: int, counter: int, overcurrent: int = 0) -> can.Message:
    return SENDER.frame(status_name(agent), {
        "FaultOverCurrent": overcurrent, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
        "Power": 10.0, "Soc": 50.0}, counter, phys=True)


class Net:
    """Agents wired by direct delivery: every frame a tick produces reaches every agent
    before the next tick (a lossless, zero-latency bus), plus a price source and a plant
    stand-in sending every agent's PLANT_<i>_Status at the DBC's cycle."""

    def __init__(self, case: int = 1) -> None:
        self.sc = load_case(case)
        self.agents = [AgentRuntime(c, CODEC) for c in agent_configs_from_scenario(self.sc)]
        self.k = 0
        self.price_ctr = 0
        self.price_on = True
        self.status_ctr = 0
        self.status_off: set[int] = set()   # agents whose plant status is not sent
        self.overcurrent: set[int] = set()  # agents whose plant reports an over-current
        self.sent: list[can.Message] = []

    @property
    def t(self) -> float:
        return self.k * TS

    def deliver(self, msg: can.Message) -> None:
        for a in self.agents:
            a.on_frame(msg, self.t)

    def price(self, rho: float) -> None:
        msg = SENDER.frame("ER_Price", {"PriceValid": 1, "Rho": fx.to_fixed(rho),
                                        "Segment": 0}, self.price_ctr % 16)
        self.price_ctr += 1
        self.deliver(msg)

    def run(self, seconds: float, skip: set[int] = frozenset()) -> None:
        for _ in range(round(seconds / TS)):
            if self.price_on and self.k % every_ticks("ER_Price") == 0:
                self.price(self.sc.price_at(self.t)[0])
            if self.k % every_ticks(status_name(1)) == 0:
                for a in self.agents:
                    if a.cfg.id not in self.status_off:
                        self.deliver(status_frame(a.cfg.id, self.status_ctr % COUNTER_MODULO,
                                                  int(a.cfg.id in self.overcurrent)))
                self.status_ctr += 1
            out = [m for a in self.agents if a.cfg.id not in skip for m in a.tick(self.t)]
            self.sent += out
            for m in out:
                self.deliver(m)
            self.k += 1

    def error(self) -> float:
        return max(abs(a.lam - 0.8) for a in self.agents)


def one_agent(pinned: bool = True, status: bool = True) -> AgentRuntime:
    """Agent 1 (pinned) or 2 of case 1, with one fresh status frame at t = 0 unless not
    ``status``."""
    a = AgentRuntime(agent_configs_from_scenario(load_case(1))[0 if pinned else 1], CODEC)
    if status:
        a.on_frame(status_frame(a.cfg.id, 0), 0.0)
    return a


def price_frame(counter: int, rho: float = 0.8, valid: int = 1) -> can.Message:
    return SENDER.frame("ER_Price", {"PriceValid": valid, "Rho": fx.to_fixed(rho),
                                     "Segment": 0}, counter)


def mc_frame(agent: int, counter: int, lam: float = 0.8, state: int = 1) -> can.Message:
    return SENDER.frame(mc_name(agent), {"State": state, "Lambda": fx.to_fixed(lam),
                                         "Resets": 0}, counter)


# --------------------------------------------------------------------------- behaviour


def test_runtime_exchange_matches_lockstep_runner() -> None:
    """With lossless zero-latency delivery the runtimes are the lockstep runner shifted by
    one sample (neighbours are unknown at the very first tick)."""
    net = Net(1)
    lam = []
    for _ in range(net.sc.steps):
        lam.append([a.lam for a in net.agents])
        net.run(TS)
    ref = run_lockstep(net.sc)
    diff = np.abs(np.array(lam) - ref.lam[:-1])
    assert diff.max() < 0.03           # the one-sample shift during the fast transient
    assert diff[-500:].max() < 1e-4    # the same equilibrium
    assert net.error() < 1e-3
    assert all(a.state == State.RUNNING for a in net.agents)
    assert all(not +a.counters for a in net.agents), [a.summary() for a in net.agents]


def test_init_until_price_then_running() -> None:
    a = one_agent()
    a.tick(0.0)
    assert a.state == State.INIT
    a.on_frame(price_frame(0), 0.005)
    a.tick(0.01)
    assert a.state == State.RUNNING


def test_price_lost_enters_safe_and_recovers() -> None:
    net = Net(1)
    net.run(2.0)
    net.price_on = False
    net.run(0.2)   # the last price frame was at t = 1.95 s: 0.24 s ago, within price_s
    assert all(a.state == State.RUNNING for a in net.agents)
    net.run(0.02)
    assert all(a.state == State.SAFE for a in net.agents)
    held = [a.lam for a in net.agents]
    net.run(0.5)
    assert [a.lam for a in net.agents] == held     # λ frozen in SAFE
    setpoints = [m for m in net.sent[-40:] if 0x200 < m.arbitration_id <= 0x220]
    assert all(CODEC.decode(m).raw["Enable"] == 0 for m in setpoints)
    net.price_on = True
    net.run(6.0)
    assert all(a.state == State.RUNNING for a in net.agents)
    assert all(a.counters["price_timeouts"] == 1 for a in net.agents)
    assert net.error() < 1e-3


def test_silent_neighbour_drops_out_within_three_periods_and_rejoins() -> None:
    net = Net(1)
    net.run(3.0)
    hub = net.agents[0]
    assert hub.neighbours_alive == 3
    net.run(0.03, skip={2})      # agent 2 silent for 3 periods: still counted alive
    assert hub.neighbours_alive == 3
    net.run(0.01, skip={2})      # the 4th silent period: dropped
    assert hub.neighbours_alive == 2
    assert hub.counters["neighbour_timeouts"] == 1
    net.run(5.0, skip={2})
    assert max(abs(a.lam - 0.8) for a in net.agents if a.cfg.id != 2) < 1e-3
    net.run(0.02)
    assert hub.neighbours_alive == 3
    # after a timeout the 4-bit counter gap is meaningless (it aliases): not counted as loss
    assert hub.counters["lost_frames"] == 0


def test_isolate_and_reconnect_commands() -> None:
    net = Net(4)
    net.run(5.0)

    def command(cmd: int, target: int) -> None:
        net.deliver(SENDER.frame("ER_Command", {"Command": cmd, "Target": target_raw(target),
                                                "GainK": 0, "GainH": 0}, net.k % 16))

    command(1, 2)
    command(1, 2)  # repeats are idempotent
    a2 = net.agents[1]
    assert a2.state == State.ISOLATED
    assert a2.lam == pytest.approx(0.18 * 1.08, abs=1e-6)  # idle MC (1+m)β
    net.run(1.0)
    assert net.agents[0].neighbours_alive == 2  # an ISOLATED neighbour is not used
    command(2, 2)
    net.run(8.0)
    assert a2.state == State.RUNNING
    assert net.error() < 1e-3


def test_pin_and_unpin_commands() -> None:
    """CMD-7: UNPIN takes the price term out of the hub's ξ, PIN puts it into a leaf's; a
    PIN with another GainK is out of range (counted under range, not a command). With
    agent 3 pinned instead of agent 1 the star still follows a new price."""
    net = Net(1)
    net.run(5.0)

    def pin(target: int, gain_k: int) -> None:
        net.deliver(SENDER.frame("ER_Command", {"Command": int(Command.PIN),
                                                "Target": target_raw(target),
                                                "GainK": gain_k, "GainH": 0}, net.k % 16))

    hub, leaf = net.agents[0], net.agents[2]
    assert (hub.pin, leaf.pin) == (fx.ONE, 0)
    pin(1, PIN_OFF)
    pin(3, PIN_ON)
    assert (hub.pin, leaf.pin) == (0, fx.ONE)
    assert (hub.counters["commands"], leaf.counters["commands"]) == (1, 1)
    assert hub.state == leaf.state == State.RUNNING
    pin(2, 0)
    assert net.agents[1].counters["range"] == 1 and net.agents[1].counters["commands"] == 0
    assert net.agents[1].pin == 0
    net.sc = replace(net.sc, prices=(PriceStep(0.0, 0.9),))
    net.run(15.0)
    assert max(abs(a.lam - 0.9) for a in net.agents) < 1e-3


def test_set_gains_command_and_bad_gains_counted() -> None:
    a = one_agent()
    a.on_frame(SENDER.frame("ER_Command", {"Command": 3, "Target": target_raw(1), "GainK": 2000,
                                           "GainH": 3000}, 0), 0.0)
    assert (a.ctrl.config.k, a.ctrl.config.h) == (2.0, 3.0)
    a.on_frame(SENDER.frame("ER_Command", {"Command": 3, "Target": target_raw(1), "GainK": 0,
                                           "GainH": 3000}, 1), 0.0)
    # k = 0 is outside the configured bounds (×0.5..×2 of k = 1): the safety model
    # rejects it before the controller's own parameter check would
    assert a.counters["implausible_gains"] == 1 and a.ctrl.config.k == 2.0
    assert "k" in a.last_error["implausible_gains"]
    # inside the bounds but an invalid controller: still a range error
    bad = replace(a.cfg, k_min=0.0)
    b = AgentRuntime(bad, CODEC)
    b.on_frame(SENDER.frame("ER_Command", {"Command": 3, "Target": target_raw(1), "GainK": 0,
                                           "GainH": 3000}, 0), 0.0)
    assert b.counters["range"] == 1 and b.ctrl.config.k == 1.0
    assert "k" in b.last_error["range"]


def test_plant_fault_enters_safe_and_recovers() -> None:
    net = Net(1)
    net.run(1.0)
    net.overcurrent = {3}
    net.run(0.02)   # the fault is in the status frame at t = 1.0 s
    assert net.agents[2].state == State.SAFE
    net.run(0.5)
    assert net.agents[2].state == State.SAFE
    assert net.agents[2].counters["plant_faults"] == 1   # rising edges, not frames
    assert all(a.state == State.RUNNING for a in net.agents if a.cfg.id != 3)
    net.overcurrent = set()
    net.run(0.05)
    assert net.agents[2].state == State.RUNNING
    assert net.agents[2].counters["status_timeouts"] == 0


# --------------------------------------------------------------------------- rejections


def test_each_bad_frame_is_rejected_and_counted_by_cause() -> None:
    a = one_agent()
    a.on_frame(price_frame(0), 0.0)
    good = price_frame(1)                          # never delivered: 1 lost
    bad_mac = can.Message(arbitration_id=0x010, is_extended_id=False,
                          data=bytes([good.data[0] ^ 1]) + bytes(good.data[1:]))
    short = can.Message(arbitration_id=0x010, is_extended_id=False, data=bytes(good.data[:5]))
    p2 = price_frame(2, rho=50.0)
    p3 = price_frame(3)
    for msg in (bad_mac, short,
                can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)),
                can.Message(arbitration_id=0x010, is_extended_id=True, data=bytes(8)),
                p2,                                # authentic (1 lost), ρ out of [-10, 10]
                mc_frame(2, 0, lam=99.0),          # neighbour λ out of range
                p3,                                # accepted
                p3,                                # replayed: its freshness is spent
                price_frame(7),                    # 3 frames lost
                mc_frame(1, 5)):                   # our own identity, not sent by us
        a.on_frame(msg, 0.0)
    assert dict(a.counters) == {"auth": 2, "dlc": 1, "unknown_id": 2, "range": 2,
                                "lost_frames": 4, "impersonation": 1, "foreign": 1}
    assert "expected a MAC that verifies" in a.last_error["auth"]
    assert a.io.last_safety == ("auth", 0x010)
    assert a.price == fx.to_fixed(0.8)


def test_own_frames_echoed_back_are_not_impersonation() -> None:
    a = one_agent()
    a.on_frame(price_frame(0), 0.0)
    for k in range(20):
        for m in a.tick(k * TS):
            a.on_frame(m, k * TS)
    assert a.counters["impersonation"] == 0


def test_diag_frames_carry_the_counters() -> None:
    a = one_agent()
    a.on_frame(CODEC.encode("ER_Price", {"PriceValid": 1, "Rho": 0, "Segment": 0}, 0), 0.0)
    a.on_frame(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)), 0.0)
    a.note("deadline_miss", 2)
    pages = {}
    for k in range(40):
        for m in a.tick(k * TS):
            if m.arbitration_id == 0x301:
                f = CODEC.decode(m)
                pages[f.raw["Page"]] = f.raw
    assert pages[0]["DeadlineMisses"] == 2
    assert pages[3]["RejectedUnknownId"] == 1
    assert set(pages) == {0, 1, 2, 3}


def test_setpoint_map_matches_the_cost_model() -> None:
    sc = load_case(1)
    for cfg, bat in zip(agent_configs_from_scenario(sc), sc.batteries, strict=True):
        sp = SetpointMap(cfg.battery)
        for lam in np.linspace(0.1, 1.6, 31):
            raw, limited = sp(fx.to_fixed(float(lam)))
            assert raw / 100 == pytest.approx(bat.power(lam), abs=0.011)
            assert limited == (not bat.p_min < (lam / (1 + bat.m) - bat.beta) / (2 * bat.alpha)
                               < bat.p_max)


def test_setpoint_frames_follow_lambda() -> None:
    net = Net(1)
    net.run(10.0)
    last = {}
    for m in net.sent:
        if 0x200 < m.arbitration_id <= 0x204:
            last[m.arbitration_id - 0x200] = CODEC.decode(m).phys("PowerSetpoint")
    for i, b in enumerate(net.sc.batteries, start=1):
        assert last[i] == pytest.approx(b.power(0.8), abs=0.05)
    assert setpoint_name(1) == "AGENT_1_Setpoint"


# --------------------------------------------------------------------------- bus seam

def test_acceptance_filter_passes_exactly_what_the_agent_uses_or_sends() -> None:
    """Agent 2 of case 1 (a leaf of the star: one neighbour, agent 1)."""
    agent = AgentRuntime(agent_configs_from_scenario(load_case(1))[1], CODEC)
    fid = CODEC.frame_id
    used = {fid("ER_Price"), fid("ER_Command"), fid(status_name(2)), fid(mc_name(1))}
    sent = {fid(mc_name(2)), fid(setpoint_name(2)), fid("AGENT_2_Diag")}
    syncs = {fid(f"{CODEC.name_of(i)}_Sync") for i in used | sent}
    assert agent.io.accepted_ids() == sorted(used | sent | syncs)
    kw = bus_kwargs("socketcan", "vcan0")
    filters = with_acceptance_filter(kw, agent.io.accepted_ids())["can_filters"]
    assert [f["can_id"] for f in filters] == agent.io.accepted_ids()
    assert all(f["can_mask"] == 0x7FF and f["extended"] is False for f in filters)
    # python-can would filter udp_multicast / virtual in user space, uncounted: no filter
    for interface in ("udp_multicast", "virtual"):
        kw = bus_kwargs(interface)
        assert with_acceptance_filter(kw, agent.io.accepted_ids()) == kw
    assert "can_filters" not in with_acceptance_filter(bus_kwargs("socketcan"), [1], False)


def test_run_node_counts_error_frames_and_keeps_running() -> None:
    agent = one_agent()
    node_bus = can.Bus(interface="virtual", channel="error-frames", receive_own_messages=False)
    peer = can.Bus(interface="virtual", channel="error-frames", receive_own_messages=False)
    try:
        peer.send(can.Message(is_error_frame=True, arbitration_id=0x20000004, data=bytes(8)))
        peer.send(price_frame(0))
        run_node(agent, node_bus, duration=0.1)
    finally:
        node_bus.shutdown()
        peer.shutdown()
    assert agent.counters["error_frame"] == 1
    assert agent.price is not None and agent.ticks >= 5


class _Overrunning:
    """A node whose every tick takes two periods of its simulated clock (an overloaded
    host): every tick after the first starts a whole period late. Periods are powers of 2,
    so the clock's sums are exact."""

    period = 2.0 ** -6

    def __init__(self) -> None:
        self.frames = 0
        self.ticks = 0
        self.counters: dict[str, int] = {}
        self.t = 0.0

    def clock(self) -> float:
        return self.t

    def on_frame(self, msg: can.Message, t: float) -> None:
        self.frames += 1

    def tick(self, t: float) -> list[can.Message]:
        self.ticks += 1
        self.t += 2 * self.period
        return []

    def note(self, event: str, count: int = 1) -> None:
        self.counters[event] = self.counters.get(event, 0) + count


def test_run_node_still_reads_its_inputs_when_every_tick_overruns() -> None:
    """Expected (exact, simulated clock): over 20 periods the node ticks at 0, 2, ..., 18
    periods (10 ticks); each tick after the first is one period late: a deadline miss for
    it and one for the period it skipped (18 in all); the 40 frames queued before the
    start are all read, the late ticks never starving the input."""
    node = _Overrunning()
    node_bus = can.Bus(interface="virtual", channel="overrun", receive_own_messages=False)
    peer = can.Bus(interface="virtual", channel="overrun", receive_own_messages=False)
    try:
        for k in range(40):
            peer.send(price_frame(k % 16))
        run_node(node, node_bus, duration=20 * node.period, clock=node.clock)
    finally:
        node_bus.shutdown()
        peer.shutdown()
    assert node.frames == 40
    assert node.ticks == 10
    assert node.counters == {"deadline_miss": 2 * (10 - 1)}


# --------------------------------------------------------------------------- plant status


def setpoints_enable(frames: list[can.Message], agent: int = 1) -> list[int]:
    fid = CODEC.frame_id(setpoint_name(agent))
    return [CODEC.decode(m).raw["Enable"] for m in frames if m.arbitration_id == fid]


def test_status_timeout_is_five_status_cycles_from_the_contract() -> None:
    cfg = agent_configs_from_scenario(load_case(1))[0]
    assert cfg.status_timeout_s == pytest.approx(timeout_s(status_name(1))) == \
        pytest.approx(0.25)
    slow = agent_configs_from_scenario(scaled(load_case(1), 4))[0]   # Ts = 40 ms
    assert slow.status_timeout_s == pytest.approx(1.0)
    assert slow.price_timeout_s == pytest.approx(1.0)


def test_init_until_both_price_and_status_are_fresh() -> None:
    """Before its first PLANT_<id>_Status the agent stays INIT (setpoint disabled), however
    fresh the price; no timeout is counted for a status never heard."""
    a = one_agent(status=False)
    out = []
    for k in range(30):
        if k % 5 == 0:
            a.on_frame(price_frame(k // 5), k * TS)
        out += a.tick(k * TS)
    assert a.state == State.INIT
    assert set(setpoints_enable(out)) == {0}
    assert a.counters["status_timeouts"] == 0
    a.on_frame(status_frame(1, 0), 0.3)
    a.tick(0.3)
    assert a.state == State.RUNNING


def test_status_lost_enters_safe_exactly_at_the_timeout_and_recovers() -> None:
    """Injected clock, binary-exact times: status at 0.125 s, timeout 0.25 s. RUNNING at
    0.375 s (age = timeout), SAFE at the first tick past it, Enable = 0 while SAFE; a
    fresh status (from a restarted plant: its sync, then its frames) brings RUNNING back."""
    a = one_agent(status=False)
    a.on_frame(price_frame(0), 0.125)
    a.on_frame(status_frame(1, 0), 0.125)
    out = a.tick(0.125)
    assert a.state == State.RUNNING and setpoints_enable(out) == [1]
    a.on_frame(price_frame(1), 0.25)   # the price stays fresh throughout
    a.tick(0.375)
    assert a.state == State.RUNNING
    a.tick(0.375 + 1e-6)
    assert a.state == State.SAFE
    assert a.counters["status_timeouts"] == 1 and a.counters["price_timeouts"] == 0
    out = []
    for k in range(10):
        t = 0.38 + k * TS
        if k % 5 == 0:
            a.on_frame(price_frame(2 + k // 5), t)
        out += a.tick(t)
    assert a.state == State.SAFE
    assert setpoints_enable(out) and set(setpoints_enable(out)) == {0}
    assert a.counters["status_timeouts"] == 1      # one outage, one count
    SENDER.restart()                               # a restarted plant: a new boot, ...
    a.on_frame(SENDER.sync(status_name(1)), 0.48)  # ... announced by its sync first
    a.on_frame(status_frame(1, 0), 0.48)
    a.tick(0.48)
    assert a.state == State.RUNNING
    assert a.counters["foreign"] == 0 and a.counters["lost_frames"] == 0
    out = [m for k in range(5) for m in a.tick(0.49 + k * TS)]
    assert setpoints_enable(out) == [1]


def test_dead_plant_in_a_network_sends_only_its_agent_safe() -> None:
    net = Net(1)
    net.run(2.0)
    net.status_off = {2}
    net.run(0.2)
    assert net.agents[1].state == State.RUNNING
    net.run(0.1)
    assert net.agents[1].state == State.SAFE
    assert all(a.state == State.RUNNING for a in net.agents if a.cfg.id != 2)
    assert net.agents[0].neighbours_alive == 2     # a SAFE neighbour is not active
    net.status_off = set()
    net.run(6.0)
    assert all(a.state == State.RUNNING for a in net.agents)
    assert net.agents[1].counters["status_timeouts"] == 1
    assert net.error() < 1e-3


# --------------------------------------------------------------------------- diag pages


def test_diag_pages_are_the_dbc_pages_and_all_are_sent() -> None:
    """DIAG_PAGES names exactly the signals of each multiplexer page of the DBC, and the
    rotation sends every page."""
    msg = CODEC.database.get_message_by_name("AGENT_1_Diag")
    tree = next(n for n in msg.signal_tree if isinstance(n, dict))["Page"]
    assert {p: tuple(s) for p, s in tree.items()} == dict(enumerate(AgentRuntime.DIAG_PAGES))
    a = one_agent()
    a.on_frame(price_frame(0), 0.0)
    pages = set()
    for k in range(DIAG_EVERY * len(AgentRuntime.DIAG_PAGES)):
        for m in a.tick(k * TS):
            if m.arbitration_id == CODEC.frame_id("AGENT_1_Diag"):
                pages.add(CODEC.decode(m).raw["Page"])
    assert pages == set(tree)


def test_diag_counters_page_reports_timeouts_faults_and_foreign_frames() -> None:
    a = one_agent()
    a.on_frame(price_frame(0), 0.0)
    a.tick(0.0)
    a.on_frame(status_frame(1, 1, overcurrent=1), 0.01)
    a.on_frame(mc_frame(9, 0), 0.01)            # agent 9 in a 4-agent run
    a.on_frame(mc_frame(1, 0), 0.01)            # our own identity
    pages = {}
    for k in range(1, 100):
        for m in a.tick(k * TS):
            if m.arbitration_id == CODEC.frame_id("AGENT_1_Diag"):
                f = CODEC.decode(m)
                pages[f.raw["Page"]] = f.raw
    assert pages[7]["PlantFaults"] == 1
    assert pages[6]["StatusTimeouts"] == 1 and pages[6]["PriceTimeouts"] == 1
    assert pages[7]["ForeignFrames"] == 2 and pages[8]["ForeignIds"] == 1
    assert pages[8]["InterleavedCounters"] == 0


# --------------------------------------------------------------------------- foreign traffic


def test_frames_of_agents_outside_the_run_are_foreign_when_the_fleet_is_known() -> None:
    a = one_agent()
    assert a.cfg.fleet_size == 4
    a.on_frame(mc_frame(9, 0), 0.0)
    a.on_frame(CODEC.encode(setpoint_name(5), {"Enable": 1, "PowerSetpoint": 0}, 0), 0.0)
    a.on_frame(mc_frame(3, 0), 0.0)                  # a neighbour: in the fleet
    assert a.counters["foreign_id"] == 2 and a.counters["foreign"] == 2
    assert "agent 5" in a.last_error["foreign_id"]   # the last one
    unknown = AgentRuntime(replace(a.cfg, fleet_size=None), CODEC)
    unknown.on_frame(mc_frame(9, 0), 0.0)
    assert not +unknown.counters


def test_a_second_sender_or_a_replay_fails_auth_a_lossy_sender_does_not() -> None:
    a = one_agent()
    for c in (0, 1, 3):                     # a gap of 1 lost frame
        a.on_frame(price_frame(c), 0.0)
    replayed = price_frame(7)               # 3 lost
    a.on_frame(replayed, 0.0)
    assert a.counters["lost_frames"] == 4 and a.counters["auth"] == 0
    forger = FleetSender(CODEC, keys={"router": bytes(16 * [9])})  # right layout, no key
    a.on_frame(forger.frame("ER_Price", {"PriceValid": 1, "Rho": fx.to_fixed(0.5),
                                         "Segment": 0}, 8), 0.0)
    a.on_frame(replayed, 0.0)               # a genuine frame again: its freshness is spent
    assert a.counters["auth"] == 2 and a.price == fx.to_fixed(0.8)
    a.on_frame(price_frame(7 + 15, rho=0.9), 0.0)    # the edge of the window: 14 lost
    assert a.price == fx.to_fixed(0.9) and a.counters["lost_frames"] == 18


def test_restarted_router_after_the_price_timeout_is_heard_after_its_sync() -> None:
    a = one_agent()
    a.on_frame(price_frame(9), 0.0)
    a.tick(0.0)
    a.tick(0.3)                                      # price timed out
    assert a.counters["price_timeouts"] == 1
    SENDER.restart()                                 # a restarted router: boot 2 ...
    a.on_frame(price_frame(0, rho=0.7), 0.31)        # ... whose sync this agent missed
    assert a.counters["unsynced"] == 1 and a.counters["auth"] == 0 and a.price_rx == 0.0
    a.on_frame(SENDER.sync("ER_Price"), 0.32)        # the next sync (1 s, or a hello)
    a.on_frame(price_frame(1, rho=0.7), 0.33)
    assert a.counters["foreign"] == 0 and a.counters["auth"] == 0 and a.price_rx == 0.33
    assert a.price == fx.to_fixed(0.7) and a.counters["resyncs"] == 1


def test_a_frame_that_slips_in_before_the_kernel_filter_is_dropped_as_the_filter_would(
) -> None:
    """GEN-5: python-can binds a SocketCAN socket before it installs the filter, so a
    frame can arrive in between. The node reads through AcceptanceBus, which drops every
    data frame the filter would not pass (uncounted, as the filter would) and keeps the
    ones it passes and error frames (LOOP-4)."""
    from firmware_py.node import AcceptanceBus, behind_filter, with_acceptance_filter

    frames = [can.Message(arbitration_id=0x7F0, data=bytes(8), is_extended_id=False),
              can.Message(arbitration_id=0x010, data=bytes(8), is_extended_id=True),
              can.Message(arbitration_id=0x010, data=bytes(8), is_extended_id=False),
              can.Message(arbitration_id=0x20000080, is_error_frame=True)]

    class Queue:
        def recv(self, timeout: float | None = None) -> can.Message | None:
            return frames.pop(0) if frames else None

        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            raise AssertionError("not sent")

    kw = with_acceptance_filter({"interface": "socketcan", "channel": "vcan0"}, [0x010, 0x101])
    reader = behind_filter(Queue(), kw)  # type: ignore[arg-type]
    assert isinstance(reader, AcceptanceBus)
    got = [reader.recv(timeout=0), reader.recv(timeout=0), reader.recv(timeout=0)]
    assert [(m.arbitration_id, m.is_error_frame) for m in got if m] == [
        (0x010, False), (0x20000080, True)]
    assert got[2] is None
    plain = Queue()
    assert behind_filter(plain, {"interface": "udp_multicast"}) is plain  # type: ignore[arg-type]
