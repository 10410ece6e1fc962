"""Bus load per fleet size at Ts = 10 ms: classic CAN and CAN FD, periodic and
event-triggered λ (issue 23 item 4, its computed half; ``bess-ded bench --fleet-load``,
docs/performance.md "Bus load per fleet size").

Computed, not measured: every frame of the fleet is the DBC's (``auth.fleet_messages``:
length, cycle time at Ts = 10 ms, ER_Balance every page each cycle, a Diag page a cycle,
every ``<name>_Sync``; the Mac is inside the 8 bytes, today's shared-key scheme "a"),
its time on the bus the worst case of sim.bench.canframe at the DBC's Baudrate (nominal)
and the FD twin's BaudrateCANFD (``auth.FD_DATA_RATE``, the FD data phase). The DBC has
frames for agents 1..N_AGENTS_MAX (64): every fleet of the table is made of its own
frames. The fleets are rings 1–2–…–N–1 (``auth.ring_scenario``) and the paper's cases
where N fits (case 1: 4 agents, star; case 7: 12, ring).

Configurations (``CONFIGS``):

- classic, periodic: every frame a classic frame, every agent's MC every tick;
- classic, event-triggered: the MC frames scaled by the MC frame ratio event / periodic
  measured in the lockstep (firmware-spec TX-7 at the default threshold and heartbeat;
  the heartbeat frames and every State change are sent frames, so they count): over the
  whole run, once settled (the samples after the periodic run's settling instant), and
  in the worst ``WINDOW_TICKS`` window (the transient: all λ move at once). The other
  frames (Setpoint, Status, Diag, syncs, the router's) are periodic either way;
- FD, periodic / event-triggered: the same frames as CAN FD frames with the bit-rate
  switch, at the FD DBC's lengths (8 bytes; λ and its sync 32, a tag per receiver:
  AUTH-34);
- FD, packed (not in the protocol): ``PACK`` agents' MC frames (8 bytes each, Mac and
  counter included) in one 64-byte FD frame each tick, the other frames as FD periodic:
  what a 64-byte payload would allow a packing node (a relay, one more tick of delay,
  its own authentication story) at best.

The event ratio of each fleet is measured on it (rings: ``ring_duration`` s, long enough
for the periodic run to settle; the cases: their own schedule); ``--quick`` measures the
rings up to QUICK_MAX agents and takes the largest's ratios for the larger rings (the table
says so).
Deterministic (no clock): the tests check the numbers.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from firmware_py.config import Transmit
from firmware_py.frames import N_AGENTS_MAX
from sim.bench.auth import (
    SCHEMES,
    Bus,
    Message,
    bus_load,
    dbc_bitrate,
    fleet_messages,
    ring_scenario,
)
from sim.bench.canframe import FD_MAX, fd_frame_time

TS = 0.01
SIZES = (4, 8, 16, 24, 32, 48, 64)
QUICK_MAX = 32               # --quick: the largest ring whose event ratio is measured
LOAD_LIMIT = 0.60            # issue 23's acceptance: a 64-agent FD fleet at ≤ 60 %
WINDOW_TICKS = 10            # the worst window of the event-triggered run: 100 ms
MC_BYTES = 8
PACK = FD_MAX // MC_BYTES    # 8 MC payloads in one 64-byte FD frame
SHARED = next(s for s in SCHEMES if s.key == "a")        # today's frames, classic
SHARED_FD = next(s for s in SCHEMES if s.key == "a-fd")  # the same frames as FD frames
_AGENT_FRAME = re.compile(r"^(AGENT|PLANT)_(\d+)_")
_MC = re.compile(r"^AGENT_\d+_MC$")


@dataclass(frozen=True)
class Config:
    """One line of the table: the bus and how the MC frames go out."""

    key: str
    label: str
    fd: bool
    mc: str   # "periodic" | "whole" | "settled" | "peak" (EventRatio's) | "packed"
    tags: bool = True  # on FD: λ and its sync with a tag per receiver (AUTH-34), 32 bytes


CONFIGS = (
    Config("classic", "classic, periodic", False, "periodic"),
    Config("classic-event", "classic, event-triggered (whole run)", False, "whole"),
    Config("classic-event-settled", "classic, event-triggered, once settled", False,
           "settled"),
    Config("classic-event-peak", "classic, event-triggered, worst 100 ms", False, "peak"),
    Config("fd", "FD, periodic (λ tagged: 32 bytes, the rest 8; BRS)", True, "periodic"),
    Config("fd-event", "FD, event-triggered (whole run)", True, "whole"),
    Config("fd-event-settled", "FD, event-triggered, once settled", True, "settled"),
    Config("fd-event-peak", "FD, event-triggered, worst 100 ms", True, "peak"),
    Config("fd-untagged", "FD, λ untagged (8 bytes), periodic", True, "periodic", False),
    Config("fd-untagged-event", "FD, λ untagged, event-triggered (whole run)", True, "whole",
           False),
    Config("fd-untagged-event-settled", "FD, λ untagged, event-triggered, once settled", True,
           "settled", False),
    Config("fd-packed", f"FD, {PACK} untagged MC per 64-byte frame (not in the protocol)",
           True, "packed", False),
)


def own_config(sc: Any, mc: str) -> Config:
    """The line of ``sc``'s own bus (classic, FD with or without λ tags) for ``mc``."""
    return next(c for c in CONFIGS if c.fd == sc.fd and c.mc == mc
                and (not c.fd or c.tags == sc.lambda_tags))


@dataclass(frozen=True)
class Fleet:
    """A fleet of the table: its label, size and scenario (the event run's graph)."""

    label: str
    n: int
    scenario: Any


@dataclass(frozen=True)
class EventRatio:
    """MC frames sent event-triggered / periodic, measured in the lockstep on ``source``."""

    whole: float
    settled: float | None   # None: the periodic run never settled
    peak: float             # the worst WINDOW_TICKS window
    source: str             # the fleet measured
    duration: float         # s of its run


def id_plan_room() -> dict[str, int]:
    """Per family of per-agent frames (``AGENT_<i>_MC``, ..., their syncs), how many agents
    its 11-bit IDs have room for in the DBC's ID plan: base + 1 .. the next family's base
    or other frame's ID (or 0x800), exclusive. The fleet size the plan allows without
    moving a base is the smallest."""
    from firmware_py.frames import FrameCodec

    codec = FrameCodec()
    families: dict[str, int] = {}
    others: set[int] = {0x800}
    for m in codec.database.messages:
        a = _AGENT_FRAME.match(m.name)
        if a is None:
            others.add(m.frame_id)
        elif int(a[2]) == 1:
            families[m.name.replace("_1_", "_<i>_", 1)] = m.frame_id - 1
    anchors = sorted(others | set(families.values()))
    return {name: min(x for x in anchors if x > base) - base - 1
            for name, base in sorted(families.items(), key=lambda kv: kv[1])}


def ring_duration(n: int) -> float:
    """Seconds of a ring's event run: 30 s, or 2 s per agent (a ring of 64 settles in
    ~65 s at the default gains): long enough for the periodic run to settle."""
    return max(30.0, 2.0 * n)


def fleets(sizes: tuple[int, ...] = SIZES, cases: bool = True) -> list[Fleet]:
    """Rings of ``sizes`` and (``cases``) the paper's cases 1 and 7, by size."""
    from sim.model.scenario import load_case

    out = [Fleet(f"ring-{n}", n, ring_scenario(n, ring_duration(n))) for n in sizes]
    if cases:
        out += [Fleet(f"case {c}", sc.n, sc) for c in (1, 7) for sc in [load_case(c)]]
    return sorted(out, key=lambda f: (f.n, not f.label.startswith("case")))


def fleet_frames(fleet: Fleet, ts: float = TS) -> list[Message]:
    """Every secured message and sync of ``fleet`` at ``ts`` from the DBC."""
    return fleet_messages(fleet.scenario, ts)


def is_mc(msg: Message) -> bool:
    """An agent's MC frame (λ): the one event-triggering thins (not its sync)."""
    return bool(_MC.match(msg.name))


def event_ratio(sc: Any, source: str, transmit: Transmit | None = None) -> EventRatio:
    """The MC frame ratio event / periodic of ``sc`` in the lockstep (module doc)."""
    from sim.bench.event import settled_samples
    from sim.model.lockstep import run_lockstep

    tx = transmit or Transmit("event")
    a = run_lockstep(replace(sc, transmit=Transmit()))
    b = run_lockstep(replace(sc, transmit=tx))
    assert a.mc_sent is not None and b.mc_sent is not None
    settled = settled_samples(a, sc.ts)
    per_a, per_b = a.mc_sent.sum(axis=1), b.mc_sent.sum(axis=1)
    ones = np.ones(min(WINDOW_TICKS, len(per_a)))
    win_a = np.convolve(per_a, ones, "valid")
    win_b = np.convolve(per_b, ones, "valid")
    peak = float(np.max(win_b / np.maximum(win_a, 1)))
    sa = int(a.mc_sent[settled].sum())
    return EventRatio(float(per_b.sum() / per_a.sum()),
                      float(b.mc_sent[settled].sum() / sa) if sa else None, peak, source,
                      sc.duration)


def event_ratios(fl: list[Fleet], quick: bool) -> dict[str, EventRatio]:
    """Each fleet's measured ratio; ``quick``: rings above QUICK_MAX take the ratio of
    the largest ring measured."""
    out: dict[str, EventRatio] = {}
    for f in fl:
        if not (quick and f.n > QUICK_MAX):
            out[f.label] = event_ratio(f.scenario, f.label)
    for f in fl:
        if f.label not in out:
            donors = [g for g in fl if g.label in out and g.label.startswith("ring")]
            out[f.label] = (out[max(donors, key=lambda g: g.n).label] if donors
                            else event_ratio(f.scenario, f.label))
    return out


BUS_LOAD_MAX = 1.0   # a bus run's fleet must fit: above it frames queue without bound


def run_bus_load(sc: Any) -> tuple[float, str]:
    """The computed load of scenario ``sc``'s fleet on a bus run (classic, or CAN FD for
    ``[bus] fd``) at its Ts, and how it was computed. Periodic: every frame of the DBC at
    its cycle. Event-triggered: the MC frames × the ratio event / periodic of ``sc`` in the
    lockstep over the whole run (its start sends as much as periodic; a short burst above
    100 % only queues frames), measured only when the periodic load does not fit already
    (a 64-agent ring: ~3 s)."""
    fleet = Fleet(sc.name, sc.n, sc)
    cfg = own_config(sc, "periodic")
    msgs = fleet_frames(fleet, sc.ts)
    load = config_load(cfg, fleet, None, msgs=msgs)
    assert load is not None
    if sc.transmit.mode != "event" or load["load"] <= BUS_LOAD_MAX:
        return load["load"], "every frame periodic"
    ratio = event_ratio(sc, sc.name, sc.transmit)
    event = config_load(own_config(sc, "whole"), fleet, ratio, msgs=msgs)
    assert event is not None
    return event["load"], (f"MC frames event-triggered, {100 * ratio.whole:.1f} % of "
                           "periodic over the run (lockstep)")


def check_bus_load(sc: Any) -> float:
    """``run_bus_load`` of ``sc``, or a ConfigError naming it when it is above
    BUS_LOAD_MAX: the fleet cannot run on the bus (refused before a run writes anything)."""
    from firmware_py.errors import ConfigError

    load, how = run_bus_load(sc)
    fd = sc.fd
    if load > BUS_LOAD_MAX:
        kind = "CAN FD" if fd else "classic CAN"
        raise ConfigError(sc.source, "graph.agents", f"expected a fleet whose computed bus "
                          f"load on {kind} at Ts = {sc.ts * 1e3:g} ms is at most "
                          f"{100 * BUS_LOAD_MAX:.0f} %, but got {100 * load:.1f} % for "
                          f"{sc.n} agents ({how}; sim.bench.fleetload): "
                          + ("" if fd else "use CAN FD (--fd), ")
                          + ("" if sc.transmit.mode == "event" else "--transmit event, ")
                          + "fewer agents or a --time-scale")
    return load


def frame_time(msg: Any, bus: Bus) -> float:
    """Seconds a recorded frame takes on the bus, worst-case stuffing (canframe): classic,
    or FD with its data phase at ``bus.data`` when it switched the bit rate."""
    n = len(msg.data)
    if not msg.is_fd:
        return bus.classic(n)
    return fd_frame_time(n, bus.nominal, bus.data if msg.bitrate_switch else bus.nominal)


def measured_run(run: Path) -> dict[str, Any]:
    """A bus run's load measured from its recording (``run``: a `bess-ded up` directory,
    its run.log and scenario.toml) beside the computed figure for the same scenario and
    span. Measured: every recorded frame's time on the bus (``frame_time``: the DBC's
    bit rates, the frame's own format, length and bit-rate switch) over the recorded
    span. Computed: ``config_load`` of the scenario's frames, the MC frames × the
    lockstep's event ratio over the same span (periodic: 1). A time-scaled run (Ts =
    10 ms·F) has 1/F of the load of the same run at Ts = 10 ms: both figures are also
    given × F, what the fleet puts on a bus in real time."""
    import can

    from firmware_py.contract import MC_BASE, MC_CYCLE_S
    from sim.model.scenario import load_scenario

    sc = load_scenario(run / "scenario.toml")
    frames = list(can.LogReader(str(run / "run.log")))
    if len(frames) < 2:
        raise ValueError(f"{run / 'run.log'}: expected a recording of a run, but got "
                         f"{len(frames)} frames")
    bus = Bus(dbc_bitrate())
    stamps = [m.timestamp for m in frames]
    span = max(stamps) - min(stamps)
    busy = sum(frame_time(m, bus) for m in frames)
    mc = sum(1 for m in frames if MC_BASE < m.arbitration_id <= MC_BASE + sc.n)
    fleet = Fleet(sc.name, sc.n, replace(sc, duration=span))
    cfg = own_config(sc, "whole" if sc.transmit.mode == "event" else "periodic")
    ratio = (event_ratio(fleet.scenario, sc.name, sc.transmit)
             if sc.transmit.mode == "event" else None)
    computed = config_load(cfg, fleet, ratio, bus, fleet_frames(fleet, sc.ts))
    assert computed is not None
    scale = sc.ts / MC_CYCLE_S
    return {
        "run": str(run), "scenario": sc.name, "agents": sc.n, "fd": sc.fd,
        "transmit": sc.transmit.mode, "ts_s": sc.ts, "time_scale": scale, "span_s": span,
        "frames": len(frames), "fd_frames": sum(m.is_fd for m in frames),
        "frames_per_s": len(frames) / span, "computed_frames_per_s": computed["frames_per_s"],
        "mc_ratio_measured": mc / (sc.n * span / sc.ts),
        "mc_ratio_computed": 1.0 if ratio is None else ratio.whole,
        "load_measured": busy / span, "load_computed": computed["load"],
        "load_measured_at_10ms": scale * busy / span,
        "load_computed_at_10ms": scale * computed["load"],
    }


MEASURED_HEADERS = ["run", "agents", "bus, λ", "Ts [ms]", "span [s]", "frames/s meas. / comp.",
                    "MC ratio meas. / comp.", "load meas. / comp.", "at Ts = 10 ms"]


def measured_rows(runs: list[dict[str, Any]]) -> list[list[str]]:
    """The comparison table's rows (``measured_run`` of each run)."""
    return [[r["scenario"], str(r["agents"]),
             f"{'FD' if r['fd'] else 'classic'}, {r['transmit']}", f"{1e3 * r['ts_s']:g}",
             f"{r['span_s']:.1f}",
             f"{r['frames_per_s']:.0f} / {r['computed_frames_per_s']:.0f}",
             f"{r['mc_ratio_measured']:.3f} / {r['mc_ratio_computed']:.3f}",
             f"{100 * r['load_measured']:.1f} % / {100 * r['load_computed']:.1f} %",
             f"{100 * r['load_measured_at_10ms']:.1f} % / "
             f"{100 * r['load_computed_at_10ms']:.1f} %"] for r in runs]


SCENARIO_HEADERS = ["scenario", "agents", "λ", "Ts [ms]", "run [s]", "MC ratio (run)",
                    "classic", "FD", f"its bus ≤ {100 * LOAD_LIMIT:.0f} %"]


def scenario_load(sc: Any) -> dict[str, Any]:
    """Scenario ``sc``'s fleet at its Ts on classic CAN and CAN FD (``load``: on its own
    bus): every DBC frame at its cycle, for ``transmit = "event"`` the MC frames × ``sc``'s
    lockstep ratio over its run (``run_bus_load`` measures it only when needed)."""
    fleet, event = Fleet(sc.name, sc.n, sc), sc.transmit.mode == "event"
    msgs, ratio = fleet_frames(fleet, sc.ts), (event_ratio(sc, sc.name, sc.transmit)
                                               if event else None)
    loads = {}
    for cfg in (c for c in CONFIGS if c.mc == ("whole" if event else "periodic")
                and (not c.fd or c.tags == sc.lambda_tags)):  # its own FD format
        got = config_load(cfg, fleet, ratio, msgs=msgs)
        assert got is not None
        loads["fd" if cfg.fd else "classic"] = got["load"]
    own = loads["fd" if sc.fd else "classic"]
    return {"scenario": sc.name, "source": str(sc.source), "agents": sc.n, "fd": sc.fd,
            "transmit": sc.transmit.mode, "ts_s": sc.ts, "duration_s": sc.duration,
            "mc_ratio": 1.0 if ratio is None else ratio.whole, "load_classic":
            loads["classic"], "load_fd": loads["fd"], "load": own, "fits": own <= LOAD_LIMIT}


def scenario_rows(runs: list[dict[str, Any]]) -> list[list[str]]:
    """The rows of ``scenario_load`` results (* over LOAD_LIMIT)."""
    def pct(x: float) -> str:
        return f"{100 * x:.1f} %" + ("*" if x > LOAD_LIMIT else "")
    return [[r["scenario"], str(r["agents"]), r["transmit"], f"{1e3 * r['ts_s']:g}",
             f"{r['duration_s']:g}", f"{r['mc_ratio']:.3f}", pct(r["load_classic"]),
             pct(r["load_fd"]), f"{'FD' if r['fd'] else 'classic'}: "
             + ("yes" if r["fits"] else "no")] for r in runs]


def fd_lengths(msgs: list[Message]) -> list[Message]:
    """``msgs`` at the FD DBC's lengths: λ and its sync carry a tag per receiver there
    (AUTH-34: 32 bytes), every other frame its classic 8."""
    from dbc import FD_DBC_PATH
    from firmware_py.frames import FrameCodec

    length = {m.name: m.length for m in FrameCodec(FD_DBC_PATH).database.messages}
    return [replace(m, length=length.get(m.name, m.length)) for m in msgs]


def packed(msgs: list[Message]) -> list[Message]:
    """``msgs`` with the MC frames packed PACK to a 64-byte FD frame (not in the
    protocol: the ``fd-packed`` line)."""
    mcs = [m for m in msgs if is_mc(m)]
    out = [m for m in msgs if not is_mc(m)]
    for k in range(0, len(mcs), PACK):
        group = mcs[k:k + PACK]
        out.append(Message(f"MC_PACK_{k // PACK + 1}", "packer", (), (), group[0].per_s,
                           MC_BYTES * len(group), "agent"))
    return out


def config_load(cfg: Config, fleet: Fleet, ratio: EventRatio | None,
                bus: Bus | None = None, msgs: list[Message] | None = None
                ) -> dict[str, float] | None:
    """Bus load (fraction) and frames/s of ``fleet`` under ``cfg`` (None: the event ratio
    it needs was not measured, a run that never settled)."""
    bus = bus or Bus(dbc_bitrate())
    msgs = fleet_frames(fleet) if msgs is None else msgs
    if cfg.fd and cfg.tags:
        msgs = fd_lengths(msgs)
    if cfg.mc == "packed":
        msgs = packed(msgs)
    elif cfg.mc != "periodic":
        r = None if ratio is None else getattr(ratio, cfg.mc)
        if r is None:
            return None
        msgs = [replace(m, per_s=m.per_s * r) if is_mc(m) else m for m in msgs]
    return bus_load(SHARED_FD if cfg.fd else SHARED, fleet.scenario, bus, msgs)


def largest_fitting(loads: dict[str, dict[str, float] | None], fl: list[Fleet],
                    limit: float = LOAD_LIMIT) -> int | None:
    """The largest N of the fleets whose load is ≤ ``limit`` (None: none fits)."""
    sizes = [f.n for f in fl if (v := loads[f.label]) is not None and v["load"] <= limit]
    return max(sizes, default=None)


def affine_capacity(loads: dict[str, dict[str, float] | None], fl: list[Fleet],
                    limit: float = LOAD_LIMIT) -> int:
    """The largest N of any size (not only the table's) at ≤ ``limit`` for a periodic
    configuration, whose load is affine in N (every agent sends the same frames): the
    line through the two largest rings, solved for ``limit``."""
    rings = sorted((f.n, v["load"]) for f in fl if f.label.startswith("ring")
                   and (v := loads[f.label]) is not None)
    (n1, l1), (n2, l2) = rings[-2:]
    per_agent = (l2 - l1) / (n2 - n1)
    return math.floor((limit - (l2 - n2 * per_agent)) / per_agent + 1e-9)


def title() -> str:
    """The table's title: Ts, computed from the DBC."""
    return f"Bus load per fleet size at Ts = {TS * 1e3:g} ms, computed from the DBC"


def run(quick: bool, sizes: tuple[int, ...] = SIZES, cases: bool = True
        ) -> tuple[list[str], list[list[str]], dict[str, Any]]:
    """The headers, rows and data (for --json) of the table: CONFIGS × fleets."""
    fl = fleets(sizes, cases)
    bus = Bus(dbc_bitrate())
    ratios = event_ratios(fl, quick)
    frames = {f.label: fleet_frames(f) for f in fl}
    headers = ["configuration", *(f"{f.label.removeprefix('ring-')}" if f.label.startswith(
        "ring") else f"{f.label} ({f.n})" for f in fl), f"largest N ≤ {100 * LOAD_LIMIT:.0f} %"]
    rows, loads_all, largest, affine = [], {}, {}, {}
    for cfg in CONFIGS:
        loads = {f.label: config_load(cfg, f, ratios[f.label], bus, frames[f.label])
                 for f in fl}
        big = largest_fitting(loads, fl)
        loads_all[cfg.key], largest[cfg.key] = loads, big
        if cfg.mc == "periodic":
            affine[cfg.key] = affine_capacity(loads, fl)
        cells = ["–" if v is None else f"{100 * v['load']:.1f} %"
                 + ("*" if v["load"] > LOAD_LIMIT else "") for v in loads.values()]
        every = all(v is not None and v["load"] <= LOAD_LIMIT for v in loads.values())
        rows.append([cfg.label, *cells, "none" if big is None else
                     f"{big}" + (" (all)" if every else "")])
    data = {
        "ts_s": TS, "nominal_bps": bus.nominal, "fd_data_bps": bus.data,
        "load_limit": LOAD_LIMIT, "dbc_agents": N_AGENTS_MAX, "pack": PACK,
        "window_ticks": WINDOW_TICKS, "id_plan_room": id_plan_room(),
        "fleets": {f.label: {"agents": f.n, "frames": len(frames[f.label])} for f in fl},
        "configs": {c.key: {"label": c.label, "fd": c.fd, "mc": c.mc} for c in CONFIGS},
        "loads": loads_all, "largest_n": largest, "largest_n_any_periodic": affine,
        "event_ratio": {k: {"whole": r.whole, "settled": r.settled, "peak": r.peak,
                            "measured_on": r.source, "duration_s": r.duration}
                        for k, r in ratios.items()},
    }
    return headers, rows, data


def note(data: dict[str, Any]) -> str:
    """The table's note: rates, what is computed, where the event ratios come from."""
    borrowed = sorted({f"{k} ← {v['measured_on']}" for k, v in data["event_ratio"].items()
                       if v["measured_on"] != k})
    tx = Transmit("event")
    room = data["id_plan_room"]
    tight = min(room, key=room.get)
    any_n = ", ".join(f"{data['configs'][k]['label'].split(',')[0]} {v}"
                      for k, v in data["largest_n_any_periodic"].items())
    return (f"computed, not measured: worst-case frames (canframe) at "
            f"{data['nominal_bps'] / 1e3:.0f} kbit/s (DBC Baudrate), FD data phase "
            f"{data['fd_data_bps'] / 1e6:g} Mbit/s (the FD DBC's BaudrateCANFD); * over "
            f"{100 * LOAD_LIMIT:.0f} % (issue 23's limit); periodic, any N (affine in N): "
            f"largest {any_n}. Event-triggered: MC frames × the "
            f"ratio event/periodic measured in the lockstep (threshold {tx.threshold:g}, "
            f"heartbeat {tx.heartbeat} ticks; heartbeats count), rings run "
            f"max(30 s, 2 s × N)"
            + (f"; ratios taken from another run: {', '.join(borrowed)}" if borrowed else "")
            + f". The DBC's 11-bit ID plan has room for {room[tight]} agents without moving a"
            f" base ({tight} the tightest); its frames exist for {data['dbc_agents']}"
            + ". A scenario's own fleet at its Ts: `bench --fleet-load --case CASE`; "
            "measured on the bus: `bench --fleet-load --measured DIR` of a `bess-ded up "
            "[--fd]` run")


_COLOURS = {"periodic": "C0", "whole": "C1", "settled": "C2", "peak": "C3", "packed": "C4"}


def plot(data: dict[str, Any], path: Path) -> None:
    """Load against N (the rings), one line per configuration, the 60 % limit marked."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rings = sorted((v["agents"], k) for k, v in data["fleets"].items() if k.startswith("ring"))
    fig = Figure(figsize=(9, 5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    for key, cfg in data["configs"].items():
        pts = [(n, 100 * v["load"]) for n, k in rings
               if (v := data["loads"][key][k]) is not None]
        ax.plot(*zip(*pts, strict=True), marker="o" if cfg["fd"] else "s", ms=3,
                color=_COLOURS[cfg["mc"]], lw=0.8 if cfg["mc"] == "peak" else 1.5,
                ls="-" if cfg["fd"] else "-.", label=cfg["label"])
    ax.axhline(100 * data["load_limit"], color="red", lw=1, ls=":",
               label=f"{100 * data['load_limit']:.0f} % (issue 23)")
    ax.axvline(data["dbc_agents"], color="grey", lw=0.8, ls=":")
    ax.set_xlabel("agents N (ring)")
    ax.set_ylabel("bus load [%]")
    ax.set_xticks([n for n, _ in rings])
    ax.set_title(f"Bus load per fleet size, Ts = {1e3 * data['ts_s']:g} ms, "
                 f"{data['nominal_bps'] / 1e3:.0f} kbit/s (FD data "
                 f"{data['fd_data_bps'] / 1e6:g} Mbit/s), computed from the DBC",
                 fontsize=10)
    ax.legend(fontsize=7)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":  # pragma: no cover
    from sim.report.textfmt import table

    h, r, d = run(quick=False)
    print(title())
    print(table(h, r, "l" + "r" * (len(h) - 1)))
    print(f"  ({note(d)})")
