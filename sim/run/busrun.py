"""`bess-ded up`: the router, the plant and every agent as separate OS processes on one bus.

This process only watches: it records every frame to DIR/run.log (candump
format), shows live progress, stops the nodes with SIGTERM at the end and
computes the metrics from the recording alone.

Over 500 lines: one run's life (specs, start, record, stop, in-process variant)
shares the Progress listener and the node specs; a split by process vs in-process is
the next step (docs/architecture.md).
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import random
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from firmware_py import contract, secoc
from firmware_py.config import agent_configs_from_scenario
from firmware_py.errors import BessDedError, FrameError
from firmware_py.frames import FrameCodec
from firmware_py.node import GuardedBus, bus_kwargs, open_bus
from sim.model.scenario import Scenario, to_toml
from sim.run.keyset import load_boot_floors, load_key_set, write_boot_floors, write_key_set
from sim.run.runreport import Recording, report
from sim.run.verdict import TOLERANCE, RunFacts

__all__ = ["BusOptions", "NodeSpec", "Recording", "in_process_nodes", "record", "run",
           "run_in_process"]

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


class BusRunError(BessDedError):
    """A bus run could not start or went wrong (no price frame, a node that
    cannot start, ...)."""


@dataclass
class BusOptions:
    """The bus a run uses: python-can interface, channel and extra config (JSON)."""

    interface: str | None = None
    channel: str | None = None
    config: str | None = None   # JSON of extra python-can arguments

    def resolved(self) -> dict[str, Any]:
        """The python-can arguments of this bus (flags, then CAN_* environment)."""
        return bus_kwargs(self.interface, self.channel, self.config)

    def argv(self) -> list[str]:
        """The same bus, as flags for a child node (resolved here so all nodes agree).
        Settings every node takes by itself (``bus_kwargs``'s defaults, e.g. socketcan's
        fd) are left out: firmware_c's node program takes no --bus-config."""
        kw = self.resolved()
        own = bus_kwargs(kw["interface"], kw.get("channel"), None)
        out = ["--interface", kw.pop("interface")]
        if "channel" in kw:
            out += ["--channel", str(kw.pop("channel"))]
        kw = {k: v for k, v in kw.items() if k not in own or own[k] != v}
        if kw:
            out += ["--bus-config", json.dumps(kw)]
        return out


@dataclass
class NodeSpec:
    """One node process of a run: its name, argv, start delay and process."""

    name: str
    argv: list[str]
    delay: float = 0.0            # start this long after `up` starts it (fault tests)
    proc: subprocess.Popen[bytes] | None = None


def _die_with_parent() -> None:
    """In the child: get SIGTERM if `up` dies, so no node outlives it (Linux only)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class Progress(can.Listener):
    """Live view from the frames: max|λ−ρ| and frames per second."""

    def __init__(self, codec: FrameCodec, n: int) -> None:
        self.codec, self.n = codec, n
        self.rho: float | None = None
        self.lam: dict[int, float] = {}
        self.frames = 0
        self.t_last_frame = 0.0  # its timestamp (wall-clock)
        self.t_first_price: float | None = None
        self.seen: set[int] = set()  # every frame ID heard so far
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        """Count a recorded frame; keep ρ and each agent's λ for the live view."""
        fid = msg.arbitration_id
        with self.lock:
            self.frames += 1
            self.t_last_frame = msg.timestamp
            self.seen.add(fid)
            if fid != contract.ER_PRICE_ID and not 0 < fid - contract.MC_BASE <= self.n:
                return
            try:
                f = self.codec.decode(msg)
            except FrameError:
                return
            if f.name == "ER_Price":
                self.rho = f.phys("Rho")
                if self.t_first_price is None:
                    self.t_first_price = time.monotonic()
            elif f.agent is not None:
                self.lam[f.agent] = f.phys("Lambda")

    def error(self) -> float | None:
        """max|λ_i − ρ| over every agent heard, whatever its state (as the verdict judges)."""
        with self.lock:
            if self.rho is None or not self.lam:
                return None
            return max(abs(v - self.rho) for v in self.lam.values())


SIM_NODES = ("plant", "router")  # the simulated nodes, started after the agents


PRIVATE_PORTS = (30000, 43000)  # below the test sessions' blocks (tests/conftest.py: 43200+)


def private_port(bus: BusOptions) -> tuple[BusOptions, int | None]:
    """On udp_multicast without a port named (flag or CAN_CONFIG), the same bus on a port
    of its own: every run on python-can's default port hears every other one (seen: ~900
    resets per agent and identical diagnostics in two concurrent runs). A different
    multicast group is not enough: Linux delivers a port's datagrams for every group
    joined on the host to every socket bound to that port. Returns (bus, chosen port)."""
    kw = bus.resolved()
    if kw["interface"] != "udp_multicast" or "port" in kw:
        return bus, None
    free = sorted(set(range(*PRIVATE_PORTS)) - _bound_udp_ports())
    if not free:
        raise BusRunError(f"no free UDP port in {PRIVATE_PORTS[0]}..{PRIVATE_PORTS[1] - 1} for "
                          "a private udp_multicast bus: name one with --bus-config "
                          "'{\"port\": N}'")
    port = random.SystemRandom().choice(free)
    extra = {k: v for k, v in kw.items() if k not in ("interface", "channel")}
    return BusOptions(kw["interface"], kw.get("channel"),
                      json.dumps({**extra, "port": port})), port


def _udp_sockets() -> Iterator[list[str]]:
    """The columns of each UDP socket on this host (/proc/net/udp{,6}; none elsewhere):
    [1] the local address:port (hex), [9] the inode, the last the kernel's drops."""
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        yield from (line.split() for line in lines)


def _bound_udp_ports() -> set[int]:
    """Local UDP ports with a socket bound on this host (empty where /proc has none)."""
    return {int(cols[1].rsplit(":", 1)[1], 16) for cols in _udp_sockets()}


def node_specs(sc: Scenario, scenario_path: Path, out: Path, bus: BusOptions,
               extra: dict[str, list[str]] | None = None,
               rt_priority: int = RT_PRIORITY, keys: Path | None = None,
               exclude: frozenset[str] = frozenset(),
               c_agents: frozenset[int] = frozenset(),
               c_node: Path | None = None) -> list[NodeSpec]:
    """Argv for every node. Agents and plant first; the router last, since its first
    price frame is t = 0 of the schedule. Every node runs under SCHED_FIFO
    ``rt_priority`` where the OS allows it (0: not), as firmware on an embedded Linux
    would; plant and router too, or the agents starve them on an overloaded host.
    ``keys``: the key set directory (each node gets ``--key DIR/<node>.key``); None:
    every node runs ``--insecure``. ``exclude``: nodes not started here (a device under
    test takes their place: `bess-ded restbus`); an agent's configuration file is still
    written, for the device. ``c_agents``: the agents that run the C firmware's node
    program ``c_node`` (firmware_c's bessded-agent, SocketCAN only) from the same
    configuration and key files."""
    extra = extra or {}

    def key(name: str) -> list[str]:
        return ["--insecure"] if keys is None else ["--key", str(keys / f"{name}.key")]

    rt = ["--rt-priority", str(rt_priority)] if rt_priority else []
    cfg_dir = out / "agents"
    cfg_dir.mkdir(parents=True, exist_ok=True)
    py = [sys.executable, "-m"]
    specs = []
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
            specs.append(NodeSpec(name, [str(c_node), "--config", str(path)] + key(name)
                                  + ["--channel", str(bus.resolved().get("channel"))] + rt))
            continue
        specs.append(NodeSpec(name, py + ["firmware_py", "--config", str(path)] + key(name)
                              + bus.argv() + rt + extra.get(name, [])))
    for role in SIM_NODES:
        if role in exclude:
            continue
        specs.append(NodeSpec(role, py + ["sim.cli", role, "--case", str(scenario_path),
                                          "--period", repr(sc.ts), "--counters-json",
                                          str(counters_path(out, role))]
                              + key(role) + bus.argv() + rt + extra.get(role, [])))
    return specs


def counters_path(out: Path, role: str) -> Path:
    """Where the plant or router writes its counters at exit (--counters-json)."""
    return out / "logs" / f"{role}.counters.json"


def sim_node_counters(out: Path) -> dict[str, Any]:
    """The plant's and router's ticks and counters, for those that wrote them (a node
    that was SIGKILLed did not)."""
    return {role: json.loads(path.read_text()) for role in SIM_NODES
            if (path := counters_path(out, role)).is_file()}


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
    """SIGTERM every node, wait for a clean exit, SIGKILL what is left. Returns exit codes.
    ``rt_priority``: the SCHED_FIFO priority the nodes run at (node_specs)."""
    with _above_the_nodes(rt_priority):
        for s in specs:
            if s.proc is not None and s.proc.poll() is None:
                s.proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + STOP_GRACE_S
    codes: dict[str, int | None] = {}
    for s in specs:
        if s.proc is None:
            codes[s.name] = None
            continue
        try:
            codes[s.name] = s.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            s.proc.kill()
            codes[s.name] = s.proc.wait()
    return codes


def run(sc: Scenario, out: Path, bus: BusOptions, **kw: Any) -> dict[str, Any]:
    """``record`` and return the metrics only."""
    return record(sc, out, bus, **kw).metrics


class _Terminated(KeyboardInterrupt):
    """SIGTERM, handled like Ctrl-C: stop the nodes, then report what was recorded."""


@contextlib.contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    def handler(signum: int, frame: Any) -> None:
        raise _Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread (a test driving record() from a thread)
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def record(sc: Scenario, out: Path, bus: BusOptions, duration: float | None = None,
           extra: dict[str, list[str]] | None = None, delays: dict[str, float] | None = None,
           quiet: bool = False, rt_priority: int = RT_PRIORITY,
           actions: Sequence[tuple[float, Callable[[list[NodeSpec], Path], None]]] = (),
           plot: bool = True, time_scale: float = 1.0, keys: Path | None = None,
           insecure: bool = False, dut: str | None = None, dut_wait_s: float = 60.0,
           on_ready: Callable[[Path | None], None] | None = None,
           c_agents: frozenset[int] = frozenset(), c_node: Path | None = None,
           tolerance: float = TOLERANCE) -> Recording:
    """Run the scenario on the bus for ``duration`` s of price time (default: the
    scenario's). ``extra`` adds argv per node (fault flags),
    ``delays`` starts a node late (s after t = 0), ``actions`` calls
    ``action(specs, logdir)`` once at t s after t = 0 (fault tests: kill or restart a
    node through ``spec.proc`` / ``start``; whatever is in ``spec.proc`` at the end is
    stopped as usual). ``plot=False`` skips bus_run.png (matplotlib's import and render
    cost ~20 s in the QEMU guest). ``time_scale``: the factor ``sc`` was stretched by,
    for the plot's axis.

    ``dut``: a node of the scenario ("agent_3", "plant") that is not started here: a
    device under test on the same bus takes its place (`bess-ded restbus`). The router
    starts only once every frame the device sends has been heard (within
    ``dut_wait_s``, else BusRunError), so t = 0 finds it running. ``on_ready(key_dir)``
    is called once the key set and the agents' configuration files are written, before
    any node starts (to tell the operator, or a test, what to give the device).
    ``c_agents`` run firmware_c's node program ``c_node`` instead of firmware_py.
    ``tolerance``: the verdict's bound on the final |λ − ρ| (cu/kWh).

    SIGINT or SIGTERM stops the run early: the nodes are stopped and the outputs are
    written for what was recorded, with the verdict marked interrupted. Every node that
    exits during the run is a ``node_died`` anomaly (fault tests kill nodes on purpose
    and assert it)."""
    # the bus first: a run that cannot start (a bad --interface, --channel, ...) fails
    # before it writes anything, so an earlier run's outputs and keys in OUT stay intact
    watch = open_bus(**{**bus.resolved(), "receive_own_messages": False})
    try:
        enlarge_receive_buffer(watch)
        # a device under test may never come: then the earlier run in OUT stays as it was
        with _previous_kept(out) if dut else contextlib.nullcontext():
            return _record(sc, out, bus, watch, duration, extra, delays, quiet,
                           rt_priority, actions, plot, time_scale, keys, insecure, dut,
                           dut_wait_s, on_ready, c_agents, c_node, tolerance)
    finally:
        watch.shutdown()


@contextlib.contextmanager
def _previous_kept(out: Path) -> Iterator[None]:
    """Run into ``out`` with an earlier run's outputs there moved beside it (OUT.previous)
    and put back if the run fails (its own outputs then go to OUT.failed, for their node
    logs); deleted once it has run. A leftover OUT.previous (a run killed outright) may be
    the only copy of a run: refused, never overwritten."""
    if not out.is_dir() or not any(out.iterdir()):
        yield
        return
    aside, failed = out.with_name(out.name + ".previous"), out.with_name(out.name + ".failed")
    if aside.exists():
        raise BusRunError(f"{aside} exists (an earlier run's outputs, left by a run that "
                          f"was killed): move it back to {out} or delete it, then run again")
    out.rename(aside)
    out.mkdir()
    try:
        yield
    except BaseException as e:
        if failed.exists():
            shutil.rmtree(failed)
        out.rename(failed)
        aside.rename(out)
        if isinstance(e, BusRunError):
            raise BusRunError(f"{e} ({out} still holds the previous run; this attempt's "
                              f"logs are in {failed})") from None
        raise
    shutil.rmtree(aside)


def _record(sc: Scenario, out: Path, bus: BusOptions, watch: can.BusABC,
            duration: float | None,
            extra: dict[str, list[str]] | None, delays: dict[str, float] | None,
            quiet: bool, rt_priority: int,
            actions: Sequence[tuple[float, Callable[[list[NodeSpec], Path], None]]],
            plot: bool, time_scale: float, keys: Path | None, insecure: bool,
            dut: str | None, dut_wait_s: float,
            on_ready: Callable[[Path | None], None] | None,
            c_agents: frozenset[int], c_node: Path | None,
            tolerance: float) -> Recording:
    out.mkdir(parents=True, exist_ok=True)
    duration = sc.duration if duration is None else duration
    # the nodes read exactly what ran: variants resolved, time scale applied
    scenario_path = out / "scenario.toml"
    scenario_path.write_text(to_toml(sc))
    logdir = out / "logs"
    logdir.mkdir(exist_ok=True)
    for role in SIM_NODES:  # a previous run's, in a reused DIR
        counters_path(out, role).unlink(missing_ok=True)
    run_facts_path(out).unlink(missing_ok=True)
    codec = FrameCodec()
    key_dir = None if insecure else keys or provision_keys(sc, out / "keys")
    specs = node_specs(sc, scenario_path, out, bus, extra, rt_priority, key_dir,
                       frozenset({dut}) if dut else frozenset(), c_agents, c_node)
    # read before any node starts, for the nodes this run starts (not a device under
    # test, whose key file is its own): a sync of an earlier boot is then a replay
    # (--insecure senders always run at boot 1: no floor to know)
    started = {s.name for s in specs}
    boot_floors = (None if key_dir is None else
                   {n: b for n, b in load_boot_floors(key_dir).items() if n in started})
    if key_dir is not None and boot_floors:  # AUTH-21: the nodes take no earlier boot either
        write_boot_floors(key_dir, sorted(started), boot_floors)
    if on_ready is not None:
        on_ready(key_dir)
    for s in specs:
        s.delay = (delays or {}).get(s.name, 0.0)
    monitor_keys = (load_key_set(key_dir) if key_dir is not None else
                    {n: secoc.derive_node_key(secoc.INSECURE_MASTER, n)
                     for n in secoc.fleet_nodes(sc.n)})
    writer = _Until(can.Logger(str(out / "run.log")))
    progress = Progress(codec, sc.n)
    # above the real-time nodes on udp_multicast, where 14 nodes' datagrams fill one
    # socket buffer while they take both CPUs; on SocketCAN (a vcan guest, a HIL rig) at
    # normal priority, where a real-time recorder took the CPU of the nodes it recorded
    # (the QEMU guest's case runs missed their ticks and did not converge)
    udp = bus.resolved().get("interface") == "udp_multicast"
    notifier = Recorder(watch, [writer, progress], rt_priority if udp else 0)
    deaths: list[tuple[str, float, int]] = []
    interrupted = False
    try:
        with _sigterm_interrupts():
            try:
                _run_nodes(specs, logdir, progress, duration, quiet, actions, deaths,
                           _dut_ids(sc, dut) if dut else frozenset(), dut_wait_s)
            except KeyboardInterrupt:
                interrupted = True
                if not quiet:
                    print("\n  interrupted: stopping the nodes and reporting what was "
                          "recorded", file=sys.stderr, flush=True)
    finally:
        # the run ends here: what the nodes send while they shut down is not the run's
        writer.t_stop = time.time()  # frame timestamps are wall-clock
        codes = stop_all(specs, rt_priority)
        _drain(progress)
        notifier.stop()
        writer.stop()
    facts = RunFacts(exit_codes=codes, deaths=deaths, node_counters=sim_node_counters(out),
                     interrupted=interrupted, recorder_counters=notifier.counters(),
                     insecure=key_dir is None)
    write_run_facts(out, facts, boot_floors, time_scale, tolerance)
    return report(sc, out / "run.log", out, facts, plot=plot, time_scale=time_scale,
                  codec=codec, keys=monitor_keys, boot_floors=boot_floors,
                  tolerance=tolerance)


def run_facts_path(out: Path) -> Path:
    """What `up` knew beyond the recording (exit codes, deaths, --insecure, the boot
    floors its monitor used, time scale, tolerance): `analyze DIR` reads it back, so the
    same run gets the same verdict from both."""
    return out / "logs" / "run_facts.json"


def write_run_facts(out: Path, facts: RunFacts, boot_floors: Mapping[str, int] | None,
                    time_scale: float, tolerance: float) -> None:
    """Write ``out``'s run_facts.json: what ``analyze`` needs of a run beyond its
    log (exit codes, deaths, boot floors, time scale, tolerance)."""
    doc = {**facts.as_json(), "boot_floors": dict(boot_floors or {}),
           "time_scale": time_scale, "tolerance": tolerance}
    run_facts_path(out).write_text(json.dumps(doc, indent=2) + "\n")


def provision_keys(sc: Scenario, key_dir: Path) -> Path:
    """A fresh key set for one run in ``key_dir`` (0700; a previous run's is replaced):
    every run signs with keys no other run holds, so nothing recorded elsewhere replays."""
    if key_dir.exists():
        shutil.rmtree(key_dir)
    key_dir.mkdir(mode=0o700, parents=True)
    write_key_set(sc, key_dir, secrets.token_bytes(secoc.KEY_BYTES))
    return key_dir


class Recorder:
    """The recorder's receive thread (in place of can.Notifier, which ends at the first
    exception python-can raises from recv): every frame goes to ``listeners``; what the
    bus delivers that is not a frame is counted by cause (GuardedBus, ``counters``) and
    the recording goes on."""

    def __init__(self, bus: can.BusABC, listeners: Sequence[can.Listener],
                 rt_priority: int = 0) -> None:
        self.bus = GuardedBus(bus, lambda cause: None, who="recorder")
        self.listeners = list(listeners)
        self.rt_priority = rt_priority
        # A recorder the host starves longer than its receive buffer lasts (record()
        # enlarges it: enlarge_receive_buffer) loses frames, in stretches the 4-bit
        # counters cannot show; the kernel's drops are counted (``rx_overflow``).
        self._socket = bus_socket(bus)
        self._overflow = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        # Above the nodes' SCHED_FIFO priority (``rt_priority``: theirs, 0: they run at
        # normal priority): at normal priority the recorder got only what 14 real-time
        # nodes left of 2 CPUs, and lost 2.3 s of frames at a stretch beside them.
        if self.rt_priority:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK,
                                      os.sched_param(min(self.rt_priority + 1, 99)))
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=0.1)
            if msg is not None:
                for listener in self.listeners:
                    listener.on_message_received(msg)

    def counters(self) -> dict[str, int]:
        """The inputs dropped so far, by cause (only those that occurred), the kernel's
        drops at a full receive buffer (``rx_overflow``) included."""
        out = {k: v for k, v in self.bus.counters.items() if v}
        if self._socket is not None and self._socket.fileno() >= 0:  # the bus still open
            self._overflow = _udp_drops(self._socket)
        if self._overflow:
            out["rx_overflow"] = self._overflow
        return out

    def stop(self) -> None:
        """Stop the receive thread (within 5 s) and read the socket's drop count."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        if self._socket is not None and self._socket.fileno() >= 0:
            self._overflow = _udp_drops(self._socket)


def _udp_drops(sock: socket.socket) -> int:
    """Datagrams the kernel dropped for this UDP socket (its ``drops`` column in
    /proc/net/udp{,6}); 0 for other sockets."""
    try:
        inode = str(os.fstat(sock.fileno()).st_ino)
    except OSError:
        return 0
    return next((int(cols[-1]) for cols in _udp_sockets()
                 if len(cols) > 12 and cols[9] == inode), 0)


class _Until(can.Listener):
    """Pass frames to ``inner`` up to ``t_stop`` (frame time), once it is set."""

    def __init__(self, inner: can.Listener) -> None:
        self.inner = inner
        self.t_stop: float | None = None

    def on_message_received(self, msg: can.Message) -> None:
        if self.t_stop is None or msg.timestamp <= self.t_stop:
            self.inner.on_message_received(msg)

    def stop(self) -> None:
        self.inner.stop()


def _run_nodes(specs: list[NodeSpec], logdir: Path, progress: Progress, duration: float,
               quiet: bool,
               actions: Sequence[tuple[float, Callable[[list[NodeSpec], Path], None]]],
               deaths: list[tuple[str, float, int]],
               dut_ids: frozenset[int] = frozenset(), dut_wait_s: float = 60.0) -> None:
    # All at once (the router last): started one after the other, each would start
    # while the others already run, which in the QEMU guest took ~40 s per node (a router
    # held until the plant was heard came up 41 s after it there, beside the running
    # real-time nodes). With a device under test, the router waits until the device is
    # heard.
    held = [s for s in specs if dut_ids and s.name == "router"]
    for s in specs:
        if s.delay == 0 and s not in held:
            start(s, logdir)
    if held:
        _await_device(specs, logdir, progress, dut_ids, dut_wait_s, quiet)
        start(held[0], logdir)
    t_start = time.monotonic()
    while progress.t_first_price is None:
        if time.monotonic() - t_start > START_TIMEOUT_S:
            raise BusRunError(f"no price frame within {START_TIMEOUT_S:.0f} s: see "
                              f"{logdir}/router.log")
        _check_alive(specs, logdir)
        time.sleep(0.05)
    t0 = progress.t_first_price
    last_print, frames_then, t_then = 0.0, progress.frames, time.monotonic()
    tty = sys.stderr.isatty()
    pending = sorted(actions, key=lambda a: a[0])
    seen_dead: set[int] = set()
    while (now := time.monotonic()) - t0 < duration:
        while pending and now - t0 >= pending[0][0]:
            pending.pop(0)[1](specs, logdir)
        for s in specs:
            if s.proc is None and now - t0 >= s.delay > 0:
                start(s, logdir)
            elif s.proc is not None and s.proc.pid not in seen_dead \
                    and (code := s.proc.poll()) is not None:
                seen_dead.add(s.proc.pid)
                deaths.append((s.name, now - t0, code))
                if not quiet:
                    print(("\n" if tty else "") + f"  {s.name} exited with code {code} at "
                          f"t = {now - t0:.1f} s", file=sys.stderr, flush=True)
        if not quiet and now - last_print >= (0.5 if tty else 5.0):
            last_print = now
            err = progress.error()
            rate = (progress.frames - frames_then) / max(now - t_then, 1e-9)
            frames_then, t_then = progress.frames, now
            print(("\r" if tty else "") + f"  t = {now - t0:6.1f} / {duration:.0f} s   "
                  f"max|λ−ρ| = {'   n/a  ' if err is None else f'{err:.2e}'}   "
                  f"frames/s = {rate:6.0f}", end="" if tty else "\n", file=sys.stderr,
                  flush=True)
        time.sleep(0.05)
    if not quiet and tty:
        print(file=sys.stderr)


def _dut_ids(sc: Scenario, dut: str) -> frozenset[int]:
    """The frames a device under test must be heard sending before t = 0."""
    if dut == "plant":
        return frozenset(contract.STATUS_BASE + i for i in range(1, sc.n + 1))
    i = int(dut.removeprefix("agent_"))
    return frozenset({contract.MC_BASE + i, contract.SETPOINT_BASE + i})


def _await_device(specs: list[NodeSpec], logdir: Path, progress: Progress,
                  ids: frozenset[int], wait_s: float, quiet: bool) -> None:
    t_start = time.monotonic()
    last_note = t_start
    while True:
        with progress.lock:
            missing = ids - progress.seen
        if not missing:
            return
        now = time.monotonic()
        if now - t_start > wait_s:
            raise BusRunError(f"the device under test sent no "
                              f"{', '.join(f'0x{i:03X}' for i in sorted(missing))} within "
                              f"{wait_s:g} s: is it on this bus, with this run's key file?")
        if not quiet and now - last_note >= 5.0:
            last_note = now
            print(f"  waiting for the device under test ({now - t_start:.0f} s): no "
                  f"{', '.join(f'0x{i:03X}' for i in sorted(missing))} yet",
                  file=sys.stderr, flush=True)
        _check_alive(specs, logdir)
        time.sleep(0.05)


RECORDER_QUIET_S = 0.5  # the recorder is done when no frame came for this long


def _drain(progress: Progress) -> None:
    """After the nodes have stopped, let the recorder read what its socket still queues:
    in the loaded QEMU guest it ran up to ~40 s behind the bus (case 7), and stopping
    it at once cut that off the log. Done when it has read a frame stamped after the
    stop (the queue is FIFO; other senders may go on) or nothing came for a while."""
    t_stop = time.time()  # frame timestamps are wall-clock
    deadline = time.monotonic() + START_TIMEOUT_S
    last, t_last = -1, time.monotonic()
    while time.monotonic() < deadline and progress.t_last_frame < t_stop:
        n = progress.frames
        if n != last:
            last, t_last = n, time.monotonic()
        elif time.monotonic() - t_last >= RECORDER_QUIET_S:
            return
        time.sleep(0.05)


RECORDER_RCVBUF = 16 << 20  # bytes: ~20k CAN frames (an skb per frame) of slack


def bus_socket(bus: can.BusABC) -> socket.socket | None:
    """The bus's own socket, None for interfaces without one. python-can exposes the
    socketcan socket as ``bus.socket``; udp_multicast keeps its own in
    ``bus._multicast._socket`` (no public accessor)."""
    sock = getattr(bus, "socket", None)
    if sock is None:
        sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    return sock if isinstance(sock, socket.socket) else None


def enlarge_receive_buffer(bus: can.BusABC) -> None:
    """A recorder the nodes starve (on SocketCAN it runs at normal priority beside
    real-time nodes; on udp_multicast above them, but the host may still starve it):
    the kernel queues the frames for it here instead of dropping them (a socketcan
    socket holds only ~200 frames by default, a udp_multicast one ~300). Other
    interfaces are left as they are."""
    sock = bus_socket(bus)
    if sock is None:
        return
    for opt in (getattr(socket, "SO_RCVBUFFORCE", 33), socket.SO_RCVBUF):  # FORCE: root
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, RECORDER_RCVBUF)
            return
        except OSError:
            continue


def _check_alive(specs: list[NodeSpec], logdir: Path) -> None:
    for s in specs:
        if s.proc is not None and s.proc.poll() is not None:
            tail = (logdir / f"{s.name}.log").read_text(errors="replace")[-800:]
            raise BusRunError(f"node {s.name} exited with code {s.proc.returncode} before the "
                              f"run started:\n{tail}")


def _note(nodes: list[Any], i: int, cause: str) -> None:
    nodes[i].note(cause)


def in_process_nodes(sc: Scenario, codec: FrameCodec, rings: Mapping[str, secoc.Keyring],
                     plant_faults: tuple[Any, ...] = (), router_silent: tuple[Any, ...] = ()
                     ) -> dict[str, Callable[[], Any]]:
    """Node name (as in `up`) → a factory of that node as an in-process object (``on_frame(msg,
    t)``, ``tick(t)`` → frames), agents first, then the plant and the router: what
    ``run_in_process`` steps, and ``sim.testkit.SimFleet`` for any subset of them."""
    from firmware_py.runtime import AgentRuntime
    from sim.nodes.plant import PlantNode
    from sim.nodes.router import RouterNode

    factories: dict[str, Callable[[], Any]] = {
        f"agent_{c.id}": functools.partial(AgentRuntime, c, codec, rings[f"agent_{c.id}"])
        for c in agent_configs_from_scenario(sc)}
    factories["plant"] = lambda: PlantNode(sc, period=sc.ts, faults=plant_faults,
                                           keys=rings["plant"])
    factories["router"] = lambda: RouterNode(sc, period=sc.ts, silent=router_silent,
                                             keys=rings["router"])
    return factories


def recorder_keys(rings: Mapping[str, secoc.Keyring]) -> dict[str, bytes]:
    """The key the recorder verifies each node's frames with: the one most of the other
    nodes hold for it (the fleet's, as `up`'s recorder reads DIR/keys), not the node's own,
    so a node given another key is caught as its receivers catch it."""
    out = {}
    for n, ring in rings.items():
        held = Counter(k for m, r in rings.items() if m != n
                       and (k := r.key_of(n)) is not None)
        out[n] = held.most_common(1)[0][0] if held else ring.key
    return out


def run_in_process(sc: Scenario, out: Path, duration: float, channel: str = "bess-ded",
                   plant_faults: tuple[Any, ...] = (), router_silent: tuple[Any, ...] = (),
                   restarts: Sequence[tuple[str, float, float]] = (),
                   keyrings: Mapping[str, secoc.Keyring] | None = None,
                   insecure: bool = False,
                   inject: Callable[[float], Sequence[can.Message]] | None = None,
                   observe: Callable[[float, dict[str, Any]], None] | None = None,
                   tolerance: float = TOLERANCE) -> dict[str, Any]:
    """The same nodes as `up` on python-can's in-process ``virtual`` bus, stepped on a
    simulated clock.

    Every node has its own bus instance, so each frame really crosses the bus (encode,
    CRC, bus, decode, E2E and range checks), but no thread races the wall clock: one
    loop advances t by Ts, hands every node what its bus holds, then ticks every node.
    A frame sent at sample k is read at sample k + 1 (one sample of transport delay, as
    on a bus cycled at Ts), so the run is deterministic and faster than real time; the
    multi-process runs (``run``) cover real-time scheduling. Frames are stamped with the
    simulated time (t = 0: the router's first price frame). Records DIR/run.log and
    returns the metrics.

    ``restarts``: (node name as in `up`, e.g. ``"agent_4"``; t_down; t_up), a node killed
    and restarted: from the first sample at or after t_down it neither reads nor sends
    (what reaches its bus meanwhile is lost, as with a dead process), and from the first
    sample at or after t_up a fresh node (new state, the same configuration) runs in its
    place, as a restarted process would (its keyring keeps its boot counter, as its
    key file would). t_up = inf: never restarted.

    Keys: each node's keyring from ``keyrings`` (node name → Keyring, e.g.
    ``Keyring.fleet(master, ...)``: passing the same ones to two runs is a key set
    reused, its boot counters moving on), else from a fresh master key per run whose
    key files go to DIR/keys (as `up` writes them); ``insecure``: the public demo keys.
    ``inject(t)``: frames an attacker sends at sample t (after the nodes' own), on a
    bus instance of its own; the recording and the analysis see them as any frame.
    ``observe(t, nodes)``: called after every sample with the live nodes by name (a
    test's window on state the bus does not carry, e.g. an agent's neighbours alive).
    """
    out.mkdir(parents=True, exist_ok=True)
    codec = FrameCodec()
    nodes_ = secoc.fleet_nodes(sc.n)
    if insecure:
        rings = {n: secoc.Keyring.insecure_for(n) for n in nodes_}
    elif keyrings is not None:
        rings = dict(keyrings)
    else:  # a fresh key set, written to DIR/keys as `up` does (for `analyze` later)
        master = secrets.token_bytes(secoc.KEY_BYTES)
        rings = secoc.Keyring.fleet(master, nodes_)
        key_dir = out / "keys"
        if key_dir.exists():
            shutil.rmtree(key_dir)
        key_dir.mkdir(mode=0o700)
        write_key_set(sc, key_dir, master)
    # each node's boot at this start, as `up` reads it from the key files (the recorder's
    # floors: a sync of an earlier boot is from an earlier run, AUTH-21)
    boot_floors = None if insecure else {n: r.boot + 1 for n, r in rings.items()}
    factories = in_process_nodes(sc, codec, rings, plant_faults, router_silent)
    names = list(factories)
    nodes: list[Any] = [make() for make in factories.values()]
    down = {name: (t_down, t_up) for name, t_down, t_up in restarts}
    if unknown := set(down) - set(names):
        raise BusRunError(f"restarts: expected node names among {names}, but got "
                          f"{sorted(unknown)}")
    if any(abs(n.period - sc.ts) > 1e-12 for n in nodes):
        raise BusRunError(f"every node must tick at Ts = {sc.ts} s to be stepped together")
    kw: dict[str, Any] = {"interface": "virtual", "channel": channel,
                          "receive_own_messages": False, "preserve_timestamps": True}
    buses = [can.Bus(**kw) for _ in nodes]
    watch = can.Bus(**kw)
    recorder = GuardedBus(watch, lambda cause: None, who="recorder")
    # what each node reads, as run_node reads it (the node at index i, restarts included)
    guards = [GuardedBus(bus, functools.partial(_note, nodes, i), who=name)
              for i, (bus, name) in enumerate(zip(buses, names, strict=True))]
    attacker = can.Bus(**kw) if inject is not None else None
    writer = can.Logger(str(out / "run.log"))
    try:
        eps = 1e-9 * sc.ts
        for k in range(round(duration / sc.ts)):
            t = k * sc.ts
            alive = [True] * len(nodes)
            for i, name in enumerate(names):
                if name in down:
                    t_down, t_up = down[name]
                    if t_down - eps <= t < t_up - eps:
                        alive[i] = False
                    elif t >= t_up - eps and t - sc.ts < t_up - eps:
                        nodes[i] = factories[name]()  # restarted: a fresh process
            for node, guarded, up in zip(nodes, guards, alive, strict=True):
                while (msg := guarded.recv(timeout=0)) is not None:  # as run_node reads
                    if up:
                        node.on_frame(msg, t)
            for node, bus, up in zip(nodes, buses, alive, strict=True):
                for frame in node.tick(t) if up else ():
                    frame.timestamp = t
                    bus.send(frame)
            if observe is not None:
                observe(t, {n: node for n, node, up in zip(names, nodes, alive, strict=True)
                            if up})
            if attacker is not None and inject is not None:
                for frame in inject(t):
                    frame.timestamp = t
                    attacker.send(frame)
            while (msg := recorder.recv(timeout=0)) is not None:
                writer.on_message_received(msg)
    finally:
        writer.stop()
        for bus in [*buses, watch, *([attacker] if attacker else [])]:
            bus.shutdown()
    counters = {role: {"ticks": node.ticks, "counters": dict(node.counters)}
                for role, node in zip(SIM_NODES, nodes[-2:], strict=True)}
    dropped = {k: v for k, v in recorder.counters.items() if v}
    # left as `up` leaves them, so `analyze DIR` judges this run as it is judged here
    (out / "scenario.toml").write_text(to_toml(sc))
    (out / "logs").mkdir(exist_ok=True)
    for role, c in counters.items():
        counters_path(out, role).write_text(json.dumps(c) + "\n")
    facts = RunFacts(node_counters=counters, recorder_counters=dropped, insecure=insecure)
    write_run_facts(out, facts, boot_floors, 1.0, tolerance)
    m = report(sc, out / "run.log", out, facts, plot=False, codec=codec,
               keys=recorder_keys(rings), tolerance=tolerance,
               boot_floors=boot_floors).metrics
    m["node_summaries"] = [n.summary() for n in nodes]
    return m
