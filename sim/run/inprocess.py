"""The nodes of `bess-ded up` in this process, on python-can's ``virtual`` bus, stepped
on a simulated clock (``run_in_process``), and the node objects it steps
(``in_process_nodes``, also the test kit's ``SimFleet``'s).
"""

from __future__ import annotations

import functools
import json
import secrets
import shutil
from collections import Counter
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import can

from dbc import dbc_path
from firmware_py import contract, pricesig, secoc
from firmware_py.config import agent_configs_from_scenario
from firmware_py.faultinject import FaultyBus, RxFaults, every_frame, node_seed
from firmware_py.frames import FrameCodec
from firmware_py.node import GuardedBus
from sim.model.scenario import Scenario, to_toml
from sim.run.busopts import BusRunError
from sim.run.keyset import write_key_set
from sim.run.nodeprocs import SIM_NODES, counters_path
from sim.run.runreport import report, write_run_facts
from sim.run.verdict import TOLERANCE, RunFacts


def _note(nodes: list[Any], i: int, cause: str) -> None:
    nodes[i].note(cause)


def in_process_nodes(sc: Scenario, codec: FrameCodec, rings: Mapping[str, secoc.Keyring],
                     plant_faults: tuple[Any, ...] = (), router_silent: tuple[Any, ...] = (),
                     c_agents: Collection[int] = ()) -> dict[str, Callable[[], Any]]:
    """Node name (as in `up`) → a factory of that node as an in-process object (``on_frame(msg,
    t)``, ``tick(t)`` → frames), agents first, then the plant and the router: what
    ``run_in_process`` steps, and ``sim.testkit.SimFleet`` for any subset of them.
    ``c_agents``: the agent IDs that run firmware_c's runtime (sim.cbind.cagent.CAgent,
    the same node seam) instead of firmware_py's."""
    from firmware_py.runtime import AgentRuntime
    from sim.nodes.plant import PlantNode
    from sim.nodes.router import RouterNode

    factories: dict[str, Callable[[], Any]] = {}
    for c in agent_configs_from_scenario(sc):
        ring = rings[f"agent_{c.id}"]
        if c.id in c_agents:
            from sim.cbind.cagent import CAgent

            factories[f"agent_{c.id}"] = functools.partial(CAgent, c, ring, fd=sc.fd,
                                                           lambda_tags=sc.lambda_tags)
        else:
            factories[f"agent_{c.id}"] = functools.partial(AgentRuntime, c, codec, ring)
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
    n_agents = sum(label.startswith("agent_") for label in rings)
    # a ring whose node key is the one the others hold for it is the fleet's: its frame
    # keys outweigh those of a node given another key set (a link frame has two parties)
    of_fleet = {n for n, ring in rings.items() if out[n] == ring.key}
    for name in contract.keyed_frames(n_agents):  # AUTH-28: the key its fleet's parties
        sender = contract.sender_of(name)        # hold, the sender's breaking a tie
        got: Counter[bytes] = Counter()
        for m, r in rings.items():
            if (k := r.key_for(name)) is not None:
                got[k] += 2 * (m in of_fleet) + (m == sender)
        if got:
            out[name] = got.most_common(1)[0][0]
    for i in contract.agent_ids(n_agents):  # AUTH-30: the router's, the target's breaking a tie
        cmd: Counter[bytes] = Counter()
        for m, r in rings.items():
            if (k := r.command_key(f"agent_{i}")) is not None:
                cmd[k] += 2 if m == "router" else 1
        if cmd:
            out[contract.command_key_name(i)] = cmd.most_common(1)[0][0]
    agents = [n for n in rings if n.startswith("agent_")]
    for a in agents:  # AUTH-34: each λ tag under the key its receiver holds
        for receiver, ring_rx in rings.items():
            if receiver != a and (k := ring_rx.tag_key(a, receiver)
                                  or rings[a].tag_key(a, receiver)) is not None:
                out[secoc.pair_label(a, receiver)] = k
    for ring in rings.values():  # signed_price: the router's public price key
        out.update(pricesig.monitor_entries(ring.price_verify, ring.fleet_id))
    return out


def injected_loss(p: float, seed: int, frames: str,
                  per_node: Mapping[str, tuple[int, int]]) -> dict[str, Any]:
    """The random-loss fault mode's record of a run (metrics' ``injected_loss``): its
    probability, seed, which frames it applied to and, per node, (frames dropped,
    frames it applied to)."""
    dropped = {n: d for n, (d, _) in per_node.items()}
    seen = {n: k for n, (_, k) in per_node.items()}
    return {"probability": p, "seed": seed, "frames": frames, "dropped": dropped,
            "received": seen, "dropped_total": sum(dropped.values()),
            "received_total": sum(seen.values())}


def run_in_process(sc: Scenario, out: Path, duration: float, channel: str = "bess-ded",
                   plant_faults: tuple[Any, ...] = (), router_silent: tuple[Any, ...] = (),
                   restarts: Sequence[tuple[str, float, float]] = (),
                   keyrings: Mapping[str, secoc.Keyring] | None = None,
                   insecure: bool = False,
                   inject: Callable[[float], Sequence[can.Message]] | None = None,
                   observe: Callable[[float, dict[str, Any]], None] | None = None,
                   tolerance: float = TOLERANCE, loss: float = 0.0,
                   loss_seed: int = 0, c_agents: Collection[int] = ()) -> dict[str, Any]:
    """The same nodes as `up` on python-can's in-process ``virtual`` bus, stepped on a
    simulated clock.

    Every node has its own bus instance, so each frame really crosses the bus (encode,
    MAC, bus, decode, range and freshness checks), but no thread races the wall clock: one
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

    ``c_agents``: the agent IDs that run firmware_c's runtime through its Python binding
    (sim.cbind.cagent.CAgent) instead of firmware_py's (in_process_nodes).

    ``loss``: the random-loss fault mode (docs/faults.md): every node (agents, plant,
    router) loses each frame it receives, of every kind, with probability ``loss``,
    drawn from its own generator seeded from ``loss_seed`` and its name
    (``faultinject.node_seed``), so a run is reproduced by its seed. The recorder hears
    every frame (the loss is at the receivers, not on the wire); the frames dropped are
    counted per node in the metrics' ``injected_loss`` and the verdict does not blame
    them on a node (``RunFacts.injected_loss``).
    """
    out.mkdir(parents=True, exist_ok=True)
    codec = FrameCodec(dbc_path(sc.fd, sc.lambda_tags))
    nodes_ = secoc.fleet_nodes(sc.n)
    if insecure:
        rings = {n: secoc.Keyring.insecure_for(n) for n in nodes_}
    elif keyrings is not None:
        rings = dict(keyrings)
    else:  # a fresh key set, written to DIR/keys as `up` does (for `analyze` later)
        master = secrets.token_bytes(secoc.KEY_BYTES)
        rings = secoc.Keyring.fleet(master, nodes_, signed_price=sc.signed_price)
        key_dir = out / "keys"
        if key_dir.exists():
            shutil.rmtree(key_dir)
        key_dir.mkdir(mode=0o700)
        write_key_set(sc, key_dir, master)
    # each node's boot at this start, as `up` reads it from the key files (the recorder's
    # floors: a sync of an earlier boot is from an earlier run, AUTH-21)
    boot_floors = None if insecure else {n: r.boot + 1 for n, r in rings.items()}
    factories = in_process_nodes(sc, codec, rings, plant_faults, router_silent, c_agents)
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
    guards: list[Any] = [GuardedBus(bus, functools.partial(_note, nodes, i), who=name)
                         for i, (bus, name) in enumerate(zip(buses, names, strict=True))]
    if not 0 <= loss < 1:
        raise BusRunError(f"loss: expected a probability in [0, 1), but got {loss}")
    if loss > 0:  # at the receivers, behind what each node's GuardedBus already refused
        guards = [FaultyBus(g, RxFaults(loss, seed=node_seed(loss_seed, name),
                                        match=every_frame))
                  for g, name in zip(guards, names, strict=True)]
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
    if sc.signed_price:  # AUTH-32, AUTH-33: the agents' signature causes (no Diag slot)
        for name, node in zip(names, nodes, strict=True):
            if name.startswith("agent_"):
                counters[name] = node.verdict_counters()
    dropped = {k: v for k, v in recorder.counters.items() if v}
    # left as `up` leaves them, so `analyze DIR` judges this run as it is judged here
    (out / "scenario.toml").write_text(to_toml(sc))
    (out / "logs").mkdir(exist_ok=True)
    for role, c in counters.items():
        counters_path(out, role).write_text(json.dumps(c) + "\n")
    injected = None
    if loss > 0:
        injected = injected_loss(loss, loss_seed, "every frame each node receives",
                                 {n: (g.dropped, g.matched)
                                  for n, g in zip(names, guards, strict=True)})
    facts = RunFacts(node_counters=counters, recorder_counters=dropped, insecure=insecure,
                     injected_loss=injected)
    write_run_facts(out, facts, boot_floors, 1.0, tolerance)
    m = report(sc, out / "run.log", out, facts, plot=False, codec=codec,
               keys=recorder_keys(rings), tolerance=tolerance,
               boot_floors=boot_floors).metrics
    m["node_summaries"] = [n.summary() for n in nodes]
    return m
