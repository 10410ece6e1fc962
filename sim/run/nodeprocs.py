"""The node processes of a bus run: their argv (``node_specs``), start (``start``), stop
(``stop_all``) and the counters the plant and router leave at exit.

Part of `bess-ded up` (``sim.run.busrun``); the test kit's ``ProcessFleet`` starts and
stops its nodes through the same functions.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from firmware_py.config import agent_configs_from_scenario
from firmware_py.nodeargs import fd_argv
from sim.model.scenario import Scenario
from sim.run.busopts import C_BUS_EXPECTED, BusOptions, BusRunError, c_node_bus_argv

STOP_GRACE_S = 5.0     # SIGTERM → SIGKILL
# nodes must be up (router speaking) by then. In tools/vcan-run's emulated guest a node
# needs ~8 s of CPU to import python-can/cantools and parse the DBC (host: ~0.5 s), and
# case 7 starts 14 of them on 2 vCPUs.
IN_GUEST = os.environ.get("VCAN_RUN_GUEST") == "1"
START_TIMEOUT_S = 240.0 if IN_GUEST else 60.0
# SCHED_FIFO priority of every node process: with 14 Python nodes on 2 cores, ordinary
# scheduling lets ticks slip past Ts/2 (≈ 2–10 % misses in case 7); real-time priority
# keeps them < 1 % (docs/performance.md). Needs root/CAP_SYS_NICE, else ignored.
RT_PRIORITY = 10


@dataclass
class NodeSpec:
    """One node process of a run: its name, argv, start delay and process; ``members``:
    the agents a host process runs (its exit and death are each of theirs), else none."""

    name: str
    argv: list[str]
    delay: float = 0.0            # start this long after `up` starts it (fault tests)
    proc: subprocess.Popen[bytes] | None = None
    members: tuple[str, ...] = ()

    @property
    def nodes(self) -> tuple[str, ...]:
        """The nodes of the run this process is: its members, or itself."""
        return self.members or (self.name,)


def _die_with_parent() -> None:
    """In the child: get SIGTERM if `up` dies, so no node outlives it (Linux only)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


SIM_NODES = ("plant", "router")  # the simulated nodes, started after the agents



def node_specs(sc: Scenario, scenario_path: Path, out: Path, bus: BusOptions,
               extra: dict[str, list[str]] | None = None,
               rt_priority: int = RT_PRIORITY, keys: Path | None = None,
               exclude: frozenset[str] = frozenset(),
               c_agents: frozenset[int] = frozenset(),
               c_node: Path | None = None, agents_per_process: int = 1) -> list[NodeSpec]:
    """Argv for every node. Agents and plant first; the router last, since its first
    price frame is t = 0 of the schedule. Every node runs under SCHED_FIFO
    ``rt_priority`` where the OS allows it (0: not), as firmware on an embedded Linux
    would; plant and router too, or the agents starve them on an overloaded host; a
    host of several agents one above (the rig must not hold all its agents' ticks).
    ``keys``: the key set directory (each node gets ``--key DIR/<node>.key``); None:
    every node runs ``--insecure``. ``exclude``: nodes not started here (a device under
    test takes their place: `bess-ded restbus`); an agent's configuration file is still
    written, for the device. ``c_agents``: the agents that run the C firmware's node
    program ``c_node`` (firmware_c's bessded-agent, on socketcan or udp_multicast:
    busopts.c_node_bus_argv) from the same
    configuration and key files. ``agents_per_process``: K > 1 runs the Python agents K
    to a process (``host_1``, ``host_2``, ...: one loop and one bus socket each,
    firmware_py.host), in agent order; they then take no fault-injection flags."""
    extra = extra or {}
    if agents_per_process < 1:
        raise BusRunError(f"agents per process: expected 1 or more, but got "
                          f"{agents_per_process}")

    def key(name: str) -> list[str]:
        return ["--insecure"] if keys is None else ["--key", str(keys / f"{name}.key")]

    rt = ["--rt-priority", str(rt_priority)] if rt_priority else []
    # a host of agents one above the rig's simulated plant and router: its loop is the
    # latency of all its agents, and it waited up to 9 ms for a CPU while both ran
    # bursts of frames at the same priority (FIFO does not preempt its equals). Not a
    # process per agent: twelve of them above the rig starved it beside a CPU hog (the
    # plant lost frames past its freshness window and failed their MACs).
    rt_host = ["--rt-priority", str(min(rt_priority + 1, 99))] if rt_priority else []
    bus_argv = bus.argv() + fd_argv(sc.fd, sc.lambda_tags)  # every node the bus's format
    cfg_dir = out / "agents"
    cfg_dir.mkdir(parents=True, exist_ok=True)
    py = [sys.executable, "-m"]
    # signed_price: the agents' counters of it have no Diag slot, so they write them at exit
    # (firmware_py and firmware_c's bessded-agent alike)
    counters = ["--counters-dir", str(out / "logs")] if sc.signed_price else []
    specs = []
    hosted: list[tuple[str, list[str]]] = []   # (agent, its --config and key flags)
    for cfg in agent_configs_from_scenario(sc):
        path = cfg_dir / f"agent_{cfg.id}.toml"
        path.write_text(cfg.to_toml())
        name = f"agent_{cfg.id}"
        if name in exclude:
            continue
        if cfg.id in c_agents:
            if c_node is None or extra.get(name):
                raise BusRunError(f"{name}: the C agent needs its node program and takes no "
                                  "fault-injection flags")
            c_bus = c_node_bus_argv(bus)
            if c_bus is None:
                raise BusRunError(f"{name}: the C agent's bus: expected {C_BUS_EXPECTED}, "
                                  f"but got {bus.resolved()}")
            specs.append(NodeSpec(name, [str(c_node), "--config", str(path)] + key(name)
                                  + c_bus + fd_argv(sc.fd, sc.lambda_tags) + rt + counters))
            continue
        if agents_per_process == 1:
            specs.append(NodeSpec(name, py + ["firmware_py", "--config", str(path)] + key(name)
                                  + bus_argv + rt + counters + extra.get(name, [])))
        elif extra.get(name):
            raise BusRunError(f"{name}: an agent of a host process (agents per process "
                              f"{agents_per_process}) takes no fault-injection flags")
        else:
            hosted.append((name, ["--config", str(path)] + key(name)))
    for k in range(0, len(hosted), agents_per_process):
        group = hosted[k:k + agents_per_process]
        specs.append(NodeSpec(f"host_{k // agents_per_process + 1}",
                              py + ["firmware_py"] + [a for _, argv in group for a in argv]
                              + bus_argv + rt_host + counters,
                              members=tuple(n for n, _ in group)))
    for role in SIM_NODES:
        if role in exclude:
            continue
        specs.append(NodeSpec(role, py + ["sim.cli", role, "--case", str(scenario_path),
                                          "--period", repr(sc.ts), "--counters-json",
                                          str(counters_path(out, role))]
                              + key(role) + bus_argv + rt + extra.get(role, [])))
    return specs


def counters_path(out: Path, role: str) -> Path:
    """Where the plant or router writes its counters at exit (--counters-json)."""
    return out / "logs" / f"{role}.counters.json"


def sim_node_counters(out: Path) -> dict[str, Any]:
    """The plant's and router's ticks and counters, for those that wrote them (a node
    that was SIGKILLed did not)."""
    out_ = {role: json.loads(path.read_text()) for role in SIM_NODES
            if (path := counters_path(out, role)).is_file()}
    # signed_price: the agents' counters of it (firmware_py's and bessded-agent's
    # --counters-dir)
    for path in sorted((out / "logs").glob("agent_*.counters.json")):
        out_[path.name.removesuffix(".counters.json")] = json.loads(path.read_text())
    return out_


def start(spec: NodeSpec, logdir: Path) -> None:
    """Start ``spec``'s process (its own session, stdout and stderr appended to
    ``logdir``/NAME.log), dying with its parent."""
    # append: a node restarted mid-run (fault tests) keeps its first life's log
    logfile = (logdir / f"{spec.name}.log").open("ab")
    # a session of its own: a terminal's Ctrl-C reaches `up` alone, which then stops the
    # nodes together and cuts the recording there (PR_SET_PDEATHSIG still ends a node
    # whose `up` was killed)
    spec.proc = subprocess.Popen(spec.argv, stdout=logfile, stderr=subprocess.STDOUT,
                                 stdin=subprocess.DEVNULL, preexec_fn=_die_with_parent,
                                 start_new_session=True)
    logfile.close()


@contextlib.contextmanager
def _above_the_nodes(rt_priority: int) -> Iterator[None]:
    """Run the block under SCHED_FIFO above the nodes' ``rt_priority`` (0: they run at
    normal priority, nothing to outrank), where the OS allows it.

    Stopping sends one SIGTERM per node. A real-time node that gets its signal preempts
    a normal-priority sender at once to tear down, and the nodes not yet signalled then
    starve and count deadline misses that are the harness's, not theirs (case 7: ~12
    per plant and router, all in the 0.1 s after the run)."""
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    raised = False
    if rt_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(min(rt_priority + 1, 99)))
            raised = True
        except OSError:  # not root: the nodes run at normal priority too (set_realtime)
            pass
    try:
        yield
    finally:
        if raised:
            os.sched_setscheduler(0, policy, param)


def stop_all(specs: list[NodeSpec], rt_priority: int = RT_PRIORITY) -> dict[str, int | None]:
    """SIGTERM every node, wait for a clean exit, SIGKILL what is left. Returns exit codes
    by node (a host's, each of its agents').
    ``rt_priority``: the SCHED_FIFO priority the nodes run at (node_specs)."""
    with _above_the_nodes(rt_priority):
        for s in specs:
            if s.proc is not None and s.proc.poll() is None:
                s.proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + STOP_GRACE_S
    codes: dict[str, int | None] = {}
    for s in specs:
        code = None
        if s.proc is not None:
            try:
                code = s.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                s.proc.kill()
                code = s.proc.wait()
        codes.update(dict.fromkeys(s.nodes, code))
    return codes



def check_alive(specs: list[NodeSpec], logdir: Path) -> None:
    """Before t = 0: a BusRunError with the tail of its log if a started node has exited."""
    for s in specs:
        if s.proc is not None and s.proc.poll() is not None:
            tail = (logdir / f"{s.name}.log").read_text(errors="replace")[-800:]
            raise BusRunError(f"node {s.name} exited with code {s.proc.returncode} before the "
                              f"run started:\n{tail}")
