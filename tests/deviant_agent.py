"""A deliberately non-conformant agent node, for the conformance and attack tests:
firmware_py's agent with one known deviation applied, either one of
sim.conformance.MUTANTS (e.g. BAND-2: the reset band re-armed at the reset sample
itself) or one of LIARS (a compromised agent holding only its own key: it signs what it
sends, so only what it says can give it away).

    python tests/deviant_agent.py BAND-2 --config agent_3.toml --key agent_3.key ...
    python tests/deviant_agent.py LIE-SETPOINT --config agent_3.toml --key agent_3.key ...
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import can

from firmware_py import fixedpoint as fx
from firmware_py import runtime
from firmware_py.__main__ import main
from firmware_py.contract import is_active
from firmware_py.frames import mc_name, setpoint_name
from sim.conformance import MUTANTS

LIE_SETPOINT_KW = 89.0     # what the liar commands its plant (case 1, agent 3: 41.2 honest)
LIE_LAMBDA_OFFSET = 0.0024  # cu/kWh told above its λ: 0.3 % of ρ = 0.8
LIE_RAMP_PER_S = 0.002     # cu/kWh per s the ramping liar adds to its told λ


def _lie_setpoint(a: runtime.AgentRuntime) -> None:
    """Publishes its honest λ, commands its plant LIE_SETPOINT_KW whenever it dispatches."""
    def frame() -> can.Message:
        enable = is_active(a.state)
        p = round(LIE_SETPOINT_KW * 100) if enable else 0
        return a.io.send(setpoint_name(a.cfg.id), {"Enable": int(enable), "PowerSetpoint": p})
    a._setpoint_frame = frame  # type: ignore[method-assign]


def _told(a: runtime.AgentRuntime, offset: Callable[[runtime.AgentRuntime], float]) -> int:
    return a.lambda_q24 + (fx.to_fixed(offset(a), "lie") if is_active(a.state) else 0)


def _lie_lambda(offset: Callable[[runtime.AgentRuntime], float]
                ) -> Callable[[runtime.AgentRuntime], None]:
    """Tells its neighbours λ + offset and dispatches its plant consistently with that
    told λ (the careful liar: its setpoints match what it says)."""
    def apply(a: runtime.AgentRuntime) -> None:
        def mc() -> can.Message:
            return a.io.send(mc_name(a.cfg.id), {
                "State": int(a.state), "Lambda": _told(a, offset),
                "Resets": a.cstate.resets % (a._mc_max["Resets"] + 1)})

        def sp() -> can.Message:
            enable = is_active(a.state)
            p, _ = a.setpoint(_told(a, offset)) if enable else (0, False)
            return a.io.send(setpoint_name(a.cfg.id), {"Enable": int(enable),
                                                       "PowerSetpoint": p})
        a._mc_frame = mc  # type: ignore[method-assign]
        a._setpoint_frame = sp  # type: ignore[method-assign]
    return apply


LIARS: dict[str, Callable[[runtime.AgentRuntime], None]] = {
    "LIE-SETPOINT": _lie_setpoint,
    "LIE-LAMBDA": _lie_lambda(lambda a: LIE_LAMBDA_OFFSET),
    "LIE-RAMP": _lie_lambda(lambda a: LIE_RAMP_PER_S * a.ticks * a.period),
}


def deviate(requirement: str, agent: int | None = None) -> None:
    """Every AgentRuntime built from now on (of agent ``agent`` only, if given) breaks
    ``requirement`` (a MUTANTS key) or lies as LIARS[requirement] does."""
    apply = LIARS[requirement] if requirement in LIARS else MUTANTS[requirement][1]
    init = runtime.AgentRuntime.__init__

    def deviant_init(self: runtime.AgentRuntime, *args: object, **kw: object) -> None:
        init(self, *args, **kw)  # type: ignore[arg-type]
        if agent is None or self.cfg.id == agent:
            apply(self)

    runtime.AgentRuntime.__init__ = deviant_init  # type: ignore[method-assign]


@contextmanager
def lying(requirement: str, agent: int) -> Iterator[None]:
    """``deviate(requirement, agent)`` for the agents built inside the block (in-process
    runs: sim.run.busrun.run_in_process); every AgentRuntime after it is honest again."""
    init = runtime.AgentRuntime.__init__
    deviate(requirement, agent)
    try:
        yield
    finally:
        runtime.AgentRuntime.__init__ = init  # type: ignore[method-assign]


if __name__ == "__main__":
    deviate(sys.argv[1])
    sys.exit(main(sys.argv[2:]))
