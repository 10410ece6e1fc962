"""Turn a recorded candump log back into a Trajectory, plus what the log says about the run.

The bus run's metrics come only from what crossed the bus: λ_i from AGENT_i_MC,
ρ from ER_Price, P_i from PLANT_i_Status, counters from AGENT_i_Diag, the router's
ledger from ER_Balance. Values are sampled on the Ts grid by holding the last frame
received (what a neighbour sees). Every frame is decoded once, here, whatever reads
the result: ``bess-ded up`` after a run, ``bess-ded analyze`` on any candump log.

Besides the signals, ``read_log`` keeps what tells a clean recording from a bad one:
undecodable frames by cause, frames on IDs outside the run, per-message counter
sequences (recorder misses vs. interleaved senders), silences of the whole bus.

Over 500 lines: ``LogContents`` and ``read_log``, which fills it in one pass, are one
unit with the few readers of its result (trajectory, diagnostics, the router's events);
the MAC and freshness checks are sim.run.monitor's.
"""

from __future__ import annotations

import math
import re
from collections import Counter, defaultdict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any

import can
import numpy as np

from firmware_py import contract, pricesig
from firmware_py.contract import COUNTER_MODULO, MC_CYCLE_S, TIMEOUT_CYCLES, State
from firmware_py.errors import ConfigError, FrameError
from firmware_py.frames import COUNTER_STEP_MAX, FrameCodec, target_agent
from sim.model.scenario import MAX_AGENT_SAMPLES, Scenario
from sim.model.trajectory import Trajectory
from sim.run.monitor import Forged, Monitor, Stale, StaleBoot, SyncJump, cycle_or_inf

# a message silent this long restarts its counter sequence, as a node widens a timed-out
# sender's freshness window (firmware_py.nodeio.LOST_WINDOWS)
SEQUENCE_TIMEOUT_CYCLES = TIMEOUT_CYCLES
# a node is silent when a message of its own is missing for SEQUENCE_TIMEOUT_CYCLES of its
# cycles and at least this many Ts (the agents' price timeout): shorter stalls of a
# loaded host show up as bus silences and deadline misses, not as a node gone
NODE_SILENCE_MIN_TS = 25


@dataclass
class SequenceStats:
    """One message's rolling-counter sequence as the recorder saw it.

    A single sender advances its counter by 1 per frame; a recorder that misses k frames
    sees a jump of k + 1. A repeat, or a jump of more than half the modulus, is not what
    one sender does: it is a second sender on the same ID (interleaved sequences) or a
    replay. After a silence of SEQUENCE_TIMEOUT_CYCLES cycles the sequence restarts (a
    restarted node counts from 0 again), as the firmware's own receivers do."""

    frames: int = 0
    gaps: list[tuple[float, float]] = field(default_factory=list)  # > the timeout
    missed: int = 0          # frames inferred lost by the recorder
    out_of_sequence: int = 0  # repeats and backward jumps: another sender or a replay
    last: int | None = None
    t_last: float | None = None


@dataclass
class LogContents:
    """What one pass over a CAN log found: every decoded series, the counters'
    sequences and gaps, diag pages, and (with the run's keys) the frames
    that failed or could not be verified."""

    frames: int = 0
    undecodable: Counter[str] = field(default_factory=Counter)
    series: dict[tuple[str, str], list[tuple[float, float]]] = field(
        default_factory=lambda: defaultdict(list))
    diag: dict[int, dict[str, int]] = field(default_factory=lambda: defaultdict(dict))
    t_first_price: float | None = None
    t_end: float = 0.0
    sequences: dict[str, SequenceStats] = field(default_factory=dict)
    # frames of messages that exist in the DBC but not in this run (AGENT_9_MC in a
    # 4-agent fleet), by message name
    outside_run: Counter[str] = field(default_factory=Counter)
    # gaps between consecutive frames longer than the silence threshold: (t_from, t_to)
    silences: list[tuple[float, float]] = field(default_factory=list)
    # per cyclic message, after the first price: gaps of more than SEQUENCE_TIMEOUT_CYCLES
    # cycles, the end of the log included: (t_from, t_to)
    message_silences: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    # State of each agent's first recorded MC frame: an agent is INIT until the first
    # price, so anything else means the recorder missed the start and t = 0 is late
    first_mc_state: dict[str, int] = field(default_factory=dict)
    # with the run's keys: secured frames whose MAC does not verify (forged or replayed),
    # and those before their sender's first sync (not checkable), by message name
    forged: Counter[str] = field(default_factory=Counter)
    unverified: Counter[str] = field(default_factory=Counter)
    # with the run's keys: syncs and secured frames whose MAC verifies, by sender (node
    # label); a sender with none but forged ones signs with another key (a key mismatch)
    verified: Counter[str] = field(default_factory=Counter)
    keys_checked: bool = False
    # with the run's keys: genuine secured frames that came after a newer one of their
    # sender (valid MAC under a past freshness value): late, left out, not forged
    stale: Counter[str] = field(default_factory=Counter)
    # syncs whose MAC verifies but whose boot is below one the sender already used (or
    # below its boot at the run's start): a replay of an earlier run or boot, or the
    # sender's key file rolled back (AUTH-21); label -> (lowest such boot, its floor)
    stale_boot: dict[str, tuple[int, int]] = field(default_factory=dict)
    stale_boot_syncs: Counter[str] = field(default_factory=Counter)  # those syncs, by name
    # syncs whose MAC verifies but whose boot jumps more than SYNC_BOOT_JUMP_MAX above the
    # sender's (AUTH-27: a key holder's forgery), by name; refused like the nodes refuse them
    sync_jump: Counter[str] = field(default_factory=Counter)
    # signed_price: ER_Price frames that are not the signed segment's and ER_PriceSig
    # pages refused (AUTH-32, AUTH-33), left out as the agents leave them out
    unsigned: Counter[str] = field(default_factory=Counter)
    # genuine syncs that undid such a forged advance within the bound (AUTH-27), by name
    sync_undone: Counter[str] = field(default_factory=Counter)
    syncs: int = 0
    # frames the capture received before an earlier-stamped one (read_log sorts them)
    reordered: int = 0
    # per agent, in bus order: (t, "mc", State, Lambda raw) and (t, "setpoint", Enable,
    # PowerSetpoint raw), for the setpoint-consistency check (sim.nodes.consistency)
    dispatch: dict[int, list[tuple[float, str, int, int]]] = field(
        default_factory=lambda: defaultdict(list))
    # every ER_Command recorded: (t, Command, Target, GainK) raw (router_events)
    commands: list[tuple[float, int, int, int]] = field(default_factory=list)
    # every PLANT_Totals recorded: (t, BatteryPower kW, BatteryCostRate cu/h, the status
    # Power of each agent heard since the previous one: the cycle it sums), for the
    # ledger check (verdict)
    totals: list[tuple[float, float, float, dict[int, float]]] = field(default_factory=list)
    # log lines that hold no frame, by cause (LINE_CAUSES): skipped, never silently
    skipped_lines: Counter[str] = field(default_factory=Counter)
    # timestamps of frames far outside the recording's time span (a clock jump or a
    # corrupt line): left out, so one of them cannot stretch the analysis to years
    time_outliers: list[float] = field(default_factory=list)

    def warnings(self) -> list[str]:
        """What was left out of the log before the analysis, one line per cause."""
        out = []
        if self.skipped_lines:
            causes = "; ".join(f"{v} {LINE_CAUSES[k]}"
                               for k, v in sorted(self.skipped_lines.items()))
            out.append(f"skipped {sum(self.skipped_lines.values())} log line(s) that hold no "
                       f"frame: {causes}")
        if self.time_outliers:
            shown = ", ".join(f"{t:.6f}" for t in self.time_outliers[:3])
            more = ", ..." if len(self.time_outliers) > 3 else ""
            out.append(f"left out {len(self.time_outliers)} frame(s) whose timestamp lies more "
                       f"than {OUTLIER_GAP_TS:g} Ts away from the rest of the recording "
                       f"(t = {shown}{more})")
        return out

    @property
    def start_recorded(self) -> bool:
        """True when every agent's first recorded MC frame is in INIT: the
        recording saw the run's start."""
        return all(s == State.INIT for s in self.first_mc_state.values())

    @property
    def counter_gaps(self) -> Counter[str]:
        """Frames the recorder missed, per message (from the counter jumps)."""
        return Counter({k: s.missed for k, s in self.sequences.items() if s.missed})

    @property
    def out_of_sequence(self) -> Counter[str]:
        """Frames out of their message's counter sequence, per message."""
        return Counter({k: s.out_of_sequence for k, s in self.sequences.items()
                        if s.out_of_sequence})

    def mc_frames(self, agent: int) -> int:
        """How many AGENT_<agent>_MC frames the log holds."""
        s = self.sequences.get(f"AGENT_{agent}_MC")
        return 0 if s is None else s.frames

    def ticks_run(self, agent: int) -> int:
        """How many ticks the agent ran, at least, by its frames: one MC frame per tick
        when it sends every tick; with event-triggered λ fewer, but its k setpoints (one
        every SETPOINT_EVERY ticks from its first) took (k − 1)·SETPOINT_EVERY + 1."""
        s = self.sequences.get(f"AGENT_{agent}_Setpoint")
        setpoints = 0 if s is None else s.frames
        every = contract.every_ticks(contract.setpoint_name(1))
        return max(self.mc_frames(agent), (setpoints - 1) * every + 1)


# why a log line holds no frame (LogContents.skipped_lines), as the report words it
LINE_CAUSES = {
    "truncated": "truncated last line (no newline at the end: the capture was cut off)",
    "bad_timestamp": "with a timestamp that is not a finite number",
    "malformed": "not in candump -L format",
    "not_text": "with bytes that are not text",
}
# a frame this many Ts or more away from the rest of the recording is a timestamp outlier:
# an hour at Ts = 10 ms. Long: a fleet whose bus stalls for minutes must still be judged
# whole (its silences are anomalies); a far-off stamp (years) must not stretch the grid
OUTLIER_GAP_TS = 360_000

# candump -L: "(1700000000.123456) vcan0 123#DEADBEEF" (an optional " R"/" T" direction)
_CANDUMP = re.compile(r"\((?P<t>[^()\s]*)\)\s+(?P<ch>\S+)\s+(?P<id>[0-9A-Fa-f]{1,8})#"
                      r"(?P<data>\S*)(?:\s+[RrTt])?")
_HEX = re.compile(r"(?:[0-9A-Fa-f]{2})*")
CAN_ERR_FLAG, CAN_ERR_BUSERROR = 0x20000000, 0x80  # linux/can/error.h, as python-can reads


def _parse_candump(line: str) -> can.Message | str:
    """One candump -L line as a Message, or the cause (LINE_CAUSES) it is not one. Strict,
    unlike python-can's reader: an odd hex digit, a NaN time or a cut line is no frame."""
    m = _CANDUMP.fullmatch(line)
    if m is None:
        return "malformed"
    try:
        t = float(m["t"])
    except ValueError:
        return "bad_timestamp"
    if not math.isfinite(t):
        return "bad_timestamp"
    ident, data = int(m["id"], 16), m["data"]
    extended = len(m["id"]) > 3
    if ident & CAN_ERR_FLAG and ident & CAN_ERR_BUSERROR:
        return can.Message(timestamp=t, is_error_frame=True, channel=m["ch"])
    if not extended and ident > 0x7FF:
        return "malformed"
    fd = data.startswith("#")
    if fd:
        if len(data) < 2 or data[1] not in "0123456789ABCDEFabcdef":
            return "malformed"
        flags, data = int(data[1], 16), data[2:]
    if not fd and data[:1] in ("R", "r"):
        if not (data[1:] == "" or (data[1:].isdigit() and int(data[1:]) <= 8)):
            return "malformed"
        return can.Message(timestamp=t, arbitration_id=ident & 0x1FFFFFFF,
                           is_extended_id=extended, is_remote_frame=True,
                           dlc=int(data[1:] or 0), channel=m["ch"])
    if not _HEX.fullmatch(data) or len(data) > (128 if fd else 16):
        return "malformed"
    return can.Message(timestamp=t, arbitration_id=ident & 0x1FFFFFFF, is_extended_id=extended,
                       is_fd=fd, bitrate_switch=fd and bool(flags & 1),
                       error_state_indicator=fd and bool(flags & 2),
                       data=bytes.fromhex(data), channel=m["ch"])


def read_frames(path: Path, skipped: Counter[str]) -> Iterator[can.Message]:
    """The frames of a log, counting every line that holds none in ``skipped`` by cause.
    candump -L (.log) is read line by line here; other formats by python-can's LogReader,
    without its frames whose timestamp is not finite."""
    if path.suffix.lower() != ".log":
        try:
            for msg in can.LogReader(str(path)):
                if math.isfinite(msg.timestamp):
                    yield msg
                else:
                    skipped["bad_timestamp"] += 1
        except Exception as e:  # noqa: BLE001 (each reader fails its own way on a bad file)
            raise ConfigError(str(path), "LOG", f"expected a CAN log python-can reads, but "
                              f"got: {type(e).__name__}: {e}") from None
        return
    with open(path, "rb") as f:
        for raw in f:
            try:
                line = raw.decode("utf-8").strip()
            except UnicodeDecodeError:
                skipped["not_text"] += 1
                continue
            if not line:
                continue
            got = _parse_candump(line)
            if isinstance(got, can.Message):
                yield got
            elif not raw.endswith(b"\n"):
                skipped["truncated"] += 1  # only the last line can lack its newline
            else:
                skipped[got] += 1


def _main_span(frames: list[can.Message], gap: float) -> tuple[list[can.Message], list[float]]:
    """The frames of the recording's main stretch (sorted by timestamp), and the
    timestamps of the others: frames more than ``gap`` from the biggest stretch of frames
    without such a gap (a far-future or far-past stamp among them)."""
    if not frames:
        return frames, []
    t = np.array([m.timestamp for m in frames])
    order = np.argsort(t, kind="stable")
    cuts = np.flatnonzero(np.diff(t[order]) > gap) + 1
    if not cuts.size:
        return [frames[i] for i in order], []
    bounds = np.concatenate(([0], cuts, [t.size]))
    main = int(np.argmax(np.diff(bounds)))  # the most frames; the earliest on a tie
    lo, hi = bounds[main], bounds[main + 1]
    outliers = [float(t[i]) for i in np.concatenate((order[:lo], order[hi:]))]
    return [frames[i] for i in order[lo:hi]], outliers


def read_log(path: Path, codec: FrameCodec | None = None, n: int | None = None,
             ts: float | None = None, keys: Mapping[str, bytes] | None = None,
             boot_floors: Mapping[str, int] | None = None,
             silence_ts: float = 3) -> LogContents:
    """Decode every frame of a candump-format log (``can.LogReader``: any suffix it knows).

    ``n``: the run's fleet size, so frames of agents beyond it count as outside the run;
    ``ts``: the run's sample time, for the silence threshold (``silence_ts``·Ts: more in a
    run whose agents send their λ event-triggered, sim.run.verdict.silence_ts) and for the message
    cycles of a time-scaled run (the DBC's cycles are for Ts = 10 ms); ``keys``: the
    run's node keys (label → key), to leave out forged and replayed secured frames
    (``forged``) as every receiver does. Without them, secured frames are taken as
    they are: a forgery on the bus then reads as the run's own data. ``boot_floors``:
    each node's lowest boot counter in this recording (``Monitor``).

    Frames are taken in the order of their timestamps, not of the file: a capture
    socket can receive one sender's frames out of order (vcan on a multi-core host
    queues each frame on the sending CPU, and a descheduled CPU delivers late), while
    the kernel stamped them in the order they were sent; ``reordered`` counts them.

    Damaged logs are read as far as they hold frames: a line that is not one (garbage, a
    NaN timestamp, a last line cut off) is skipped and counted (``skipped_lines``), and a
    frame far off the recording's time span (a clock jump) is left out and listed
    (``time_outliers``); ``LogContents.warnings`` words both for the report."""
    codec = codec or FrameCodec()
    out = LogContents()
    monitor = (Monitor(keys, boot_floors, lambda name: cycle_or_inf(name, ts or MC_CYCLE_S))
               if keys else None)
    out.keys_checked = monitor is not None
    price_sig = None
    if keys and pricesig.MONITOR_PUBLIC in keys:  # signed_price: the price as agents take it
        price_sig = pricesig.PriceSigReceiver(keys[pricesig.MONITOR_PUBLIC],
                                              keys[pricesig.MONITOR_FLEET].hex())
    if monitor is not None and price_sig is not None:  # AUTH-33: a held price advance
        receiver = price_sig                               # is taken only when signed
        monitor.vouches[contract.ER_PRICE_ID] = (
            lambda boot: receiver.current is not None and receiver.current.boot >= boot)
    segment_raw: int | None = None
    segment = 0
    status_power: dict[int, float] = {}  # agent -> its status Power since the last totals
    segment_mod = codec.raw_range("ER_Price", "Segment")[1] + 1
    silence = silence_ts * ts if ts else None
    cycles: dict[str, float] = {}
    t_prev: float | None = None
    captured = list(read_frames(path, out.skipped_lines))
    out.reordered = sum(b.timestamp < a.timestamp for a, b in pairwise(captured))
    frames, out.time_outliers = _main_span(captured, OUTLIER_GAP_TS * (ts or MC_CYCLE_S))
    for msg in frames:   # in timestamp order; ties keep the file's
        out.frames += 1
        t = msg.timestamp
        out.t_end = t  # frames come in timestamp order
        if (silence is not None and t_prev is not None and out.t_first_price is not None
                and t - t_prev > silence):
            out.silences.append((t_prev, t))
        t_prev = t if t_prev is None else max(t_prev, t)
        try:
            f = codec.decode(msg)
        except FrameError as e:
            out.undecodable[e.cause] += 1
            continue
        if n is not None and f.agent is not None and f.agent > n:
            out.outside_run[f.name] += 1
            continue
        kind = codec.kind(f.frame_id)
        if kind == "transfer":  # ER_PriceSig (signed_price): checked, never a series
            if price_sig is not None:
                bad = price_sig.take(f.raw)
                if bad is not None:
                    out.unsigned[f.name] += 1
            continue
        if kind == "sync":
            out.syncs += 1
        if (price_sig is not None and f.name == "ER_Price"
                and price_sig.check(f.raw) is not None):
            out.unsigned[f.name] += 1  # AUTH-33: not the signed price, as at the agents
            continue
        if monitor is not None:
            try:
                if kind == "sync":
                    monitor.sync(f, msg.data, t)
                elif not monitor.check(f, msg.data, t):
                    out.unverified[f.name] += 1
                    continue
                out.verified[contract.sender_of(f.name.removesuffix("_Sync"))] += 1
            except Stale:
                out.stale[f.name] += 1
                continue
            except Forged:
                out.forged[f.name] += 1
                continue
            except SyncJump:
                out.sync_jump[f.name] += 1
                continue
            except StaleBoot as e:
                low = out.stale_boot.get(e.label, (e.boot, e.floor))
                out.stale_boot[e.label] = (min(low[0], e.boot), max(low[1], e.floor))
                out.stale_boot_syncs[f.name] += 1
                continue
        if kind == "sync":
            continue
        if f.name not in cycles:
            cycles[f.name] = cycle_or_inf(f.name, ts or MC_CYCLE_S)
        _sequence(out.sequences.setdefault(f.name, SequenceStats()), f.counter, t,
                  SEQUENCE_TIMEOUT_CYCLES * cycles[f.name])
        if f.name == "ER_Price":
            if out.t_first_price is None:
                out.t_first_price = t
            out.series[("price", "Rho")].append((t, f.phys("Rho")))
            # Segment counts mod 8 on the wire: unwrap it
            segment = (f.raw["Segment"] if segment_raw is None
                       else segment + (f.raw["Segment"] - segment_raw) % segment_mod)
            segment_raw = f.raw["Segment"]
            out.series[("price", "Segment")].append((t, segment))
        elif f.name.endswith("_MC"):
            out.first_mc_state.setdefault(f.name, f.raw["State"])
            for sig in ("Lambda", "State", "Resets"):
                out.series[(f.name, sig)].append((t, f.phys(sig)))
            out.dispatch[f.agent or 0].append((t, "mc", f.raw["State"], f.raw["Lambda"]))
        elif f.name.endswith("_Setpoint"):
            out.dispatch[f.agent or 0].append((t, "setpoint", f.raw["Enable"],
                                               f.raw["PowerSetpoint"]))
        elif f.name.endswith("_Status"):
            for sig in ("Power", "PowerLimited"):
                out.series[(f.name, sig)].append((t, f.phys(sig)))
            status_power[f.agent or 0] = f.phys("Power")
        elif f.name == contract.TOTALS:
            out.totals.append((t, f.phys("BatteryPower"), f.phys("BatteryCostRate"),
                               status_power))
            status_power = {}
        elif f.name.endswith("_Diag"):
            out.diag[f.agent or 0].update({k: v for k, v in f.raw.items()
                                           if k not in ("Mac", "Counter", "Page")})
        elif f.name == "ER_Command":
            out.commands.append((t, f.raw["Command"], target_agent(f.raw["Target"]),
                                 f.raw["GainK"]))
        elif f.name == "ER_Balance":  # one page's signals
            for sig in f.raw:
                if sig not in ("Mac", "Counter", "Page"):
                    out.series[("balance", sig)].append((t, f.phys(sig)))
    if monitor is not None:
        out.sync_undone.update(monitor.undone)
    _message_silences(out, cycles, NODE_SILENCE_MIN_TS * (ts or MC_CYCLE_S))
    return out


def _message_silences(out: LogContents, cycles: dict[str, float], floor: float) -> None:
    t0 = out.t_first_price
    if t0 is None:
        return
    for name, s in out.sequences.items():
        limit = max(SEQUENCE_TIMEOUT_CYCLES * cycles[name], floor)
        gaps = [(a, b) for a, b in s.gaps if b > t0 and b - max(a, t0) > limit]
        if s.t_last is not None and out.t_end - s.t_last > limit:
            gaps.append((s.t_last, out.t_end))
        if gaps:
            out.message_silences[name] = gaps


def _sequence(s: SequenceStats, counter: int, t: float, timeout: float) -> None:
    s.frames += 1
    if s.t_last is not None and t - s.t_last > timeout:
        s.gaps.append((s.t_last, t))
    elif s.last is not None and s.t_last is not None:
        delta = (counter - s.last) % COUNTER_MODULO
        if delta == 0 or delta > COUNTER_STEP_MAX:
            s.out_of_sequence += 1
        else:
            s.missed += delta - 1
    s.last, s.t_last = counter, t


def _hold(series: list[tuple[float, float]], grid: np.ndarray, before: float) -> np.ndarray:
    """Last value at or before each grid time (``before`` where nothing was received yet)."""
    if not series:
        return np.full(grid.shape, before)
    t, v = np.array(series).T
    idx = np.searchsorted(t, grid, side="right") - 1
    return np.where(idx >= 0, v[np.clip(idx, 0, None)], before)


def planned_participation(sc: Scenario, t: np.ndarray) -> np.ndarray:
    """(K, N): agent i is meant to take part in the dispatch at t_k: everyone, except
    between an ``isolate`` event and the next ``reconnect`` (as the lockstep runner
    applies them, at sample round(t_event/Ts))."""
    planned = np.ones((t.size, sc.n), dtype=bool)
    k = np.rint(t / sc.ts)
    for e in sorted(sc.events, key=lambda e: e.t):
        planned[k >= round(e.t / sc.ts), e.agent - 1] = e.action == "reconnect"
    return planned


def trajectory_from_log(sc: Scenario, log: LogContents, label: str = "bus") -> Trajectory:
    """The run recorded in ``log`` as a Trajectory sampled at Ts from the first
    ER_Price frame (t = 0); ValueError if the log holds no price."""
    if log.t_first_price is None:
        raise ValueError("the log holds no ER_Price frame: the router never spoke")
    t0, ts = log.t_first_price, sc.ts
    if (log.t_end - t0) / ts * sc.n > MAX_AGENT_SAMPLES:  # refused, not memory exhausted
        raise ConfigError(sc.source, "log", f"expected a recording of at most "
                          f"{MAX_AGENT_SAMPLES:.0e} agent-samples ({sc.n} agents × its span "
                          f"/ Ts = {ts:g} s), but it spans {log.t_end - t0:.6g} s from the "
                          f"first price")
    grid = t0 + np.arange(0.0, log.t_end - t0, ts)
    lam = np.column_stack([_hold(log.series[(f"AGENT_{i}_MC", "Lambda")], grid, sc.lambda0[i - 1])
                           for i in range(1, sc.n + 1)])
    state = np.column_stack([_hold(log.series[(f"AGENT_{i}_MC", "State")], grid, State.INIT)
                             for i in range(1, sc.n + 1)])
    p = np.column_stack([_hold(log.series[(f"PLANT_{i}_Status", "Power")], grid, 0.0)
                         for i in range(1, sc.n + 1)])
    resets = []
    for i in range(1, sc.n + 1):
        r = log.series[(f"AGENT_{i}_MC", "Resets")]
        resets.append([t - t0 for (t, v), (_, v0) in zip(r[1:], r, strict=False) if v != v0])
    u = np.vstack([np.diff(lam, axis=0) / ts, np.zeros((1, sc.n))])
    expected = planned_participation(sc, grid - t0)
    for i, t_last in failed_over(log).items():  # dead, and failed over: no longer judged
        if 1 <= i <= sc.n:
            expected[grid > t_last, i - 1] = False
    return Trajectory(t=grid - t0, lam=lam, rho=_hold(log.series[("price", "Rho")], grid, np.nan),
                      segment=_hold(log.series[("price", "Segment")], grid, 0).astype(int),
                      active=np.vectorize(contract.is_active, otypes=[bool])(state), p=p, u=u,
                      resets=resets, label=label, expected=expected, state=state.astype(int))


def node_diagnostics(log: LogContents) -> dict[str, Any]:
    """Per agent: the last value of every diagnostics counter it broadcast."""
    return {f"agent_{a}": dict(sorted(d.items())) for a, d in sorted(log.diag.items())}


def router_events(log: LogContents, gap_s: float = 0.1) -> list[dict[str, Any]]:
    """The router's commands as events of the run, from the recorded ER_Command frames:
    each command once (the router repeats it, COMMAND_REPEATS frames 10 ms apart: frames
    of the same command and target within ``gap_s`` of the last are one event), in bus
    order: ``{"t", "command", "target"}``, command the DBC's name (PIN: ``pin`` or
    ``unpin`` by its GainK, CMD-7). A PIN is the router's pinned-agent failover."""
    from firmware_py.contract import Command
    from firmware_py.frames import PIN_ON

    out: list[dict[str, Any]] = []
    last: dict[tuple[int, int, int], float] = {}
    for t, cmd, target, gain_k in log.commands:
        key = (cmd, target, gain_k)
        if key in last and t - last[key] <= gap_s:
            last[key] = t
            continue
        last[key] = t
        if cmd == Command.PIN:
            name = "pin" if gain_k == PIN_ON else "unpin"
        else:
            name = Command(cmd).name.lower() if cmd in Command._value2member_map_ else str(cmd)
        out.append({"t": t - (log.t_first_price or 0.0), "command": name, "target": target})
    return out


def failovers(events: list[dict[str, Any]], gap_s: float = 0.1) -> list[dict[str, Any]]:
    """The pinned-agent failovers among ``router_events``: the pins, those within
    ``gap_s`` of each other as one failover: ``{"t", "pinned": [agents]}``."""
    out: list[dict[str, Any]] = []
    for e in events:
        if e["command"] != "pin":
            continue
        if out and e["t"] - out[-1]["t"] <= gap_s:
            out[-1]["pinned"].append(e["target"])
        else:
            out.append({"t": e["t"], "pinned": [e["target"]]})
    return out


def failed_over(log: LogContents) -> dict[int, float]:
    """The agents the router failed over from and that never came back: agent → the time
    of its last MC frame (recording time), for each agent silent from before a PIN
    (GainK = PIN_ON, CMD-7) to the end of the recording. The run is judged without them
    from that time on (trajectory_from_log: a dead agent's held λ is no dispatch); its
    silence stays an anomaly (node_silent)."""
    from firmware_py.contract import Command
    from firmware_py.frames import PIN_ON

    pins = [t for t, cmd, _, gain_k in log.commands if cmd == Command.PIN and gain_k == PIN_ON]
    out: dict[int, float] = {}
    for (name, sig), series in log.series.items():
        if sig != "Lambda" or not name.endswith("_MC") or not series:
            continue
        last = series[-1][0]
        if any(t > last for t in pins):
            out[int(name.split("_")[1])] = last
    return out


def router_ledger(log: LogContents) -> dict[str, float] | None:
    """The router's own cost ledger as broadcast in ER_Balance: its cost rates integrated
    over the recorded frames (rectangle rule, each rate held until the next frame), from
    the first price frame on, and the last grid power. None without ER_Balance frames."""
    cost = log.series.get(("balance", "CostRate"), [])
    opt = log.series.get(("balance", "OptimalCostRate"), [])
    grid = log.series.get(("balance", "GridPower"), [])
    t0 = log.t_first_price
    if not cost or t0 is None:
        return None

    def integral(series: list[tuple[float, float]]) -> float:
        pts = [(t, v) for t, v in series if t >= t0]
        return sum(v * (t1 - t) for (t, v), (t1, _) in zip(pts, pts[1:], strict=False)) / 3600

    return {"cost": integral(cost), "optimal_cost": integral(opt),
            "cost_rate": cost[-1][1], "optimal_cost_rate": opt[-1][1] if opt else float("nan"),
            "grid_power": grid[-1][1] if grid else float("nan")}
