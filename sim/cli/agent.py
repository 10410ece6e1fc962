"""`bess-ded agent --config FILE`: run one agent firmware node (deployment on its own host)."""

from __future__ import annotations

import argparse

from firmware_py.__main__ import add_arguments, run_agent

from ._common import one_line_errors


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("agent", help="run one agent node from its TOML config",
                       description=__doc__)
    add_arguments(p)
    one_line_errors(p)
    p.set_defaults(func=run_agent)
