"""Fleets for a test: any subset of a scenario's nodes, on a real bus or a simulated clock.

* ``ProcessFleet``: the nodes as `bess-ded` processes (``busrun.node_specs`` and
  ``busrun.start``, as `bess-ded up` starts them), on any bus python-can reaches; the
  wall clock is the bus time.
* ``SimFleet``: the same nodes as objects in this process (``busrun.in_process_nodes``,
  as ``run_in_process`` steps them), each on its own python-can ``virtual`` bus
  instance, stepped Ts by Ts on a simulated clock that a ``Tester`` on it advances
  while it waits (deterministic, faster than real time).
* ``KeySet``: a fleet's keys in a directory, as `bess-ded keys` writes them.
"""

from __future__ import annotations

import functools
import itertools
import os
import secrets
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import can

from dbc import dbc_path
from firmware_py import contract, secoc
from firmware_py.config import agent_configs_from_scenario
from firmware_py.errors import BessDedError
from firmware_py.frames import FrameCodec, mc_name
from firmware_py.node import GuardedBus
from sim.model.scenario import Scenario, load_scenario, scaled, to_toml
from sim.run import busrun

from .tester import Tester, TesterError, fleet_keys, node_label

__all__ = ["FleetError", "KeySet", "ProcessFleet", "SimFleet", "fleet_scenario",
           "node_names"]


class FleetError(BessDedError):
    """A fleet could not start or a node of it died (the test kit's error)."""


def fleet_scenario(case: int | str | Path | Scenario, variant: str | None = None,
                   time_scale: float = 1.0) -> Scenario:
    """A paper case (1..7), a scenario .toml or a ``Scenario``; its variant (for cases
    with variants); stretched by ``time_scale`` (Ts·F, as ``bess-ded up --time-scale``)."""
    from sim.model.scenario_select import pick_variant, resolve_scenario

    if isinstance(case, Scenario):
        sc = case
    elif isinstance(case, Path):
        sc = load_scenario(case)
    elif isinstance(case, int | str) and not isinstance(case, bool):
        sc = resolve_scenario(str(case))
    else:
        raise TesterError("case", "a case number, a scenario .toml path or a Scenario", case)
    sc, _ = pick_variant(sc, variant)
    return scaled(sc, time_scale)


def node_names(sc: Scenario, nodes: Iterable[str | int] | None) -> list[str]:
    """The nodes named (agent numbers, 'agent_<i>', 'plant', 'router'), checked against
    the scenario, in start order (agents, plant, router); None: every node."""
    every = secoc.fleet_nodes(sc.n)
    if nodes is None:
        return every
    if isinstance(nodes, str | int):
        raise TesterError("nodes", "a list of nodes (e.g. ['router', 'plant', 1, 2, 4])",
                          nodes)
    chosen = set()
    for n in nodes:
        try:
            label = node_label(n)
        except TesterError:
            label = str(n)
        if label not in every:
            raise TesterError("nodes", f"nodes of {sc.name} ({', '.join(every)}, or agent "
                              f"numbers 1..{sc.n})", n)
        chosen.add(label)
    return [n for n in every if n in chosen]


class KeySet:
    """A fleet's keys in ``directory``: node key files as `bess-ded keys` writes them.

    ``KeySet.fresh(dir)``: a new master key, key files written per scenario (``for_``);
    ``KeySet(dir)``: an existing set (``bess-ded keys --fleet ... --out DIR``)."""

    def __init__(self, directory: Path | str, master: bytes | None = None) -> None:
        self.directory = Path(directory)
        self.master = master
        self._written_for: str | None = None

    @classmethod
    def fresh(cls, directory: Path | str) -> KeySet:
        """A new key set in ``directory`` (made 0700) with a random master key."""
        d = Path(directory)
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
        os.chmod(d, 0o700)
        return cls(d, secrets.token_bytes(secoc.KEY_BYTES))

    def for_(self, sc: Scenario) -> Path:
        """The directory, with every key file ``sc``'s nodes need (written from the master
        key the first time, or checked: an existing set must cover the fleet)."""
        if self.master is not None:
            if self._written_for != sc.name:
                from sim.run.keyset import write_key_set

                write_key_set(sc, self.directory, self.master)
                self._written_for = sc.name
            return self.directory
        from sim.run.keyset import check_key_set

        check_key_set(self.directory, sc.n)
        return self.directory

    def node_keys(self) -> dict[str, bytes]:
        """Every node's key (label → key), for a ``Tester``."""
        if self.master is not None:
            return fleet_keys(self.master)
        from sim.run.keyset import load_key_set

        keys = load_key_set(self.directory)
        if not keys:
            raise TesterError("keys", f"a key set in {self.directory} (bess-ded keys --fleet "
                              f"... --out {self.directory})", "no .key file")
        return keys

    def keyrings(self, nodes: Sequence[str]) -> dict[str, secoc.Keyring]:
        """In-memory keyrings of ``nodes`` (a ``SimFleet``'s)."""
        if self.master is not None:
            return secoc.Keyring.fleet(self.master, list(nodes))
        return {n: secoc.Keyring.from_file(self.directory / f"{n}.key") for n in nodes}

    def __repr__(self) -> str:  # never print a key
        return f"KeySet({str(self.directory)!r}, fresh={self.master is not None})"


# ---------------------------------------------------------------------------- processes


class ProcessFleet:
    """Nodes of a scenario as `bess-ded` processes on ``bus`` (``busrun.BusOptions``).

    ``out``: where the scenario, the agents' configuration files (``config_path``) and
    the nodes' logs (``log``) go; ``keys``: a ``KeySet`` (None: every node --insecure).
    Nothing runs until ``start``; ``stop`` (or the ``with`` block's end) stops every
    node it started (SIGTERM, then SIGKILL)."""

    def __init__(self, case: int | str | Path | Scenario, out: Path, bus: busrun.BusOptions,
                 keys: KeySet | None, *, variant: str | None = None, time_scale: float = 1.0,
                 rt_priority: int = 0) -> None:
        from sim.run.fleet_plan import IN_PROCESS_INTERFACES

        interface = bus.resolved()["interface"]
        if interface in IN_PROCESS_INTERFACES:
            raise TesterError("bus", "a bus that connects processes (udp_multicast, "
                              "socketcan, ...): python-can's virtual bus exists inside one "
                              "process only (for an in-process fleet: SimFleet, "
                              "bess_fleet(processes=False))", interface)
        self.scenario = fleet_scenario(case, variant, time_scale)
        self.time_scale = time_scale
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.bus = bus
        self.keys = keys
        self.rt_priority = rt_priority
        self.logdir = self.out / "logs"
        self.logdir.mkdir(exist_ok=True)
        scenario_path = self.out / "scenario.toml"
        scenario_path.write_text(to_toml(self.scenario))
        key_dir = None if keys is None else keys.for_(self.scenario)
        self._specs = {s.name: s for s in busrun.node_specs(
            self.scenario, scenario_path, self.out, bus, rt_priority=rt_priority,
            keys=key_dir)}
        self.started: list[str] = []
        self.exit_codes: dict[str, int | None] = {}

    @property
    def ts(self) -> float:
        """The sample time the nodes run at (the scenario's Ts × time scale)."""
        return self.scenario.ts

    def start(self, nodes: Iterable[str | int] | None = None) -> list[str]:
        """Start ``nodes`` (None: every node not started yet), agents and plant first, the
        router last (its first price frame is t = 0 of the schedule)."""
        names = node_names(self.scenario, nodes)
        for name in names:
            spec = self._specs[name]
            if spec.proc is not None and spec.proc.poll() is None:
                raise FleetError(f"{name}: expected a node that is not running, but it runs "
                                 f"(pid {spec.proc.pid})")
            busrun.start(spec, self.logdir)
            if name not in self.started:
                self.started.append(name)
        return names

    def stop(self, nodes: Iterable[str | int] | None = None) -> dict[str, int | None]:
        """Stop ``nodes`` (None: every node started); their exit codes (also in
        ``exit_codes``)."""
        names = self.started if nodes is None else node_names(self.scenario, nodes)
        codes = busrun.stop_all([self._specs[n] for n in names if self._specs[n].proc],
                                self.rt_priority)
        self.exit_codes.update(codes)
        return codes

    def alive(self) -> dict[str, bool]:
        """Each started node: True while its process runs."""
        return {n: (p := self._specs[n].proc) is not None and p.poll() is None
                for n in self.started}

    def assert_alive(self) -> None:
        """Every node started is still running (else its exit code and log tail)."""
        dead = [n for n, up in self.alive().items() if not up]
        if dead:
            n = dead[0]
            proc = self._specs[n].proc
            raise AssertionError(f"{', '.join(dead)} exited (code "
                                 f"{proc.returncode if proc else None}); {n}'s log:\n"
                                 + self.log(n)[-800:])

    def argv(self, node: str | int) -> list[str]:
        """The command line of our own node for ``node`` (what a device replaces)."""
        return list(self._specs[node_names(self.scenario, [node])[0]].argv)

    def config_path(self, agent: str | int) -> Path:
        """Agent ``agent``'s configuration file (neighbours, gains, limits, Ts)."""
        name = node_names(self.scenario, [agent])[0]
        if not name.startswith("agent_"):
            raise TesterError("agent", "an agent (the plant and router take the scenario: "
                              "out/scenario.toml)", agent)
        return self.out / "agents" / f"{name}.toml"

    def key_path(self, node: str | int) -> Path | None:
        """``node``'s key file (None: the fleet runs --insecure)."""
        name = node_names(self.scenario, [node])[0]
        return None if self.keys is None else self.keys.directory / f"{name}.key"

    def log(self, node: str | int) -> str:
        """What ``node`` printed (its stdout and stderr)."""
        name = node_names(self.scenario, [node])[0]
        path = self.logdir / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def __enter__(self) -> ProcessFleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# ---------------------------------------------------------------------------- simulated clock

_channels = itertools.count()


class SimFleet:
    """Nodes of a scenario in this process, on a simulated clock (the clock of the
    ``Tester``s made with ``tester()``): every node on its own ``virtual`` bus instance
    of a private channel, stepped every Ts as ``busrun.run_in_process`` steps them (a
    frame sent at sample k is read at k + 1). Time passes only while a tester waits
    (``expect``, ``sleep``, ...) or ``run(duration)``. ``nodes``: the nodes simulated
    (None: all); ``keys``: a ``KeySet`` (None: --insecure)."""

    def __init__(self, case: int | str | Path | Scenario,
                 nodes: Iterable[str | int] | None = None, keys: KeySet | None = None, *,
                 variant: str | None = None, time_scale: float = 1.0,
                 channel: str | None = None) -> None:
        self.scenario = sc = fleet_scenario(case, variant, time_scale)
        self.names = node_names(sc, nodes)
        self.keys = keys
        rings = (keys.keyrings(secoc.fleet_nodes(sc.n)) if keys is not None else
                 {n: secoc.Keyring.insecure_for(n) for n in secoc.fleet_nodes(sc.n)})
        self._rings = rings
        # the scenario's frame format ([bus] fd, [security] lambda_tags)
        self.codec = FrameCodec(dbc_path(sc.fd, sc.lambda_tags))
        factories = busrun.in_process_nodes(sc, self.codec, rings)
        self.channel = channel or f"bess-testkit-{os.getpid()}-{next(_channels)}"
        self._bus_kw: dict[str, Any] = {"interface": "virtual", "channel": self.channel,
                                        "receive_own_messages": False,
                                        "preserve_timestamps": True}
        self.nodes: dict[str, Any] = {n: factories[n]() for n in self.names}
        self._buses = {n: can.Bus(**self._bus_kw) for n in self.names}
        self._guards: dict[str, GuardedBus] = {}
        self._extra: list[can.BusABC] = []
        self._testers: list[Tester] = []
        self._tasks: list[list[Any]] = []  # [next_due, period, fn]
        self._k = 0
        self._t = 0.0
        self.closed = False

    @property
    def ts(self) -> float:
        """The fleet's sample period Ts (s)."""
        return self.scenario.ts

    # the Clock protocol of sim.testkit.tester
    def now(self) -> float:
        """The simulated time of the last step (0 before the first)."""
        return self._t

    def wait(self, tester: Tester, dt: float) -> None:
        """Step the fleet once (the Clock protocol: bus time passes by one Ts)."""
        self.step()

    def every(self, period: float, fn: Callable[[float], None]) -> Callable[[], None]:
        """Call ``fn(t)`` every ``period`` of simulated time from now; returns a stop
        function."""
        task = [self._t, period, fn]
        self._tasks.append(task)

        def halt() -> None:
            if task in self._tasks:
                self._tasks.remove(task)

        return halt

    def attach(self, tester: Tester) -> None:
        """Deliver the fleet's frames to ``tester`` from now on."""
        self._testers.append(tester)

    def detach(self, tester: Tester) -> None:
        """Stop delivering frames to ``tester``."""
        if tester in self._testers:
            self._testers.remove(tester)

    def add(self, name: str, node: Any) -> None:
        """A node of your own in the fleet (a model, or a binding of your firmware): any
        object with ``on_frame(msg, t)`` and ``tick(t)`` → frames to send, stepped with
        the others on a bus instance of its own. ``agent_config`` and ``keyring`` give
        what a node of the scenario needs."""
        if name in self.nodes:
            raise TesterError("name", f"a node not yet in the fleet (it runs "
                              f"{', '.join(self.nodes)})", name)
        for attr in ("on_frame", "tick"):
            if not callable(getattr(node, attr, None)):
                raise TesterError(name, "a node with on_frame(msg, t) and tick(t) methods",
                                  type(node).__name__)
        self.nodes[name] = node
        self._buses[name] = can.Bus(**self._bus_kw)

    def agent_config(self, agent: str | int) -> Any:
        """Agent ``agent``'s configuration (``firmware_py.config.AgentConfig``)."""
        from firmware_py.config import agent_configs_from_scenario

        name = node_names(self.scenario, [agent])[0]
        for cfg in agent_configs_from_scenario(self.scenario):
            if f"agent_{cfg.id}" == name:
                return cfg
        raise TesterError("agent", "an agent of the scenario", agent)

    def keyring(self, node: str | int) -> secoc.Keyring:
        """``node``'s keyring in this fleet (its key and every peer's)."""
        return self._rings[node_names(self.scenario, [node])[0]]

    def open_bus(self) -> can.BusABC:
        """Another bus instance on the fleet's channel (closed with the fleet)."""
        bus = can.Bus(**self._bus_kw)
        self._extra.append(bus)
        return bus

    def tester(self, keys: Any = None, **kw: Any) -> Tester:
        """A ``Tester`` on this fleet's bus and clock (keys: the fleet's by default)."""
        kw.setdefault("codec", self.codec)
        if self.codec.tag_slots(mc_name(1)):  # AUTH-34: who hears each agent's λ here
            kw.setdefault("tag_receivers", {c.id: contract.lambda_receivers(
                [n.id for n in c.neighbours]) for c in agent_configs_from_scenario(self.scenario)})
        return Tester(self.open_bus(), self.keys if keys is None else keys, clock=self, **kw)

    def _note(self, name: str, cause: str) -> None:
        self.nodes[name].note(cause)

    def step(self) -> None:
        """One sample: every node reads what its bus holds, then ticks and sends; the
        testers' periodic messages due are sent; the testers read the bus."""
        if self.closed:
            raise FleetError("the simulated fleet is closed")
        t = self._k * self.scenario.ts
        self._k += 1
        self._t = t
        for name, node in self.nodes.items():
            guarded = self._guards.get(name)
            if guarded is None or guarded.bus is not self._buses[name]:  # new, or restarted
                guarded = self._guards[name] = GuardedBus(
                    self._buses[name], functools.partial(self._note, name), who=name)
            while (msg := guarded.recv(timeout=0)) is not None:  # as run_node reads
                node.on_frame(msg, t)
        for name, node in self.nodes.items():
            bus = self._buses[name]
            for frame in node.tick(t):
                frame.timestamp = t
                bus.send(frame)
        eps = 1e-9 * self.scenario.ts
        for task in list(self._tasks):
            while task in self._tasks and task[0] <= t + eps:
                task[2](t)
                task[0] += task[1]
        for tester in list(self._testers):
            tester.pump()

    def run(self, duration: float) -> None:
        """Step ``duration`` of simulated time."""
        end = self._t + duration
        while self._t < end - 1e-9 * self.scenario.ts:
            self.step()

    def close(self) -> None:
        """Close every attached tester and shut every bus down (once)."""
        if self.closed:
            return
        self.closed = True
        for tester in list(self._testers):
            tester.close()
        for bus in [*self._buses.values(), *self._extra]:
            bus.shutdown()

    def __enter__(self) -> SimFleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
