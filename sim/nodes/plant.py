"""The plant simulator node (``PLANT``): every BESS's battery and DC-DC chopper.

One node simulates the whole fleet, because on the bus the plant is one DBC node
(``PLANT_<i>_Status`` for every i). It takes ``AGENT_<i>_Setpoint`` frames and
publishes every ``PLANT_<i>_Status`` once per status cycle: the DBC's 50 ms at Ts =
10 ms, stretched like every cadence in a time-scaled run (``contract.cycle_s``: every
5 ticks of the scenario's Ts), then ``PLANT_Totals`` for the router's ledger (the sum
of those powers and the batteries' cost rate at them, under a key the agents do not
hold); nothing else couples it to the agents,
so real choppers speaking the same frames can replace it (docs/deployment.md).

Physical model, per BESS (units: kW, V, A, s; P > 0 = discharge into the grid)
----------------------------------------------------------------------------------

* Chopper current loop: first order, time constant ``TAU_S`` = 50 ms (a closed
  inner current loop of a 100 kW-class DC-DC converter with its outer power loop:
  slow enough that 50 ms setpoint steps are smoothed, far faster than the
  consensus, which settles in seconds). Discretised exactly for the actual elapsed time dt
  between ticks, with the reference latched at the previous tick (zero-order hold):
  ``I += (1 − exp(−dt/τ))·(I_ref − I)``.
* Reference: ``I_ref = P_ref / V`` with V the terminal voltage at the tick, so
  in steady state the delivered power V·I equals P_ref.
* Current limit: ``I_max = 1.1 · max(|p_min|, p_max) / (0.9 · v_nom)``: the rated
  power at the lowest open-circuit voltage (SoC = 0), plus a 10 % margin, so
  rated power is reachable at every SoC and the limit only engages on abnormal
  references (for the bundled cases |p_min| = p_max, so this is p_max/(0.9·v_nom)·1.1).
* Power limits: P_ref is clipped to [p_min, p_max].
* Open-circuit voltage: ``V_oc(SoC) = v_nom · (0.9 + 0.2·SoC)`` (linear, ±10 %
  around v_nom at 50 % SoC, the usual flat-ish middle of a Li-ion pack's curve).
  Terminal voltage ``V = V_oc − R·I`` (R = r_internal).
* State of charge: ``dSoC/dt = −P_cell / (3600 · capacity_kwh)`` with the cell
  power ``P_cell = P + π·|P|`` and the paper's inner loss ratio taken literally as a
  per-unit loss ``π = α|P| + β`` (α in 1/kW, β dimensionless, their numeric values
  from the scenario). Assumption: the paper gives π only as a cost-model term; we
  read it as the fraction of the terminal power lost inside the pack, in both
  directions (discharging draws P + loss from the cells, charging stores |P| − loss).
  The R·I² drop is considered part of that loss, not counted twice. With the
  bundled coefficients the loss is large (β = 0.2 means 20 %), but over a 50 s
  scenario the SoC moves by well under 1 %: the SoC is for the status frame and
  the SoC protection, the consensus does not use it. Integrated with the trapezoid
  rule over each tick; clamped to [0, 1].
* Protections (flags of ``PLANT_<i>_Status``):
  - ``PowerLimited``: the setpoint had to be clipped (p_min/p_max, the SoC
    protection below, or an injected power limit) or the current limit engaged;
  - ``FaultSoc``: SoC outside [``SOC_MIN``, ``SOC_MAX``] = [0.05, 0.95]; while low,
    further discharge is blocked (P_ref ≤ 0); while high, further charge (P_ref ≥ 0);
  - ``FaultVoltage``: V outside [0.8, 1.2]·v_nom;
  - ``FaultOverCurrent``: only by fault injection (the reference is limited to
    I_max and a first-order loop cannot overshoot, so the model never trips by itself).

Setpoint reception (secured, like the agent runtime: firmware_py.nodeio): a frame failing
decode (DLC, range, ...) or its MAC and freshness check is rejected and counted under its
cause; freshness gaps count ``lost_frames``. A BESS whose
last accepted setpoint is older than ``contract.TIMEOUT_CYCLES`` = 5 setpoint cycles
(250 ms; the cycle is the DBC's 50 ms at Ts = 10 ms, stretched with Ts in a
time-scaled run) gets P_ref = 0: the current loop ramps it down with τ.
Each fresh→stale transition counts one ``setpoint_timeouts``. ``Enable = 0`` also
means P_ref = 0. Before the first setpoint a BESS holds 0 kW (not a timeout).
Foreign traffic (frames of agents outside the scenario, impersonated status frames,
interleaved counters on a setpoint ID) is counted under ``foreign`` and its cause
(firmware_py.nodeio).

Setpoint ramp limit (docs/safety-model.md): while a BESS is enabled with a fresh
setpoint, its reference P_ref moves towards the setpoint by at most ``ramp_kw_s``·dt
per tick, by default p_max per ``RAMP_FULL_S`` = 0.25 s (at Ts = 10 ms, stretched with Ts
in a time-scaled run), so a forged or faulty setpoint cannot jump a battery to its limit
in one frame. Going to 0 (disabled, stale setpoint) is not ramp-limited: that is the
safe direction and the current loop smooths it with τ anyway. Each tick the ramp
engages after a tick it did not counts one ``setpoint_ramp_limited`` (an episode, not
every tick); it does not set PowerLimited. The healthy start transient of the paper
cases engages it once per BESS (see docs/safety-model.md for what it changes).

Setpoint consistency (sim.nodes.consistency): the plant also hears every agent's MC frame
(its key file holds every agent's key) and takes a setpoint only when it is the agent's
own dispatch rule applied to the λ it publishes; otherwise it counts
``setpoint_inconsistent`` (and ``setpoint_inconsistent_agent_<i>``) and holds the last
consistent setpoint, unless ``obey_inconsistent`` (``bess-ded plant --obey-inconsistent``:
every setpoint is followed on arrival, as a plant without the check would, and only
counted). A setpoint waits for at most the agent's next MC frame to be checked.
A compromised agent cannot then steer its battery away from the λ its neighbours see.

Fault injection (tests): ``faults`` = (agent, kind, t_start, t_end) windows in
seconds from the node's first tick; while one is active the flag is forced:
``overcurrent`` → FaultOverCurrent, ``voltage`` → FaultVoltage, ``soc`` → FaultSoc
(flags only, the physics is untouched), ``power_limit`` → the BESS's power is
clamped to ±50 % of p_max and PowerLimited is set.

Over 500 lines: the node and its physics (batteries, choppers, faults) are one unit,
stepped together each tick.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import can

from dbc import dbc_path
from firmware_py.config import agent_configs_from_scenario, untrusted_s
from firmware_py.contract import (
    MC_CYCLE_S,
    TOTALS,
    cycle_s,
    mc_name,
    setpoint_name,
    status_name,
    timeout_s,
)
from firmware_py.errors import ParameterError
from firmware_py.frames import FrameCodec
from firmware_py.nodeio import HOST_ECHO_DEPTH, NodeIO
from firmware_py.secoc import Keyring
from sim.model.cost import Battery
from sim.model.scenario import Scenario
from sim.nodes.consistency import Check, Setpoint, SetpointCheck, mc_lag
from sim.nodes.nodeclock import SimNodeClock, TimeWindow

log = logging.getLogger(__name__)

TAU_S = 0.05                  # chopper current-loop time constant, s
I_MAX_MARGIN = 1.1            # current limit = 1.1 × rated power / lowest V_oc
OCV_LOW, OCV_SPAN = 0.9, 0.2  # V_oc = v_nom·(0.9 + 0.2·SoC)
SOC_MIN, SOC_MAX = 0.05, 0.95
V_MIN, V_MAX = 0.8, 1.2       # × v_nom, FaultVoltage outside
FAULT_POWER_FRACTION = 0.5    # injected power_limit: |P| ≤ 50 % of p_max
RAMP_FULL_S = 0.25            # default setpoint ramp: p_max per 0.25 s (at Ts = 10 ms)

FAULT_KINDS = ("overcurrent", "voltage", "soc", "power_limit")

# status signal → (scale, raw lo, raw hi) is taken from the codec; values are saturated
_STATUS_SIGNALS = ("Power", "Soc")
_TOTALS_SIGNALS = ("BatteryPower", "BatteryCostRate")


# --------------------------------------------------------------------------- physics


def open_circuit_voltage(b: Battery, soc: float) -> float:
    """V_oc(SoC) = v_nom·(0.9 + 0.2·SoC), V."""
    return b.v_nom * (OCV_LOW + OCV_SPAN * soc)


def current_limit(b: Battery) -> float:
    """I_max = 1.1·max(|p_min|, p_max)/(0.9·v_nom), A."""
    return I_MAX_MARGIN * 1000.0 * max(abs(b.p_min), abs(b.p_max)) / (OCV_LOW * b.v_nom)


def cell_power(b: Battery, p_kw: float) -> float:
    """Power drawn from the cells, kW: P + π|P| with π = α|P| + β (see the module doc)."""
    a = abs(p_kw)
    return p_kw + (b.alpha * a + b.beta) * a


def loop_gain(dt: float) -> float:
    """Exact first-order step over dt: the fraction of (I_ref − I) covered."""
    return -math.expm1(-dt / TAU_S) if dt > 0 else 0.0


# --------------------------------------------------------------------------- fault spec


@dataclass(frozen=True)
class PlantFault(TimeWindow):
    """An injected fault window on one BESS, times in s from the plant's first tick."""

    agent: int
    kind: str
    t_start: float
    t_end: float

    @classmethod
    def parse(cls, spec: str) -> PlantFault:
        """``AGENT:KIND:T0:T1`` (the CLI's --fault), e.g. ``2:overcurrent:5:7``."""
        parts = spec.split(":")
        if len(parts) != 4:
            raise ParameterError("--fault", "AGENT:KIND:T0:T1, e.g. 2:overcurrent:5:7", spec)
        agent, kind, t0, t1 = parts
        try:
            return cls(int(agent), kind, float(t0), float(t1))
        except ValueError:
            raise ParameterError("--fault", "AGENT:KIND:T0:T1 with an integer agent and times "
                                 "in seconds", spec) from None

    def check(self, n: int) -> PlantFault:
        """The fault itself if its BESS is in 1..``n``, its kind known and its window
        valid; else ParameterError."""
        if isinstance(self.agent, bool) or not isinstance(self.agent, int) \
                or not 1 <= self.agent <= n:
            raise ParameterError("fault.agent", f"a BESS in 1..{n}", self.agent)
        if self.kind not in FAULT_KINDS:
            raise ParameterError("fault.kind", f"one of {', '.join(FAULT_KINDS)}", self.kind)
        self.check_window("fault window", "plant")
        return self


def as_fault(f: PlantFault | Sequence[Any] | str) -> PlantFault:
    """A PlantFault from itself, an ``AGENT:KIND:T0:T1`` string or an (agent, kind, t0, t1)."""
    if isinstance(f, PlantFault):
        return f
    if isinstance(f, str):
        return PlantFault.parse(f)
    try:
        agent, kind, t0, t1 = tuple(f)
        return PlantFault(agent, kind, float(t0), float(t1))
    except (TypeError, ValueError):
        raise ParameterError("fault", "(agent, kind, t_start, t_end)", f) from None


# --------------------------------------------------------------------------- one BESS


@dataclass
class BessUnit:
    """State of one battery + chopper, and what its status frame reports."""

    agent: int
    battery: Battery
    i_max: float
    soc: float
    voltage: float
    current: float = 0.0          # A, > 0 discharging
    power: float = 0.0            # kW at the terminals, V·I
    i_ref: float = 0.0            # A, latched at the last tick
    p_ref: float = 0.0            # kW, after limits
    p_set: float = 0.0            # kW, last accepted setpoint
    enable: bool = False
    setpoint_rx: float | None = None
    stale: bool = True
    power_limited: bool = False
    fault_overcurrent: bool = False
    fault_voltage: bool = False
    fault_soc: bool = False
    setpoint_timeouts: int = 0
    ramp_kw_s: float = math.inf   # setpoint ramp limit, kW/s
    ramp_limited: bool = False

    @classmethod
    def create(cls, agent: int, b: Battery) -> BessUnit:
        """BESS ``agent`` at rest: battery ``b`` at its initial SoC and open-circuit
        voltage."""
        return cls(agent=agent, battery=b, i_max=current_limit(b), soc=b.soc0,
                   voltage=open_circuit_voltage(b, b.soc0))

    def advance(self, dt: float) -> None:
        """Integrate the current loop and the SoC over dt with the latched I_ref."""
        if dt <= 0:
            return
        b = self.battery
        p_old = self.power
        self.current += loop_gain(dt) * (self.i_ref - self.current)
        v_mid = open_circuit_voltage(b, self.soc) - b.r_internal * self.current
        p_new = v_mid * self.current / 1000.0
        cell = 0.5 * (cell_power(b, p_old) + cell_power(b, p_new))
        self.soc = min(1.0, max(0.0, self.soc - cell * dt / (3600.0 * b.capacity_kwh)))
        self.voltage = open_circuit_voltage(b, self.soc) - b.r_internal * self.current
        self.power = self.voltage * self.current / 1000.0

    def control(self, forced: set[str], dt: float = 0.0) -> bool:
        """Latch a new reference from the setpoint, the ramp, the limits and the
        protections. True when the ramp limit engaged at this tick after it did not."""
        b = self.battery
        live = self.enable and not self.stale
        p_set = self.p_set if live else 0.0
        p = min(b.p_max, max(b.p_min, p_set))
        limited = p != p_set
        ramped = False
        if live and math.isfinite(self.ramp_kw_s):
            step = self.ramp_kw_s * max(dt, 0.0)
            if abs(p - self.p_ref) > step:
                p = self.p_ref + math.copysign(step, p - self.p_ref)
                ramped = True
        edge = ramped and not self.ramp_limited
        self.ramp_limited = ramped
        if "power_limit" in forced:
            cap = FAULT_POWER_FRACTION * b.p_max
            p = min(cap, max(-cap, p))
            limited = True
        self.fault_soc = not SOC_MIN <= self.soc <= SOC_MAX
        if self.soc < SOC_MIN and p > 0:
            p, limited = 0.0, True     # empty: no further discharge
        elif self.soc > SOC_MAX and p < 0:
            p, limited = 0.0, True     # full: no further charge
        self.p_ref = p
        v = max(self.voltage, 1e-3 * b.v_nom)
        i_ref = 1000.0 * p / v
        if abs(i_ref) > self.i_max:
            i_ref = math.copysign(self.i_max, i_ref)
            limited = True
        self.i_ref = i_ref
        self.power_limited = limited
        self.fault_voltage = not V_MIN * b.v_nom <= self.voltage <= V_MAX * b.v_nom
        self.fault_overcurrent = abs(self.current) > self.i_max
        self.fault_overcurrent |= "overcurrent" in forced
        self.fault_voltage |= "voltage" in forced
        self.fault_soc |= "soc" in forced
        return edge

    def flags(self) -> str:
        """The active fault and limit flags as text (e.g. "OC|LIM"), "ok" if none."""
        names = [n for n, on in (("OC", self.fault_overcurrent), ("V", self.fault_voltage),
                                 ("SOC", self.fault_soc), ("LIM", self.power_limited)) if on]
        return "|".join(names) or "ok"


# --------------------------------------------------------------------------- the node


class Cyclic:
    """A cyclic transmission due every ``cycle`` s from the first tick, tolerant to tick
    jitter (``tol``); after a stall it re-aligns instead of bursting."""

    def __init__(self, cycle: float, tol: float) -> None:
        self.cycle = cycle
        self.tol = tol
        self.next: float | None = None

    def due(self, t: float) -> bool:
        """True when a transmission is due at ``t`` (and schedules the next)."""
        if self.next is not None and t < self.next - self.tol:
            return False
        self.next = (t if self.next is None else self.next) + self.cycle
        if self.next <= t + self.tol:
            self.next = t + self.cycle
        return True


class PlantNode(SimNodeClock):
    """Node (firmware_py.node) simulating every BESS of a scenario.

    ``counters`` (a Counter): rejected setpoint frames by cause (``dlc``, ``range``,
    ``unknown_id``, ``malformed``, ``impersonation``, ``auth``, ``unsynced``, ...),
    ``lost_frames``, ``foreign`` (with ``foreign_id``), ``untrusted_sources``
    (firmware_py.nodeio),
    ``setpoint_ramp_limited`` (ramp episodes), ``setpoints`` (accepted),
    ``setpoint_timeouts``, ``status_frames``, ``totals_frames`` (PLANT_Totals),
    ``soc_faults`` / ``voltage_faults`` / ``overcurrent_faults`` (rising edges of the
    flags), ``injected_faults`` (fault windows entered), ``encode_saturations``
    (a measurement outside its signal's range, sent saturated), and the loop's
    ``deadline_miss`` / ``send_failure``.
    """

    def __init__(self, scenario: Scenario, period: float = 0.01,
                 faults: Iterable[PlantFault | Sequence[Any] | str] = (),
                 codec: FrameCodec | None = None, ramp_full_s: float | None = None,
                 keys: Keyring | None = None, obey_inconsistent: bool = False) -> None:
        """``ramp_full_s``: the setpoint ramp limit as the time to go from 0 to p_max
        (None: RAMP_FULL_S stretched with the scenario's Ts; 0: no ramp limit).
        ``obey_inconsistent``: follow a setpoint that is not the agent's dispatch rule
        applied to the λ it publishes (sim.nodes.consistency) instead of holding the last
        consistent one; it is counted either way."""
        if not (math.isfinite(period) and period > 0):
            raise ParameterError("period", "a positive number of seconds", period)
        if ramp_full_s is None:
            ramp_full_s = RAMP_FULL_S * scenario.ts / MC_CYCLE_S
        if not ramp_full_s >= 0:
            raise ParameterError("ramp_full_s", "a time ≥ 0 s (0: no ramp limit)", ramp_full_s)
        self.scenario = scenario
        self.period = period
        self.codec = codec or FrameCodec(dbc_path(scenario.fd, scenario.lambda_tags))
        self.units = [BessUnit.create(i, b) for i, b in enumerate(scenario.batteries, start=1)]
        for u in self.units:
            u.ramp_kw_s = (max(abs(u.battery.p_min), u.battery.p_max) / ramp_full_s
                           if ramp_full_s > 0 else math.inf)
        self.faults = tuple(as_fault(f).check(scenario.n) for f in faults)
        c = self.codec
        # the DBC's cycles are for Ts = 10 ms; the scenario's Ts stretches them (time scale)
        self.setpoint_timeout = timeout_s(setpoint_name(1), scenario.ts)
        self.status_cycle = cycle_s(status_name(1), scenario.ts)
        self._status = Cyclic(self.status_cycle, period / 2)
        self._setpoint_ids = {c.frame_id(setpoint_name(u.agent)): u for u in self.units}
        self._status_names = [status_name(u.agent) for u in self.units]
        self._setpoint_fid = {u.agent: fid for fid, u in self._setpoint_ids.items()}
        # each agent's MC frames too: its setpoints must be its λ through its dispatch rule
        self._mc_ids = {c.frame_id(mc_name(u.agent)): u for u in self.units}
        self.obey_inconsistent = obey_inconsistent
        self._checks = {cfg.id: SetpointCheck(cfg.battery, period=scenario.ts,
                                              lag=mc_lag(cfg))
                        for cfg in agent_configs_from_scenario(scenario)}
        self.io = NodeIO(c, "the plant", own=[*self._status_names, TOTALS],
                         wanted=[*self._setpoint_ids, *self._mc_ids],
                         fleet_size=scenario.n, untrusted_s=untrusted_s(scenario.ts),
                         keys=keys, sync_s=cycle_s("ER_Price_Sync", scenario.ts),
                         echo_depth=HOST_ECHO_DEPTH, timed=self._setpoint_ids)
        self.counters = self.io.counters
        self.last_error = self.io.last_error
        # every signal the plant sends, by name (the status's and the totals' differ)
        sent = [(self._status_names[0], s) for s in _STATUS_SIGNALS] + [
            (TOTALS, s) for s in _TOTALS_SIGNALS]
        self._ranges = {s: c.raw_range(name, s) for name, s in sent}
        self._scales = {s: c.scale(name, s) for name, s in sent}
        self._active_faults: set[int] = set()
        self._sp_scale = c.scale(setpoint_name(1), "PowerSetpoint")
        self._init_clock()

    # ------------------------------------------------------------------ receive

    def on_frame(self, msg: can.Message, t: float) -> None:
        """Take one received frame at time ``t``: a setpoint for a BESS, or an MC
        frame its setpoint is checked against."""
        f = self.io.receive(msg, t)
        if f is None:
            return
        mc_unit = self._mc_ids.get(f.frame_id)
        if mc_unit is not None:
            done = self._checks[mc_unit.agent].mc(f.raw["State"], f.raw["Lambda"], t)
            self._decided(mc_unit, [done] if done else [])
            return
        unit = self._setpoint_ids[f.frame_id]
        self.counters["setpoints"] += 1
        unit.setpoint_rx = t   # the agent is alive, whatever it commands
        unit.stale = False
        sp = Setpoint(bool(f.raw["Enable"]), f.raw["PowerSetpoint"], t)
        if self.obey_inconsistent:  # obeyed at once; the check only counts
            self._apply(unit, sp)
        self._decided(unit, self._checks[unit.agent].setpoint(sp))

    def _apply(self, u: BessUnit, sp: Setpoint) -> None:
        u.enable = sp.enable
        u.p_set = sp.raw * self._sp_scale

    def _decided(self, u: BessUnit, outcomes: list[tuple[Check, Setpoint]]) -> None:
        """Apply the setpoints whose check is decided and consistent (an inconsistent one
        leaves the last consistent one in force); with ``obey_inconsistent`` every
        setpoint was applied on arrival and this only counts."""
        for check, sp in outcomes:
            if check is Check.UNVERIFIED:
                self.counters["setpoint_unverified"] += 1
                continue
            if check is Check.INCONSISTENT:
                self.counters["setpoint_inconsistent"] += 1
                self.counters[f"setpoint_inconsistent_agent_{u.agent}"] += 1
                if self.counters[f"setpoint_inconsistent_agent_{u.agent}"] == 1:
                    log.warning("plant: agent %d commands %.2f kW, not its dispatch rule at "
                                "the λ it publishes: %s", u.agent, sp.raw * self._sp_scale,
                                "obeyed (obey_inconsistent)" if self.obey_inconsistent
                                else "holding its last consistent setpoint")
                continue
            if not self.obey_inconsistent:
                self._apply(u, sp)

    # ------------------------------------------------------------------ periodic

    def tick(self, t: float) -> list[can.Message]:
        """One plant period at ``t``: every BESS's current loop, SoC and protection
        advanced; the syncs and status frames due."""
        dt, t_rel = self._advance(t)
        forced = self._forced(t_rel)
        for u in self.units:
            u.advance(dt)
            self._check_setpoint_age(u, t)
            before = (u.fault_soc, u.fault_voltage, u.fault_overcurrent)
            if u.control(forced.get(u.agent, set()), dt):
                self.counters["setpoint_ramp_limited"] += 1
            for name, was, now in zip(("soc_faults", "voltage_faults", "overcurrent_faults"),
                                      before, (u.fault_soc, u.fault_voltage,
                                               u.fault_overcurrent), strict=True):
                self.counters[name] += now and not was
        out = self.io.syncs(t)
        if self._status.due(t):
            powers = [self._raw("Power", u.power) for u in self.units]  # as reported
            out += [self._status_frame(u, name, p)
                    for u, name, p in zip(self.units, self._status_names, powers, strict=True)]
            out.append(self._totals_frame(powers))
        return out

    def _forced(self, t_rel: float) -> dict[int, set[str]]:
        out: dict[int, set[str]] = {}
        for k, f in enumerate(self.faults):
            if f.active(t_rel):
                out.setdefault(f.agent, set()).add(f.kind)
                if k not in self._active_faults:
                    self._active_faults.add(k)
                    self.counters["injected_faults"] += 1
                    log.info("plant: injected %s on BESS %d from t = %.3f s", f.kind, f.agent,
                             t_rel)
            else:
                self._active_faults.discard(k)
        return out

    def _check_setpoint_age(self, u: BessUnit, t: float) -> None:
        if u.stale or u.setpoint_rx is None:
            return
        if t - u.setpoint_rx > self.setpoint_timeout + 1e-9:
            u.stale = True
            u.setpoint_timeouts += 1
            self.counters["setpoint_timeouts"] += 1
            self.io.sender_lost(self._setpoint_fid[u.agent])  # the counter gap aliases
            log.info("plant: BESS %d setpoint timed out (%.0f ms old): ramping to 0", u.agent,
                     1e3 * (t - u.setpoint_rx))

    def _raw(self, signal: str, value: float) -> int:
        lo, hi = self._ranges[signal]
        r = round(value / self._scales[signal])
        if r < lo or r > hi:
            self.counters["encode_saturations"] += 1
            r = min(hi, max(lo, r))
        return r

    def _status_frame(self, u: BessUnit, name: str, power: int) -> can.Message:
        """``name`` for unit ``u``, its Power the raw ``power`` (``_raw``'d once a cycle:
        the totals sum the same values)."""
        msg = self.io.send(name, {
            "FaultOverCurrent": int(u.fault_overcurrent), "FaultVoltage": int(u.fault_voltage),
            "FaultSoc": int(u.fault_soc), "PowerLimited": int(u.power_limited),
            "Power": power,
            "Soc": self._raw("Soc", 100.0 * u.soc),
        })
        self.counters["status_frames"] += 1
        return msg

    def _totals_frame(self, raw_powers: list[int]) -> can.Message:
        """PLANT_Totals: the sum of the powers the status frames just sent report (raw),
        and the batteries' cost rate at them (the router's ledger, AUTH-29)."""
        powers = [r * self._scales["Power"] for r in raw_powers]
        cost = float(sum(u.battery.cost_rate(p) for u, p in zip(self.units, powers, strict=True)))
        msg = self.io.send(TOTALS, {"BatteryPower": self._raw("BatteryPower", sum(powers)),
                                    "BatteryCostRate": self._raw("BatteryCostRate", cost)})
        self.counters["totals_frames"] += 1
        return msg

    # ------------------------------------------------------------------ reporting

    def unit(self, agent: int) -> BessUnit:
        """The state of BESS ``agent`` (1-based)."""
        if not 1 <= agent <= len(self.units):
            raise ParameterError("agent", f"a BESS in 1..{len(self.units)}", agent)
        return self.units[agent - 1]

    def summary(self) -> str:
        """The plant's summary at exit: counters, and per BESS its power, current,
        voltage, SoC and flags."""
        t = self.elapsed
        c = ", ".join(f"{k}={v}" for k, v in sorted(self.counters.items()) if v) or "none"
        lines = [f"plant: {len(self.units)} BESS, t={t:.2f} s, ticks={self.ticks}, counters: {c}"]
        lines += [f"  BESS {u.agent}: P={u.power:7.2f} kW (ref {u.p_ref:7.2f}) "
                  f"I={u.current:7.1f} A V={u.voltage:6.1f} V SoC={100 * u.soc:5.2f} % {u.flags()}"
                  f"{' setpoint stale' if u.stale else ''}" for u in self.units]
        return "\n".join(lines)
