"""Known deviations (``MUTANTS``): firmware_py's agent with one requirement broken,
for the report to name a deviation that explains a device's frames, and for the tests;
and known misreadings of the configuration file (``misreads``): the file read with
one key's default instead of its value, or a value rounded otherwise (CFG-3..7)."""

from __future__ import annotations

import tomllib
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import can

from firmware_py import config as fc
from firmware_py import fixedpoint as fx
from firmware_py.config import AgentConfig, Neighbour, Transmit
from firmware_py.contract import status_name, timeout_s
from firmware_py.controllers import ControllerConfig, PIController
from firmware_py.runtime import AgentRuntime


class _BandAtReset(PIController):
    """The band re-armed at the reset sample itself (BAND-2 violated)."""

    def step(self, s: Any, xi: Any) -> Any:
        out_state, out = super().step(s, xi)
        if out.reset and abs(xi) > self.band:
            out_state = replace(out_state, armed=True)
        return out_state, out


def _band_at_reset(rt: AgentRuntime) -> None:
    _patch_controller(rt, "_BandAtReset", _BandAtReset)


def _armed_false(rt: AgentRuntime) -> None:
    rt.cstate = replace(rt.cstate, armed=False)


def _patch_controller(rt: AgentRuntime, name: str, mixin: type) -> None:
    cls = type(rt.ctrl)
    rt.ctrl.__class__ = type(name + cls.__name__, (mixin, cls), {})


class _IgnoringRuntime(AgentRuntime):
    """firmware_py's agent that does not act on one command frame: verified and counted
    as any, its effect (state, controller, gains, PIN) undone at once."""

    ignored: tuple[int, bytes] = (-1, b"")

    def on_frame(self, msg: can.Message, t: float) -> None:
        """As AgentRuntime's, but the ignored frame changes no state of the control."""
        if (msg.arbitration_id, bytes(msg.data)) != self.ignored:
            super().on_frame(msg, t)
            return
        kept = self.state, self.cstate, self.ctrl, self.pin
        super().on_frame(msg, t)
        self.state, self.cstate, self.ctrl, self.pin = kept


def ignoring(msg: can.Message) -> Callable[[AgentRuntime], None]:
    """A deviation: the device does not act on the command frame ``msg`` (the checker's
    counterfactual for "a command it must obey was not obeyed": ``explain``)."""
    def deviation(rt: AgentRuntime) -> None:
        rt.__class__ = _IgnoringRuntime
        assert isinstance(rt, _IgnoringRuntime)
        rt.ignored = (msg.arbitration_id, bytes(msg.data))
    return deviation


MUTANTS: dict[str, tuple[str, Callable[[AgentRuntime], None]]] = {
    "BAND-2": ("the reset band re-arms at the reset sample itself", _band_at_reset),
    "BAND-1": ("the reset is not armed at start", _armed_false),
}
"""Known deviations: requirement → (what the DUT does instead, how to make the oracle do
it). Used only to name the requirement when the DUT fails."""


def misreads(cfg: AgentConfig, text: str | None = None) -> list[tuple[str, str, AgentConfig]]:
    """The configurations a device that misreads ``cfg``'s file (the reference parser's
    reading) runs from: (requirement, what the device does, that configuration), one
    key at a time: the key's default taken instead of the file's value (CFG-3, CFG-4,
    CFG-6, CFG-7: a misspelt or unread key), ``neighbour_periods`` rounded instead of
    truncated (CFG-6: from the file's ``text``, if given), the period kept in whole ns
    and Ts taken from it (CFG-3). Only readings that differ from ``cfg`` are listed.
    Used only to name the requirement when a DUT fails (``explain``), like
    ``MUTANTS``."""
    c = cfg.controller
    dflt = ControllerConfig()  # the defaults of ts, k, h, band (the same for every kind)
    out: list[tuple[str, str, AgentConfig]] = []

    def add(must: str, what: str, alt: AgentConfig) -> None:
        if alt != cfg:
            out.append((must, what, alt))

    def ctrl(**kw: Any) -> AgentConfig:
        return replace(cfg, controller=replace(c, **kw))

    ns_ts = round(c.ts * 1e9) / 1e9
    add("CFG-3", f"it reads controller.ts as {ns_ts!r} s (the period kept in whole ns, "
        f"Ts and its Q30 word taken from it), not {c.ts!r}", ctrl(ts=ns_ts))
    if ns_ts != c.ts:  # ... TSQ only: k·ts and h·ts from the file's ts, as written
        k2, h2 = c.k * c.ts / ns_ts, c.h * c.ts / ns_ts
        if all(fx.to_q30(a * ns_ts) == fx.to_q30(b * c.ts) for a, b in ((k2, c.k),
                                                                         (h2, c.h))):
            add("CFG-3", f"its TSQ (ν's Q30 period) is the period in whole ns, {ns_ts!r} "
                f"s, not the file's ts {c.ts!r} (k·ts and h·ts from the file's)",
                ctrl(ts=ns_ts, k=k2, h=h2))
    if c.kind == "dwell" and round(c.dwell / c.ts) != c.dwell_samples:  # CTRL-2: ceil
        add("CTRL-2", f"it rounds controller.dwell / ts = {c.dwell / c.ts:.3g} to "
            f"{round(c.dwell / c.ts)} samples, not up to {c.dwell_samples}",
            ctrl(dwell=round(c.dwell / c.ts) * c.ts))
    if dflt.ts != ns_ts:
        add("CFG-3", f"it takes controller.ts's default {dflt.ts!r}, not the file's "
            f"{c.ts!r}", ctrl(ts=dflt.ts))
    for key in ("k", "h", "band"):
        add("CFG-3", f"it takes controller.{key}'s default {getattr(dflt, key)!r}, not the "
            f"file's {getattr(c, key)!r}", ctrl(**{key: getattr(dflt, key)}))
    if any(n.weight != 1.0 for n in cfg.neighbours):
        add("CFG-4", "it takes the neighbour weights' default 1.0, not the file's "
            + ", ".join(f"{n.weight!r}" for n in cfg.neighbours),
            replace(cfg, neighbours=tuple(Neighbour(n.id) for n in cfg.neighbours)))
    defaults: list[tuple[str, str, Any]] = [
        ("CFG-6", "neighbour_timeout_periods", cfg.transmit.neighbour_periods),
        ("CFG-6", "price_timeout_s", timeout_s("ER_Price", c.ts)),
        ("CFG-6", "status_timeout_s", timeout_s(status_name(cfg.id), c.ts)),
        ("CFG-7", "lambda_min", -10.0), ("CFG-7", "lambda_max", 10.0),
        ("CFG-7", "rho_min", fc.RHO_MIN), ("CFG-7", "rho_max", fc.RHO_MAX),
        ("CFG-7", "price_step_max", fc.PRICE_STEP_MAX),
        ("CFG-7", "price_persist", fc.PRICE_PERSIST),
        ("CFG-7", "lambda_step_max", fc.LAMBDA_STEP_GAIN * c.k * c.ts),
        ("CFG-7", "k_min", fc.GAIN_LO * c.k), ("CFG-7", "k_max", fc.GAIN_HI * c.k),
        ("CFG-7", "h_min", fc.GAIN_LO * c.h), ("CFG-7", "h_max", fc.GAIN_HI * c.h),
        ("CFG-7", "untrusted_after", fc.UNTRUSTED_AFTER),
    ]
    add("WMSR-1", f"it does not trim (agent.resilient_f's default 0 taken, or no resilient "
        f"update), not F = {cfg.resilient_f}", replace(cfg, resilient_f=0))
    written = tomllib.loads(text).get("timeouts", {}).get("neighbour_periods") if text else None
    if isinstance(written, (int, float)) and int(written + 0.5) != int(written):
        add("CFG-6", f"it rounds timeouts.neighbour_periods = {written!r} to "
            f"{int(written + 0.5)}, not truncates it to {cfg.neighbour_timeout_periods}",
            replace(cfg, neighbour_timeout_periods=int(written + 0.5)))
    for must, field, value in defaults:
        add(must, f"it takes {_KEYS.get(field, 'limits.' + field)}'s default {value!r}, "
            f"not the file's {getattr(cfg, field)!r}", replace(cfg, **{field: value}))
    if cfg.transmit.event:  # CFG-9: [transmit]'s keys, one at a time
        for key in ("threshold", "heartbeat"):
            add("CFG-9", f"it takes transmit.{key}'s default "
                f"{getattr(Transmit(), key)!r}, not the file's {getattr(cfg.transmit, key)!r}",
                replace(cfg, transmit=replace(cfg.transmit, **{key: getattr(Transmit(), key)})))
    return out


_KEYS = {"neighbour_timeout_periods": "timeouts.neighbour_periods",
         "price_timeout_s": "timeouts.price_s", "status_timeout_s": "timeouts.status_s"}

