"""`bess-ded up`: the router, the plant and every agent as separate OS processes on one bus.

This process only watches: it records every frame to DIR/run.log (candump
format), shows live progress, stops the nodes with SIGTERM at the end and
computes the metrics from the recording alone (``record``, ``run``).

The run's parts live beside it: the bus options and sockets (``sim.run.busopts``), the
node processes (``sim.run.nodeprocs``), the recorder and live view
(``sim.run.recorder``), the report and run_facts.json (``sim.run.runreport``), the key
set (``sim.run.keyset``); the same nodes in this process on a simulated clock are
``sim.run.inprocess``. This module re-exports their public names, so
``sim.run.busrun`` stays the one import of a run's API (docs/api.md).
"""

from __future__ import annotations

import contextlib
import shutil
import signal
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import can

from dbc import dbc_path
from firmware_py import contract, secoc
from firmware_py.faultinject import node_seed
from firmware_py.frames import FrameCodec
from firmware_py.node import open_bus
from sim.model.scenario import Scenario, to_toml
from sim.run.busopts import (
    PRIVATE_PORTS,
    RECORDER_RCVBUF,
    BusOptions,
    BusRunError,
    bound_udp_ports,
    bus_socket,
    enlarge_receive_buffer,
    private_port,
)
from sim.run.inprocess import in_process_nodes, injected_loss, recorder_keys, run_in_process
from sim.run.keyset import (
    derived_keys,
    load_boot_floors,
    load_key_set,
    provision_keys,
    write_boot_floors,
)
from sim.run.nodeprocs import (
    IN_GUEST,
    RT_PRIORITY,
    SIM_NODES,
    START_TIMEOUT_S,
    STOP_GRACE_S,
    NodeSpec,
    check_alive,
    counters_path,
    node_specs,
    sim_node_counters,
    start,
    stop_all,
)
from sim.run.recorder import Cutoff, Progress, Recorder, drain
from sim.run.runreport import Recording, report, run_facts_path, write_run_facts
from sim.run.verdict import TOLERANCE, RunFacts

__all__ = ["IN_GUEST", "PRIVATE_PORTS", "RECORDER_RCVBUF", "RT_PRIORITY", "SIM_NODES",
           "START_TIMEOUT_S", "STOP_GRACE_S", "BusOptions", "BusRunError", "NodeSpec",
           "Progress", "Recorder", "Recording", "bound_udp_ports", "bus_socket",
           "counters_path", "enlarge_receive_buffer", "in_process_nodes", "node_specs",
           "private_port", "provision_keys", "record", "recorder_keys", "run",
           "run_facts_path", "run_in_process", "sim_node_counters", "start", "stop_all",
           "write_run_facts"]


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
           tolerance: float = TOLERANCE, loss: float = 0.0, loss_seed: int = 0,
           agents_per_process: int = 1) -> Recording:
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
    ``agents_per_process``: the Python agents K to a process (nodeprocs.node_specs).

    ``loss``: the random-loss fault mode (`up --loss`, docs/faults.md): every node started
    here loses each frame it receives but its own echo with probability ``loss``, from
    its own generator seeded from ``loss_seed`` and its name (its fault-injection flags,
    ``--inject-rx-loss``); the losses each node counted are the metrics'
    ``injected_loss`` and the verdict does not blame them on a node.

    SIGINT or SIGTERM stops the run early: the nodes are stopped and the outputs are
    written for what was recorded, with the verdict marked interrupted. Every node that
    exits during the run is a ``node_died`` anomaly (fault tests kill nodes on purpose
    and assert it)."""
    # the bus first: a run that cannot start (a bad --interface, --channel, ...) fails
    # before it writes anything, so an earlier run's outputs and keys in OUT stay intact
    watch = open_bus(**{**bus.resolved(), "receive_own_messages": False})
    try:
        enlarge_receive_buffer(watch, RECORDER_RCVBUF)
        # a device under test may never come: then the earlier run in OUT stays as it was
        with _previous_kept(out) if dut else contextlib.nullcontext():
            return _record(sc, out, bus, watch, duration, extra, delays, quiet,
                           rt_priority, actions, plot, time_scale, keys, insecure, dut,
                           dut_wait_s, on_ready, c_agents, c_node, tolerance, loss,
                           loss_seed, agents_per_process)
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
            tolerance: float, loss: float = 0.0, loss_seed: int = 0,
            agents_per_process: int = 1) -> Recording:
    out.mkdir(parents=True, exist_ok=True)
    if not 0 <= loss < 1:
        raise BusRunError(f"loss: expected a probability in [0, 1), but got {loss}")
    if loss > 0:
        extra = loss_argv(sc, loss, loss_seed, extra)
    duration = sc.duration if duration is None else duration
    # the nodes read exactly what ran: variants resolved, time scale applied
    scenario_path = out / "scenario.toml"
    scenario_path.write_text(to_toml(sc))
    logdir = out / "logs"
    logdir.mkdir(exist_ok=True)
    for role in SIM_NODES:  # a previous run's, in a reused DIR
        counters_path(out, role).unlink(missing_ok=True)
    for path in logdir.glob("agent_*.counters.json"):  # signed_price's (--counters-dir)
        path.unlink()
    run_facts_path(out).unlink(missing_ok=True)
    codec = FrameCodec(dbc_path(sc.fd, sc.lambda_tags))
    key_dir = None if insecure else keys or provision_keys(sc, out / "keys")
    specs = node_specs(sc, scenario_path, out, bus, extra, rt_priority, key_dir,
                       frozenset({dut}) if dut else frozenset(), c_agents, c_node,
                       agents_per_process)
    # read before any node starts, for the nodes this run starts (not a device under
    # test, whose key file is its own): a sync of an earlier boot is then a replay
    # (--insecure senders always run at boot 1: no floor to know)
    started = {n for s in specs for n in s.nodes}
    boot_floors = (None if key_dir is None else
                   {n: b for n, b in load_boot_floors(key_dir).items() if n in started})
    if key_dir is not None and boot_floors:  # AUTH-21: the nodes take no earlier boot either
        write_boot_floors(key_dir, sorted(started), boot_floors)
    if on_ready is not None:
        on_ready(key_dir)
    for s in specs:
        s.delay = (delays or {}).get(s.name, 0.0)
    monitor_keys = (load_key_set(key_dir) if key_dir is not None else
                    derived_keys(secoc.INSECURE_MASTER, sc.n))
    writer = Cutoff(can.Logger(str(out / "run.log")))
    progress = Progress(codec, sc.n)
    # real-time on udp_multicast (the rig's priority; the agents run one above), where
    # 14 nodes' datagrams fill one socket buffer while they take both CPUs; on SocketCAN
    # (a vcan guest, a HIL rig) at normal priority, where a real-time recorder took the
    # CPU of the nodes it recorded (the QEMU guest's case runs missed their ticks and did
    # not converge)
    udp = bus.resolved().get("interface") == "udp_multicast"
    notifier = Recorder(watch, [writer, progress], rt_priority if udp else 0)
    deaths: list[tuple[str, float, int]] = []
    interrupted = False
    try:
        with _sigterm_interrupts():
            try:
                _run_nodes(specs, logdir, progress, duration, quiet, actions, deaths,
                           _dut_ids(sc, dut) if dut else frozenset(), dut_wait_s,
                           _hosted_ids(specs))
            except KeyboardInterrupt:
                interrupted = True
                if not quiet:
                    print("\n  interrupted: stopping the nodes and reporting what was "
                          "recorded", file=sys.stderr, flush=True)
    finally:
        # the run ends here: what the nodes send while they shut down is not the run's
        writer.t_stop = time.time()  # frame timestamps are wall-clock
        codes = stop_all(specs, rt_priority)
        drain(progress)
        notifier.stop()
        writer.stop()
    facts = RunFacts(exit_codes=codes, deaths=deaths, node_counters=sim_node_counters(out),
                     interrupted=interrupted, recorder_counters=notifier.counters(),
                     insecure=key_dir is None,
                     injected_loss=(None if loss == 0 else
                                    injected_loss(loss, loss_seed, LOSS_FRAMES,
                                                  _injected_counts(specs, logdir, out))))
    write_run_facts(out, facts, boot_floors, time_scale, tolerance)
    return report(sc, out / "run.log", out, facts, plot=plot, time_scale=time_scale,
                  codec=codec, keys=monitor_keys, boot_floors=boot_floors,
                  tolerance=tolerance)



# what `up --loss` drops: what its nodes' --inject-rx-all/--inject-rx-loss apply to
LOSS_FRAMES = "every frame each node receives but its own echo"


def loss_argv(sc: Scenario, loss: float, seed: int,
              extra: dict[str, list[str]] | None) -> dict[str, list[str]]:
    """``extra`` with each node's fault flags for the random-loss fault mode: every
    agent, the plant and the router lose each frame they receive (but their own echo)
    with probability ``loss``, each from its own seed (faultinject.node_seed)."""
    out = {k: list(v) for k, v in (extra or {}).items()}
    for name in [f"agent_{i}" for i in range(1, sc.n + 1)] + list(SIM_NODES):
        flags = ["--inject-rx-loss", repr(loss), "--inject-seed",
                 str(node_seed(seed, name))]
        out[name] = out.get(name, []) + flags + (["--inject-rx-all"]
                                                 if name.startswith("agent_") else [])
    return out


def _injected_counts(specs: list[NodeSpec], logdir: Path, out: Path
                     ) -> dict[str, tuple[int, int]]:
    """(frames dropped, frames the loss applied to) per node, as each printed (agents,
    in their log) or wrote (plant, router: counters JSON) them at exit; a node that
    left no count (killed) is left out."""
    counts: dict[str, tuple[int, int]] = {}
    counters = sim_node_counters(out)
    for s in specs:
        if s.name in counters:
            inj = counters[s.name].get("injected")
            if inj:
                counts[s.name] = (int(inj["dropped"]), int(inj["received"]))
            continue
        path = logdir / f"{s.name}.log"
        who = s.name.replace("_", " ") + ": injected "
        lines = path.read_text(errors="replace").splitlines() if path.is_file() else []
        for line in lines:  # "agent 3: injected 12 losses of 120 frames, 0 delays"
            if line.startswith(who):
                w = line.split()
                counts[s.name] = (counts.get(s.name, (0, 0))[0] + int(w[3]),
                                  counts.get(s.name, (0, 0))[1] + int(w[6]))
    return counts


def _run_nodes(specs: list[NodeSpec], logdir: Path, progress: Progress, duration: float,
               quiet: bool,
               actions: Sequence[tuple[float, Callable[[list[NodeSpec], Path], None]]],
               deaths: list[tuple[str, float, int]],
               dut_ids: frozenset[int] = frozenset(), dut_wait_s: float = 60.0,
               hosted_ids: frozenset[int] = frozenset()) -> None:
    # All at once (the router last): started one after the other, each would start
    # while the others already run, which in the QEMU guest took ~40 s per node (a router
    # held until the plant was heard came up 41 s after it there, beside the running
    # real-time nodes). With a device under test, the router waits until the device is
    # heard; with hosts of agents, until every hosted agent is.
    held = [s for s in specs if (dut_ids or hosted_ids) and s.name == "router"]
    for s in specs:
        if s.delay == 0 and s not in held:
            start(s, logdir)
    if held:
        if dut_ids:
            _await_device(specs, logdir, progress, dut_ids, dut_wait_s, quiet)
        if hosted_ids:
            _await_device(specs, logdir, progress, hosted_ids, START_TIMEOUT_S, quiet,
                          "the agents of the hosts")
        start(held[0], logdir)
    t_start = time.monotonic()
    while progress.t_first_price is None:
        if time.monotonic() - t_start > START_TIMEOUT_S:
            raise BusRunError(f"no price frame within {START_TIMEOUT_S:.0f} s: see "
                              f"{logdir}/router.log")
        check_alive(specs, logdir)
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
                deaths.extend((n, now - t0, code) for n in s.nodes)
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


def _hosted_ids(specs: list[NodeSpec]) -> frozenset[int]:
    """The MC frames of the agents of hosts (several agents a process): a host starts
    them one after the other over a sync period (firmware_py.node.spread_phases), and
    the price must not begin before the last one is on (it would be INIT, an anomaly)."""
    return frozenset(contract.MC_BASE + int(m.removeprefix("agent_"))
                     for s in specs if len(s.members) > 1 for m in s.members)


def _dut_ids(sc: Scenario, dut: str) -> frozenset[int]:
    """The frames a device under test must be heard sending before t = 0."""
    if dut == "plant":
        return frozenset(contract.STATUS_BASE + i for i in range(1, sc.n + 1))
    i = int(dut.removeprefix("agent_"))
    return frozenset({contract.MC_BASE + i, contract.SETPOINT_BASE + i})


def _await_device(specs: list[NodeSpec], logdir: Path, progress: Progress,
                  ids: frozenset[int], wait_s: float, quiet: bool,
                  who: str = "the device under test") -> None:
    t_start = time.monotonic()
    last_note = t_start
    while True:
        with progress.lock:
            missing = ids - progress.seen
        if not missing:
            return
        now = time.monotonic()
        if now - t_start > wait_s:
            raise BusRunError(f"{who} sent no "
                              f"{', '.join(f'0x{i:03X}' for i in sorted(missing))} within "
                              f"{wait_s:g} s: is it on this bus, with this run's key file?")
        if not quiet and now - last_note >= 5.0:
            last_note = now
            print(f"  waiting for {who} ({now - t_start:.0f} s): no "
                  f"{', '.join(f'0x{i:03X}' for i in sorted(missing))} yet",
                  file=sys.stderr, flush=True)
        check_alive(specs, logdir)
        time.sleep(0.05)
