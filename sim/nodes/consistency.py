"""Is an agent's power setpoint its own dispatch rule applied to the λ it publishes?

An agent sends AGENT_i_MC (its λ and state) every tick and AGENT_i_Setpoint every few
ticks, both from the same λ (firmware_py.runtime: ``_setpoint_frame`` maps
``lambda_q24`` through ``SetpointMap``, after the battery's power limits). A compromised
agent holding its own key can still command its plant something else than its λ says,
steering the fleet while its neighbours see an honest λ. The plant and the verdict
therefore check each setpoint against the λ of the agent's recent MC frames, with the
firmware's own map (never re-derived here), within the wire's rounding.

A setpoint that matches none of the last ``MC_WINDOW`` MC frames waits for the next one
(it may have overtaken the MC frame of its own tick): it is consistent if that one
explains it, or if it lies between what the MC frames before and after it give (the
MC frame of its own tick was lost), inconsistent if not; if more than one MC frame was
lost between them (``period`` given: their times more than 2.5 periods apart), λ may
have turned in the gap (a reset), so the setpoint is left unverified. With
event-triggered λ an agent's λ may be up to its threshold from the one its last MC frame
carries (``lag``): a setpoint between what those two give is consistent. A disabled
setpoint (0 kW) is always consistent: it is the safe direction, as a stale setpoint is.
A second setpoint arriving while one still waits (the MC frames are not getting through)
leaves the first unverified, not inconsistent.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from enum import Enum

from firmware_py.config import AgentConfig, DispatchParams
from firmware_py.contract import State, is_active
from firmware_py.runtime import SetpointMap

MC_WINDOW = 3          # MC frames a setpoint may lag (frames lost, ticks of jitter)
ROUNDING_RAW = 1       # setpoint raw units (0.01 kW) the wire's rounding may account for


class Check(Enum):
    """The outcome of checking a setpoint against its agent's λ."""

    CONSISTENT = "consistent"
    INCONSISTENT = "inconsistent"
    UNVERIFIED = "unverified"   # no MC frame came to check it against


@dataclass
class Setpoint:
    """One setpoint the plant received: enable, raw power and its time."""

    enable: bool
    raw: int                    # PowerSetpoint, 0.01 kW
    t: float


@dataclass
class SetpointCheck:
    """One agent's setpoints checked against its own λ (``params``: its DispatchParams)."""

    params: DispatchParams
    period: float | None = None  # the MC cadence (s): tells one lost MC frame from several
    mcs: deque[tuple[int, int]] = field(default_factory=lambda: deque(maxlen=MC_WINDOW))
    pending: Setpoint | None = None
    last_mc_t: float | None = None
    # Q24: how far the agent's λ may be from the one its last MC frame carries; with
    # event-triggered λ (firmware-spec TX-7) its threshold, else 0 (every tick sent)
    lag: int = 0

    def __post_init__(self) -> None:
        self.map = SetpointMap(self.params)

    def expected(self, state: int, lam_raw: int) -> tuple[bool, int]:
        """(Enable, PowerSetpoint raw) the firmware sends for this MC state and λ."""
        active = is_active(State(state)) if state in State._value2member_map_ else False
        return (True, self.map(lam_raw)[0]) if active else (False, 0)

    def _explains(self, sp: Setpoint, state: int, lam_raw: int) -> bool:
        if not sp.enable and sp.raw == 0:
            return True   # disabled: the safe direction, whatever the state says
        # the map is monotone in λ: λ within ±lag of the frame's gives setpoints in between
        enable, lo = self.expected(state, lam_raw - self.lag)
        hi = self.expected(state, lam_raw + self.lag)[1]
        return sp.enable == enable and lo - ROUNDING_RAW <= sp.raw <= hi + ROUNDING_RAW

    def _between(self, sp: Setpoint, a: tuple[int, int], b: tuple[int, int]) -> bool:
        """Within the setpoints of two consecutive MC frames, one of them dispatching:
        the MC frame of the setpoint's own tick was lost between them (λ moves little in
        one tick; the state may have changed in it)."""
        pa, pb = self.map(a[1])[0], self.map(b[1])[0]
        return (sp.enable and (self.expected(*a)[0] or self.expected(*b)[0])
                and min(pa, pb) - ROUNDING_RAW <= sp.raw <= max(pa, pb) + ROUNDING_RAW)

    def mc(self, state: int, lam_raw: int, t: float | None = None
           ) -> tuple[Check, Setpoint] | None:
        """An MC frame of the agent (received at ``t``); the outcome of a setpoint that
        waited for it."""
        prev = self.mcs[-1] if self.mcs else None
        prev_t, self.last_mc_t = self.last_mc_t, t
        self.mcs.append((state, lam_raw))
        sp, self.pending = self.pending, None
        if sp is None:
            return None
        if self._explains(sp, state, lam_raw):
            return Check.CONSISTENT, sp
        if prev is None:  # the checker started between its tick's MC frame and it
            return Check.UNVERIFIED, sp
        if (self.period is not None and t is not None and prev_t is not None
                and t - prev_t > 2.5 * self.period):
            return Check.UNVERIFIED, sp  # several MC frames lost: λ may have turned
        ok = self._between(sp, prev, (state, lam_raw))
        return (Check.CONSISTENT if ok else Check.INCONSISTENT), sp

    def setpoint(self, sp: Setpoint) -> list[tuple[Check, Setpoint]]:
        """A setpoint of the agent: the outcomes decided now (this one, or one left
        waiting before it); an empty list while this one waits for the next MC frame."""
        out = []
        if self.pending is not None:
            out.append((Check.UNVERIFIED, self.pending))
            self.pending = None
        if any(self._explains(sp, s, lam) for s, lam in self.mcs):
            out.append((Check.CONSISTENT, sp))
        else:
            self.pending = sp
        return out


def mc_lag(cfg: AgentConfig) -> int:
    """SetpointCheck's ``lag`` for an agent configured as ``cfg``: its event threshold
    (Q24), 0 when it sends every tick."""
    return cfg.transmit.threshold_q24 if cfg.transmit.event else 0
