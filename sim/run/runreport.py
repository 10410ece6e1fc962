"""From a candump log of a fleet to metrics.json, trajectory.csv, the anomalies and the plot.

The one path every bus result takes: ``bess-ded up`` after its run (or after Ctrl-C),
``bess-ded analyze`` on a log from ``up``, ``candump -L``, ``bess-ded record``, nodes
started by hand or a HIL rig. So a log gives the same numbers whoever recorded it.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from dbc import dbc_path
from firmware_py.frames import FrameCodec
from sim.model import metrics
from sim.model.scenario import Scenario
from sim.model.trajectory import Trajectory
from sim.run import buslog
from sim.run.verdict import (
    TOLERANCE,
    RunFacts,
    Verdict,
    anomalies_json,
    judge,
    loss_text,
    node_deadlines,
    silence_ts,
)


@dataclass
class Recording:
    """What a bus run leaves: its metrics, the verdict and the decoded log they came from."""

    metrics: dict[str, Any]
    log: buslog.LogContents
    trajectory: Trajectory | None
    verdict: Verdict
    written: list[Path]  # the files ``report`` wrote, in order


def report(sc: Scenario, log_path: Path, out: Path, facts: RunFacts | None = None,
           plot: bool = True, time_scale: float = 1.0,
           codec: FrameCodec | None = None, keys: Mapping[str, bytes] | None = None,
           boot_floors: Mapping[str, int] | None = None,
           tolerance: float = TOLERANCE) -> Recording:
    """Decode ``log_path`` against the scenario ``sc`` (as it ran: variant chosen, time
    scale applied), judge it and write DIR/metrics.json, DIR/trajectory.csv and, with
    ``plot``, DIR/bus_run.png. ``time_scale`` only relabels the plot's time axis in
    scenario seconds. ``keys``: the run's node keys (label → key): forged and replayed
    secured frames are then left out of the analysis and reported; ``boot_floors``:
    each node's lowest boot counter in the run (sim.run.monitor.Monitor); ``tolerance``: how close
    to ρ every dispatching agent's final λ must be for the run to converge (cu/kWh)."""
    facts = facts or RunFacts()
    out.mkdir(parents=True, exist_ok=True)
    # the frame format the run's bus had
    codec = codec or FrameCodec(dbc_path(sc.fd, sc.lambda_tags))
    log = buslog.read_log(log_path, codec, n=sc.n, ts=sc.ts, keys=keys,
                          boot_floors=boot_floors, silence_ts=silence_ts(sc))
    tr = buslog.trajectory_from_log(sc, log) if log.t_first_price is not None else None
    m: dict[str, Any] = {"scenario": sc.name, "time_scale": time_scale}
    if tr is not None and tr.t.size:
        m.update(metrics.compute(sc, tr))
    else:
        tr = None
    diag = buslog.node_diagnostics(log)
    sim_nodes = facts.node_counters or {}
    verdict = judge(sc, log, tr, m, facts, tolerance)
    deadlines = node_deadlines(log, sim_nodes)
    m.update({
        "source": "bus",
        "log": str(log_path),
        "verdict": verdict.as_json(),
        "anomalies": anomalies_json(verdict),
        "frames_recorded": log.frames,
        "frames_undecodable": dict(log.undecodable),
        "frames_missed_by_recorder": sum(log.counter_gaps.values()),
        "frames_out_of_sequence": dict(log.out_of_sequence),
        "frames_outside_run": dict(log.outside_run),
        "bus_silences": len(log.silences),
        "start_recorded": log.start_recorded,
        "node_diagnostics": diag,
        "node_counters": sim_nodes,
        "recorder_counters": facts.recorder_counters or {},
        "deadline_misses": {k: misses for k, (misses, _) in deadlines.items()},
        "node_ticks": {k: ticks for k, (_, ticks) in deadlines.items()},
        "exit_codes": facts.exit_codes or {},
        "tolerance": tolerance,
        "insecure": facts.insecure,
        "injected_loss": (None if facts.injected_loss is None else
                          {**facts.injected_loss,
                           "explains": [asdict(a) for a in verdict.loss_explained]}),
        "router_ledger": buslog.router_ledger(log),
        # the router's commands (events, not anomalies), its failovers among them
        "events": (events := buslog.router_events(log)),
        "failovers": buslog.failovers(events),
        # lines of the log that held no frame, and frames far off its time span: left out
        "log_lines_skipped": dict(log.skipped_lines),
        "timestamp_outliers": log.time_outliers,
        "log_warnings": log.warnings(),
    })
    written = [out / "metrics.json"]
    written[0].write_text(json.dumps(m, indent=2, default=_json_default) + "\n")
    if tr is not None:
        written.append(out / "trajectory.csv")
        tr.write_csv(written[-1])
        if plot:
            from sim.report import plots

            written.append(out / "bus_run.png")
            plots.figure([("over the CAN bus", tr)], ("lam", "p", "grid"), written[-1],
                         title=sc.title or sc.name, load_kw=sc.load_kw, t_max=None,
                         time_scale=time_scale, batteries=sc.batteries)
    return Recording(m, log, tr, verdict, written)


def _json_default(x: Any) -> Any:
    if hasattr(x, "item"):
        return x.item()
    return float(x)


def summary_lines(m: dict[str, Any], verdict: Verdict, time_scale: float = 1.0) -> list[str]:
    """The human summary of a bus run, as ``up`` and ``analyze`` print it. Times are in
    scenario seconds (a time-scaled run's divided by the scale)."""
    def secs(x: float | None) -> str:
        return "never" if x is None else f"{x / time_scale:.2f} s"

    lines = [f"  warning: {w}" for w in m.get("log_warnings", [])]
    st = m.get("settling_times_s")
    if st is not None:
        unit = " (scenario time)" if time_scale != 1 else ""
        per_seg = ", ".join(f"segment {k}: {secs(x)}" for k, x in enumerate(st))
        lines.append(f"  settling (2 % band){unit}: {per_seg}")
        lines.append(f"  final max|λ−ρ| = {m['final_error']:.2e} cu/kWh over the agents meant "
                     f"to be dispatching; resets per agent {m['resets']}")
        cost = m.get("cost")
        ledger = m.get("router_ledger")
        if cost is not None:
            line = (f"  cost rate {cost:.2f} cu/h (KKT optimum {m['optimal_cost']:.2f} cu/h)")
            if ledger:
                line += (f"; router's ledger: {ledger['cost']:.4f} cu spent, optimum "
                         f"{ledger['optimal_cost']:.4f} cu")
            lines.append(line)
    for fo in m.get("failovers", []):
        lines.append(f"  failover at {secs(fo['t'])}: the router pinned agent"
                     f"{'s' if len(fo['pinned']) > 1 else ''} "
                     f"{', '.join(map(str, fo['pinned']))} (every pinned agent was lost)")
    lines.append(f"  frames recorded {m['frames_recorded']}, undecodable "
                 f"{sum(m['frames_undecodable'].values())}, missed by the recorder "
                 f"{m['frames_missed_by_recorder']}, deadline misses "
                 f"{json.dumps(m['deadline_misses'])}")
    if (inj := m.get("injected_loss")) is not None:
        lines.append("  " + loss_text(inj, verdict.loss_explained))
    if verdict.anomalies:
        lines.append(f"  anomalies ({len(verdict.anomalies)}):")
        lines += [f"    - {a.text(time_scale)}" for a in verdict.anomalies]
    else:
        lines.append("  anomalies: none")
    if verdict.interrupted:
        head = "INTERRUPTED"
    elif verdict.converged:
        head = "CONVERGED" + (" with anomalies" if verdict.anomalies else "")
    else:
        head = "NOT CONVERGED: " + "; ".join(verdict.reasons)
    if verdict.cause and not verdict.interrupted:
        lines.append(f"  most likely cause: {verdict.cause}")
    lines.append(f"  verdict: {head} (exit code {verdict.exit_code})")
    return lines


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
