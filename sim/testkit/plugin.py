"""The pytest plugin of the bess-ded test kit (docs/testing.md), registered as ``bess_ded``
through the ``pytest11`` entry point: installing the package makes these fixtures
available to any test.

* ``bess_bus_options``: the bus (``busrun.BusOptions``): ``--bess-interface``,
  ``--bess-channel``, ``--bess-bus-config`` (else CAN_INTERFACE, CAN_CHANNEL,
  CAN_CONFIG); default: python-can's udp_multicast on a port private to the test;
* ``bess_bus``: a python-can bus on it, shut down after the test;
* ``bess_keys``: a ``KeySet``: a fresh fleet key set in the test's tmp_path, or
  ``--bess-keys DIR`` (``bess-ded keys --fleet ... --out DIR``);
* ``bess_tester``: a ``Tester`` on ``bess_bus`` with ``bess_keys``;
* ``bess_fleet``: a factory of fleets, stopped after the test:
  ``bess_fleet(case=1, nodes=["router", "plant", 1, 2, 4])`` starts those nodes as
  `bess-ded` processes on ``bess_bus_options`` and waits until ``bess_tester`` heard
  each of them; ``bess_fleet(..., processes=False)`` is a ``SimFleet`` in-process on a
  simulated clock (its own bus and clock: ``fleet.tester()``).

Nothing happens at import or collection: every fixture acts only when a test asks for it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import pytest

HEARD_TIMEOUT_S = 60.0  # a node process imports python-can, cantools and the DBC first


def pytest_addoption(parser: pytest.Parser) -> None:
    """The test kit's command-line options (--bess-interface, --bess-channel,
    --bess-bus-config, --bess-time-scale, --bess-keys)."""
    g = parser.getgroup("bess-ded", "bess-ded test kit (docs/testing.md)")
    g.addoption("--bess-interface", metavar="NAME", default=None,
                help="python-can interface of the bess_bus fixture (socketcan, pcan, ...; "
                     "default: CAN_INTERFACE, else udp_multicast on a port private to "
                     "each test)")
    g.addoption("--bess-channel", metavar="CH", default=None,
                help="its channel (vcan0, can0, ...; default: CAN_CHANNEL)")
    g.addoption("--bess-bus-config", metavar="JSON", default=None,
                help="extra python-can arguments as a JSON object, e.g. "
                     "'{\"bitrate\": 500000}' (default: CAN_CONFIG)")
    g.addoption("--bess-keys", metavar="DIR", type=Path, default=None,
                help="the fleet key set of bess_keys (bess-ded keys --fleet ... --out DIR; "
                     "default: a fresh one per test)")
    g.addoption("--bess-time-scale", metavar="F", type=float, default=None,
                help="default time scale of bess_fleet (Ts·F: slow hosts, emulators; "
                     "default: 1)")


# the markers the examples use (docs/testing.md), for projects that do not define them
MARKERS = {
    "realtime": "bess-ded test kit: node processes on the wall clock (assert only what "
                "holds at any load)",
    "slow": "bess-ded test kit: bus-level runs of seconds",
}


def pytest_configure(config: pytest.Config) -> None:
    """Register the kit's markers and refuse bad --bess-* options once, before
    any test runs."""
    defined = {line.split(":")[0].split("(")[0].strip() for line in config.getini("markers")}
    for name, text in MARKERS.items():
        if name not in defined:
            config.addinivalue_line("markers", f"{name}: {text}")
    opt = config.getoption
    given = [opt(o) for o in ("--bess-interface", "--bess-channel", "--bess-bus-config")]
    if any(v is not None for v in given):  # checked at once, not in every test's setup
        _bus_options(*given)
    scale = opt("--bess-time-scale")
    if scale is not None and not (scale >= 1 and scale != float("inf")):
        raise pytest.UsageError(f"--bess-time-scale: expected a factor ≥ 1, but got {scale!r}")
    keys = opt("--bess-keys")
    if keys is not None and not Path(keys).is_dir():
        raise pytest.UsageError(f"--bess-keys: expected a key set directory (bess-ded keys "
                                f"--fleet ... --out DIR), but got {str(keys)!r}")


def _bus_options(interface: str | None, channel: str | None, config: str | None) -> Any:
    from sim.run import busrun

    bus = busrun.BusOptions(interface, channel, config)
    try:
        bus.resolved()
        bus, _port = busrun.private_port(bus)
    except Exception as e:  # a bad option: one clear line, not a traceback
        raise pytest.UsageError(f"bess-ded test kit: {e}") from None
    return bus


@pytest.fixture
def bess_bus_options(request: pytest.FixtureRequest) -> Any:
    """The bus of this test: the --bess-* options, else CAN_* variables, else
    udp_multicast on a free port of its own (never python-can's shared default)."""
    opt = request.config.getoption
    return _bus_options(opt("--bess-interface"), opt("--bess-channel"),
                        opt("--bess-bus-config"))


@pytest.fixture
def bess_bus(bess_bus_options: Any) -> Iterator[Any]:
    """A python-can bus on ``bess_bus_options``, shut down after the test."""
    from firmware_py.node import open_bus

    bus = open_bus(**{**bess_bus_options.resolved(), "receive_own_messages": False})
    try:
        yield bus
    finally:
        bus.shutdown()


@pytest.fixture
def bess_keys(request: pytest.FixtureRequest, tmp_path: Path) -> Any:
    """The fleet's keys (``KeySet``): --bess-keys DIR, else a fresh set in tmp_path."""
    from .fleet import KeySet

    given = request.config.getoption("--bess-keys")
    if given is not None:  # a directory: checked by pytest_configure
        return KeySet(given)
    return KeySet.fresh(tmp_path / "keys")


@pytest.fixture
def bess_tester(bess_bus: Any, bess_keys: Any) -> Iterator[Any]:
    """A ``Tester`` on ``bess_bus``, holding every key of ``bess_keys``."""
    from .tester import Tester

    tester = Tester(bess_bus, bess_keys)
    try:
        yield tester
    finally:
        tester.close()


def _heard_message(node: str, n: int) -> str:
    if node == "router":
        return "ER_Price"
    if node == "plant":
        return "PLANT_1_Status"
    return f"AGENT_{node.removeprefix('agent_')}_MC"


@pytest.fixture
def bess_fleet(request: pytest.FixtureRequest, tmp_path: Path, bess_keys: Any
               ) -> Iterator[Callable[..., Any]]:
    """``bess_fleet(case=1, nodes=None, *, processes=True, time_scale=None, variant=None,
    wait=True)``: the scenario's ``nodes`` (agent numbers, 'agent_<i>', 'plant',
    'router'; None: all) as `bess-ded` processes on the test's bus (``ProcessFleet``,
    started at once, the router last; ``wait``: until ``bess_tester`` heard each), or
    with ``processes=False`` in-process on a simulated clock (``SimFleet``). Every fleet
    is stopped after the test."""
    from .fleet import ProcessFleet, SimFleet

    fleets: list[Any] = []
    default_scale = request.config.getoption("--bess-time-scale") or 1.0

    def make(case: Any = 1, nodes: Iterable[str | int] | None = None, *,
             processes: bool = True, time_scale: float | None = None,
             variant: str | None = None, wait: bool = True) -> Any:
        scale = default_scale if time_scale is None else time_scale
        if not processes:
            sim = SimFleet(case, nodes, bess_keys, variant=variant, time_scale=scale)
            fleets.append(sim)
            return sim
        bus = request.getfixturevalue("bess_bus_options")
        tester = request.getfixturevalue("bess_tester") if wait else None
        fleet = ProcessFleet(case, tmp_path / f"fleet{len(fleets) + 1}", bus, bess_keys,
                             variant=variant, time_scale=scale)
        fleets.append(fleet)
        started = fleet.start(nodes)
        if tester is not None:
            for node in started:
                try:
                    tester.expect(_heard_message(node, fleet.scenario.n),
                                  HEARD_TIMEOUT_S * scale, since=float("-inf"))
                except AssertionError as e:
                    fleet.assert_alive()
                    raise AssertionError(f"bess_fleet: {node} was not heard on the bus: "
                                         f"{e}\n{node}'s log:\n{fleet.log(node)[-800:]}"
                                         ) from None
            tester.mark()
        return fleet

    try:
        yield make
    finally:
        for fleet in reversed(fleets):
            if isinstance(fleet, ProcessFleet):
                fleet.stop()
            else:
                fleet.close()
