"""Single faults planted in firmware_py's agent, written from docs/firmware-spec.md: the
measure of how good the conformance schedule is (issue 22, "Measure the suite on itself").

Each ``Fault`` is one plausible implementation slip against one requirement: ``apply(rt)``
plants it in a fresh ``AgentRuntime`` (as ``sim.conformance.simulate``'s ``deviation``:
only that device is changed, never the oracle). None of them was written for the
schedule: they come from the spec's rules and the issue's classes of slips (arithmetic
at the edges, comparisons at exact boundaries, commands at their limits, state entry and
exit, the freshness machinery, the diagnostics), whether or not the schedule exercises
them.

Every fault is a genuine deviation: its ``witness`` is a short run at unit level (a few
frames and ticks, or ξ fed to the controller) whose output, the frames the agent sends
and the values its Diag frame carries, differs from the faultless agent's
(tests/test_conformance_faults.py checks each). The witness is also what the schedule
would need to catch the fault, where it does not. Faults that no run can tell from the
spec (equivalent mutants) are not in the set; docs/conformance.md lists the ones dropped.

``tools/conformance_score.py`` runs the schedule against each fault and scores it.
"""

from __future__ import annotations

import importlib.util
import math
import tomllib
import types
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import can

from firmware_py import contract, pricesig, secoc
from firmware_py import fixedpoint as fx
from firmware_py.config import (
    AgentConfig,
    Neighbour,
    Transmit,
    agent_configs_from_scenario,
    parse_agent_config,
)
from firmware_py.contract import Command, State, is_active
from firmware_py.controllers import (
    DwellResetPIController,
    FiniteTimeController,
    ProportionalController,
    ResetPIController,
)
from firmware_py.errors import ParameterError
from firmware_py.frames import (
    PIN_ON,
    FrameCodec,
    diag_name,
    mc_name,
    setpoint_name,
    status_name,
    target_agent,
    target_raw,
)
from firmware_py.nodeio import STREAK_CAUSES, FleetSender
from firmware_py.runtime import GAIN_DIV, AgentRuntime
from firmware_py.secoc import INSECURE_BOOT, Keyring, fleet_nodes
from sim.model.scenario import load_case
from sim.testkit.tester import fleet_keys

Apply = Callable[[AgentRuntime], None]


@dataclass(frozen=True)
class Fault:
    """One slip: ``name``, the requirement it breaks, what the faulty device does, how to
    plant it; ``group``: the issue's class of slips; ``witness(apply)``: a unit-level
    run's output with the fault planted (``apply``) or not (None): they differ."""

    name: str
    requirement: str
    description: str
    apply: Apply
    group: str = ""
    witness: Callable[[Apply | None], Any] | None = None
    # a slip of the configuration path: the device's reading of its TOML file (the
    # tester's, conformance_config), instead of the reference parser's; ``apply`` then
    # plants nothing
    misread: Callable[[str], AgentConfig] | None = None


# --------------------------------------------------------------------------- planting


def _swap(obj: Any, mixin: type) -> None:
    """``obj`` becomes an instance of ``mixin`` over its own class (methods, properties)."""
    cls = type(obj)
    obj.__class__ = type(f"{mixin.__name__}{cls.__name__}", (mixin, cls), {})


def _bind(obj: Any, name: str, fn: Callable[..., Any], **knobs: Any) -> None:
    """``obj.name`` becomes ``fn(obj, ..., **knobs)`` (an instance attribute)."""
    setattr(obj, name, types.MethodType(lambda self, *a, **kw: fn(self, *a, **knobs, **kw),
                                        obj))


def _wrap(obj: Any, name: str, around: Callable[..., Any]) -> None:
    """``obj.name(*a)`` becomes ``around(real, *a)``."""
    real = getattr(obj, name)
    setattr(obj, name, lambda *a, **kw: around(real, *a, **kw))


def _on_ctrl(patch: Callable[[AgentRuntime, Any], None]) -> Apply:
    """A fault of the controller: planted in the agent's controller and again in the one
    an accepted SET_GAINS builds (CMD-5)."""
    def apply(rt: AgentRuntime) -> None:
        patch(rt, rt.ctrl)

        def set_gains(real: Callable[..., None], *a: Any) -> None:
            real(*a)
            patch(rt, rt.ctrl)
        _wrap(rt, "_set_gains", set_gains)
    return apply


def _ar(mixin: type) -> Apply:
    return _on_ctrl(lambda rt, c: _swap(c.ar, mixin))


def _ctrl(mixin: type, only: type = object) -> Apply:
    return _on_ctrl(lambda rt, c: _swap(c, mixin) if isinstance(c, only) else None)


# ------------------------------------------------------------------- arithmetic (mixins)


class _MulTiesAway:
    """mulq rounds ties away from zero (NUM-2: toward +∞)."""

    def mul(self, a: Any, b: Any) -> int:
        p = int(a) * int(b)
        r = (abs(p) + (1 << 23)) >> 24
        return r if p >= 0 else -r


class _NarrowFloor:
    """wire(x) = x >> 30: the Q54 state truncated, not rounded (NUM-8)."""

    def narrow(self, v: Any) -> int:
        return int(v) >> fx.GUARD


class _SatWraps:
    """ξ wraps around int32 (two's complement) instead of saturating (NUM-3)."""

    def sat(self, v: Any) -> tuple[int, bool]:
        return (int(v) + (1 << 31)) % (1 << 32) - (1 << 31), False


class _SatUncounted:
    """ξ saturates but the clamp is not counted (XI-3)."""

    def sat(self, v: Any) -> tuple[int, bool]:
        value, _ = super().sat(v)  # type: ignore[misc]
        return value, False


def _trunc24(x: float, name: str = "value") -> int:
    raw = int(x * (1 << fx.Q))  # toward zero: the slip
    if not fx.INT32_MIN <= raw <= fx.INT32_MAX:
        raise ParameterError(name, "a value that fits int32 Q24", x)
    return raw


class _QuantiseTrunc:
    def quantise(self, x: float, name: str) -> int:
        return _trunc24(x, name)


def _q24_truncates(rt: AgentRuntime) -> None:
    """Every configuration value → Q24 by truncation (NUM-4: rne, ties to even)."""
    def patch(rt: AgentRuntime, c: Any) -> None:
        _swap(c.ar, _QuantiseTrunc)
        c.band = _trunc24(c.config.band)
    _on_ctrl(patch)(rt)
    cfg = rt.cfg
    rt.cstate = rt.ctrl.initial_state(cfg.lambda0)
    for attr, value in (("lam_min", cfg.lambda_min), ("lam_max", cfg.lambda_max),
                        ("rho_min", cfg.rho_min), ("rho_max", cfg.rho_max),
                        ("price_step_max", cfg.price_step_max),
                        ("lambda_step_max", float(cfg.lambda_step_max or 0.0))):
        setattr(rt, attr, _trunc24(value))
    for slot, n in zip(rt.neighbours.values(), cfg.neighbours, strict=True):
        slot.weight = _trunc24(n.weight)


def _own_lambda_clamped(rt: AgentRuntime) -> None:
    """The own λ held in [lambda_min, lambda_max] after each step (STEP-12: only sat54)."""
    lo, hi = fx.widen(rt.lam_min), fx.widen(rt.lam_max)

    def patch(rt: AgentRuntime, c: Any) -> None:
        def step(real: Callable[..., Any], s: Any, xi: Any) -> Any:
            new, out = real(s, xi)
            return replace(new, lam=min(max(new.lam, lo), hi)), out
        _wrap(c, "step", step)
    _on_ctrl(patch)(rt)


class _RootNearest:
    """fpow's integer square roots round to the nearest integer, not down (NUM-5: the
    exact floor of the root)."""

    def frac_pow(self, v: Any) -> int:
        root = abs(int(v))
        for _ in range(self.pow_sqrts):  # type: ignore[attr-defined]
            x = root << fx.Q
            floor = math.isqrt(x)
            root = floor + (x - floor * floor > floor)
        out = root
        for _ in range(self.pow_num - 1):  # type: ignore[attr-defined]
            out = fx.mul(out, root)
        return out


class _PowProductsFirst:
    """fpow raises |v| to the power p first, then takes the n roots (CTRL-3: the roots
    first, then p − 1 products): the same real value, other roundings."""

    def frac_pow(self, v: Any) -> int:
        out = root = abs(int(v))
        for _ in range(self.pow_num - 1):  # type: ignore[attr-defined]
            out = fx.mul(out, root)
        for _ in range(self.pow_sqrts):  # type: ignore[attr-defined]
            out = fx.sqrt_q(out)
        return out


class _DeltaOnWireGrid:
    """pc's and ft's Δλ rounded to the wire's Q24 grid before it is added (STEP-10,
    STEP-11: the product exact, Q54): the guard bits of the step lost."""

    def step(self, s: Any, xi: Any) -> Any:
        new, out = super().step(s, xi)  # type: ignore[misc]
        dlam = fx.widen(fx.narrow(out.dlam))
        lam, _ = fx.saturate_state(s.lam + dlam)
        return replace(new, lam=lam), replace(out, dlam=dlam)


class _SetpointFloor:
    """P(λ) = (λ·G >> 40) − O: the product truncated, not rounded (SP-1)."""

    def __call__(self, lam: int) -> tuple[int, bool]:
        s: Any = self
        p = ((lam * s.gain) >> s.shift) - s.offset
        if p > s.hi:
            return s.hi, True
        if p < s.lo:
            return s.lo, True
        return p, False


# ----------------------------------------------------------- the controller step (copies)


def _pi_step(self: Any, s: Any, xi: Any, rearm_ge: bool = False) -> Any:
    """PIController.step with one comparison changed: the re-arm at |ξ| ≥ BAND."""
    reset = self._reset_now(s, xi)
    nu = 0 if reset else s.nu
    outside = abs(xi) >= self.band if rearm_ge else abs(xi) > self.band
    armed = not reset and (s.armed or outside)
    nu_word = self.ar.narrow(nu)
    dlam, sat1 = self.ar.sat_state(-(self.ar.gain_mul(self.kts, xi)
                                     + self.ar.gain_mul(self.hts, nu_word)))
    nu_next, sat2 = self.ar.sat_state(nu + self.ar.gain_mul(self.ts_q, xi))
    return self._advance(s, xi, dlam, sat1 + sat2, nu_next, reset, armed)


class _RearmGe:
    def step(self, s: Any, xi: Any) -> Any:
        return _pi_step(self, s, xi, rearm_ge=True)


class _ZeroNoCrossing:
    """ξ = 0 after a non-zero ξprev is no crossing (STEP-2: it is one)."""

    def _reset_now(self, s: Any, xi: Any) -> bool:
        crossed = (s.xi_prev > 0 and xi < 0) or (s.xi_prev < 0 and xi > 0)
        return crossed and s.armed


class _ResetUnarmed:
    """Every crossing resets, armed or not (STEP-3: reset = crossing ∧ armed)."""

    def _reset_now(self, s: Any, xi: Any) -> bool:
        return (s.xi_prev > 0 and xi <= 0) or (s.xi_prev < 0 and xi >= 0)


class _DwellStrict:
    """The dwell lets a crossing reset only once since_reset > D (DWELL-1: ≥ D)."""

    def _reset_now(self, s: Any, xi: Any) -> bool:
        return (ResetPIController._reset_now(self, s, xi)  # type: ignore[arg-type]
                and s.since_reset > self.dwell_samples)  # type: ignore[attr-defined]


# ------------------------------------------------------------------- runtime (copies)


def _update_neighbours(self: Any, t: float, strict: bool = False, extra: int = 0) -> None:
    timeout = (self.cfg.neighbour_timeout_periods + extra) * self.period
    for fid, slot in self.neighbours.items():
        age = None if slot.last_rx is None else t - slot.last_rx
        alive = age is not None and (age < timeout if strict else age <= timeout)
        if slot.alive and not alive:
            self.counters["neighbour_timeouts"] += 1
            self.io.sender_lost(fid)
        slot.alive = alive


class _PriceStrict:
    """A price exactly price_s old is stale (STATE-2: fresh while t − price_rx ≤ price_s)."""

    @property
    def price_ok(self) -> bool:
        s: Any = self
        return s.price_rx is not None and s._now - s.price_rx < s.cfg.price_timeout_s


def _update_inputs(self: Any, isolated_quiet: bool = False) -> None:
    for name, ok, was, fid in (("price", self.price_ok, self._price_fresh, self.price_id),
                               ("status", self.status_ok, self._status_fresh,
                                self.status_id)):
        if was and not ok and not (isolated_quiet and self.state == State.ISOLATED):
            self.counters[f"{name}_timeouts"] += 1
            self.io.sender_lost(fid)
    self._price_fresh, self._status_fresh = self.price_ok, self.status_ok


def _update_state(self: Any, safe_from: tuple[State, ...] = (State.RUNNING,),
                  zero: bool = True, rearm: bool = False) -> None:
    self._update_inputs()
    healthy = self._price_fresh and self._status_fresh and not self.plant_fault
    if self.state in safe_from and not healthy:
        self.state = State.SAFE
        if zero:
            self.cstate = replace(self.cstate, nu=0, xi_prev=0)
    elif self.state in (State.INIT, State.SAFE) and healthy:
        self.state = State.RUNNING
        if zero:
            self.cstate = replace(self.cstate, nu=0, xi_prev=0)
        if rearm:
            self.cstate = replace(self.cstate, armed=True, since_reset=0)


def _on_mc(self: Any, slot: Any, f: Any, t: float, ge: bool = False,
           keep_rejected: bool = False) -> None:
    """AgentRuntime._on_mc with LAM-1's comparison ``ge`` (≥) or a rejected λ still
    stored (``keep_rejected``)."""
    state = f.raw["State"]
    lam = self._check_lambda(f"{f.name}.Lambda", f.raw["Lambda"])
    if (slot.alive and slot.lam is not None and slot.last_rx is not None
            and is_active(slot.state) and is_active(State(state))):
        samples = max(1, round((t - slot.last_rx) / self.period))
        limit = samples * self.lambda_step_max
        if abs(lam - slot.lam) >= limit if ge else abs(lam - slot.lam) > limit:
            self.io.safety_reject("implausible_lambda", f.frame_id, "λ step")
            if not keep_rejected:
                return
    slot.lam = lam
    slot.state = State(state)
    slot.last_rx = t


def _on_price(self: Any, f: Any, t: float, ge: bool = False, persist_less: int = 0,
              valid0_fresh: bool = False, candidate_first: bool = False) -> None:
    """AgentRuntime._on_price with PRICE-3's comparison ``ge`` (≥), PRICE-4's count
    accepting ``persist_less`` frames early, PRICE-1's PriceValid = 0 refreshing, or
    ``candidate_first``: a step always a candidate first (PRICE-5: with price_persist = 1
    taken at its second frame, not at once)."""
    if not f.raw["PriceValid"]:
        if valid0_fresh:
            self.price_rx = t
        return
    rho = self._check_lambda("ER_Price.Rho", f.raw["Rho"])
    if not self.rho_min <= rho <= self.rho_max:
        self._candidate(None)
        self.io.safety_reject("implausible_price", f.frame_id, "price bounds")
        return
    if self.price is not None:
        step = abs(rho - self.price)
        if step >= self.price_step_max if ge else step > self.price_step_max:
            n = self._candidate(rho)
            persist = max(self.cfg.price_persist, 2 if candidate_first else 1)
            if n < persist - persist_less:
                self.io.safety_reject("implausible_price", f.frame_id, "price step")
                return
            self.counters["price_steps_accepted"] += 1
    self._candidate(None)
    self.price = rho
    self.price_rx = t


class _Anyone(int):
    """A Target that every agent id equals (a receive path that does not check it)."""

    def __eq__(self, other: object) -> bool:
        return True

    def __ne__(self, other: object) -> bool:
        return False

    __hash__ = int.__hash__


def _any_target(rt: AgentRuntime) -> None:
    """The Target checked nowhere: NodeIO passes every command to the MAC check (under
    the agent's own command key, AUTH-30) and _on_command obeys what verifies."""
    rt.io._target = _Anyone()
    _bind(rt, "_on_command", _on_command, any_target=True)


def _on_command(self: Any, f: Any, fid: int, any_target: bool = False,
                exclusive: bool = False, bounds_cause: str = "implausible_gains",
                isolate_from: tuple[State, ...] | None = None) -> None:
    """AgentRuntime._on_command with one slip: the Target not checked, the gain bounds
    exclusive, out-of-bounds gains filed under another cause, ISOLATE only from some
    states."""
    if target_agent(f.raw["Target"]) != self.cfg.id and not any_target:
        return
    cmd = f.raw["Command"]
    self.counters["commands"] += 1
    if cmd in (Command.ISOLATE, Command.RECONNECT):
        self.counters[f"commands_{Command(cmd).name.lower()}"] += 1
    can_isolate = (self.state != State.ISOLATED if isolate_from is None
                   else self.state in isolate_from)
    if cmd == Command.ISOLATE and can_isolate:
        self.state = State.ISOLATED
        self.cstate = self.ctrl.initial_state(self.idle_lambda)
    elif cmd == Command.RECONNECT and self.state == State.ISOLATED:
        self.state = State.INIT
    elif cmd == Command.SET_GAINS:
        k, h = f.phys("GainK"), f.phys("GainH")
        c = self.cfg
        inside = (c.k_min < k < c.k_max and c.h_min < h < c.h_max if exclusive
                  else c.k_min <= k <= c.k_max and c.h_min <= h <= c.h_max)
        if not inside:
            if bounds_cause == "implausible_gains":
                self.io.safety_reject("implausible_gains", fid, "gain bounds")
            else:
                self.io.fail(fid, bounds_cause, "gain bounds", self._now)
            return
        self._set_gains(f.raw["GainK"], f.raw["GainH"], k, h)
    elif cmd == Command.PIN:
        self.pin = fx.ONE if f.raw["GainK"] == PIN_ON else 0


def _on_status(self: Any, f: Any, t: float, soc_fault: bool = False,
               level: bool = False) -> None:
    """AgentRuntime._on_status with FaultSoc taken for a fault, or every faulty frame
    counted (``level``) instead of the rising edge."""
    r = f.raw
    fault = bool(r["FaultOverCurrent"] or r["FaultVoltage"] or (soc_fault and r["FaultSoc"]))
    if fault and (level or not self.plant_fault):
        self.counters["plant_faults"] += 1
    self.plant_fault = fault
    self.power_limited = bool(r["PowerLimited"] or r["FaultSoc"])
    self.status_rx = t


def _setpoint_frame(self: Any) -> can.Message:
    """The setpoint enabled in SAFE too (SP-3: only in RUNNING)."""
    enable = self.state in (State.RUNNING, State.SAFE)
    p, limited = self.setpoint(self.lambda_q24) if enable else (0, False)
    return self.io.send(setpoint_name(self.cfg.id), {"Enable": int(enable),
                                                     "PowerSetpoint": p})


def _diag_frame(self: Any, page: int) -> can.Message:
    """Diag values wrapped at their signal's range (mod max + 1) instead of saturated
    (DIAG-2)."""
    values = self.diag_values()
    raw = {name: values[name] % (self._diag_max[name] + 1) for name in self.DIAG_PAGES[page]}
    return self.io.send(diag_name(self.cfg.id), {"Page": page, **raw})


def _xi_any_state(self: Any) -> list[tuple[int, int]]:
    """ξ's terms taken over every alive neighbour, whatever its State (XI-1: alive and
    RUNNING)."""
    return [(s.weight, s.lam) for s in self.neighbours.values()
            if s.alive and s.lam is not None]


# ------------------------------------------------------------------ runtime (wrappers)


def _gains_keep_nu(rt: AgentRuntime) -> None:
    def around(real: Callable[..., None], *a: Any) -> None:
        nu = rt.cstate.nu
        real(*a)
        rt.cstate = replace(rt.cstate, nu=nu)
    _wrap(rt, "_set_gains", around)


def _isolate_keeps_counters(rt: AgentRuntime) -> None:
    def around(real: Callable[..., None], f: Any, fid: int) -> None:
        before, was = rt.cstate, rt.state
        real(f, fid)
        if was != State.ISOLATED and rt.state == State.ISOLATED:
            rt.cstate = replace(rt.cstate, resets=before.resets,
                                saturations=before.saturations)
    _wrap(rt, "_on_command", around)


def _reconnect_any_state(rt: AgentRuntime) -> None:
    def around(real: Callable[..., None], f: Any, fid: int) -> None:
        real(f, fid)
        if target_agent(f.raw["Target"]) == rt.cfg.id and f.raw["Command"] == Command.RECONNECT:
            rt.state = State.INIT
    _wrap(rt, "_on_command", around)


def _gains_no_last_safety(rt: AgentRuntime) -> None:
    io = rt.io

    def around(real: Callable[..., None], cause: str, fid: int, reason: str) -> None:
        last = io.last_safety
        real(cause, fid, reason)
        if cause == "implausible_gains":
            io.last_safety = last
    _wrap(io, "safety_reject", around)


def _untrusted_after_gt(rt: AgentRuntime) -> None:
    """The untrusted verdict at the streak's (untrusted_after + 1)-th failure (RX-13)."""
    io = rt.io

    def fail(self: Any, fid: int, cause: str, reason: str, t: float) -> None:
        self.reject(cause, reason)
        if cause == "auth":
            self.last_safety = ("auth", fid)
        if cause not in STREAK_CAUSES:
            return
        self._streak[fid] += 1
        if self._streak[fid] > self.untrusted_after:
            self._streak[fid] = 0
            self._untrusted_until[fid] = t + self.untrusted_s
            self.counters["untrusted_sources"] += 1
            self.last_safety = ("untrusted", fid)
    _bind(io, "fail", fail)


def _extended_is_malformed(rt: AgentRuntime) -> None:
    io = rt.io

    def around(real: Callable[..., Any], msg: can.Message, *a: Any, **kw: Any) -> Any:
        if msg.is_extended_id:
            io.reject("malformed", "extended ID")
            return None
        return real(msg, *a, **kw)
    _wrap(io, "receive", around)


def _fresh_at_start(rt: AgentRuntime) -> None:
    rt._price_fresh = rt._status_fresh = True


# --------------------------------------------------------------------- freshness


class _CandidateLt:
    """AUTH-12's candidate with c < (last & 15) instead of ≤: a frame exactly 16 values
    on is taken for the last one."""

    def candidate(self, sender: Any, truncated: int) -> int | None:
        s: Any = self
        last = s._last.get(sender)
        if last is None:
            return None
        high = last >> s.tx_bits
        if truncated < last & 15:
            high += 1
        return high << s.tx_bits | truncated


class _OneWindow:
    """A lost ID gets one try, not LOST_WINDOWS (AUTH-13)."""

    def search(self, sender: Any, truncated: int, windows: int, verifies: Any) -> Any:
        return super().search(sender, truncated, 1, verifies)  # type: ignore[misc]


class _NoStale:
    """A late genuine frame is not tried in the past window: auth (AUTH-25)."""

    def search_late(self, *a: Any) -> bool:
        return False


class _SyncAlwaysLate:
    """Every sync behind the last accepted value is late, never a replay (AUTH-16)."""

    def late_sync(self, behind: int) -> bool:
        return True


def _accept_keeps_lost(rt: AgentRuntime) -> None:
    io = rt.io

    def around(real: Callable[..., Any], frame: Any, *a: Any) -> Any:
        lost = frame.frame_id in io._lost
        out = real(frame, *a)
        if lost and out is not None:
            io._lost.add(frame.frame_id)
        return out
    _wrap(io, "_authentic", around)


def _unsynced_is_auth(rt: AgentRuntime) -> None:
    io = rt.io

    def around(real: Callable[..., Any], frame: Any, msg: Any, key: Any, t: float,
               *a: Any) -> Any:
        if io._fv.last(frame.frame_id) is None and io._joining is None:
            io.fail(frame.frame_id, "auth", "no freshness yet", t)
            return None
        return real(frame, msg, key, t, *a)
    _wrap(io, "_authentic", around)


def _in_step_sync_counted(rt: AgentRuntime) -> None:
    io = rt.io

    def around(real: Callable[..., Any], fid: int, fv: int, *a: Any, **kw: Any) -> Any:
        last = io._fv.last(fid)
        real(fid, fv, *a, **kw)
        if last is not None and fv - 1 == last:
            io.counters["resyncs"] += 1
    _wrap(io, "_take_sync", around)


def _floor_inclusive(rt: AgentRuntime) -> None:
    """A sync at its sender's floor is refused too (AUTH-21: below the floor)."""
    io = rt.io

    def below(self: Any, name: str, boot: int, sync_id: int, t: float) -> bool:
        floor = self.keys.floor_of(contract.sender_of(name.removesuffix("_Sync")))
        if floor == 0 or boot > floor:
            return False
        self.fail(sync_id, "auth", "below the floor", t)
        return True
    _bind(io, "_below_floor", below)


def _no_hello(rt: AgentRuntime) -> None:
    """A peer's first or restarted sync does not make the hello pending (AUTH-9)."""
    io = rt.io
    for name in ("_take_sync", "_join_sync", "_peer_sync"):
        def around(real: Callable[..., Any], *a: Any, **kw: Any) -> Any:
            due = io._hello_due
            out = real(*a, **kw)
            io._hello_due = due
            return out
        _wrap(io, name, around)


def _diag_shares_mc_count(rt: AgentRuntime) -> None:
    """The Diag frame signed with the MC frame's message count (AUTH-4: its own)."""
    io = rt.io
    mc, diag = (rt.codec.frame_id(n(rt.cfg.id)) for n in (mc_name, diag_name))

    def around(real: Callable[..., Any], name: str, raw: Any) -> Any:
        if rt.codec.frame_id(name) != diag:
            return real(name, raw)
        io._tx_count[diag] = io._tx_count[mc]
        out = real(name, raw)
        io._tx_count[mc] = io._tx_count[diag]
        return out
    _wrap(io, "send", around)


def _count_wraps_in_boot(rt: AgentRuntime) -> None:
    """A message count wraps to 0 in the same boot (AUTH-5: a new boot first)."""
    io = rt.io

    def around(real: Callable[..., Any], name: str, raw: Any) -> Any:
        fid = rt.codec.frame_id(name)
        if io._tx_count.get(fid, 0) > contract.FRESHNESS.max_counter:
            io._tx_count[fid] = 0
        return real(name, raw)
    _wrap(io, "send", around)


# --------------------------------------------------------------------------- witnesses

CODEC = FrameCodec()
MASTER = bytes(range(16))
KEYS = fleet_keys(MASTER, 4)  # node keys and link frame keys (AUTH-28)
BASE: AgentConfig = agent_configs_from_scenario(load_case(1))[2]  # case 1, agent 3
EXACT_TS = 2.0 ** -7  # Ts whose multiples are exact in binary64: boundaries hit exactly


def q(x: float) -> int:
    return round(x * (1 << fx.Q))


def config(ctrl: dict[str, Any] | None = None, **changes: Any) -> AgentConfig:
    """Case 1 agent 3's configuration with ``changes`` (the derived limits derived
    again unless given)."""
    derived: dict[str, Any] = dict.fromkeys(("lambda_step_max", "k_min", "k_max", "h_min",
                                             "h_max", "untrusted_s"))
    return replace(BASE, controller=replace(BASE.controller, **(ctrl or {})),
                   **{**derived, **changes})


class Rig:
    """One agent on a simulated clock, fed by hand: the tester's frames between ticks
    k and k + 1 at (k + frac)·Ts, the tick at (k + 0.9)·Ts. ``secure``: a fleet key set
    (syncs, join window, ``floors``), else the insecure keys (every input taken from
    boot 1 without a sync). Records what the agent sends."""

    def __init__(self, apply: Apply | None, secure: bool = False, floors: int = 0,
                 boot: int = 1, **changes: Any) -> None:
        self.cfg = config(**changes)
        node = f"agent_{self.cfg.id}"
        if secure:
            ring = Keyring(node, KEYS[node], 0, lambda _b: None, master=MASTER,
                           floors={n: floors for n in fleet_nodes(4) if n != node}
                           if floors else None)
            self.tx = FleetSender(CODEC, KEYS, boot=boot)
        else:
            ring = Keyring.insecure_for(node)
            self.tx = FleetSender(CODEC, None)
        self.rt = AgentRuntime(self.cfg, CODEC, keys=ring)
        if apply is not None:
            apply(self.rt)
        self.ts = self.cfg.controller.ts
        self.nbr = mc_name(self.cfg.neighbours[0].id)
        self.k = 0
        self.out: list[tuple[int, bytes]] = []
        self.first_sync: dict[str, can.Message] = {}

    def at(self, frac: float) -> float:
        return (self.k + frac) * self.ts

    def deliver(self, msg: can.Message, frac: float = 0.5, t: float | None = None
                ) -> can.Message:
        self.rt.on_frame(msg, self.at(frac) if t is None else t)
        return msg

    def price(self, rho: float = 0.8, valid: int = 1, frac: float = 0.25) -> can.Message:
        return self.deliver(self.tx.frame("ER_Price", {"PriceValid": valid, "Segment": 0,
                                                       "Rho": q(rho)}), frac)

    def status(self, frac: float = 0.75, **flags: int) -> can.Message:
        raw = {"FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
               "Power": 0, "Soc": 100, **flags}
        return self.deliver(self.tx.frame(status_name(self.cfg.id), raw), frac)

    def mc_frame(self, lam: float = 1.2, lsb: int = 0, state: State = State.RUNNING,
                 raw: int | None = None) -> can.Message:
        return self.tx.frame(self.nbr, {"State": int(state), "Resets": 0,
                                        "Lambda": q(lam) + lsb if raw is None else raw})

    def mc(self, lam: float = 1.2, lsb: int = 0, state: State = State.RUNNING,
           raw: int | None = None, frac: float = 0.5, t: float | None = None) -> can.Message:
        return self.deliver(self.mc_frame(lam, lsb, state, raw), frac, t)

    def command(self, cmd: Command, target: int | None = None, k: float = 0.0,
                h: float = 0.0) -> can.Message:
        return self.deliver(self.tx.frame("ER_Command", {
            "Command": int(cmd), "Target": target_raw(self.cfg.id if target is None else target),
            "GainK": round(k * 1000), "GainH": round(h * 1000)}), 0.6)

    def forged(self, msg: can.Message) -> can.Message:
        msg.data[0] ^= 0x5A
        return self.deliver(msg, 0.6)

    def skip(self, name: str, n: int) -> None:
        """``n`` frames of ``name`` the agent never receives (lost on the bus)."""
        for _ in range(n):
            self.tx.frame(name, self._zero(name))

    @staticmethod
    def _zero(name: str) -> dict[str, int]:
        if name.startswith("AGENT_"):
            return {"State": 1, "Lambda": q(1.2), "Resets": 0}
        return {"PriceValid": 1, "Segment": 0, "Rho": q(0.8)}

    def syncs(self, skip: tuple[str, ...] = ()) -> None:
        for name in ("ER_Price", "ER_Command", status_name(self.cfg.id), self.nbr):
            if name not in skip:
                self.first_sync.setdefault(name, self.deliver(self.tx.sync(name), 0.1))

    def secure_start(self, skip: tuple[str, ...] = ()) -> Rig:
        """The agent's hello, the tester's syncs, then the join window (AUTH-26) out."""
        self.tick()
        self.syncs(skip)
        while self.at(0.25) < 0.25 * contract.cycle_s("ER_Price_Sync", self.ts):
            self.tick()
        return self

    def tick(self, t: float | None = None) -> Rig:
        for m in self.rt.tick(self.at(0.9) if t is None else t):
            self.out.append((m.arbitration_id, bytes(m.data)))
        self.k += 1
        return self

    def run(self, n: int, rho: float = 0.8, lam: float = 1.2, lsb: int = 0,
            price: bool = True, status: bool = True, nbr: bool = True, valid: int = 1,
            state: State = State.RUNNING, **flags: int) -> Rig:
        """``n`` ticks with the price and the status every 5 ticks and the neighbour's
        MC every tick (each unless False)."""
        for _ in range(n):
            if price and self.k % 5 == 0:
                self.price(rho, valid)
            if nbr:
                self.mc(lam, lsb, state)
            if status and self.k % 5 == 0:
                self.status(**flags)
            self.tick()
        return self

    def observed(self) -> tuple[list[tuple[int, bytes]], dict[str, int]]:
        """What the agent sent, and what its Diag pages carry now (DIAG-2's saturation
        as on the wire; DeadlineMisses is the host's)."""
        values = self.rt.diag_values()
        values.pop("DeadlineMisses")
        return self.out, {k: min(v, self.rt._diag_max[k]) for k, v in values.items()}


def drive(script: Callable[[Rig], Any], **rig: Any) -> Callable[[Apply | None], Any]:
    """A witness: ``script`` run on a Rig (``rig``: its arguments); what it observed."""
    def witness(apply: Apply | None) -> Any:
        r = Rig(apply, **rig)
        script(r)
        return r.observed()
    return witness


def steps(xis: list[int], **rig: Any) -> Callable[[Apply | None], Any]:
    """A witness: ξ fed straight to the agent's controller; the states it goes through."""
    def witness(apply: Apply | None) -> Any:
        r = Rig(apply, **rig)
        s, out = r.rt.cstate, []
        for xi in xis:
            s, o = r.rt.ctrl.step(s, xi)
            out.append((s, o.reset))
        return out
    return witness


def _seq(*calls: Callable[[Rig], Any]) -> Callable[[Rig], None]:
    def script(r: Rig) -> None:
        for c in calls:
            c(r)
    return script


def _poke(**state: Any) -> Callable[[Rig], None]:
    def poke(r: Rig) -> None:
        r.rt.cstate = replace(r.rt.cstate, **state)
    return poke


def _to_running_then_silent(r: Rig, lam: float = 1.0) -> None:
    r.run(3, lam=lam)
    r.run(40, lam=lam, price=False)


def _entry_with_band(r: Rig) -> None:
    """Back to RUNNING disarmed (as after a reset with |ξ| inside the band since), then
    ξ inside the band on either side: a crossing no armed agent would reset on."""
    _to_running_then_silent(r, lam=1.2)  # ξ = 0: λ stays λ(0)
    r.rt.cstate = replace(r.rt.cstate, armed=False)
    r.price(0.8)
    r.mc(raw=r.rt.lambda_q24 - 1000)
    r.status()
    r.tick()
    r.mc(raw=r.rt.lambda_q24 + 1000)
    r.tick()


def _exact_neighbour_timeout(r: Rig, periods: float) -> None:
    r.run(4, lam=1.0)
    t_last = r.at(0.5)
    r.mc(1.0, t=t_last)
    r.tick()
    r.run(1, lam=1.0, nbr=False)
    r.tick(t=t_last + periods * r.ts)


def _exact_price_timeout(r: Rig) -> None:
    t_price = r.at(0.25)
    r.run(1)
    while r.at(0.9) < t_price + r.cfg.price_timeout_s:
        r.run(1, price=False)
    r.tick(t=t_price + r.cfg.price_timeout_s)


def _held_then_late(r: Rig) -> None:
    r.run(3)
    held = r.mc_frame()
    r.run(2)
    r.deliver(held, 0.6)
    r.tick()


def _neighbour_gap(r: Rig) -> None:
    r.run(3)
    r.run(5, nbr=False)       # timed out: its MC ID lost (LIVE-3)
    r.skip(r.nbr, 20)         # and 20 of its frames never reach the agent
    r.run(3)


def _replayed_sync(r: Rig) -> None:
    r.secure_start()
    r.run(20)
    r.deliver(can.Message(arbitration_id=r.first_sync[r.nbr].arbitration_id,
                          is_extended_id=False, data=bytes(r.first_sync[r.nbr].data)), 0.6)
    r.tick()


def _peer_restart(r: Rig) -> None:
    r.secure_start()
    r.run(30)
    r.tx.restart()
    r.syncs()
    r.run(5)


def _count_wrap(r: Rig) -> None:
    r.tick()
    r.rt.io._tx_count[CODEC.frame_id(mc_name(r.cfg.id))] = contract.FRESHNESS.max_counter
    r.tick().tick()


def _crossing_then_isolate(r: Rig) -> None:
    r.run(4, lam=1.22)         # ξ < 0
    r.run(4, lam=1.18)         # ξ > 0: a crossing, armed: a reset
    r.command(Command.ISOLATE)
    r.tick()


def _boot_not_incremented(rt: AgentRuntime) -> None:
    """The boot the start took given back: frames under the key file's counter."""
    rt.io.boot = rt.io.keys.boot = rt.io.keys.boot - 1


def filed_ring() -> Keyring:
    """Agent 3's keyring as read from a key file that says boot FILED_BOOT (what the
    tester writes, AUTH-3)."""
    from sim.conformance import FILED_BOOT

    return Keyring("agent_3", KEYS["agent_3"], FILED_BOOT, lambda _b: None, master=MASTER)


def sync_boots(frames: Iterable[can.Message]) -> list[Any]:
    """The Boot of each sync among ``frames``."""
    return [CODEC.decode(m).raw.get("Boot") for m in frames
            if m.arbitration_id in contract.SYNCED_BY]


def _boot_of_first_sync(apply: Apply | None) -> Any:
    """An agent whose key file says boot 6: the Boot of its syncs at its start."""
    rt = AgentRuntime(BASE, CODEC, keys=filed_ring())
    if apply is not None:
        apply(rt)
    return sync_boots(rt.tick(0.0))


# --------------------------------------------------------------------------- the set

ARITH, BOUND, CMDS, STATES, FRESH, DIAG = ("arithmetic", "boundary", "commands", "state",
                                           "freshness", "diagnostics")

FAULTS: list[Fault] = [
    # arithmetic at the edges: ties, saturation bounds, wrap-around, counted clamps
    Fault("mulq_ties_away", "NUM-2", "mulq rounds a tie away from zero (−1.5 LSB → −2), "
          "not toward +∞", _ar(_MulTiesAway), ARITH,
          drive(lambda r: r.run(5, lsb=3), neighbours=(Neighbour(1, 0.5),),
                ctrl={"kind": "pc", "k": 150.0}, k_max=150.0)),
    Fault("wire_truncates", "NUM-8", "the wire λ is the Q54 state truncated (x >> 30), "
          "not rounded", _ar(_NarrowFloor), ARITH, drive(lambda r: r.run(10, lam=1.0))),
    Fault("q24_truncates", "NUM-4", "configuration values go to Q24 by truncation, not "
          "rne (λ(0), band, limits, weights, the idle MC)", _q24_truncates, ARITH,
          steps([5000, -5000, 1678, -3000])),
    Fault("xi_wraps", "NUM-3", "ξ wraps around int32 instead of saturating", _ar(_SatWraps),
          ARITH, drive(lambda r: r.run(3, lam=-99.0), lambda0=99.0, lambda_min=-127.0,
                       lambda_max=127.0)),
    Fault("xi_sat_uncounted", "XI-3", "ξ saturates but the clamp is not counted in "
          "Saturations", _ar(_SatUncounted), ARITH,
          drive(lambda r: r.run(3, lam=-99.0), lambda0=99.0, lambda_min=-127.0,
                lambda_max=127.0)),
    Fault("own_lambda_clamped", "STEP-12", "the own λ is clamped to [lambda_min, "
          "lambda_max] after each step", _own_lambda_clamped, ARITH,
          drive(lambda r: r.run(3, lam=10.0), ctrl={"kind": "pc", "k": 150.0},
                k_max=150.0, lambda0=9.5)),
    Fault("setpoint_truncates", "SP-1", "the setpoint map truncates λ·G >> 40 instead of "
          "rounding", lambda rt: _swap(rt.setpoint, _SetpointFloor), ARITH,
          drive(lambda r: r.run(30, lam=1.0))),
    # pc's and ft's step (case 2's variants): their own rules of arithmetic
    Fault("ft_root_nearest", "NUM-5", "fpow's integer square root rounds to nearest, not "
          "down", _ar(_RootNearest), ARITH, steps([3, 50, -7], ctrl={"kind": "ft"})),
    Fault("ft_products_first", "CTRL-3", "fpow takes |ξ|^p first, then the n roots (a = "
          "3/4: |ξ|³ then two roots)", _ar(_PowProductsFirst), ARITH,
          steps([3, 50, -7], ctrl={"kind": "ft", "ft_exponent": 0.75})),
    Fault("ft_step_on_wire_grid", "STEP-11", "ft's Δλ rounded to Q24 before it is added "
          "(the step's guard bits lost)", _ctrl(_DeltaOnWireGrid, FiniteTimeController),
          ARITH, steps([3, 50, -7], ctrl={"kind": "ft"})),
    Fault("pc_step_on_wire_grid", "STEP-10", "pc's Δλ rounded to Q24 before it is added "
          "(the step's guard bits lost)", _ctrl(_DeltaOnWireGrid, ProportionalController),
          ARITH, steps([3, 50, -7], ctrl={"kind": "pc"})),
    # comparisons at exact boundaries
    Fault("band_rearm_ge", "BAND-3", "the band re-arms at |ξ| ≥ BAND (not >)",
          _ctrl(_RearmGe), BOUND, steps([5000, -5000, 1678, -3000])),
    Fault("crossing_zero_not", "STEP-2", "ξ = 0 after a non-zero ξprev is no crossing",
          _ctrl(_ZeroNoCrossing), BOUND, steps([5000, 0])),
    Fault("reset_ignores_band", "STEP-3", "every crossing resets, armed or not (plain "
          "Clegg)", _ctrl(_ResetUnarmed), BOUND, steps([5000, -5000, 100, -100])),
    Fault("dwell_strict", "DWELL-1", "the dwell lets a crossing reset only once "
          "since_reset > D (not ≥)", _ctrl(_DwellStrict, DwellResetPIController), BOUND,
          steps([5000, -5000, 5000, -5000, 5000], ctrl={"kind": "dwell", "dwell": 0.03})),
    Fault("nbr_timeout_strict", "LIVE-2", "a neighbour exactly neighbour_periods·Ts old "
          "is dead (< instead of ≤)",
          lambda rt: _bind(rt, "_update_neighbours", _update_neighbours, strict=True),
          BOUND, drive(lambda r: _exact_neighbour_timeout(r, 3), ctrl={"ts": EXACT_TS},
                       price_timeout_s=0.25, status_timeout_s=0.25)),
    Fault("nbr_timeout_one_more", "LIVE-2", "a neighbour dies one period late "
          "((neighbour_periods + 1)·Ts)",
          lambda rt: _bind(rt, "_update_neighbours", _update_neighbours, extra=1), BOUND,
          drive(lambda r: _exact_neighbour_timeout(r, 3.5))),
    Fault("price_timeout_strict", "STATE-2", "a price exactly price_s old is stale "
          "(< instead of ≤)", lambda rt: _swap(rt, _PriceStrict), BOUND,
          drive(_exact_price_timeout, ctrl={"ts": EXACT_TS}, price_timeout_s=0.25,
                status_timeout_s=0.25)),
    Fault("lam_step_ge", "LAM-1", "a neighbour λ step of exactly lambda_step_max is "
          "implausible (≥ instead of >)", lambda rt: _bind(rt, "_on_mc", _on_mc, ge=True),
          BOUND, drive(_seq(lambda r: r.run(3, lam=1.0),
                            lambda r: r.run(1, lam=1.0, lsb=q(0.1)), lambda r: r.run(2)))),
    Fault("price_step_ge", "PRICE-3", "a price step of exactly price_step_max is "
          "checked as a step (≥ instead of >)",
          lambda rt: _bind(rt, "_on_price", _on_price, ge=True), BOUND,
          drive(_seq(lambda r: r.run(3), lambda r: r.run(6, rho=1.3)), pinned=True)),
    Fault("price_persist_early", "PRICE-4", "a new price level is accepted one frame "
          "early (at price_persist − 1 frames)",
          lambda rt: _bind(rt, "_on_price", _on_price, persist_less=1), BOUND,
          drive(_seq(lambda r: r.run(5), lambda r: r.run(10, rho=1.5)), pinned=True)),
    Fault("persist_one_candidate_first", "PRICE-5", "with price_persist = 1 a price step is "
          "a candidate first, taken at its second frame",
          lambda rt: _bind(rt, "_on_price", _on_price, candidate_first=True), BOUND,
          drive(_seq(lambda r: r.run(5), lambda r: r.run(10, rho=1.5)), pinned=True,
                price_persist=1)),
    Fault("untrusted_after_gt", "RX-13", "the untrusted verdict at the (untrusted_after "
          "+ 1)-th failure", _untrusted_after_gt, BOUND,
          drive(_seq(lambda r: r.run(2),
                     *[lambda r: r.forged(r.tx.frame("ER_Price", r._zero("ER_Price")))] * 5,
                     lambda r: r.run(2)))),
    # commands at their limits
    Fault("gains_bounds_exclusive", "CMD-5", "SET_GAINS bounds exclusive: k = k_max "
          "exactly is refused", lambda rt: _bind(rt, "_on_command", _on_command,
                                                 exclusive=True), CMDS,
          drive(_seq(lambda r: r.run(2), lambda r: r.command(Command.SET_GAINS, k=2.0,
                                                             h=2.0), lambda r: r.run(3)))),
    Fault("gains_truncated", "CMD-5", "SET_GAINS' KTS and HTS truncated (raw·TSQ div D), "
          "not rounded half up", lambda rt: setattr(
              rt, "_gain_q30", lambda raw: (raw * int(rt.ctrl.ts_q)) // GAIN_DIV), CMDS,
          drive(_seq(lambda r: r.run(2, lam=-99.0), lambda r: r.command(
              Command.SET_GAINS, k=1.234, h=2.0), lambda r: r.run(3, lam=-99.0)),
                lambda0=99.0, lambda_min=-127.0, lambda_max=127.0)),
    Fault("gains_keep_nu", "CMD-5", "an accepted SET_GAINS keeps ν (it must zero it)",
          _gains_keep_nu, CMDS,
          drive(_seq(lambda r: r.run(5, lam=1.0), lambda r: r.command(
              Command.SET_GAINS, k=1.5, h=3.0), lambda r: r.run(3, lam=1.0)))),
    Fault("gains_bounds_as_range", "CMD-5", "SET_GAINS outside the bounds is filed under "
          "range, not implausible_gains",
          lambda rt: _bind(rt, "_on_command", _on_command, bounds_cause="range"), CMDS,
          drive(_seq(lambda r: r.run(2), lambda r: r.command(Command.SET_GAINS, k=3.0,
                                                             h=2.0), lambda r: r.tick()))),
    Fault("command_any_target", "CMD-1", "a command for another agent is taken as its own "
          "(Target not checked): verified under its own command key, so `auth` (AUTH-30)",
          _any_target,
          CMDS, drive(_seq(lambda r: r.run(2), lambda r: r.command(Command.ISOLATE, 1),
                           lambda r: r.tick()))),
    # state entry and exit
    Fault("isolate_keeps_counters", "STATE-7", "ISOLATE keeps resets and ctrl_sats (they "
          "restart at 0)", _isolate_keeps_counters, STATES, drive(_crossing_then_isolate)),
    Fault("isolate_only_running", "STATE-7", "ISOLATE is obeyed only in RUNNING (not in "
          "INIT or SAFE)", lambda rt: _bind(rt, "_on_command", _on_command,
                                           isolate_from=(State.RUNNING,)), STATES,
          drive(_seq(lambda r: r.tick(), lambda r: r.command(Command.ISOLATE),
                     lambda r: r.tick()))),
    Fault("reconnect_any_state", "STATE-8", "RECONNECT moves any state to INIT (it acts "
          "only in ISOLATED)", _reconnect_any_state, STATES,
          drive(_seq(lambda r: r.run(5, lam=1.0), lambda r: r.command(Command.RECONNECT),
                     lambda r: r.run(3, lam=1.0)))),
    Fault("isolated_goes_safe", "STATE-9", "a stale input moves ISOLATED to SAFE",
          lambda rt: _bind(rt, "_update_state", _update_state,
                           safe_from=(State.RUNNING, State.ISOLATED)), STATES,
          drive(_seq(lambda r: r.run(2), lambda r: r.command(Command.ISOLATE),
                     lambda r: r.run(40, price=False)))),
    Fault("isolated_no_timeouts", "TMO-2", "no price or status timeout is counted while "
          "ISOLATED", lambda rt: _bind(rt, "_update_inputs", _update_inputs,
                                      isolated_quiet=True), STATES,
          drive(_seq(lambda r: r.run(2), lambda r: r.command(Command.ISOLATE),
                     lambda r: r.run(40, price=False)))),
    Fault("init_goes_safe", "STATE-5", "INIT goes to SAFE when an input is stale",
          lambda rt: _bind(rt, "_update_state", _update_state,
                           safe_from=(State.RUNNING, State.INIT)), STATES,
          drive(lambda r: r.tick().tick())),
    Fault("entries_keep_nu", "STATE-3", "entering SAFE and RUNNING keeps ν and ξprev",
          lambda rt: _bind(rt, "_update_state", _update_state, zero=False), STATES,
          drive(_seq(_to_running_then_silent, lambda r: r.run(5, lam=1.0)))),
    Fault("running_entry_rearms", "STATE-6", "entering RUNNING re-arms the band and "
          "restarts since_reset", lambda rt: _bind(rt, "_update_state", _update_state,
                                                   rearm=True), STATES,
          drive(_entry_with_band)),
    Fault("safe_setpoint_enabled", "SP-3", "the setpoint stays enabled in SAFE (λ held, "
          "so P held)", lambda rt: _bind(rt, "_setpoint_frame", _setpoint_frame), STATES,
          drive(_to_running_then_silent)),
    # the freshness machinery
    Fault("candidate_lt", "AUTH-12", "the candidate adds a window only when c < (last & "
          "15): a frame 16 values on fails", lambda rt: _swap(rt.io._fv, _CandidateLt),
          FRESH, drive(_seq(lambda r: r.run(3), lambda r: r.skip(r.nbr, 15),
                            lambda r: r.run(3)))),
    Fault("lost_one_window", "AUTH-13", "a lost ID is tried in one window, not 8",
          lambda rt: _swap(rt.io._fv, _OneWindow), FRESH, drive(_neighbour_gap)),
    Fault("accept_keeps_lost", "AUTH-15", "an accepted frame does not clear the lost "
          "flag", _accept_keeps_lost, FRESH,
          drive(_seq(lambda r: r.run(3), lambda r: r.forged(r.mc_frame()),
                     lambda r: r.tick()))),
    Fault("stale_is_auth", "AUTH-25", "a genuine frame delivered late is auth, not stale",
          lambda rt: _swap(rt.io._fv, _NoStale), FRESH, drive(_held_then_late)),
    Fault("replayed_sync_stale", "AUTH-16", "a sync 16 or more values behind is taken "
          "for a late one (stale), not a replay (auth)",
          lambda rt: _swap(rt.io._fv, _SyncAlwaysLate), FRESH,
          drive(_replayed_sync, secure=True)),
    Fault("in_step_sync_counted", "AUTH-16", "a sync in step with the last accepted "
          "value counts a resync", _in_step_sync_counted, FRESH,
          drive(_seq(lambda r: r.secure_start(), lambda r: r.run(5),
                     lambda r: r.deliver(r.tx.sync(r.nbr), 0.6), lambda r: r.tick()),
                secure=True)),
    Fault("floor_inclusive", "AUTH-21", "a sync at its sender's boot floor is refused "
          "(only below it must be)", _floor_inclusive, FRESH,
          drive(_seq(lambda r: r.secure_start(), lambda r: r.run(3)), secure=True,
                floors=1)),
    Fault("no_hello", "AUTH-9", "a peer's first or restarted sync does not make the "
          "agent's own syncs due (no hello)", _no_hello, FRESH,
          drive(_peer_restart, secure=True)),
    Fault("unsynced_is_auth", "AUTH-11", "a frame of an ID with no freshness state is "
          "auth, not unsynced", _unsynced_is_auth, FRESH,
          drive(_seq(lambda r: r.secure_start(skip=("ER_Price",)), lambda r: r.run(3)),
                secure=True)),
    Fault("diag_shares_mc_count", "AUTH-4", "the Diag frame is signed with the MC "
          "frame's message count, not its own", _diag_shares_mc_count, FRESH,
          drive(lambda r: r.run(11))),
    Fault("boot_not_incremented", "AUTH-3", "the key file's boot counter used as it is at "
          "the start (B, not B + 1: the last run's freshness values again)",
          _boot_not_incremented, FRESH, _boot_of_first_sync),
    Fault("count_wraps_in_boot", "AUTH-5", "a message count wraps to 0 in the same boot "
          "(no new boot)", _count_wraps_in_boot, FRESH, drive(_count_wrap)),
    # the diagnostics
    Fault("diag_wraps", "DIAG-2", "Diag counters wrap at their width instead of "
          "saturating", lambda rt: _bind(rt, "_diag_frame", _diag_frame), DIAG,
          drive(_seq(_poke(resets=70000), lambda r: r.tick()))),
    Fault("gains_no_last_safety", "DIAG-4", "an implausible_gains rejection is not "
          "recorded as the last safety event", _gains_no_last_safety, DIAG,
          drive(_seq(lambda r: r.run(2), lambda r: r.command(Command.SET_GAINS, k=3.0,
                                                             h=2.0), lambda r: r.tick()))),
    Fault("plant_fault_level", "RX-11", "plant_faults counts every faulty status, not the "
          "false → true changes", lambda rt: _bind(rt, "_on_status", _on_status,
                                                   level=True), DIAG,
          drive(_seq(lambda r: r.run(2), lambda r: r.run(15, FaultOverCurrent=1)))),
    Fault("soc_is_fault", "RX-11", "FaultSoc is taken for a plant fault (SAFE)",
          lambda rt: _bind(rt, "_on_status", _on_status, soc_fault=True), DIAG,
          drive(_seq(lambda r: r.run(2), lambda r: r.run(10, FaultSoc=1)))),
    Fault("extended_is_malformed", "RX-1", "an extended ID is filed under malformed, not "
          "unknown_id", _extended_is_malformed, DIAG,
          drive(_seq(lambda r: r.run(2), lambda r: r.deliver(can.Message(
              arbitration_id=0x103, is_extended_id=True, data=bytes(8))),
              lambda r: r.tick()))),
    Fault("timeouts_unheard", "TMO-3", "an input never received counts a timeout (fresh "
          "at start)", _fresh_at_start, DIAG,
          drive(lambda r: r.tick())),
    Fault("price_invalid_refreshes", "PRICE-1", "a PriceValid = 0 frame keeps the price "
          "fresh", lambda rt: _bind(rt, "_on_price", _on_price, valid0_fresh=True), DIAG,
          drive(_seq(lambda r: r.run(2), lambda r: r.run(40, valid=0)))),
    Fault("implausible_lambda_kept", "LIVE-1", "a neighbour λ rejected as implausible is "
          "still stored", lambda rt: _bind(rt, "_on_mc", _on_mc, keep_rejected=True), DIAG,
          drive(_seq(lambda r: r.run(3, lam=1.0), lambda r: r.run(3, lam=1.5)))),
    Fault("xi_any_state", "XI-1", "ξ takes every alive neighbour, whatever the State its "
          "frames carry", lambda rt: _bind(rt, "xi_terms", _xi_any_state), DIAG,
          drive(lambda r: r.run(5, lam=1.0, state=State.SAFE))),
]

# ------------------------------------ runs that exercise more (ONLY_ON): --resilient, --insecure

Pair = tuple[int, int]  # (weight, λ_j) in Q24, as the runtime's ξ takes them


def _light_first(lam: int, pairs: list[Pair], f: int) -> list[Pair]:
    """W-MSR with WMSR-2's tie the wrong way: of equal λ_j the smaller weight trimmed."""
    above = sorted((p for p in pairs if p[1] > lam), key=lambda p: (p[1], -p[0]), reverse=True)
    below = sorted((p for p in pairs if p[1] < lam), key=lambda p: (-p[1], -p[0]),
                   reverse=True)
    return above[f:] + below[f:] + [p for p in pairs if p[1] == lam]


def ties_light_first(rt: AgentRuntime) -> None:
    """Plants WMSR-2's tie the wrong way (the trimming done before ξ, F kept)."""
    f, own = rt.cfg.resilient_f, rt.xi_terms
    rt.cfg = replace(rt.cfg, resilient_f=0)  # the trimming done here, before ξ
    rt.xi_terms = lambda: _light_first(  # type: ignore[method-assign]
        rt.lambda_q24, own(), f)


def no_trimming(rt: AgentRuntime) -> None:
    """Plants a device that does not trim (resilient_f taken as 0)."""
    rt.cfg = replace(rt.cfg, resilient_f=0)


def _insecure_keeps_replay_rule(rt: AgentRuntime) -> None:
    rt.io.keys.insecure = False  # the public keys, a keyed node's sync rules


def _two_neighbours_equal(r: Rig) -> None:
    """Both neighbours at the same λ (a tie on one side of Λ: WMSR-2), into RUNNING."""
    other = mc_name(r.cfg.neighbours[1].id)
    for _ in range(20):
        if r.k % 5 == 0:
            r.price()
        r.mc(1.5)
        r.deliver(r.tx.frame(other, {"State": int(State.RUNNING), "Resets": 0,
                                     "Lambda": q(1.5)}), 0.55)
        if r.k % 5 == 0:
            r.status()
        r.tick()


FAULTS += [
    Fault("wmsr_not_applied", "WMSR-1", "the resilient update is not applied: ξ over every "
          "alive neighbour although resilient_f = F > 0", no_trimming, ARITH,
          drive(lambda r: r.run(20, lam=1.5), resilient_f=1)),
    Fault("wmsr_ties_light_first", "WMSR-2", "of neighbours at the same λ_j the one with the "
          "smaller weight is trimmed first", ties_light_first, ARITH,
          drive(_two_neighbours_equal, resilient_f=1,
                neighbours=(Neighbour(2, 1.0), Neighbour(4, 2.0)))),
    Fault("insecure_refuses_replay", "AUTH-20", "with --insecure a sync that goes back is "
          "refused as a replay, not taken as a restarted sender's", _insecure_keeps_replay_rule,
          FRESH, drive(_replayed_sync)),
]

# ---------------------------------------------------- the signed price (--signed-price)


class _SegmentIgnored(pricesig.PriceSigReceiver):
    """AUTH-33's comparison without the Segment."""

    def check(self, raw: dict[str, int]) -> str | None:
        cur = self.current
        return (None if cur is not None and (raw["PriceValid"], raw["Rho"]) == (cur.valid,
                                                                               cur.rho)
                else "unsigned")


class _OlderTaken(pricesig.PriceSigReceiver):
    """AUTH-32 without the replay rule: a verified signature is held, older or not."""

    def take(self, raw: dict[str, Any], min_boot: int = 0) -> tuple[str, str] | None:
        held, self.current = self.current, None
        refused = super().take(raw, 0)
        if self.current is None:
            self.current = held
        return refused


class _PageOverwritten(pricesig.PriceSigReceiver):
    """A page repeated with other bytes overwrites the first (an array per page)."""

    def take(self, raw: dict[str, Any], min_boot: int = 0) -> tuple[str, str] | None:
        if raw["Page"] and self._header is not None:
            self._parts.pop(raw["Page"], None)
        return super().take(raw, min_boot)


class _LastPageTruncated(pricesig.PriceSigReceiver):
    """The last page's bytes past the signature ignored, not refused."""

    def take(self, raw: dict[str, Any], min_boot: int = 0) -> tuple[str, str] | None:
        if raw["Page"] == pricesig.SIG_PAGES:
            raw = {**raw, "Signature": raw["Signature"] & 0xFF}
        return super().take(raw, min_boot)


def _receiver(kind: type) -> Apply:
    def apply(rt: AgentRuntime) -> None:
        rt.price_sig = kind(rt.price_sig.public, rt.price_sig.fleet)
    return apply


def _price_checked_after_freshness(rt: AgentRuntime) -> None:
    """AUTH-33's check after the MAC and freshness: a refused price moves the count."""
    rt.io._prechecks.clear()
    on_price = rt._on_price

    def checked(f: Any, t: float) -> None:
        refused = rt._signed_price(f)
        if refused is not None:
            rt.io.reject(*refused)
            return
        on_price(f, t)
    rt._on_price = checked  # type: ignore[method-assign]


def signed_setup() -> tuple[AgentConfig, Keyring]:
    """Case 1 agent 3 with signed_price, on the demo keys with the demo master's price key."""
    cfg = config(signed_price=True)
    ring = Keyring.insecure_for(f"agent_{cfg.id}")
    ring.price_verify = pricesig.public_key(secoc.derive_price_sign_key(secoc.INSECURE_MASTER))
    return cfg, ring


def signed_feed(agent: Any) -> dict[str, int]:
    """``agent`` (``signed_setup``'s; firmware_py's runtime or the C agent) fed the router's
    signed price, a key holder's refused prices (the schedule's, 8 counts ahead) and the
    router's next price: its rejection counters."""
    from sim.conformance.schedule import _PriceSigner

    tx, signer = FleetSender(CODEC, None), _PriceSigner(CODEC, None, INSECURE_BOOT)
    insider = FleetSender(CODEC, None)
    frames = [*signer.before(1, q(0.8)), tx.frame("ER_Price", {"PriceValid": 1, "Segment": 0,
                                                               "Rho": q(0.8)})]
    insider.follow("ER_Price", INSECURE_BOOT, tx.next_count("ER_Price") + 7)
    frames += [m for _, burst, _ in signer.refused(insider) for m in burst]
    frames.append(tx.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": q(0.8)}))
    for n, msg in enumerate(frames):
        agent.on_frame(msg, n * 1e-3)
    counters = agent.io.counters if isinstance(agent, AgentRuntime) else agent.counters
    return {k: v for k, v in counters.items() if v}


def _signed_witness(apply: Apply | None) -> dict[str, int]:
    cfg, ring = signed_setup()
    rt = AgentRuntime(cfg, CODEC, keys=ring)
    if apply is not None:
        apply(rt)
    return signed_feed(rt)


FAULTS += [
    Fault("signed_segment_ignored", "AUTH-33", "an ER_Price is taken when its PriceValid "
          "and ρ are the signed segment's, whatever its Segment", _receiver(_SegmentIgnored),
          FRESH, _signed_witness),
    Fault("signed_checked_after_freshness", "AUTH-33", "the signed-price check comes after "
          "the MAC and freshness: a key holder's refused price moves the router's count",
          _price_checked_after_freshness, FRESH, _signed_witness),
    Fault("signature_older_taken", "AUTH-32", "a genuine signature of an older segment is "
          "held (no replay rule)", _receiver(_OlderTaken), FRESH, _signed_witness),
    Fault("signature_page_overwritten", "AUTH-32", "a signature page repeated with other "
          "bytes overwrites the first (not sig_malformed)", _receiver(_PageOverwritten),
          FRESH, _signed_witness),
    Fault("signature_last_page_truncated", "AUTH-32", "bytes past the signature in its last "
          "page are ignored (not sig_malformed)", _receiver(_LastPageTruncated), FRESH,
          _signed_witness),
]

# --------------------------------------------- event-triggered sending (--event-transmit)


def _mc_due(rt: AgentRuntime, late: int = 0, state: bool = True, keep_age: bool = False,
            last_tick: bool = False) -> bool:
    """TX-7's decision with a slip: the heartbeat ``late`` ticks late, a State change not
    sent (not ``state``), the age kept on a threshold send (``keep_age``), or λ compared
    with the last tick's instead of the last sent (``last_tick``)."""
    tx, lam = rt.cfg.transmit, rt.lambda_q24
    last, age = rt.transmit_memory()
    age += 1
    quiet = (last is not None and age < tx.heartbeat + late
             and (last[1] == rt.state or not state)
             and abs(lam - last[0]) <= tx.threshold_q24)
    if quiet:
        rt.adopt_transmit((lam, rt.state) if last_tick else last, age)
        return False
    rt.adopt_transmit((lam, rt.state), age if keep_age and age < tx.heartbeat else 0)
    return True


def _event_witness(r: Rig) -> None:
    """An event-triggered agent: settled at λ(0) (heartbeats only), then drifting at a
    third of the threshold a tick (a frame every few ticks), then the price gone (SAFE:
    a State change)."""
    r.run(40, lam=1.2)
    r.run(20, lam=1.206)
    r.run(40, lam=1.206, price=False)


EVENT = {"transmit": Transmit("event"), "neighbour_timeout_periods": 15}

FAULTS += [
    Fault("event_heartbeat_late", "TX-7", "in event mode the heartbeat goes one tick late "
          "(age ≤ heartbeat still quiet)", lambda rt: _bind(rt, "_mc_due", _mc_due, late=1),
          STATES, drive(_event_witness, **EVENT)),
    Fault("event_state_change_unsent", "TX-7", "in event mode a State change is not sent at "
          "once (only λ's threshold and the heartbeat)",
          lambda rt: _bind(rt, "_mc_due", _mc_due, state=False), STATES,
          drive(_event_witness, **EVENT)),
    Fault("event_age_kept", "TX-7", "in event mode a frame sent for λ's threshold leaves the "
          "heartbeat's count running", lambda rt: _bind(rt, "_mc_due", _mc_due, keep_age=True),
          STATES, drive(_event_witness, **EVENT)),
    Fault("event_threshold_per_tick", "TX-7", "in event mode λ is compared with the last "
          "tick's λ, not with the λ last sent (a slow drift never sent)",
          lambda rt: _bind(rt, "_mc_due", _mc_due, last_tick=True), STATES,
          drive(_event_witness, **EVENT)),
]

# ----------------------------------------------------------- the configuration path (item 4)

CONFIG = "configuration"


def _dropping(table: str, key: str) -> Callable[[str], AgentConfig]:
    """A parser that never reads ``table.key`` (a misspelt or forgotten key): the default."""
    def parse(text: str) -> AgentConfig:
        data = tomllib.loads(text)
        data[table].pop(key, None)
        return parse_agent_config(data, "<misread>")
    return parse


def _weights_default(text: str) -> AgentConfig:
    """A parser that reads each [[neighbour]]'s id but not its weight (1.0)."""
    data = tomllib.loads(text)
    data["neighbour"] = [{"id": nb["id"]} for nb in data.get("neighbour", [])]
    return parse_agent_config(data, "<misread>")


def _periods_rounded(text: str) -> AgentConfig:
    """neighbour_periods rounded to the nearest integer, not truncated (CFG-6: 4.7 → 5)."""
    data = tomllib.loads(text)
    t = data.get("timeouts", {})
    if "neighbour_periods" in t:
        t["neighbour_periods"] = int(t["neighbour_periods"] + 0.5)
    return parse_agent_config(data, "<misread>")


def _ts_whole_ns(text: str) -> AgentConfig:
    """Ts kept as a whole number of ns (the loop's period) and TSQ taken from that."""
    data = tomllib.loads(text)
    c = data["controller"]
    c["ts"] = round(c.get("ts", 0.01) * 1e9) / 1e9
    return parse_agent_config(data, "<misread>")


def _reading(parse: Callable[[str], AgentConfig], base: AgentConfig | None = None
             ) -> Callable[[Apply | None], Any]:
    """A witness of a configuration fault: the tester's file for case 1, agent 3 (or
    ``base``) as the faulty parser reads it (the fault's ``apply``) or as the reference
    does (None)."""
    def witness(apply: Apply | None) -> Any:
        from sim import conformance as conf

        text, ref = conf.written_config(base or BASE)
        got = ref if apply is None else parse(text)
        return replace(got, source="")
    return witness


def _config_fault(name: str, requirement: str, description: str,
                  parse: Callable[[str], AgentConfig], base: AgentConfig | None = None
                  ) -> Fault:
    return Fault(name, requirement, description, lambda rt: None, CONFIG,
                 _reading(parse, base), misread=parse)


EVENT_BASE = replace(BASE, transmit=Transmit("event"))  # as --event-transmit writes it


def _heartbeat_default(text: str) -> AgentConfig:
    """transmit.heartbeat never read: the default 13 (the device's loader does not check
    it against neighbour_periods, as the reference does)."""
    cfg = parse_agent_config(tomllib.loads(text), "<misread>")
    return replace(cfg, transmit=replace(cfg.transmit, heartbeat=Transmit().heartbeat))


FAULTS += [
    _config_fault("cfg_heartbeat_default", "CFG-9", "transmit.heartbeat is never read: the "
                  "default 13, not the file's value", _heartbeat_default, EVENT_BASE),
    _config_fault("cfg_threshold_default", "CFG-9", "transmit.threshold is never read: the "
                  "default 3e-4, not the file's value", _dropping("transmit", "threshold"),
                  EVENT_BASE),
    _config_fault("cfg_untrusted_after_default", "CFG-7", "limits.untrusted_after is never "
                  "read (a misspelt key): the default 5, not the file's value",
                  _dropping("limits", "untrusted_after")),
    _config_fault("cfg_price_s_default", "CFG-6", "timeouts.price_s is never read: the "
                  "default 5 price cycles, not the file's value",
                  _dropping("timeouts", "price_s")),
    _config_fault("cfg_weights_default", "CFG-4", "the [[neighbour]] weight is never read: "
                  "every a_ij = 1.0", _weights_default),
    _config_fault("cfg_k_max_default", "CFG-7", "limits.k_max is never read: the default "
                  "2·k, not the file's bound", _dropping("limits", "k_max")),
    _config_fault("cfg_periods_rounded", "CFG-6", "timeouts.neighbour_periods rounded to "
                  "the nearest integer, not truncated (4.7 → 5, not 4)", _periods_rounded),
    _config_fault("cfg_ts_whole_ns", "CFG-3", "the period kept in whole ns and Ts (its Q30 "
                  "word TSQ) taken from it, not from the file's ts", _ts_whole_ns),
]

BY_NAME = {f.name: f for f in FAULTS}
assert len(BY_NAME) == len(FAULTS), "fault names must be unique"


# --------------------------------------------------------------------------- scoring

SCHEDULE_KEYS = fleet_keys(MASTER, 12)
PRICE_SEED = secoc.derive_price_sign_key(MASTER)  # the router's (signed_price, AUTH-31)
# a device that meets a condition of ``ONLY_ON`` (case, agent), where case 1's agent 3
# does not: a dwell device, one of more than F = 1 neighbours
ON_DEVICE = {"dwell": (6, 3), "resilient ties": (7, 5), "pc": (2, 3), "ft": (2, 3)}
# the conditions a run option sets up (``schedule_setup``'s ``run``) → that option
# the runs on one of case 2's variants (a pc or an ft device) → the variant's label
VARIANT_OF = {"pc": "PC", "ft": "finite-time"}
RUN_OPTIONS = {"resilient": "--resilient 1", "resilient ties": "--resilient 1",
               "insecure": "--insecure", "persist 1": "--price-persist 1",
               "signed price": "--signed-price", "event": "--event-transmit",
               **{run: f"--variant {label}" for run, label in VARIANT_OF.items()}}


def played_on(fault: Any, case: int, dut: int) -> tuple[int, int, str]:
    """Where ``score`` plays ``fault``: (case, agent, run). ``run``: the condition of
    ``ONLY_ON`` its requirement is exercised under, where a run option sets it up (""
    for most; "resilient…": the run with --resilient 1, "insecure": with --insecure),
    on agent ``dut`` of ``case`` if that device meets it, else on ``ON_DEVICE``'s."""
    from sim import conformance as conf

    on = conf.ONLY_ON.get(fault.requirement, "") if fault is not None else ""
    if on in ON_DEVICE and on not in conf.exercised_on(_run_config(case, dut, on)[1], False,
                                                       False):
        case, dut = ON_DEVICE[on]
    # (the flood is the exact timing's: ``score``'s ``exact``, a run of its own)
    return case, dut, on if on in RUN_OPTIONS else ""


def _run_config(case: int, dut: int, run: str = "") -> tuple[str, AgentConfig]:
    """The configuration file the tester writes for agent ``dut`` of ``case`` on ``run``
    (``RUN_OPTIONS``: --resilient 1 for a "resilient…" run, --price-persist 1,
    --signed-price, --event-transmit, case 2's variant PC or finite-time for a "pc" or
    "ft" run) and the reference parser's reading of it."""
    from sim import conformance as conf

    sc = load_case(case)
    if VARIANT_OF.get(run) in {v.label for v in sc.variants}:  # pc, ft: case 2's variant
        sc = sc.variant(VARIANT_OF[run])
    agent = agent_configs_from_scenario(sc)[dut - 1]
    if run.startswith("resilient"):
        agent = replace(agent, resilient_f=1)
    if run == "signed price":
        agent = replace(agent, signed_price=True)
    if run == "event":
        agent = replace(agent, transmit=Transmit("event"))
    return conf.written_config(agent, 1 if run == "persist 1" else conf.PRICE_PERSIST)


def schedule_setup(case: int, dut: int, flood: bool = False, run: str = ""
                   ) -> tuple[AgentConfig, Callable[[], Keyring], list[Any]]:
    """The conformance run of tests/test_conformance.py: scenario ``case`` with the device
    in agent ``dut``'s place, a fleet key set with every peer's floor at boot 2 (as `up`
    writes them), the tester at boot 2; ``run`` "insecure": the public keys, every sender
    at boot 1 (--insecure), "resilient…": with --resilient 1."""
    from sim import conformance as conf

    sc = load_case(case)
    _, cfg = _run_config(case, dut, run)
    node = f"agent_{dut}"
    if run == "insecure":
        return cfg, lambda: Keyring.insecure_for(node), conf.plan(
            cfg, None, sc.prices[0].rho, boot=INSECURE_BOOT, flood=flood)

    # with --signed-price the tester signs as the router (the master's price key)
    sign = {pricesig.TESTER_SIGN: PRICE_SEED, pricesig.MONITOR_FLEET: bytes.fromhex(
        secoc.fleet_id(MASTER))} if cfg.signed_price else {}

    def ring() -> Keyring:  # the key file's counter as the tester writes it (AUTH-3)
        return Keyring(node, SCHEDULE_KEYS[node], conf.FILED_BOOT, lambda _b: None,
                       master=MASTER,
                       floors={n: 2 for n in fleet_nodes(12) if n != node},
                       price_verify=pricesig.public_key(PRICE_SEED) if sign else None,
                       fleet=secoc.fleet_id(MASTER) if sign else "")

    return cfg, ring, conf.plan(cfg, {**SCHEDULE_KEYS, **sign}, sc.prices[0].rho, boot=2,
                                flood=flood)


def schedule_text(case: int, dut: int, run: str = "") -> str:
    """The configuration file the tester writes for ``schedule_setup``'s device."""
    return _run_config(case, dut, run)[0]


@dataclass
class Score:
    """One fault against the schedule. ``failed``: the requirements the verdict fails, in
    its order (the report's FAIL lines, the first divergence's first); ``unexercised``:
    those of them failed only as "not exercised" (the device's frames ended before their
    step); ``first_diff``: the requirements the first difference alone fails (what the
    report would name if that were all)."""

    fault: str
    requirement: str
    group: str
    case: int
    dut: int
    run: str  # the condition of ONLY_ON the run meets ("": the default run; played_on)
    failed: list[str]
    unexercised: list[str]
    first_diff: list[str]
    problems: list[str]
    explained_by: list[str]
    first_mismatch: str
    seconds: float

    @property
    def caught(self) -> bool:
        return bool(self.failed or self.problems)

    @property
    def named_first(self) -> bool:
        return bool(self.failed) and self.failed[0] == self.requirement

    @property
    def named(self) -> bool:
        return self.requirement in self.failed

    @property
    def named_by_first_diff(self) -> bool:
        return self.requirement in self.first_diff


def score(fault: Any, case: int = 1, dut: int = 3, jitter: float = 0.3,
          seed: int = 0, make_dut: Callable[..., Any] | None = None,
          dut_from_text: Callable[[str], Callable[..., Any]] | None = None,
          exact: bool = False, run: str = "") -> Score:
    """Play the schedule in process against the agent with ``fault`` (None: none) and
    judge it as `bess-ded conformance` does (check, explain, verdict). ``make_dut``: the
    device, as ``simulate`` takes it (tests/conformance_faults_c.py: the C agent on a
    library with the fault built in; then ``fault`` only names it, nothing is planted);
    ``dut_from_text``: the device given the configuration file the tester writes (the C
    agent reads it with its own loader). A fault with ``misread``: firmware_py's agent
    configured from that file as the faulty parser reads it. ``exact``: the device's
    clock trusted (``simulate`` and ``check`` with ``exact``: no timing tolerance);
    ``run``: the faultless agent's run (``played_on``; a fault's is its own)."""
    import time

    from sim import conformance as conf

    start = time.perf_counter()
    if fault is not None:
        case, dut, run = played_on(fault, case, dut)
    cfg, ring, planned = schedule_setup(case, dut, exact, run)  # in process: a flood
    text = schedule_text(case, dut, run)
    if dut_from_text is not None:
        make_dut = dut_from_text(text)
    misread = getattr(fault, "misread", None)
    if misread is not None and make_dut is None:
        dut_cfg = misread(text)
        make_dut = lambda _c, codec, k: AgentRuntime(dut_cfg, codec, keys=k)  # noqa: E731
    frames = conf.simulate(cfg, ring(), planned,
                           None if fault is None or make_dut is not None else fault.apply,
                           jitter=jitter, seed=seed, make_dut=make_dut, exact=exact)
    key = ring().key
    outcome = conf.check(cfg, ring(), key, frames, exact=exact)
    conf.explain(cfg, ring(), key, frames, outcome, config_text=text)
    results = conf.verdict(outcome)
    first = conf.Outcome(mismatches=outcome.mismatches[:1],
                         auth_errors=[] if outcome.mismatches else outcome.auth_errors[:1],
                         explained_by=dict(outcome.explained_by),
                         steps_seen={s.name for s in conf.STEPS}, exercised_on=outcome.exercised_on)
    return Score("none" if fault is None else fault.name,
                 "" if fault is None else fault.requirement,
                 "" if fault is None else fault.group, case, dut, run,
                 [r.must for r in results if not r.passed],
                 [r.must for r in results if not r.passed
                  and r.detail.startswith("not exercised")],
                 [r.must for r in conf.verdict(first) if not r.passed],
                 list(outcome.problems), sorted(outcome.explained_by),
                 str(outcome.mismatches[0]) if outcome.mismatches else
                 (outcome.auth_errors[0] if outcome.auth_errors else ""),
                 time.perf_counter() - start)


def score_tool():  # type: ignore[no-untyped-def]
    """tools/conformance_score.py as a module (its ``table``, ``summary``, ``main``): what
    the fault-score tests of firmware_py and firmware_c print and check."""
    path = Path(__file__).resolve().parents[1] / "tools" / "conformance_score.py"
    spec = importlib.util.spec_from_file_location("conformance_score", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
