"""Known deviations (``MUTANTS``): firmware_py's agent with one requirement broken,
for the report to name a deviation that explains a device's frames, and for the tests."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

from firmware_py.controllers import PIController
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


MUTANTS: dict[str, tuple[str, Callable[[AgentRuntime], None]]] = {
    "BAND-2": ("the reset band re-arms at the reset sample itself", _band_at_reset),
    "BAND-1": ("the reset is not armed at start", _armed_false),
}
"""Known deviations: requirement → (what the DUT does instead, how to make the oracle do
it). Used only to name the requirement when the DUT fails."""
