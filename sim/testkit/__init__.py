"""A test kit for one's own node on a bess-ded bus (docs/testing.md).

``Tester`` sends and expects frames by message and signal name (counters and
authentication handled); ``ProcessFleet`` and ``SimFleet`` run any subset of a
scenario's nodes, as ``bess-ded`` processes on a real bus or in-process on a simulated
clock; ``sim.testkit.plugin`` is the pytest plugin with the ``bess_*`` fixtures.

The names are imported on first use: loading the pytest plugin (every pytest session
of an environment where bess-ded is installed) imports nothing heavy.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .fleet import FleetError, KeySet, ProcessFleet, SimFleet
    from .tester import (
        ExpectationError,
        Periodic,
        Received,
        Tester,
        TesterError,
        WallClock,
        fleet_keys,
        node_label,
    )

_WHERE = {**dict.fromkeys(("FleetError", "KeySet", "ProcessFleet", "SimFleet"), ".fleet"),
          **dict.fromkeys(("ExpectationError", "Periodic", "Received", "Tester", "TesterError",
                           "WallClock", "fleet_keys", "node_label"), ".tester")}

__all__ = ["ExpectationError", "FleetError", "KeySet", "Periodic", "ProcessFleet", "Received",
           "SimFleet", "Tester", "TesterError", "WallClock", "fleet_keys", "node_label"]


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value
