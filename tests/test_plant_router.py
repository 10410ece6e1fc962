"""The plant and router nodes, pure: frames built as the fleet's senders build them
(signed, firmware_py.nodeio.FleetSender) in through on_frame, frames out of tick, fixed
timestamps (no sleeping); plus one run on a virtual bus.

Nodes built without a keyring use the public --insecure keys: their receivers expect
every sender at boot 1, count 0, so the frames of SENDER need no sync. Every tick may
also return the node's ``<name>_Sync`` frames (first tick, every second, a peer's
(re)start): tests that look at a node's output tell them apart by the codec's kind."""

from __future__ import annotations

import functools
import itertools
import math
import threading
import time
from collections import Counter
from dataclasses import replace

import can
import pytest

from firmware_py.contract import (
    COUNTER_MODULO,
    FV_COUNT_BITS,
    SYNCED_BY,
    cycle_s,
    every_ticks,
    timeout_s,
)
from firmware_py.errors import ParameterError
from firmware_py.frames import FrameCodec, setpoint_name, status_name, target_agent
from firmware_py.node import StopFlag, run_node
from firmware_py.nodeio import FleetSender
from firmware_py.secoc import (
    INSECURE_MASTER,
    Keyring,
    derive_command_key,
    derive_frame_key,
    derive_node_key,
    frame_verifies,
)
from sim.cli import main
from sim.model.cost import Battery, expenditure, kkt_optimum
from sim.model.scenario import Scenario, load_case, scaled
from sim.nodes import plant as plant_module
from sim.nodes.plant import TAU_S, cell_power, current_limit, open_circuit_voltage
from sim.nodes.router import RouterNode

# These drive the plant's physics with setpoints alone, no agent's MC frames to check
# them against: the plant obeys them, as told to (the check itself: tests/test_liar.py).
PlantNode = functools.partial(plant_module.PlantNode, obey_inconsistent=True)


CODEC = FrameCodec()
DT = 0.01
_channels = itertools.count()

SENDER = FleetSender(CODEC)  # the agents and the plant, --insecure: boot 1, no sync needed
ROUTER_KEY = derive_node_key(INSECURE_MASTER, "router")  # what an insecure agent verifies
WRONG_KEY = bytes(16 * [9])                              # a forger's: right layout, no key


def link_key(name: str) -> bytes:
    """A link frame's insecure key (AUTH-28), what an insecure receiver verifies it with."""
    return derive_frame_key(INSECURE_MASTER, name.removesuffix("_Sync"))


@pytest.fixture(autouse=True)
def _fresh_senders() -> None:
    """Every test starts with senders that just booted, as its fresh nodes expect."""
    SENDER.reset_counts()
    SENDER.boot = 1


def T(k: int) -> float:
    """Tick k's time: exact multiples, as an MCU timer would give."""
    return k * DT


def fv(boot: int, count: int) -> int:
    """The full freshness value Boot ‖ Count."""
    return boot << FV_COUNT_BITS | count


def is_sync(msg: can.Message) -> bool:
    return CODEC.kind(msg.arbitration_id) == "sync"


def data_frames(frames: list[can.Message]) -> list[can.Message]:
    """A node's output without its ``<name>_Sync`` frames."""
    return [m for m in frames if not is_sync(m)]


def with_batteries(sc: Scenario, **changes: float) -> Scenario:
    return replace(sc, batteries=tuple(replace(b, **changes) for b in sc.batteries))


def setpoint(agent: int, p_kw: float, counter: int | None = None, enable: int = 1,
             sender: FleetSender = SENDER) -> can.Message:
    """AGENT_<agent>_Setpoint as agent ``agent`` signs it (its next count, or the next one
    whose low 4 bits are ``counter``: the skipped ones are lost frames)."""
    return sender.frame(setpoint_name(agent), {"Enable": enable,
                                               "PowerSetpoint": round(p_kw * 100)}, counter)


def status(agent: int, p_kw: float, counter: int | None = None,
           sender: FleetSender = SENDER, **flags: int) -> can.Message:
    """PLANT_<agent>_Status as the plant signs it (4 flags, Power, Soc)."""
    raw = {"FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
           "Power": round(p_kw * 100), "Soc": 120, **flags}
    return sender.frame(status_name(agent), raw, counter)


def totals(powers: dict[int, float], counter: int | None = None,
           sender: FleetSender = SENDER, sc: Scenario | None = None) -> can.Message:
    """PLANT_Totals as the plant signs it: the sum of ``powers`` (agent: kW) and the
    batteries' cost rate at them (case 1's batteries unless ``sc``)."""
    batteries = (sc or load_case(1)).batteries
    cost = sum(batteries[i - 1].cost_rate(p) for i, p in powers.items())
    raw = {"BatteryPower": round(sum(powers.values()) * 10), "BatteryCostRate": round(cost * 10)}
    return sender.frame("PLANT_Totals", raw, counter)


def flipped(msg: can.Message, byte: int, mask: int = 1) -> can.Message:
    """``msg`` with bits of one byte flipped (a corrupted or tampered frame)."""
    data = bytearray(msg.data)
    data[byte] ^= mask
    return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False,
                       data=bytes(data))


class PlantDriver:
    """Ticks a plant every 10 ms and feeds it a setpoint per BESS every 20 ms (like agents,
    signed by SENDER); keeps the decoded status frames and, apart, the sync frames."""

    def __init__(self, plant: PlantNode) -> None:
        self.plant = plant
        self.k = 0
        self.status: list[tuple[float, dict[str, float]]] = []  # (t, decoded) per frame
        self.syncs: list[tuple[float, str]] = []                # (t, name) per sync frame
        self.totals: list[tuple[float, dict[str, float]]] = []  # (t, PLANT_Totals)

    def send(self, agent: int, p_kw: float, enable: int = 1) -> None:
        self.plant.on_frame(setpoint(agent, p_kw, enable=enable), T(self.k))

    def run(self, seconds: float, setpoints: dict[int, float] | None = None) -> None:
        for _ in range(round(seconds / DT)):
            if setpoints and self.k % 2 == 0:
                for agent, p in setpoints.items():
                    self.send(agent, p)
            for msg in self.plant.tick(T(self.k)):
                f = CODEC.decode(msg)
                if is_sync(msg):
                    self.syncs.append((T(self.k), f.name))
                    continue
                if f.name == "PLANT_Totals":
                    self.totals.append((T(self.k), {s: f.phys(s) for s in f.raw}))
                    continue
                d = {s: f.phys(s) for s in ("Power", "Soc")}
                d.update({s: f.raw[s] for s in ("FaultOverCurrent", "FaultVoltage", "FaultSoc",
                                                "PowerLimited")})
                d["agent"] = f.agent
                self.status.append((T(self.k), d))
            self.k += 1

    def last(self, agent: int) -> dict[str, float]:
        return [d for _, d in self.status if d["agent"] == agent][-1]


# --------------------------------------------------------------------------- plant physics


def test_chopper_step_response_is_first_order_with_tau() -> None:
    """R = 0 keeps V = V_oc (SoC moves by ~1e-5 in 50 ms), so I_ref is constant and the
    exact discretisation must give 1 − exp(−t/τ) at every tick: 63.2 % at τ."""
    sc = with_batteries(load_case(1), r_internal=0.0)
    plant = PlantNode(sc, ramp_full_s=0)  # the current loop alone
    drv = PlantDriver(plant)
    drv.send(1, 50.0)
    u = plant.unit(1)
    i_final = 50e3 / open_circuit_voltage(u.battery, u.soc)
    drv.run(DT)  # t = 0: latches the reference, nothing has moved yet
    assert u.current == 0.0 and u.i_ref == pytest.approx(i_final)
    for k in range(1, 11):
        drv.run(DT, {1: 50.0})
        assert u.current / i_final == pytest.approx(1 - math.exp(-T(k) / TAU_S), rel=2e-5)
    # after exactly τ: 63 %
    assert TAU_S == 0.05
    p_at_tau = [d["Power"] for t, d in drv.status if d["agent"] == 1 and abs(t - 0.05) < 1e-9]
    assert len(p_at_tau) == 1  # the one status at 50 ms reports the state after 50 ms = τ
    assert p_at_tau[0] == pytest.approx((1 - math.exp(-1)) * 50.0, abs=0.02)
    plant2 = PlantNode(sc, ramp_full_s=0)
    plant2.on_frame(setpoint(1, 50.0, sender=FleetSender(CODEC)), 0.0)  # a fresh agent
    plant2.tick(0.0)
    plant2.tick(TAU_S)  # one uneven step of exactly τ: dt is the real elapsed time
    assert plant2.unit(1).current / i_final == pytest.approx(1 - math.exp(-1), rel=1e-6)
    assert plant2.unit(1).power == pytest.approx(0.632 * 50.0, rel=1e-3)


def test_steady_state_power_equals_setpoint_with_internal_resistance() -> None:
    """The delivered power equals the setpoint although the terminal voltage sags by R·I.
    PLANT_<i>_Status no longer carries Current and Voltage (dropped for the MAC; nobody
    read them): the sag is checked on the model, the frame's Power and Soc against it."""
    plant = PlantNode(load_case(1))
    drv = PlantDriver(plant)
    drv.run(1.0, {1: 66.0, 2: -40.0})
    assert drv.last(1)["Power"] == pytest.approx(66.0, abs=0.02)
    assert drv.last(2)["Power"] == pytest.approx(-40.0, abs=0.02)
    u = plant.unit(1)
    assert u.voltage == pytest.approx(open_circuit_voltage(u.battery, u.soc)
                                      - u.battery.r_internal * u.current)
    assert u.voltage < open_circuit_voltage(u.battery, u.soc)  # discharging: a real sag
    assert drv.last(1)["Power"] == pytest.approx(u.power, abs=0.005)
    assert drv.last(1)["Soc"] == pytest.approx(100 * u.soc, abs=0.25)
    assert drv.last(1)["PowerLimited"] == 0 and drv.last(3)["Power"] == 0.0  # no setpoint: 0 kW


def test_plant_totals_are_the_sum_of_the_statuses_sent_with_them() -> None:
    """PLANT_Totals, sent with each cycle's statuses, carries their powers' sum and the
    batteries' cost rate at those powers (the router's ledger: AUTH-29)."""
    sc = load_case(1)
    drv = PlantDriver(PlantNode(sc))
    drv.run(1.0, {1: 66.0, 2: -40.0, 4: 25.0})
    t, tot = drv.totals[-1]
    powers = [d["Power"] for ts, d in drv.status if ts == t]
    assert len(powers) == sc.n and len(drv.totals) == 20
    assert tot["BatteryPower"] == pytest.approx(sum(powers), abs=0.051)
    cost = expenditure(sc.batteries, powers, 0.0, 0.0)  # ρ = 0, D = 0: the batteries alone
    assert tot["BatteryCostRate"] == pytest.approx(cost, abs=0.051) and cost > 1.0


def test_power_clipped_at_limits_sets_power_limited() -> None:
    sc = load_case(1)  # BESS 1: [-120, 120] kW, BESS 2: [-100, 100] kW
    plant = PlantNode(sc)
    drv = PlantDriver(plant)
    drv.run(1.0, {1: 200.0, 2: -150.0, 3: 30.0})
    assert drv.last(1)["Power"] == pytest.approx(120.0, abs=0.02)
    assert drv.last(2)["Power"] == pytest.approx(-100.0, abs=0.02)
    assert drv.last(1)["PowerLimited"] == 1 and drv.last(2)["PowerLimited"] == 1
    assert drv.last(3)["PowerLimited"] == 0
    drv.run(0.1, {1: 100.0, 2: -50.0, 3: 30.0})  # back inside: the flag clears at once
    assert drv.last(1)["PowerLimited"] == 0 and drv.last(2)["PowerLimited"] == 0


def test_current_limit_engages_and_sets_power_limited() -> None:
    """A sagging pack (R = 0.5 Ω, near-empty) needs > I_max for p_max: the current is
    held at I_max = 1.1·p_max/(0.9·v_nom) and PowerLimited is set."""
    sc = with_batteries(load_case(1), r_internal=0.5, soc0=0.06)
    plant = PlantNode(sc)
    u = plant.unit(1)
    assert u.i_max == pytest.approx(1.1 * 120e3 / (0.9 * 700.0))
    assert current_limit(u.battery) == u.i_max
    drv = PlantDriver(plant)
    drv.run(1.0, {1: 120.0})
    assert u.current == pytest.approx(u.i_max, rel=1e-4) and u.current <= u.i_max
    assert drv.last(1)["PowerLimited"] == 1 and drv.last(1)["FaultOverCurrent"] == 0
    assert drv.last(1)["Power"] < 119.0


@pytest.mark.parametrize("p_kw", [36.0, -36.0])
def test_soc_integrates_cell_power_with_inner_loss(p_kw: float) -> None:
    """dSoC/dt = −(P + (α|P|+β)|P|)/(3600·C): a 1 kWh pack at ±36 kW for 1 s in steady state."""
    sc = with_batteries(load_case(1), capacity_kwh=1.0, soc0=0.5)
    plant = PlantNode(sc)
    drv = PlantDriver(plant)
    drv.run(0.5, {1: p_kw})  # 10 τ: steady state
    u = plant.unit(1)
    soc1 = u.soc
    drv.run(1.0, {1: p_kw})
    b = u.battery
    expected = cell_power(b, p_kw) / 3600.0 / b.capacity_kwh
    assert cell_power(b, p_kw) == pytest.approx(p_kw + (b.alpha * 36 + b.beta) * 36)
    assert soc1 - u.soc == pytest.approx(expected, rel=2e-3)
    assert drv.last(1)["Soc"] == pytest.approx(100 * u.soc, abs=0.25)


def test_soc_fault_blocks_further_discharge() -> None:
    sc = with_batteries(load_case(1), capacity_kwh=0.05, soc0=0.08)
    plant = PlantNode(sc)
    drv = PlantDriver(plant)
    drv.run(2.0, {1: 50.0})
    u = plant.unit(1)
    assert u.soc < 0.05 and drv.last(1)["FaultSoc"] == 1
    assert u.p_ref == 0.0 and abs(u.power) < 0.5 and drv.last(1)["PowerLimited"] == 1
    assert plant.counters["soc_faults"] == 1
    drv.run(0.5, {1: -20.0})  # charging is still allowed and clears the fault
    assert u.soc > 0.05 and drv.last(1)["FaultSoc"] == 0


# --------------------------------------------------------------------------- plant I/O


def test_setpoint_timeout_ramps_to_zero_and_is_counted() -> None:
    plant = PlantNode(load_case(1))
    drv = PlantDriver(plant)
    drv.run(0.5, {1: 50.0})  # last setpoint at t = 0.48
    assert drv.last(1)["Power"] == pytest.approx(50.0, abs=0.05)
    drv.run(0.24)            # up to t = 0.73: 250 ms old, not older
    assert plant.counters["setpoint_timeouts"] == 0 and plant.unit(1).p_ref == 50.0
    drv.run(0.01)            # t = 0.74: 260 ms > 250 ms
    assert plant.counters["setpoint_timeouts"] == 1 and plant.unit(1).setpoint_timeouts == 1
    assert plant.unit(1).p_ref == 0.0 and plant.unit(1).stale
    t_out = 0.74  # the tick that latched P_ref = 0
    p0 = plant.unit(1).power
    drv.run(0.25)
    for t, d in drv.status:
        if d["agent"] == 1 and t > t_out + 0.05:
            assert d["Power"] < 50.0 * math.exp(-(t - t_out - 0.05) / TAU_S) + 0.05
    assert abs(plant.unit(1).power) < 0.05 * p0  # 5 τ later: ramped down
    assert plant.counters["setpoint_timeouts"] == 1  # counted once per outage
    drv.run(0.5, {1: 20.0})  # setpoints back: followed again, no lost frames counted
    assert drv.last(1)["Power"] == pytest.approx(20.0, abs=0.05)
    assert plant.counters["lost_frames"] == 0
    assert plant.counters["auth"] == plant.counters["unsynced"] == 0  # its freshness goes on


def test_enable_zero_holds_zero_power() -> None:
    plant = PlantNode(load_case(1))
    drv = PlantDriver(plant)
    drv.run(0.5, {1: 50.0})
    for _ in range(25):
        drv.send(1, 50.0, enable=0)
        drv.run(0.02)
    assert abs(drv.last(1)["Power"]) < 0.05 and drv.last(1)["PowerLimited"] == 0
    assert plant.counters["setpoint_timeouts"] == 0


def test_bad_setpoints_are_rejected_by_cause_and_counters_checked() -> None:
    """Each bad AGENT_<i>_Setpoint is rejected under its cause and its data is not used.
    Setpoints are secured now: a corrupted frame (old: ``crc``), a replay of the same
    bytes (old: ``repeated_counter``) and a second sender on the ID without the agent's
    key (old: ``counter_clash``, foreign) all fail the MAC, under ``auth``; five in a
    row raise the untrusted-source alarm, but the ID being secured, the agent's next
    authentic frame is still used; lost frames are the steps of the freshness value.
    Foreign and own frames as before; a sync on the plant's own sync ID from someone
    else is impersonation too."""
    plant = PlantNode(load_case(1))
    fid = CODEC.frame_id(setpoint_name(1))
    own = plant.tick(0.0)        # the first tick: the plant's syncs (and statuses)
    assert [CODEC.name_of(m.arbitration_id) for m in own if is_sync(m)] == [
        *(f"{status_name(i)}_Sync" for i in range(1, 5)), "PLANT_Totals_Sync"]
    good = setpoint(1, 40.0)     # count 0
    short = can.Message(arbitration_id=fid, is_extended_id=False, data=bytes(good.data[:6]))
    plant.on_frame(short, 0.002)
    plant.on_frame(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)), 0.003)
    assert plant.counters["dlc"] == 1 and plant.counters["unknown_id"] == 1
    assert plant.unit(1).setpoint_rx is None and plant.unit(1).p_set == 0.0
    plant.on_frame(good, 0.004)
    assert plant.unit(1).p_set == 40.0 and plant.counters["setpoints"] == 1
    plant.on_frame(good, 0.005)  # the same bytes again: a replay, its freshness is spent
    assert plant.counters["auth"] == 1
    assert plant.io.last_safety == ("auth", fid)
    nxt = setpoint(1, 80.0)      # count 1, never delivered intact
    plant.on_frame(flipped(nxt, 0), 0.005)        # a bit of the MAC
    plant.on_frame(flipped(nxt, 5, 0x10), 0.005)  # a bit of PowerSetpoint: was a CRC error
    plant.on_frame(flipped(nxt, 3, 0x01), 0.005)  # a bit of the truncated freshness
    assert plant.counters["auth"] == 4
    assert "expected a MAC that verifies" in plant.last_error["auth"]
    # the same count with another payload from a sender without agent 1's key: was a
    # counter clash (foreign); now it simply fails the MAC and is not used
    forger = FleetSender(CODEC, keys={"AGENT_1_Setpoint": WRONG_KEY})
    plant.on_frame(setpoint(1, 120.0, 1, sender=forger), 0.005)
    assert plant.counters["auth"] == 5
    assert plant.counters["foreign"] == 0 and plant.unit(1).p_set == 40.0
    assert plant.counters["setpoints"] == 1
    assert plant.counters["untrusted_sources"] == 1  # 5 consecutive failures: the alarm
    plant.on_frame(setpoint(1, 60.0, 4), 0.006)  # counts 1..3 lost; a valid MAC still counts
    assert plant.counters["lost_frames"] == 3 and plant.unit(1).p_set == 60.0
    assert plant.counters["setpoints"] == 2
    # frames not for the plant are ignored without counting; its own echoes too
    plant.on_frame(SENDER.frame("ER_Price", {"PriceValid": 1, "Rho": 1 << 23,
                                             "Segment": 0}), 0.007)
    plant.on_frame(SENDER.sync("ER_Price"), 0.007)
    other = PlantNode(with_batteries(load_case(1), soc0=0.3))
    for msg in data_frames(other.tick(0.0))[:1]:
        plant.on_frame(msg, 0.008)  # someone else's PLANT_1_Status: impersonation
    rogue = FleetSender(CODEC, boot=7)  # the plant's key (public here), another boot
    plant.on_frame(rogue.sync(status_name(1)), 0.008)  # someone else's sync: impersonation
    for msg in own + plant.tick(0.05):  # our own echoes (syncs and statuses): fine
        plant.on_frame(msg, 0.051)
    assert plant.counters["impersonation"] == 2 and plant.counters["foreign"] == 2
    assert {c: plant.counters[c] for c in ("auth", "dlc", "unknown_id", "range",
                                           "unsynced")} == {
        "auth": 5, "dlc": 1, "unknown_id": 1, "range": 0, "unsynced": 0}


def test_injected_faults_set_the_status_flags() -> None:
    faults = [(1, "overcurrent", 0.2, 0.4), (2, "voltage", 0.2, 0.4), (3, "soc", 0.2, 0.4),
              (4, "power_limit", 0.2, 0.8)]
    plant = PlantNode(load_case(1), faults=faults, ramp_full_s=0)  # the current loop alone
    drv = PlantDriver(plant)
    drv.run(1.2, {4: 100.0})
    flag = {1: "FaultOverCurrent", 2: "FaultVoltage", 3: "FaultSoc", 4: "PowerLimited"}
    for t, d in drv.status:
        a = int(d["agent"])
        window = (0.2, 0.8) if a == 4 else (0.2, 0.4)
        inside = window[0] - 1e-9 <= t < window[1] - 1e-9
        assert d[flag[a]] == int(inside), (t, a)
        others = [v for k, v in flag.items() if k != a]
        assert all(d[o] == 0 for o in others), (t, a)
    p4 = {round(t, 2): d["Power"] for t, d in drv.status if d["agent"] == 4}
    assert p4[0.15] == pytest.approx(100.0 * (1 - math.exp(-0.15 / TAU_S)), rel=0.01)
    assert p4[0.75] == pytest.approx(55.0, abs=0.05)  # clamped to 50 % of p_max = 110 kW
    assert p4[1.15] == pytest.approx(100.0, abs=0.05)
    assert plant.counters["injected_faults"] == 4


def test_fault_specs_are_checked() -> None:
    with pytest.raises(ParameterError, match="fault.kind"):
        PlantNode(load_case(1), faults=[(1, "fire", 0, 1)])
    with pytest.raises(ParameterError, match="1..4"):
        PlantNode(load_case(1), faults=["5:soc:0:1"])
    with pytest.raises(ParameterError, match="T0 < T1"):
        PlantNode(load_case(1), faults=[(1, "soc", 2, 1)])


# --------------------------------------------------------------------------- router


def run_router(router: RouterNode, seconds: float, start: int = 0,
               feed: dict[int, float] | None = None) -> list[tuple[float, can.Message]]:
    """Tick ``router`` every 10 ms, feeding it the plant's (signed) totals of the powers
    of ``feed`` every 20 ms; its output, syncs included, with the tick times."""
    out = []
    for k in range(start, start + round(seconds / DT)):
        if feed and k % 2 == 0:
            router.on_frame(totals(feed), T(k))
        out += [(T(k), m) for m in router.tick(T(k))]
    return out


def test_router_price_frames_carry_the_schedule() -> None:
    """ER_Price every 50 ms with the schedule's ρ and segment (mod 8: 3 bits now), each
    signed with the router's key at boot 1 and its own count (the Counter signal is its
    low 4 bits); ER_Price_Sync about every second carries the count of the next price."""
    sc = load_case(5)
    router = RouterNode(sc)
    out = run_router(router, 50.0)
    msgs = [(t, m) for t, m in out if m.arbitration_id == 0x010]
    frames = [(t, CODEC.decode(m)) for t, m in msgs]
    assert len(frames) == 1000  # every 50 ms for 50 s
    assert all(frame_verifies(ROUTER_KEY, 0x010, m.data, fv(1, k))
               for k, (_, m) in enumerate(msgs))
    assert not frame_verifies(ROUTER_KEY, 0x010, msgs[1][1].data, fv(1, 0))
    syncs = [(t, CODEC.decode(m)) for t, m in out
             if m.arbitration_id == CODEC.frame_id("ER_Price_Sync")]
    assert [round(t, 2) for t, _ in syncs] == [float(s) for s in range(50)]
    for t, f in syncs:
        sent_before = sum(1 for tp, _ in frames if tp < t - 1e-9)
        assert (f.raw["Boot"], f.raw["Count"]) == (1, sent_before)
    assert [t for t, _ in frames[:3]] == pytest.approx([0.0, 0.05, 0.10])
    for t, f in frames:
        rho, seg = sc.price_at(t)
        assert f.raw["PriceValid"] == 1
        assert f.raw["Rho"] == round(rho * 2**24) and f.raw["Segment"] == seg % 8
    by_t = {round(t, 2): (f.phys("Rho"), f.raw["Segment"]) for t, f in frames}
    assert by_t[14.95] == (pytest.approx(0.8), 0) and by_t[15.0] == (pytest.approx(1.0), 1)
    assert by_t[34.95] == (pytest.approx(1.0), 1) and by_t[35.0] == (pytest.approx(0.6), 2)
    counters = [f.counter for _, f in frames[:20]]
    assert counters == [k % 16 for k in range(20)]


def test_router_sends_case4_commands_three_times_at_event_times() -> None:
    router = RouterNode(load_case(4))
    out = run_router(router, 25.0)
    cmd_msgs = [m for _, m in out if m.arbitration_id == 0x020]
    cmds = [(round(t, 3), CODEC.decode(m)) for t, m in out if m.arbitration_id == 0x020]
    got = [(t, f.raw["Command"], target_agent(f.raw["Target"])) for t, f in cmds]
    assert got == [(10.0, 1, 2), (10.01, 1, 2), (10.02, 1, 2),
                   (20.0, 2, 2), (20.01, 2, 2), (20.02, 2, 2)]
    assert [f.counter for _, f in cmds] == list(range(6))  # fresh counter per transmission
    # ... the low bits of a fresh freshness value: each transmission is signed anew, with
    # its target's command key (AUTH-30), not the router's node key
    agent_2 = derive_command_key(INSECURE_MASTER, "agent_2")
    assert all(frame_verifies(agent_2, 0x020, m.data, fv(1, k))
               and not frame_verifies(ROUTER_KEY, 0x020, m.data, fv(1, k))
               for k, m in enumerate(cmd_msgs))
    assert len({bytes(m.data) for m in cmd_msgs}) == 6  # no repeat reads as a replay
    assert all(f.raw["GainK"] == f.raw["GainH"] == 0 for _, f in cmds)
    assert router.counters["events"] == 2 and router.counters["command_frames"] == 6


def test_send_command_queues_three_frames_and_checks_arguments() -> None:
    router = RouterNode(load_case(1))
    router.tick(0.0)
    router.send_command("set_gains", 3, k=1.5, h=2.25)
    frames = [CODEC.decode(m) for k in range(1, 6) for m in router.tick(T(k))
              if m.arbitration_id == 0x020]
    assert [(f.raw["Command"], target_agent(f.raw["Target"]), f.raw["GainK"], f.raw["GainH"])
            for f in frames] == [(3, 3, 1500, 2250)] * 3
    with pytest.raises(ParameterError, match="one of isolate"):
        router.send_command("reboot", 1)
    with pytest.raises(ParameterError, match="1..4"):
        router.send_command("isolate", 5)
    with pytest.raises(ParameterError, match="gain"):
        router.send_command("set_gains", 1, k=70.0, h=1.0)
    with pytest.raises(ParameterError, match="only with set_gains"):
        router.send_command("isolate", 1, k=1.0)


def test_router_balance_matches_the_cost_model() -> None:
    sc = load_case(1)
    router = RouterNode(sc)
    powers = {1: 60.0, 2: 50.0, 3: 40.0, 4: 55.0}
    frames = [(t, CODEC.decode(m)) for t, m in run_router(router, 1.0, feed=powers)
              if m.arbitration_id == CODEC.frame_id("ER_Balance")]
    # both pages in the same tick, every balance cycle: rates of the same instant
    assert [(round(t, 2), f.raw["Page"]) for t, f in frames] == [
        (round(0.1 * k, 2), page) for k in range(10) for page in (0, 1)]
    assert router.counters["balance_frames"] == 20
    p = list(powers.values())
    fc = expenditure(sc.batteries, p, 0.8, sc.load_kw)
    _, fc_opt = kkt_optimum(sc.batteries, 0.8, sc.load_kw)
    page0, page1 = frames[-2][1], frames[-1][1]
    assert page0.phys("GridPower") == pytest.approx(sc.load_kw - sum(p), abs=0.05)
    assert page0.phys("CostRate") == pytest.approx(fc, abs=0.05)
    assert page1.phys("OptimalCostRate") == pytest.approx(fc_opt, abs=0.05)
    assert fc > fc_opt
    assert router.grid_power == pytest.approx(95.0)
    assert router.cost_rate == pytest.approx(fc, abs=0.05)  # the totals' 0.1 cu/h
    assert router.cost == pytest.approx(fc * 0.99 / 3600, abs=0.05 * 0.99 / 3600)  # 99 ticks
    assert router.optimal_cost == pytest.approx(fc_opt * 0.99 / 3600)
    assert router.counters["totals_frames"] == 50 and router.counters["lost_frames"] == 0
    assert "cost=" in router.summary() and "P_e=95.00 kW" in router.summary()


def test_router_rejects_bad_totals_and_times_them_out() -> None:
    """A bad PLANT_Totals is rejected and its sums not used; totals older than 5 status
    cycles time out (counted once) and the last ones are held. A corrupted frame, a
    replay and another payload from a sender without the key fail the MAC, under
    ``auth``; five in a row raise the untrusted-source alarm, and the plant's next
    authentic frame is still used (a secured ID proves itself frame by frame). Before
    the first authentic frame an insecure router takes a failing one for a frame of a
    plant already running, not a forgery: ``unsynced`` (it waits for the plant's sync).
    A status frame is not the router's input any more (AUTH-29: agent i holds its key)."""
    router = RouterNode(load_case(1))
    fid = CODEC.frame_id("PLANT_Totals")
    router.tick(0.0)
    good = totals({1: 10.0})                    # count 0
    router.on_frame(flipped(good, 4), 0.0)      # a bit of BatteryPower
    assert router.counters["unsynced"] == 1 and router.counters["auth"] == 0
    assert router.totals.power == 0.0
    router.on_frame(good, 0.0)
    assert router.totals.power == 10.0 and router.counters["totals_frames"] == 1
    router.on_frame(good, 0.0)                  # a replay
    nxt = totals({1: 20.0})                     # count 1
    router.on_frame(flipped(nxt, 2, 0x80), 0.0)  # a bit of the MAC
    router.on_frame(flipped(nxt, 6), 0.0)       # a bit of BatteryCostRate
    assert router.counters["auth"] == 3 and router.io.last_safety == ("auth", fid)
    forger = FleetSender(CODEC, keys={"PLANT_Totals": WRONG_KEY})
    router.on_frame(totals({1: 20.0}, 1, sender=forger), 0.0)  # same count, new payload
    assert router.counters["auth"] == 4
    assert router.counters["foreign"] == 0 and router.totals.power == 10.0
    assert router.counters["totals_frames"] == 1
    router.on_frame(totals({1: 99.0}, 2, sender=forger), 0.0)  # 5 failures in a row: alarm
    assert router.counters["untrusted_sources"] == 1 and router.io.untrusted(fid, 0.0)
    router.on_frame(totals({1: 15.0}), 0.0)     # authentic (count 2): still used
    assert router.totals.power == 15.0
    assert router.counters["auth"] == 5
    assert router.counters["lost_frames"] == 1  # count 1 only ever arrived corrupted
    router.on_frame(status(1, 60.0), 0.0)       # agent 1's status: not the ledger's
    assert router.totals.power == 15.0 and router.counters["totals_frames"] == 2
    for k in range(1, 27):     # 5 status cycles of 50 ms: timed out after 250 ms
        router.tick(T(k))
    assert router.counters["totals_timeouts"] == 1
    assert router.totals.power == 15.0  # held


def test_router_silent_window_sends_nothing() -> None:
    """Nothing in the window, its syncs included: the sync due at 1 s goes out with the
    first frames after the silence (it counts the 20 prices sent before), and only the
    data frames due in the window count as silenced."""
    router = RouterNode(load_case(4), silent=[(1.0, 2.0)])
    out = run_router(router, 3.0)
    assert out and not [t for t, _ in out if 1.0 - 1e-9 <= t < 2.0 - 1e-9]
    syncs = [(round(t, 2), CODEC.decode(m).raw["Count"]) for t, m in out
             if m.arbitration_id == CODEC.frame_id("ER_Price_Sync")]
    assert syncs == [(0.0, 0), (2.0, 20)]
    prices = [round(t, 2) for t, m in out if m.arbitration_id == 0x010]
    assert prices[:20] == [round(0.05 * k, 2) for k in range(20)]
    assert prices[20] == 2.0  # the cadence goes on through the silence
    assert router.counters["silenced_frames"] == 20 + 2 * 10  # 20 prices, 10 balances of 2 pages


def test_router_silent_window_drops_commands_due_in_it() -> None:
    router = RouterNode(load_case(4), silent=["9.5:10.015"])
    cmds = [round(t, 3) for t, m in run_router(router, 11.0) if m.arbitration_id == 0x020]
    assert cmds == [10.02]  # the first two transmissions fell in the silence


# --------------------------------------------------------------------------- on a bus


def test_plant_and_router_on_a_virtual_bus() -> None:
    """Both nodes under run_node in threads (the real loop, on the wall clock), a
    setpoint source and an observer, until each expected frame kind has been seen often
    enough (a condition with a generous deadline, not a fixed second: on a loaded host the
    threads get fewer ticks per second; the rates are `bess-ded bench`'s, the exact
    counts the simulated-clock tests' above). The setpoint source signs like agent 1
    (--insecure, as both nodes). The plant follows the setpoint, the router hears the
    plant, both announce their freshness by syncs, every price verifies with the
    router's key, nothing is rejected (no MAC failure, nothing unsynced), and both
    threads stop when told."""
    channel = f"plant-router-{next(_channels)}-{time.monotonic_ns()}"
    kw = {"interface": "virtual", "channel": channel, "receive_own_messages": False}
    sc = load_case(1)
    plant, router = PlantNode(sc), RouterNode(sc)
    buses = [can.Bus(**kw) for _ in range(4)]
    plant_bus, router_bus, agent_bus, watch = buses
    stop = StopFlag()
    threads = [threading.Thread(target=run_node, args=(node, bus), kwargs={"stop": stop},
                                daemon=True)
               for node, bus in ((plant, plant_bus), (router, router_bus))]
    want = {**{f"PLANT_{i}_Status": 20 for i in range(1, 5)}, "ER_Price": 10,
            "ER_Balance": 10, "PLANT_Totals": 20, "PLANT_Totals_Sync": 1,
            **{f"PLANT_{i}_Status_Sync": 1 for i in range(1, 5)},
            "ER_Price_Sync": 1, "ER_Command_Sync": 1, "ER_Balance_Sync": 1}
    seen: dict[str, list] = {}
    price_msgs: list[can.Message] = []

    def enough() -> bool:
        return (all(len(seen.get(k, [])) >= n for k, n in want.items())
                and plant.counters["setpoints"] > 20 and router.counters["totals_frames"] > 12
                and abs(router.totals.power - 30.0) <= 0.5)

    try:
        for th in threads:
            th.start()
        deadline = time.monotonic() + 120.0
        while not enough() and time.monotonic() < deadline:
            agent_bus.send(setpoint(1, 30.0))
            until = time.monotonic() + 0.02
            while (msg := watch.recv(timeout=max(0.0, until - time.monotonic()))) is not None:
                f = CODEC.decode(msg)
                seen.setdefault(f.name, []).append(f)
                if f.name == "ER_Price":
                    price_msgs.append(msg)
    finally:
        stop.set()
        for th in threads:
            th.join(timeout=30)
        for bus in buses:
            bus.shutdown()
    assert not any(th.is_alive() for th in threads)
    assert enough(), ({k: len(v) for k, v in seen.items()}, plant.counters, router.counters)
    prices = seen["ER_Price"]
    assert all(f.raw["Rho"] == round(0.8 * 2**24) for f in prices)
    assert [f.counter for f in prices] == [k % COUNTER_MODULO for k in range(len(prices))]
    assert all(frame_verifies(ROUTER_KEY, 0x010, m.data, fv(1, k))
               for k, m in enumerate(price_msgs))
    assert seen["PLANT_1_Status"][-1].phys("Power") == pytest.approx(30.0, abs=0.5)
    assert seen["PLANT_1_Status_Sync"][0].raw["Boot"] == 1
    bad = ("dlc", "range", "unknown_id", "impersonation", "malformed", "auth",
           "unsynced", "foreign")
    assert not any(plant.counters[c] or router.counters[c] for c in bad)
    # every tick accounted: the loop ticked or counted the miss (wall clock, any load)
    for node in (plant, router):
        expected = node.elapsed / node.period + 1
        assert node.ticks <= expected + 1, (node.ticks, expected)
        assert node.ticks + node.counters["deadline_miss"] >= expected - 1, (
            node.ticks, node.counters["deadline_miss"], expected)


# --------------------------------------------------------------------------- CLI


def test_cli_router_and_plant_run_and_print_their_summary(
        capsys: pytest.CaptureFixture[str]) -> None:
    channel = f"cli-{next(_channels)}-{time.monotonic_ns()}"
    bus = ["--interface", "virtual", "--channel", channel, "--duration", "0.2", "--insecure"]
    # silent from t = 0: the first tick is silenced at any load (a starved loop may skip
    # a window later in the run, and then has nothing to count)
    assert main(["router", "--case", "4", *bus, "--silent", "0:0.2"]) == 0
    assert main(["plant", "--case", "1", *bus, "--fault", "2:soc:0:1"]) == 0
    err = capsys.readouterr().err
    assert "router runs --insecure" in err and "plant runs --insecure" in err
    assert "router: t=" in err and "silenced_frames=" in err
    assert "plant: 4 BESS" in err and "BESS 2:" in err and "injected_faults=1" in err


@pytest.mark.parametrize("argv, message", [
    (["plant", "--case", "9", "--insecure"], "expected a case number (1, 2, 3, 4, 5, 6, 7)"),
    (["plant", "--case", "1", "--insecure", "--fault", "1:melt:0:1"], "fault.kind"),
    (["plant", "--case", "1", "--insecure", "--fault", "1:soc"], "AGENT:KIND:T0:T1"),
    (["router", "--case", "1", "--insecure", "--silent", "4:2"], "T0 < T1"),
    (["router", "--scenario", "/nonexistent.toml", "--insecure"], "does not exist"),
    (["router", "--case", "1", "--insecure", "--duration", "0"], "--duration"),
    (["router", "--case", "1", "--insecure", "--interface", "nosuchbus"],
     "cannot open CAN bus {'interface': 'nosuchbus'}: Unknown interface type"),
    (["router", "--case", "1", "--key", "/nonexistent.key"], "cannot read the node key"),
    (["plant", "--case", "1"], "one of the arguments --key --insecure is required"),
])
def test_cli_bad_arguments_exit_2_with_one_line(argv: list[str], message: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """One error line naming the problem, exit code 2. A node built with --insecure
    has already printed its one warning line when the bus fails to open: that line
    may precede the error, nothing else may."""
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    warnings = [ln for ln in lines if ln.startswith("bess-ded: warning:")]
    assert all("runs --insecure" in ln for ln in warnings) and len(warnings) <= 1
    assert not warnings or "--insecure" in argv
    err = [ln for ln in lines if ln not in warnings]
    assert len(err) == 1 and err[0].startswith("bess-ded: error:") and message in err[0]
    assert lines[-1] == err[0]


def test_battery_model_constants() -> None:
    b = Battery(alpha=0.004, beta=0.2, m=0.1, p_min=-120, p_max=120, v_nom=700)
    assert open_circuit_voltage(b, 0.0) == pytest.approx(630.0)
    assert open_circuit_voltage(b, 0.5) == pytest.approx(700.0)
    assert open_circuit_voltage(b, 1.0) == pytest.approx(770.0)
    assert current_limit(b) == pytest.approx(120e3 / 630.0 * 1.1)


@pytest.mark.parametrize("factor", [1, 2, 4, 10])
def test_plant_status_cadence_is_the_dbc_cycle_stretched_by_the_time_scale(factor: int
                                                                           ) -> None:
    """At Ts = 10 ms·F the plant sends every PLANT_<i>_Status once per DBC status cycle
    stretched by F: every 5 of its ticks (50 ms at F = 1), never once per tick. Its
    PLANT_<i>_Status_Sync frames are told apart (kind "sync"): all of them at the first
    tick, and always all together."""
    sc = scaled(load_case(1), factor)
    plant = PlantNode(sc, period=sc.ts)
    every = every_ticks(status_name(1))
    assert every == 5 and plant.status_cycle == pytest.approx(cycle_s(status_name(1), sc.ts))
    out = {k: plant.tick(k * sc.ts) for k in range(100)}
    sent = {k: data_frames(frames) for k, frames in out.items()}  # the syncs apart
    with_status = [k for k, frames in sent.items() if frames]
    assert with_status == list(range(0, 100, every))
    assert all(len(sent[k]) == sc.n + 1 for k in with_status)  # every status, the totals
    assert plant.counters["status_frames"] == sc.n * 100 // every
    assert plant.counters["totals_frames"] == 100 // every
    syncs = {k: [m for m in frames if is_sync(m)] for k, frames in out.items()}
    assert len(syncs[0]) == sc.n + 1  # every status's sync and the totals' at the first
    assert all(len(v) in (0, sc.n + 1) for v in syncs.values())  # tick, and all each time


def test_router_cadences_stretch_with_the_time_scale() -> None:
    sc = scaled(load_case(1), 4)
    router = RouterNode(sc, period=sc.ts)
    assert router.price_cycle == pytest.approx(cycle_s("ER_Price", sc.ts)) == \
        pytest.approx(0.2)
    assert router.totals_timeout == pytest.approx(timeout_s("PLANT_Totals", sc.ts))


def test_plant_and_router_count_foreign_traffic() -> None:
    """Frames of agents outside the scenario and impersonated frames are foreign: as
    before, and whether or not they are signed (the frames below carry valid MACs under
    the public --insecure keys). The syncs count too: AGENT_9's sync is a foreign ID, a
    sync on the node's own sync ID (another boot of its key) is impersonation."""
    plant, router = PlantNode(load_case(1)), RouterNode(load_case(1))
    foreign_setpoint = setpoint(9, 10.0)                    # agent 9 in a 4-agent run
    foreign_sync = SENDER.sync(setpoint_name(9))            # ... and its sync
    fake_status = status(2, 10.0)                           # the plant's own ID, not sent by it
    fake_price = SENDER.frame("ER_Price", {"PriceValid": 1, "Rho": 1 << 23, "Segment": 0})
    rogue = FleetSender(CODEC, boot=5)                      # the same public keys, boot 5
    for node, frames in ((plant, [foreign_setpoint, foreign_sync, fake_status,
                                  rogue.sync(status_name(2))]),
                         (router, [foreign_setpoint, foreign_sync, fake_price,
                                   rogue.sync("ER_Price")])):
        for m in frames:
            node.on_frame(m, 0.0)
        assert node.counters["foreign"] == 4, node.counters
        assert node.counters["foreign_id"] == 2 and node.counters["impersonation"] == 2
        assert node.counters["auth"] == node.counters["unsynced"] == 0


# --------------------------------------------------------------------------- SecOC


def test_plant_signs_its_status_frames_and_sends_their_syncs_every_second() -> None:
    """Every PLANT_<i>_Status and PLANT_Totals is signed with its own frame key (AUTH-28,
    AUTH-29), freshness Boot 1 ‖ its own count per ID (the Counter signal: its low 4
    bits); each sync goes out at the first tick and every second, carrying the
    freshness of that ID's next frame under the same key. A router hears the totals
    (no sync needed at boot 1) and none of the statuses (agent i's and the plant's)."""
    plant, router = PlantNode(load_case(1)), RouterNode(load_case(1))
    sent: Counter[int] = Counter()
    syncs = []
    for k in range(206):  # 0 .. 2.05 s
        for m in plant.tick(T(k)):
            fid, f = m.arbitration_id, CODEC.decode(m)
            if is_sync(m):
                count = sent[SYNCED_BY[fid]]
                assert (f.raw["Boot"], f.raw["Count"]) == (1, count)
                assert frame_verifies(link_key(f.name), fid, m.data, fv(1, count))
                syncs.append((round(T(k), 2), f.name))
            else:
                assert frame_verifies(link_key(f.name), fid, m.data, fv(1, sent[fid]))
                assert f.counter == sent[fid] % 16
                sent[fid] += 1
            router.on_frame(m, T(k))
    assert syncs == [(t, f"{name}_Sync") for t in (0.0, 1.0, 2.0)
                     for name in [*map(status_name, range(1, 5)), "PLANT_Totals"]]
    assert set(sent.values()) == {42}  # every 50 ms from t = 0 to 2.05 s
    assert router.counters["totals_frames"] == 42
    assert not any(router.counters[c] for c in ("auth", "unsynced", "lost_frames", "foreign"))


def test_plant_hears_an_agent_after_its_sync_and_answers_its_restart_with_its_own() -> None:
    """Keys from one fleet master (as `bess-ded up` provisions them): the plant drops an
    agent's setpoints before that agent's first sync (``joining``: its join window),
    follows it after; when the agent restarts (a new boot), its sync moves the plant to
    the new freshness and the plant re-announces its own syncs at once (at most every
    0.1 s), so the restarted agent hears it within one round trip."""
    master = bytes(range(16))
    plant = PlantNode(load_case(1), keys=Keyring.fleet(master, ["plant"])["plant"])
    agent = FleetSender(CODEC, boot=3,   # AUTH-28: agent 1's setpoint under its own key
                        keys={"AGENT_1_Setpoint": derive_frame_key(master, "AGENT_1_Setpoint")})
    assert plant.io.boot == 1 and len([m for m in plant.tick(0.0) if is_sync(m)]) == 5
    plant.on_frame(setpoint(1, 10.0, sender=agent), 0.0)
    assert plant.counters["joining"] == 1 and plant.unit(1).setpoint_rx is None
    plant.on_frame(agent.sync(setpoint_name(1)), 0.005)
    plant.on_frame(setpoint(1, 10.0, sender=agent), 0.005)
    # its join window (AUTH-26, 0.2 s from its first syncs): the sync kept, no frame taken
    assert plant.counters["resyncs"] == 0 and plant.counters["joining"] == 2
    hello = [k for k in range(1, 30) if any(is_sync(m) for m in plant.tick(T(k)))]
    assert hello == [10]  # a first contact: the plant's syncs again, 0.1 s after the last
    plant.on_frame(setpoint(1, 10.0, sender=agent), 0.29)  # after it: the sync is taken
    assert plant.unit(1).p_set == 10.0 and plant.counters["resyncs"] == 1
    assert plant.counters["lost_frames"] == 1   # the one of the window
    agent.restart()                                     # boot 4, counts from 0 again
    plant.on_frame(agent.sync(setpoint_name(1)), 0.295)
    plant.on_frame(setpoint(1, 20.0, sender=agent), 0.295)
    assert plant.unit(1).p_set == 20.0 and plant.counters["resyncs"] == 2
    assert [CODEC.decode(m).raw["Boot"] for m in plant.tick(0.3) if is_sync(m)] == [1] * 5
    assert not any(plant.counters[c] for c in ("auth", "foreign"))
    assert plant.counters["joining"] == 2 and plant.counters["unsynced"] == 0
    assert plant.counters["lost_frames"] == 1


def _restart_plant_under_a_running_router(keys: dict[str, Keyring]) -> RouterNode:
    """Plant and router for 1 s, then the plant restarts (a new PlantNode with the same
    keyring, as a restarted process with the same key file) and runs 1 s more."""
    sc = load_case(1)
    router = RouterNode(sc, keys=keys.get("router"))
    plant = PlantNode(sc, keys=keys.get("plant"))
    for k in range(200):
        if k == 100:
            plant = PlantNode(sc, keys=keys.get("plant"))
        for m in plant.tick(T(k)):
            router.on_frame(m, T(k))
        router.tick(T(k))
    return router


def test_a_restarted_plant_is_heard_by_the_router_after_its_sync() -> None:
    """With keys from a master, the restarted plant's boot counter advanced: its syncs
    at its first tick move the router to its new freshness, and not one status frame is
    lost or rejected."""
    router = _restart_plant_under_a_running_router(
        Keyring.fleet(bytes(range(16)), ["router", "plant"]))
    # the router's join window (AUTH-26: its first 0.2 s) takes the first 4 totals as
    # unsynced, then lost; after the plant's restart not one
    in_window = 4
    assert router.counters["totals_frames"] == 40 - in_window
    assert router.counters["joining"] == router.counters["lost_frames"] == in_window
    assert router.counters["unsynced"] == 0
    assert router.counters["resyncs"] == 2  # first contact, then the restart
    assert not any(router.counters[c] for c in ("auth", "totals_timeouts",
                                                 "untrusted_sources"))


def test_a_restarted_insecure_plant_is_heard_by_the_router_after_its_sync() -> None:
    """The same restart with --insecure keys (nothing persisted: boot 1 again). The
    documented behaviour: its receivers accept a sync that goes back."""
    router = _restart_plant_under_a_running_router({})
    assert router.counters["totals_frames"] == 40
    assert not any(router.counters[c] for c in ("auth", "unsynced", "totals_timeouts"))


def test_node_cli_time_scale_stretches_the_scenario_and_the_period() -> None:
    """`bess-ded router|plant --time-scale F` run the scenario as `up --time-scale F`
    does (Ts·F, k/F, h/F²), ticking at the stretched Ts unless --period says otherwise."""
    from sim.cli import build_parser
    from sim.cli.nodeopts import load_node_scenario
    from sim.model.scenario import scaled

    p = build_parser()
    args = p.parse_args(["router", "--case", "1", "--insecure", "--time-scale", "4"])
    sc = load_node_scenario(args)
    assert sc == scaled(load_case(1), 4.0)
    assert args.period == pytest.approx(0.04) == sc.ts
    args = p.parse_args(["plant", "--case", "1", "--insecure", "--period", "0.02"])
    assert load_node_scenario(args).ts == 0.01 and args.period == 0.02


def test_a_burst_of_commands_to_others_is_re_announced_before_it_outruns_an_agents_search(
        ) -> None:
    """AUTH-30: agent 1 verifies only the commands to it, so the router's ER_Command count
    moves unseen while it commands others. 60 commands to agent 2 (180 frames in 30 ms,
    beyond the 128 counts of an agent's widest search) and then one to agent 1: the
    router re-announces its count (ER_Command_Sync) every 64 command frames, so agent 1
    takes its command at once, well before the once-a-second sync."""
    from firmware_py.config import agent_configs_from_scenario
    from firmware_py.runtime import AgentRuntime

    sc = load_case(1)
    router = RouterNode(sc)
    agent = AgentRuntime(agent_configs_from_scenario(sc)[0], CODEC,
                         keys=Keyring.insecure_for("agent_1"))
    sync_id = CODEC.frame_id("ER_Command_Sync")
    sync_counts = []
    for k in range(40):
        if k == 1:
            for _ in range(60):
                router.send_command("set_gains", 2, k=1.0, h=2.0)
        if k == 5:
            router.send_command("set_gains", 1, k=1.5, h=2.5)
        for m in router.tick(T(k)):
            if m.arbitration_id == sync_id:
                sync_counts.append(CODEC.decode(m).raw["Count"])
            agent.on_frame(m, T(k))
    # the first sync (count 0), then one each time 64 command frames went out since
    assert sync_counts == [0, 64, 128], sync_counts
    assert agent.counters["commands"] == 3, agent.counters   # its command's three frames
    assert agent.io.counters["auth"] == 0, agent.io.counters
