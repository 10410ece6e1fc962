"""The agent runtime: neighbour table, receive checks, timeouts and the state machine
around the pure control core. Implements the Node seam of firmware_py.node.

State machine::

    INIT ──price and status fresh──▶ RUNNING ──price lost / status lost / plant fault──▶ SAFE
                                      ▲  │                                               │
                                      │  └──ISOLATE──▶ ISOLATED                          │
                                      └──RECONNECT──┘      price and status fresh, no fault

* INIT: waiting for a fresh valid price AND a fresh PLANT_<id>_Status: an agent does
  not dispatch a plant it has not heard from. λ = λ(0) is broadcast but nobody uses
  it; the setpoint is disabled. INIT is left only for RUNNING (or ISOLATED); an agent
  whose plant never reports stays in INIT, which counts no timeout (nothing was lost).
* RUNNING (``contract.is_active``): the consensus runs every Ts; the power setpoint
  follows λ.
* ISOLATED (plug-and-play): off the network. λ := the BESS's idle MC (P = 0),
  ν := 0, setpoint disabled. Neighbours drop it from ξ (they only use RUNNING
  neighbours). RECONNECT re-enters through INIT.
* SAFE: no valid price for ``price_timeout_s``, no PLANT_<id>_Status for
  ``status_timeout_s`` (a dead plant or a cut link: the agent cannot see what its
  BESS does), or the plant reports an over-current or voltage fault (a SoC limit is
  enforced by the plant and only flagged). λ is held, ν := 0, setpoint disabled
  (Enable = 0, P = 0). Leaves SAFE as soon as price and status are fresh and no
  fault is reported.

Timeouts (firmware_py.config): both default to 5 cycles of their frame at the
controller's Ts (contract.timeout_s), 0.25 s at Ts = 10 ms. A frame is fresh while
``now − last accepted ≤ timeout``. Each fresh→stale transition counts one
``price_timeouts`` / ``status_timeouts`` (whatever the state), logs it and widens that
input's freshness window (an outage's counter gap aliases); ``plant_faults`` counts
rising edges of the over-current/voltage flags.

Cadences come from the DBC: the MC frame every tick (or, with ``[transmit] mode =
"event"``, when λ moved beyond a threshold, the State changed or a heartbeat is due:
``_mc_due``), the setpoint and diagnostics every ``contract.every_ticks`` ticks (5 and 10
at the DBC's cycles), so a node with a longer Ts stretches them all alike. The diagnostics
rotate over ``DIAG_PAGES``, one page per diag frame.

Safety model (docs/safety-model.md): on top of the receive checks (and NodeIO's untrusted
sources), an accepted price outside ``[rho_min, rho_max]`` or more than
``price_step_max`` from the last accepted fresh price is rejected (``implausible_price``)
(fresh or not) — a new level repeated in ``price_persist`` consecutive frames is accepted
(``price_steps_accepted``); a RUNNING neighbour whose λ moved more than
``lambda_step_max`` per elapsed sample since its last accepted frame is rejected
(``implausible_lambda``, its last good λ kept); SET_GAINS outside ``[k_min, k_max]``,
``[h_min, h_max]`` is rejected (``implausible_gains``, gains unchanged). ISOLATE and
RECONNECT are logged at warning level with the claimed sender and counted
(``commands_isolate``, ``commands_reconnect``). PIN (GainK 1) and UNPIN (GainK 2) set or
clear the price term of ξ (``pin``, b_ii = 1), in any state, nothing else changes (CMD-7).

Every frame that is rejected lands in ``counters`` under its cause; the first few
of each cause are logged with the full reason, so nothing is dropped silently.
Foreign traffic (firmware_py.nodeio) is counted under ``foreign`` and its cause.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, replace

import can

from . import contract, pricesig
from . import fixedpoint as fx
from .config import AgentConfig, DispatchParams
from .contract import DIAG_RESERVED, Command, State, cycle_s, every_ticks, is_active, scale
from .controllers import consensus_error, make_controller
from .errors import ConfigError, FrameError, RangeError
from .frames import (
    PIN_ON,
    DecodedFrame,
    FrameCodec,
    diag_name,
    mc_name,
    setpoint_name,
    status_name,
    target_agent,
)
from .nodeio import NodeIO
from .secoc import Keyring

__all__ = ["DIAG_EVERY", "SETPOINT_EVERY", "AgentRuntime", "Command", "NeighbourSlot",
           "SetpointMap", "State"]

log = logging.getLogger(__name__)

SETPOINT_EVERY = every_ticks(setpoint_name(1))   # ticks between setpoints (5 in the DBC)
DIAG_EVERY = every_ticks(diag_name(1))           # ticks between diag frames (10)
# AGENT_<i>_Diag SafetyCause values (tools/gen_dbc.py SAFETY_CAUSE_CHOICES)
# SET_GAINS carries gains in units of 1/GAIN_DIV (GainK's DBC factor 0.001)
GAIN_DIV = round(1 / scale("ER_Command", "GainK"))
SAFETY_CAUSES = ("none", "untrusted", "implausible_price", "implausible_lambda",
                 "implausible_gains", "auth")


@dataclass
class NeighbourSlot:
    """What an agent knows of one neighbour: its weight, last λ and state, when it
    was last heard, and whether it is alive (heard within the neighbour timeout)."""

    id: int
    weight: int              # a_ij in Q24
    lam: int | None = None   # last λ_j received (Q24)
    state: State = State.INIT
    last_rx: float | None = None
    alive: bool = False


class SetpointMap:
    """λ (Q24) → power setpoint in the frame's raw unit (0.01 kW), integer only.

    P = (λ/(1+m) − β)/(2α) is affine in λ, so the firmware stores a gain G in
    Q16 and an offset O, both computed once from the configuration:
    P_raw = round(λ·G / 2**(24+16)) − O, then clipped to the battery limits.
    """

    GAIN_Q = 16

    def __init__(self, b: DispatchParams) -> None:
        self.gain = round(100 * (1 << self.GAIN_Q) / ((1 + b.m) * 2 * b.alpha))
        self.offset = round(100 * b.beta / (2 * b.alpha))
        self.lo, self.hi = round(100 * b.p_min), round(100 * b.p_max)
        self.shift = fx.Q + self.GAIN_Q

    def __call__(self, lam: int) -> tuple[int, bool]:
        """(setpoint raw, limited?)."""
        p = ((lam * self.gain + (1 << (self.shift - 1))) >> self.shift) - self.offset
        if p > self.hi:
            return self.hi, True
        if p < self.lo:
            return self.lo, True
        return p, False


class AgentRuntime:
    """One BESS agent's firmware, minus the loop that drives it (firmware_py.node)."""

    def __init__(self, cfg: AgentConfig, codec: FrameCodec | None = None,
                 keys: Keyring | None = None) -> None:
        self.cfg = cfg
        self.codec = codec or FrameCodec()
        self.period = cfg.controller.ts
        self.ctrl = make_controller(cfg.controller, fixed=True)
        self.cstate = self.ctrl.initial_state(cfg.lambda0)
        self.state = State.INIT
        self.setpoint = SetpointMap(cfg.battery)
        self.idle_lambda = cfg.battery.beta * (1 + cfg.battery.m)
        self.lam_min = fx.to_fixed(cfg.lambda_min, "lambda_min")
        self.lam_max = fx.to_fixed(cfg.lambda_max, "lambda_max")
        self.pin = fx.ONE if cfg.pinned else 0

        c = self.codec
        self.neighbours = {c.frame_id(mc_name(n.id)): NeighbourSlot(
            n.id, fx.to_fixed(n.weight, "weight")) for n in cfg.neighbours}
        self.price_id = c.frame_id("ER_Price")
        self.command_id = c.frame_id("ER_Command")
        self.status_id = c.frame_id(status_name(cfg.id))
        # signed_price (AUTH-31..33): the router's price signatures, verified here
        self.sig_id = c.frame_id(pricesig.MESSAGE) if cfg.signed_price else None
        # AUTH-13, AUTH-27: each input's timeout marks it lost (ER_Command: the price's,
        # the same sender's), so every input is a timed one
        inputs = (self.price_id, self.command_id, self.status_id, *self.neighbours)
        self.io = NodeIO(c, f"agent {cfg.id}",
                         own=(mc_name(cfg.id), setpoint_name(cfg.id), diag_name(cfg.id)),
                         wanted=inputs, fleet_size=cfg.fleet_size,
                         untrusted_after=cfg.untrusted_after,
                         untrusted_s=float(cfg.untrusted_s or 0.0), keys=keys,
                         sync_s=cycle_s("ER_Price_Sync", cfg.controller.ts),
                         transfers=() if self.sig_id is None else (self.sig_id,),
                         tag_receivers=contract.lambda_receivers([n.id for n in cfg.neighbours]),
                         timed=inputs)
        self.price_sig: pricesig.PriceSigReceiver | None = None
        if cfg.signed_price:
            public = self.io.keys.price_verify
            if public is None:
                raise ConfigError(cfg.source, "security.signed_price", "expected a key file "
                                  "with the router's public price key ([price_signature] "
                                  "verify_key), but it has none: re-provision with bess-ded "
                                  "keys for a signed_price scenario")
            self.price_sig = pricesig.PriceSigReceiver(public, self.io.keys.fleet_id)
            self.io.precheck(self.price_id, self._signed_price)
            self.io.vouch(self.price_id, self._signed_boot)
        # safety limits in Q24 (docs/safety-model.md)
        self.rho_min = fx.to_fixed(cfg.rho_min, "rho_min")
        self.rho_max = fx.to_fixed(cfg.rho_max, "rho_max")
        self.price_step_max = fx.to_fixed(cfg.price_step_max, "price_step_max")
        self.lambda_step_max = fx.to_fixed(float(cfg.lambda_step_max or 0.0),
                                           "lambda_step_max")
        self._price_candidate: int | None = None  # a new price level beyond the step limit
        self._price_candidate_n = 0
        self.counters = self.io.counters
        self.last_error = self.io.last_error
        # saturate each diag value at its signal's raw maximum (u16, or u8 NeighboursAlive)
        diag = diag_name(cfg.id)
        self._diag_max = {name: c.raw_range(diag, name)[1]
                          for page in self.DIAG_PAGES for name in page}
        self._mc_max = {name: c.raw_range(mc_name(cfg.id), name)[1]
                        for name in ("Resets",)}

        self.price: int | None = None      # ρ, Q24
        self.price_rx: float | None = None
        self.status_rx: float | None = None
        self._price_fresh = False          # for the fresh→stale edges (timeouts)
        self._status_fresh = False
        self.plant_fault = False
        self.power_limited = False
        self.ticks = 0
        self._now = 0.0
        # TX-7: the (λ, State) of the last MC frame sent and the ticks since
        self._mc_last: tuple[int, State] | None = None
        self._mc_age = 0
        self._mc_threshold = cfg.transmit.threshold_q24

    # ------------------------------------------------------------------ receive

    def on_frame(self, msg: can.Message, t: float) -> None:
        """Take one received frame at time ``t``: verified by NodeIO, then handled
        as a price, a command, the plant status or a neighbour's MC frame."""
        frame = self.io.receive(msg, t, defer_trust=True)
        if frame is None:
            return
        fid = frame.frame_id
        if fid == self.sig_id:
            self._on_price_sig(frame)
            return
        rejected = self.io.safety_rejections
        try:
            if fid == self.price_id:
                self._on_price(frame, t)
            elif fid == self.command_id:
                self._on_command(frame, fid)
            elif fid == self.status_id:
                self._on_status(frame, t)
            else:
                self._on_mc(self.neighbours[fid], frame, t)
        except FrameError as e:
            self.io.fail(fid, e.cause, str(e), t)
            return
        if self.io.safety_rejections == rejected:
            # valid and plausible: the streak of receive failures is over (a plausibility
            # rejection neither adds to it nor ends it)
            self.io.trusted(fid)

    def _check_lambda(self, name: str, raw: int) -> int:
        if not self.lam_min <= raw <= self.lam_max:
            raise RangeError(f"{name}: expected a value in [{self.cfg.lambda_min}, "
                             f"{self.cfg.lambda_max}] cu/kWh, but got {fx.to_float(raw):.6g}")
        return raw

    def _on_price_sig(self, f: DecodedFrame) -> None:
        """An ER_Price_Sig page (AUTH-32): reassembled, the signature verified once."""
        assert self.price_sig is not None
        last = self.io.last_freshness(self.price_id)
        boot = contract.FRESHNESS.split(last)[0] if last is not None else 0
        bad = self.price_sig.take(f.raw, min_boot=boot)
        if bad is not None:
            self.io.reject(*bad)

    def _signed_price(self, f: DecodedFrame) -> tuple[str, str] | None:
        """AUTH-33: an ER_Price is taken only with the signed segment's price, checked
        before its MAC and freshness."""
        assert self.price_sig is not None
        why = self.price_sig.check(f.raw)
        return None if why is None else ("unsigned_price", why)

    def _signed_boot(self, boot: int) -> bool:
        """AUTH-33, AUTH-35: a held advance of the router's price to ``boot`` is taken only
        under a price signature of that boot or later (the router signs its boot; a key
        holder of its node key signs nothing)."""
        assert self.price_sig is not None
        return self.price_sig.current is not None and self.price_sig.current.boot >= boot

    def _on_price(self, f: DecodedFrame, t: float) -> None:
        if not f.raw["PriceValid"]:
            return  # the router says it has no price: treated as no price frame
        rho = self._check_lambda("ER_Price.Rho", f.raw["Rho"])
        if not self.rho_min <= rho <= self.rho_max:
            self._candidate(None)
            self.io.safety_reject("implausible_price", f.frame_id, f"ER_Price.Rho: expected a "
                                  f"price in [{self.cfg.rho_min}, {self.cfg.rho_max}] cu/kWh "
                                  f"(limits.rho_min/rho_max), but got {fx.to_float(rho):.6g}")
            return
        # against the last accepted price even when it went stale: after an outage a new
        # level far from the old one needs price_persist frames too
        if self.price is not None and abs(rho - self.price) > self.price_step_max:
            n = self._candidate(rho)
            if n < self.cfg.price_persist:
                self.io.safety_reject(
                    "implausible_price", f.frame_id, f"ER_Price.Rho: expected a step of at most "
                    f"{self.cfg.price_step_max} cu/kWh (limits.price_step_max) from "
                    f"{fx.to_float(self.price):.6g}, but got {fx.to_float(rho):.6g} "
                    f"({n} of {self.cfg.price_persist} frames to accept it as a new level)")
                return
            self.counters["price_steps_accepted"] += 1
            log.warning("agent %d: accepted a price step %.6g → %.6g cu/kWh beyond "
                        "price_step_max after %d consecutive frames", self.cfg.id,
                        fx.to_float(self.price), fx.to_float(rho), n)
        self._candidate(None)
        self.price = rho
        self.price_rx = t

    def _candidate(self, rho: int | None) -> int:
        """Track a price level beyond the step limit: how many consecutive frames carried
        it (None: forget it)."""
        if rho is None or rho != self._price_candidate:
            self._price_candidate, self._price_candidate_n = rho, 0
        if rho is not None:
            self._price_candidate_n += 1
        return self._price_candidate_n

    def _on_mc(self, slot: NeighbourSlot, f: DecodedFrame, t: float) -> None:
        state = f.raw["State"]
        if state not in State._value2member_map_:
            raise RangeError(f"{f.name}.State: expected one of {[int(s) for s in State]}, but "
                             f"got {state}")
        lam = self._check_lambda(f"{f.name}.Lambda", f.raw["Lambda"])
        if (slot.alive and slot.lam is not None and slot.last_rx is not None
                and is_active(slot.state) and is_active(State(state))):
            # both frames RUNNING: an ISOLATE (idle MC) or a restart goes through another state
            samples = max(1, round((t - slot.last_rx) / self.period))
            if abs(lam - slot.lam) > samples * self.lambda_step_max:
                self.io.safety_reject(
                    "implausible_lambda", f.frame_id, f"{f.name}.Lambda: expected a change of "
                    f"at most {self.cfg.lambda_step_max:.6g} cu/kWh per sample "
                    f"(limits.lambda_step_max) × {samples}, but got "
                    f"{fx.to_float(slot.lam):.6g} → {fx.to_float(lam):.6g}; kept the last")
                return
        slot.lam = lam
        slot.state = State(state)
        slot.last_rx = t

    def _on_command(self, f: DecodedFrame, fid: int) -> None:
        if target_agent(f.raw["Target"]) != self.cfg.id:
            return
        cmd = f.raw["Command"]
        self.counters["commands"] += 1
        if cmd in (Command.ISOLATE, Command.RECONNECT):
            name = Command(cmd).name
            self.counters[f"commands_{name.lower()}"] += 1
            log.warning("agent %d: %s from claimed sender 0x%03X (ER_Command, counter %d) in "
                        "state %s", self.cfg.id, name, fid, f.counter, self.state.name)
        if cmd == Command.ISOLATE and self.state != State.ISOLATED:
            self.state = State.ISOLATED
            self.cstate = self.ctrl.initial_state(self.idle_lambda)
        elif cmd == Command.RECONNECT and self.state == State.ISOLATED:
            self.state = State.INIT  # tick() moves on to RUNNING when price and status are fresh
        elif cmd == Command.SET_GAINS:
            k, h = f.phys("GainK"), f.phys("GainH")
            c = self.cfg
            assert c.k_min is not None and c.k_max is not None
            assert c.h_min is not None and c.h_max is not None
            if not (c.k_min <= k <= c.k_max and c.h_min <= h <= c.h_max):
                self.io.safety_reject(
                    "implausible_gains", fid, f"ER_Command SET_GAINS: expected k in "
                    f"[{c.k_min:g}, {c.k_max:g}] and h in [{c.h_min:g}, {c.h_max:g}] "
                    f"(limits.k_min..h_max), but got k = {k:g}, h = {h:g}; gains unchanged")
                return
            self._set_gains(f.raw["GainK"], f.raw["GainH"], k, h)
        elif cmd == Command.PIN:  # CMD-7, in any state: the decoder checked GainK and GainH
            self.pin = fx.ONE if f.raw["GainK"] == PIN_ON else 0
            log.warning("agent %d: %s from claimed sender 0x%03X (ER_Command, counter %d) in "
                        "state %s", self.cfg.id, "PIN" if self.pin else "UNPIN", fid,
                        f.counter, self.state.name)
        elif cmd not in Command._value2member_map_:
            raise RangeError(f"ER_Command.Command: expected one of {[int(c) for c in Command]}, "
                             f"but got {cmd}")

    def _set_gains(self, k_raw: int, h_raw: int, k: float, h: float) -> None:
        """CMD-5: KTS and HTS from the raw gains in integers, ``(2·raw·TSQ + D) // 2D``
        with D = 1/scale (1000): what an MCU computes without floating point. Refused
        (RangeError) unless k > 0, h > 0 where the kind integrates, and both constants
        are at least one LSB and fit an int32."""
        ctrl = self.ctrl
        kts, hts = self._gain_q30(k_raw), self._gain_q30(h_raw)
        needs_h = ctrl.config.kind in ("pi", "reset", "dwell")
        if (k_raw == 0 or (needs_h and h_raw == 0) or not 0 < kts <= fx.INT32_MAX
                or (h_raw != 0 and not 0 < hts <= fx.INT32_MAX)):
            and_h = " and h > 0" if needs_h else ""
            raise RangeError(f"ER_Command SET_GAINS: expected k > 0{and_h}"
                             f" with k·ts and h·ts of at least one Q1.30 LSB, but got k = {k:g}, "
                             f"h = {h:g} (k·ts = {kts}, h·ts = {hts} LSB)")
        self.ctrl = make_controller(ctrl.config, fixed=True)
        self.ctrl.config = ctrl.config.with_gains(k, h)
        self.ctrl.kts, self.ctrl.hts = kts, hts
        self.cstate = replace(self.cstate, nu=0)

    def _gain_q30(self, raw: int) -> int:
        """A SET_GAINS gain (raw, 1/GAIN_DIV units) times Ts, in Q1.30, rounded half up."""
        return (2 * raw * int(self.ctrl.ts_q) + GAIN_DIV) // (2 * GAIN_DIV)

    def _on_status(self, f: DecodedFrame, t: float) -> None:
        r = f.raw
        # over-current and voltage faults stop the dispatch (SAFE); a SoC limit does not:
        # the plant already blocks further charge/discharge in that direction, and
        # idling the BESS would keep the SoC where it is and the fault with it
        fault = bool(r["FaultOverCurrent"] or r["FaultVoltage"])
        if fault and not self.plant_fault:
            self.counters["plant_faults"] += 1
            log.warning("agent %d: plant reports a fault (over-current %d, voltage %d)",
                        self.cfg.id, r["FaultOverCurrent"], r["FaultVoltage"])
        self.plant_fault = fault
        self.power_limited = bool(r["PowerLimited"] or r["FaultSoc"])
        self.status_rx = t

    # ------------------------------------------------------------------ periodic

    def note(self, event: str, count: int = 1) -> None:
        """Count a runtime event (deadline_miss, send_failure, ...) reported by run_node."""
        self.counters[event] += count

    @property
    def price_ok(self) -> bool:
        """A valid ER_Price accepted within ``price_timeout_s``."""
        return self.price_rx is not None and self._now - self.price_rx <= self.cfg.price_timeout_s

    @property
    def status_ok(self) -> bool:
        """A PLANT_<id>_Status accepted within ``status_timeout_s``."""
        return (self.status_rx is not None
                and self._now - self.status_rx <= self.cfg.status_timeout_s)

    def tick(self, t: float) -> list[can.Message]:
        """One control period at time ``t``: neighbour timeouts, state machine, a
        controller step when active; the frames to send (MC, setpoint, diag, syncs)."""
        self._now = t
        self._update_neighbours(t)
        self._update_state()
        if is_active(self.state):
            xi, sat = consensus_error(self.ctrl.ar, self.lambda_q24, self.xi_terms(),
                                      self.pin if self.price is not None else 0,
                                      self.price or 0, self.cfg.resilient_f)
            self.cstate, _ = self.ctrl.step(self.cstate, xi)
            self.counters["saturations"] += sat
        frames = self.io.syncs(t)
        if self._mc_due():
            frames.append(self._mc_frame())
        if self.ticks % SETPOINT_EVERY == 0:
            frames.append(self._setpoint_frame())
        if self.ticks % DIAG_EVERY == 0:
            frames.append(self._diag_frame(self.ticks // DIAG_EVERY % len(self.DIAG_PAGES)))
        self.ticks += 1
        return frames

    def xi_terms(self) -> list[tuple[int, int]]:
        """XI-1: (weight, λ) in Q24 of every neighbour alive and RUNNING: the terms of ξ."""
        return [(s.weight, s.lam) for s in self.neighbours.values()
                if s.alive and is_active(s.state) and s.lam is not None]

    def _update_neighbours(self, t: float) -> None:
        timeout = self.cfg.neighbour_timeout_periods * self.period
        for fid, slot in self.neighbours.items():
            alive = slot.last_rx is not None and t - slot.last_rx <= timeout
            if slot.alive and not alive:
                self.counters["neighbour_timeouts"] += 1
                self.io.sender_lost(fid)  # the counter gap of an outage aliases
                log.info("agent %d: neighbour %d timed out", self.cfg.id, slot.id)
            slot.alive = alive

    def _update_inputs(self) -> None:
        """Count each fresh→stale edge of the price and the plant status (in any state)."""
        for name, ok, was, fid, timeout in (
                ("price", self.price_ok, self._price_fresh, self.price_id,
                 self.cfg.price_timeout_s),
                ("status", self.status_ok, self._status_fresh, self.status_id,
                 self.cfg.status_timeout_s)):
            if was and not ok:
                self.counters[f"{name}_timeouts"] += 1
                self.io.sender_lost(fid)  # an outage's counter gap aliases
                if fid == self.price_id:  # the router's: its commands' count moved unseen too
                    self.io.sender_lost(self.command_id)
                log.warning("agent %d: %s timed out (none accepted for more than %.3f s)",
                            self.cfg.id, "valid ER_Price" if name == "price"
                            else status_name(self.cfg.id), timeout)
        self._price_fresh, self._status_fresh = self.price_ok, self.status_ok

    def _update_state(self) -> None:
        self._update_inputs()
        if self.state == State.ISOLATED:
            return
        healthy = self._price_fresh and self._status_fresh and not self.plant_fault
        if self.state == State.RUNNING and not healthy:
            why = [w for w, bad in (("price lost", not self._price_fresh),
                                    ("plant status lost", not self._status_fresh),
                                    ("plant fault", self.plant_fault)) if bad]
            log.warning("agent %d: entering SAFE (%s)", self.cfg.id, ", ".join(why))
            self.state = State.SAFE
            self.cstate = replace(self.cstate, nu=0, xi_prev=0)
        elif self.state in (State.INIT, State.SAFE) and healthy:
            if self.state == State.SAFE:
                log.info("agent %d: leaving SAFE (price and plant status fresh)", self.cfg.id)
            self.state = State.RUNNING
            self.cstate = replace(self.cstate, nu=0, xi_prev=0)

    # ------------------------------------------------------------------ transmit

    @property
    def neighbours_alive(self) -> int:
        """How many neighbours are alive and active (their λ enters ξ)."""
        return sum(s.alive and is_active(s.state) for s in self.neighbours.values())

    def _mc_due(self) -> bool:
        """TX-1/TX-7: send the MC frame this tick? Always when periodic; in event mode the
        first tick, a State change, |λ − λ last sent| > threshold, or ``heartbeat`` ticks
        since the last one (the neighbours hold the last λ they heard until then)."""
        tx = self.cfg.transmit
        lam = self.lambda_q24
        self._mc_age += 1
        if (tx.event and self._mc_last is not None and self._mc_age < tx.heartbeat
                and self._mc_last[1] == self.state
                and abs(lam - self._mc_last[0]) <= self._mc_threshold):
            return False
        self._mc_last, self._mc_age = (lam, self.state), 0
        return True

    def _mc_frame(self) -> can.Message:
        return self.io.send(mc_name(self.cfg.id), {
            "State": int(self.state), "Lambda": self.lambda_q24,
            "Resets": self.cstate.resets % self.resets_modulo})

    def _setpoint_frame(self) -> can.Message:
        enable = is_active(self.state)
        p, limited = self.setpoint(self.lambda_q24) if enable else (0, False)
        self.counters["setpoint_limited"] += limited
        return self.io.send(setpoint_name(self.cfg.id), {"Enable": int(enable), "PowerSetpoint": p})

    def diag_values(self) -> dict[str, int]:
        """Every AGENT_<id>_Diag signal's raw value, from the counters and the state."""
        c = self.counters
        last = self.io.last_safety
        return {"Resets": self.cstate.resets, "DeadlineMisses": c["deadline_miss"],
                "NeighboursAlive": self.neighbours_alive, "State": int(self.state),
                "RejectedDlc": c["dlc"], "RejectedRange": c["range"],
                "RejectedUnknownId": c["unknown_id"], "RejectedImpersonation": c["impersonation"],
                "LostFrames": c["lost_frames"],
                "Saturations": c["saturations"] + self.cstate.saturations,
                "NeighbourTimeouts": c["neighbour_timeouts"],
                "PriceTimeouts": c["price_timeouts"], "StatusTimeouts": c["status_timeouts"],
                "PlantFaults": c["plant_faults"], "ForeignFrames": c["foreign"],
                "ForeignIds": c["foreign_id"],
                "Untrusted": c["untrusted_sources"], "ImplausiblePrice": c["implausible_price"],
                "ImplausibleLambda": c["implausible_lambda"],
                "ImplausibleGains": c["implausible_gains"],
                "SafetySender": last[1] if last else 0,
                "SafetyCause": SAFETY_CAUSES.index(last[0]) if last else 0,
                "RejectedAuth": c["auth"], "Unsynced": c["unsynced"], "Resyncs": c["resyncs"],
                **dict.fromkeys(DIAG_RESERVED, 0)}

    # AGENT_<i>_Diag pages as the DBC lays them out: page k carries DIAG_PAGES[k]
    DIAG_PAGES = tuple(FrameCodec().pages(diag_name(1)).values())

    def _diag_frame(self, page: int) -> can.Message:
        values = self.diag_values()
        # counters saturate at their signal's maximum, they never wrap (DBC comment)
        raw = {name: min(values[name], self._diag_max[name]) for name in self.DIAG_PAGES[page]}
        return self.io.send(diag_name(self.cfg.id), {"Page": page, **raw})

    # ------------------------------------------------------------------ reporting

    @property
    def now(self) -> float:
        """The time of the last tick (the agent's clock never goes back)."""
        return self._now

    @property
    def diag_max(self) -> Mapping[str, int]:
        """Each Diag signal's raw maximum, where its value saturates."""
        return self._diag_max

    @property
    def resets_modulo(self) -> int:
        """The MC frame's Resets signal counts modulo this."""
        return self._mc_max["Resets"] + 1

    def input_memory(self) -> tuple[bool, bool, int | None, int]:
        """What the input checks remember between ticks besides receive times: price and
        status fresh at the last tick, and a price beyond the step limit seen n times."""
        return (self._price_fresh, self._status_fresh, self._price_candidate,
                self._price_candidate_n)

    def transmit_memory(self) -> tuple[tuple[int, State] | None, int]:
        """What TX-7 remembers between ticks: the (λ, State) of the MC frame last sent
        (None before the first) and the ticks since it."""
        return self._mc_last, self._mc_age

    def adopt_transmit(self, sent: tuple[int, State] | None, age: int) -> None:
        """TX-7's memory set from outside (a checker following a device's MC frames)."""
        self._mc_last, self._mc_age = sent, age

    def constant_tables(self) -> tuple[object, ...]:
        """What neither a frame nor a tick changes (copies of an agent may share it)."""
        return (self.codec, self.cfg, self.setpoint, self._diag_max, self._mc_max,
                *self.io.constant_tables())

    @property
    def lambda_q24(self) -> int:
        """The agent's λ as it sends it (Q24 raw): the controller state rounded to Q24."""
        return int(self.ctrl.wire_lambda(self.cstate))

    @property
    def lam(self) -> float:
        """The agent's λ on the wire, as a real value (cu/kWh)."""
        return fx.to_float(self.lambda_q24)

    def verdict_counters(self) -> dict[str, object]:
        """What the run's verdict cannot read from AGENT_<i>_Diag: the signed price's
        counters (no Diag slot) and the deadline misses, with the ticks (those not zero;
        ``--counters-dir``'s file, an in-process run's counters)."""
        return {"ticks": self.ticks,
                "counters": {k: self.counters[k]
                             for k in (*contract.SIGNED_PRICE_COUNTERS, "deadline_miss")
                             if self.counters.get(k)}}

    def summary(self) -> str:
        """The one-line summary the agent prints at exit: state, λ, resets, ticks
        and every non-zero counter."""
        c = ", ".join(f"{k}={v}" for k, v in sorted(self.counters.items()) if v) or "none"
        return (f"agent {self.cfg.id}: state={self.state.name} λ={self.lam:.6f} "
                f"resets={self.cstate.resets} ticks={self.ticks} counters: {c}")
