"""One honest verdict on a bus run: did the fleet converge, and what went wrong on the way.

``judge`` looks at everything a run leaves — the decoded recording, the trajectory on
the Ts grid, each agent's diagnostics frames, the plant's and router's counters, the
node processes' exit codes — and returns the anomalies and the verdict that
``bess-ded up`` and ``bess-ded analyze`` print, write to metrics.json and turn into
their exit code. Every rule is listed in docs/runs.md.

A run *converged* when every agent that the scenario means to be dispatching at the end
is RUNNING there, the last price segment settled into its 2 % band, and no node died.
Anything else that should not happen in a healthy run is an *anomaly*; a converged run
with anomalies is not a success either.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from firmware_py.contract import MC_CYCLE_S, State

from .buslog import LogContents
from .scenario import Scenario
from .trajectory import Trajectory

EXIT_OK = 0              # converged, no anomaly
EXIT_NOT_CONVERGED = 1   # the fleet did not converge (reasons in the verdict)
EXIT_ANOMALIES = 3       # converged, but with anomalies
EXIT_INTERRUPTED = 130   # SIGINT/SIGTERM: outputs written for what was recorded
# (2 is every command's exit code for bad input)

SILENCE_TS = 3            # a bus silence longer than this many Ts is an anomaly
SILENCE_CLUSTER_S = 1.0   # (scenario s) silences closer than this are reported as one
STATE_GRACE_TS = 10       # INIT/ISOLATED/RUNNING may lag the plan by this many Ts
DEADLINE_MISS_FRACTION = 0.01
POWER_LIMIT_HOLD_S = 1.0  # (scenario s) a battery limited over the run's last second
INIT, RUNNING, ISOLATED, SAFE = State.INIT, State.RUNNING, State.ISOLATED, State.SAFE

# AGENT_i_Diag counters that a healthy run keeps at 0: (signal, anomaly kind, what)
_AGENT_FAULT_COUNTERS = (
    ("PriceTimeouts", "price_timeout", "price timeouts (no valid ER_Price for the timeout)"),
    ("StatusTimeouts", "status_timeout", "plant-status timeouts"),
    ("PlantFaults", "plant_fault", "plant faults reported by PLANT_i_Status"),
    ("ForeignFrames", "foreign_traffic", "frames that cannot come from its own fleet (another "
     "sender on its IDs, IDs outside the run, interleaved counter sequences)"),
    ("RejectedCrc", "rejected_frames", "frames with a bad CRC"),
    ("RejectedDlc", "rejected_frames", "frames with a bad length"),
    ("RejectedRange", "rejected_frames", "frames with a value out of range"),
    ("RejectedUnknownId", "rejected_frames", "frames with an ID outside the DBC"),
    ("RepeatedCounter", "stale_frames", "frames repeating the last counter (stale data)"),
    ("Untrusted", "untrusted_source", "untrusted-source alarms (a source ID with 5 "
     "consecutive authentication or E2E failures)"),
    ("ImplausiblePrice", "implausible_frames", "prices rejected as implausible (bounds or step)"),
    ("ImplausibleLambda", "implausible_frames", "neighbour λ rejected as implausible (step per "
     "sample)"),
    ("ImplausibleGains", "implausible_frames", "SET_GAINS rejected (gains outside bounds)"),
    ("RejectedAuth", "auth_failed", "secured frames or syncs whose MAC does not verify "
     "(forged, replayed or corrupted)"),
)
# the plant's and router's counters (logs/*.counters.json) that a healthy run keeps at 0
_SIM_FAULT_COUNTERS = (
    ("setpoint_timeouts", "setpoint_timeout", "setpoint timeouts"),
    ("status_timeouts", "status_timeout", "status timeouts"),
    ("foreign", "foreign_traffic", "frames that cannot come from its own fleet (another "
     "sender on its IDs, IDs outside the run, interleaved counter sequences)"),
    ("crc", "rejected_frames", "frames with a bad CRC"),
    ("dlc", "rejected_frames", "frames with a bad length"),
    ("range", "rejected_frames", "frames with a value out of range"),
    ("unknown_id", "rejected_frames", "frames with an ID outside the DBC"),
    ("malformed", "rejected_frames", "remote, error or FD frames"),
    ("repeated_counter", "stale_frames", "frames repeating the last counter (stale data)"),
    ("send_failure", "send_failure", "frames it failed to send"),
    ("untrusted_sources", "untrusted_source", "untrusted-source alarms (a source ID with 5 "
     "consecutive authentication or E2E failures)"),
    ("untrusted", "untrusted_source", "frames rejected from an E2E-only source ID made "
     "untrusted by consecutive E2E failures"),
    ("auth", "auth_failed", "secured frames or syncs whose MAC does not verify (forged, "
     "replayed or corrupted)"),
)


@dataclass(frozen=True)
class Anomaly:
    kind: str            # e.g. "node_died", "agent_safe", "bus_silence" (docs/runs.md)
    node: str            # "agent_3", "plant", "router", "bus", "recorder", "run"
    detail: str
    t: float | None = None  # s from the first price frame (run time), where it has one

    def text(self, time_scale: float = 1.0) -> str:
        at = "" if self.t is None else f" at t = {self.t / time_scale:.2f} s"
        return f"{self.kind} [{self.node}]{at}: {self.detail}"


@dataclass
class Verdict:
    converged: bool
    reasons: list[str]           # why not converged (empty when it did)
    anomalies: list[Anomaly]
    interrupted: bool = False

    @property
    def exit_code(self) -> int:
        if self.interrupted:
            return EXIT_INTERRUPTED
        if not self.converged:
            return EXIT_NOT_CONVERGED
        return EXIT_ANOMALIES if self.anomalies else EXIT_OK

    @property
    def ok(self) -> bool:
        return self.exit_code == EXIT_OK

    def as_json(self) -> dict[str, Any]:
        return {"converged": self.converged, "reasons": self.reasons,
                "interrupted": self.interrupted, "exit_code": self.exit_code,
                "ok": self.ok}


@dataclass
class RunFacts:
    """What the harness knows beyond the recording (all optional: ``analyze`` of a
    foreign log has none of it)."""

    exit_codes: dict[str, int | None] | None = None
    deaths: list[tuple[str, float, int]] | None = None   # (node, s after t0, exit code)
    node_counters: dict[str, Any] | None = None          # plant/router counters JSON
    interrupted: bool = False


def judge(sc: Scenario, log: LogContents, tr: Trajectory | None, m: dict[str, Any],
          facts: RunFacts | None = None) -> Verdict:
    facts = facts or RunFacts()
    out: list[Anomaly] = []
    reasons: list[str] = []
    t0 = log.t_first_price
    if facts.interrupted:
        out.append(Anomaly("interrupted", "run", "stopped by a signal before the scenario's "
                           "end: results cover what was recorded"))
    _node_exits(facts, out, reasons)
    if t0 is None or tr is None:
        out.append(Anomaly("no_price", "router", "no ER_Price frame in the recording: the "
                           "router never spoke (or the recorder heard another bus)"))
        reasons.append("no price was ever heard")
        return Verdict(False, reasons, out, facts.interrupted)
    _agent_states(sc, log, tr, out, reasons)
    _recording(sc, log, out)
    _counters(sc, log, facts, out)
    _power_limits(sc, log, tr, out)
    st = m.get("settling_times_s") or [None]
    if st[-1] is None:
        reasons.append(f"the last price segment never settled into its 2 % band (final "
                       f"error {m.get('final_error', float('nan')):.2e} cu/kWh)")
    return Verdict(not reasons, reasons, out, facts.interrupted)


def _node_exits(facts: RunFacts, out: list[Anomaly], reasons: list[str]) -> None:
    died = set()
    for name, t, code in facts.deaths or []:
        died.add(name)
        out.append(Anomaly("node_died", name, f"exited with code {code} during the run", t))
        reasons.append(f"{name} died (exit code {code})")
    for name, exit_code in (facts.exit_codes or {}).items():
        if name in died:
            continue
        if exit_code is None:
            out.append(Anomaly("node_not_started", name, "was never started"))
            reasons.append(f"{name} never ran")
        elif exit_code != 0:
            out.append(Anomaly("node_died", name, f"exited with code {exit_code}"))
            reasons.append(f"{name} exited abnormally (code {exit_code})")


def _intervals(mask: np.ndarray, t: np.ndarray, ts: float) -> list[tuple[float, float]]:
    """(start, duration) of each run of True in ``mask``."""
    out = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        out.append((float(t[a]), float((b - a) * ts)))
    return out


def _agent_states(sc: Scenario, log: LogContents, tr: Trajectory, out: list[Anomaly],
                  reasons: list[str]) -> None:
    assert tr.state is not None and tr.expected is not None
    ts, grace = sc.ts, STATE_GRACE_TS * sc.ts
    for i in range(sc.n):
        name = f"agent_{i + 1}"
        if log.mc_frames(i + 1) == 0:
            out.append(Anomaly("agent_silent", name, "sent no AGENT_MC frame at all"))
            reasons.append(f"{name} was never heard")
            continue
        state, expected = tr.state[:, i], tr.expected[:, i]
        end = int(state[-1])
        if expected[-1] and end != RUNNING:
            what = State(end).name if end in State._value2member_map_ else str(end)
            out.append(Anomaly(f"agent_{what.lower()}_at_end", name,
                               f"in {what} at the end, where the scenario has it dispatching",
                               float(tr.t[-1])))
            reasons.append(f"{name} ended in {what}")
        for t, d in _intervals(state == SAFE, tr.t, ts):
            out.append(Anomaly("agent_safe", name, f"in SAFE for {d:.2f} s (the scenario "
                               "plans none)", t))
        for s, what in ((ISOLATED, "ISOLATED"), (INIT, "INIT")):
            for t, d in _intervals((state == s) & expected, tr.t, ts):
                if d > grace:
                    out.append(Anomaly(f"agent_{what.lower()}", name, f"in {what} for {d:.2f} s "
                                       f"where the scenario has it dispatching", t))
        for t, d in _intervals((state == RUNNING) & ~expected, tr.t, ts):
            if d > grace:
                out.append(Anomaly("agent_not_isolated", name, f"RUNNING for {d:.2f} s where "
                                   "the scenario has it isolated", t))


def _recording(sc: Scenario, log: LogContents, out: list[Anomaly]) -> None:
    t0 = log.t_first_price or 0.0
    for cluster in _clusters(log.silences, SILENCE_CLUSTER_S * sc.ts / MC_CYCLE_S):
        a, b = cluster[0][0], cluster[-1][1]
        longest = max(y - x for x, y in cluster)
        what = (f"no frame for {longest:.3f} s ({longest / sc.ts:.0f} Ts)" if len(cluster) == 1
                else f"{len(cluster)} gaps without a frame between t = {a - t0:.2f} and "
                f"{b - t0:.2f} s, the longest {longest:.3f} s ({longest / sc.ts:.0f} Ts)")
        out.append(Anomaly("bus_silence", "bus", f"{what}; more than {SILENCE_TS} Ts",
                           a - t0))
    by_sender: dict[str, list[tuple[float, float, str]]] = {}
    for name, gaps in log.message_silences.items():
        by_sender.setdefault(sender_of(name), []).extend((a, b, name) for a, b in gaps)
    for node, silent in sorted(by_sender.items()):
        merged: list[tuple[float, float, list[str]]] = []
        for a, b, name in sorted(silent):
            if merged and a <= merged[-1][1]:
                merged[-1] = (merged[-1][0], max(b, merged[-1][1]), merged[-1][2] + [name])
            else:
                merged.append((a, b, [name]))
        for a, b, names in merged:
            end = " (to the end of the recording)" if b >= log.t_end else ""
            out.append(Anomaly("node_silent", node, f"sent no {_names(names)} for "
                               f"{b - max(a, t0):.2f} s{end}", max(a, t0) - t0))
    if not log.start_recorded:
        out.append(Anomaly("start_not_recorded", "recorder", "an agent's first recorded MC "
                           "frame is not INIT: the recording started late, so t = 0 and every "
                           "settling time are late too"))
    missed = log.counter_gaps
    if missed:
        out.append(Anomaly("recorder_missed_frames", "recorder",
                           f"{sum(missed.values())} frames missing from the recording "
                           f"(from the counter jumps: {_top(missed)})"))
    for name, k in sorted(log.out_of_sequence.items()):
        out.append(Anomaly("foreign_traffic", "bus", f"{name}: {k} frames out of its counter "
                           "sequence (a second sender on the ID, or a replay)"))
    if log.outside_run:
        out.append(Anomaly("foreign_traffic", "bus", f"{sum(log.outside_run.values())} frames "
                           f"of messages outside this {sc.n}-agent run ({_top(log.outside_run)})"))
    for name, k in sorted(log.forged.items()):
        out.append(Anomaly("auth_failed", "bus", f"{name}: {k} frames whose MAC does not "
                           "verify with its sender's key (forged, or replayed from an earlier "
                           "window or run); the analysis left them out"))
    for label, (boot, floor) in sorted(log.stale_boot.items()):
        out.append(Anomaly("stale_boot", label, f"syncs of {label} with a valid MAC but boot "
                           f"{boot}, below its boot {floor} in this run: a replay of an "
                           f"earlier run or boot, or {label}'s key file rolled back (AUTH-21); "
                           "the analysis left them out"))
    if log.undecodable:
        out.append(Anomaly("malformed_frames", "bus", f"{sum(log.undecodable.values())} frames "
                           f"that fail the DBC's checks ({_top(log.undecodable)})"))


def _clusters(gaps: list[tuple[float, float]], within: float
              ) -> list[list[tuple[float, float]]]:
    """Gaps grouped when each starts less than ``within`` s after the previous one ends."""
    out: list[list[tuple[float, float]]] = []
    for g in sorted(gaps):
        if out and g[0] - out[-1][-1][1] < within:
            out[-1].append(g)
        else:
            out.append([g])
    return out


def sender_of(message: str) -> str:
    """The node that sends a message: ER_* → router, PLANT_* → plant, AGENT_i_* → agent_i."""
    if message.startswith("ER_"):
        return "router"
    if message.startswith("PLANT_"):
        return "plant"
    return "agent_" + message.split("_")[1]


def _names(names: list[str]) -> str:
    unique = sorted(set(names), key=names.index)
    return ", ".join(unique[:3]) + (f" (+{len(unique) - 3} more)" if len(unique) > 3 else "")


def _top(c: Any, k: int = 4) -> str:
    items = sorted(c.items(), key=lambda x: -x[1])
    more = f", … {len(items) - k} more" if len(items) > k else ""
    return ", ".join(f"{n}: {v}" for n, v in items[:k]) + more


def _counters(sc: Scenario, log: LogContents, facts: RunFacts, out: list[Anomaly]) -> None:
    for a, d in sorted(log.diag.items()):
        name = f"agent_{a}"
        for sig, kind, what in _AGENT_FAULT_COUNTERS:
            if d.get(sig, 0):
                if kind in ("untrusted_source", "implausible_frames", "auth_failed"):
                    what += _last_rejected(d)
                out.append(Anomaly(kind, name, f"{d[sig]} {what}"))
    for node, c in sorted((facts.node_counters or {}).items()):
        counters = c.get("counters", {})
        for key, kind, what in _SIM_FAULT_COUNTERS:
            if counters.get(key, 0):
                out.append(Anomaly(kind, node, f"{counters[key]} {what}"))
    for node, (misses, ticks) in node_deadlines(log, facts.node_counters).items():
        if misses and misses > DEADLINE_MISS_FRACTION * max(ticks, 1):
            out.append(Anomaly("deadline_misses", node, f"{misses} deadline misses in {ticks} "
                               f"ticks ({100 * misses / max(ticks, 1):.1f} %, more than "
                               f"{100 * DEADLINE_MISS_FRACTION:g} %)"))


def node_deadlines(log: LogContents, node_counters: dict[str, Any] | None
                   ) -> dict[str, tuple[int, int]]:
    """(deadline misses, ticks) per node: an agent's from its last AGENT_i_Diag and its
    recorded MC frames (one per tick it ran) plus the misses; the plant's and router's
    from the counters they wrote at exit."""
    out = {}
    for a, d in sorted(log.diag.items()):
        misses = d.get("DeadlineMisses", 0)
        out[f"agent_{a}"] = (misses, log.mc_frames(a) + misses)
    for node, c in (node_counters or {}).items():
        out[node] = (c.get("counters", {}).get("deadline_miss", 0), c.get("ticks", 0))
    return out


def _last_rejected(d: dict[str, int]) -> str:
    """The claimed sender and cause of the agent's last safety rejection (Diag page 7)."""
    from firmware_py.errors import UnknownFrameError
    from firmware_py.frames import FrameCodec
    from firmware_py.runtime import SAFETY_CAUSES

    sender, cause = d.get("SafetySender", 0), d.get("SafetyCause", 0)
    if not sender:
        return ""
    try:
        who = f"{FrameCodec().name_of(sender)}, 0x{sender:03X}"
    except UnknownFrameError:  # an ID outside the DBC is still worth naming
        who = f"0x{sender:03X}"
    why = SAFETY_CAUSES[cause] if 0 <= cause < len(SAFETY_CAUSES) else str(cause)
    return f"; the last one claimed to come from {who} ({why})"


def _power_limits(sc: Scenario, log: LogContents, tr: Trajectory, out: list[Anomaly]) -> None:
    t_end = (log.t_first_price or 0.0) + float(tr.t[-1])
    hold = POWER_LIMIT_HOLD_S * sc.ts / MC_CYCLE_S
    for i in range(1, sc.n + 1):
        flags = [(t, v) for t, v in log.series.get((f"PLANT_{i}_Status", "PowerLimited"), [])
                 if t >= t_end - hold]
        if flags and all(v for _, v in flags):
            out.append(Anomaly("power_limit", f"plant (BESS {i})", "held at a power or current "
                               f"limit over the run's last {POWER_LIMIT_HOLD_S:g} s",
                               float(tr.t[-1])))


def anomalies_json(v: Verdict) -> list[dict[str, Any]]:
    return [asdict(a) for a in v.anomalies]
