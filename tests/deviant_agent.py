"""A deliberately non-conformant agent node, for the conformance tests: firmware_py's agent
with one known deviation of sim.conformance.MUTANTS applied (e.g. BAND-2: the reset band
re-armed at the reset sample itself).

    python tests/deviant_agent.py BAND-2 --config agent_3.toml --key agent_3.key ...
"""

from __future__ import annotations

import sys

from firmware_py import runtime
from firmware_py.__main__ import main
from sim.conformance import MUTANTS


def deviate(requirement: str) -> None:
    """Every AgentRuntime built from now on breaks ``requirement``."""
    _, apply = MUTANTS[requirement]
    init = runtime.AgentRuntime.__init__

    def deviant_init(self: runtime.AgentRuntime, *args: object, **kw: object) -> None:
        init(self, *args, **kw)  # type: ignore[arg-type]
        apply(self)

    runtime.AgentRuntime.__init__ = deviant_init  # type: ignore[method-assign]


if __name__ == "__main__":
    deviate(sys.argv[1])
    sys.exit(main(sys.argv[2:]))
