"""A test kit for one's own node on a bess-ded bus (docs/testing.md).

``Tester`` sends and expects frames by message and signal name (counters, CRC and
authentication handled); ``ProcessFleet`` and ``SimFleet`` run any subset of a
scenario's nodes, as ``bess-ded`` processes on a real bus or in-process on a simulated
clock; ``sim.testkit.plugin`` is the pytest plugin with the ``bess_*`` fixtures.
"""

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

__all__ = ["ExpectationError", "FleetError", "KeySet", "Periodic", "ProcessFleet", "Received",
           "SimFleet", "Tester", "TesterError", "WallClock", "fleet_keys", "node_label"]
