"""The analysis of a recorded CAN log of a fleet: metrics, trajectory, anomalies, plot and
the verdict, what ``bess-ded analyze`` runs (docs/api.md, docs/runs.md).

``prepare_analysis`` reads what the log's run left beside it (a directory ``bess-ded up``
wrote: its keys, node counters, run facts and scenario) and checks the inputs;
``LogAnalysis.run`` decodes and judges the log through the code ``up`` judges its own
runs with (sim.run.runreport.report). ``analyze_log`` does both.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from dbc import dbc_path
from firmware_py.errors import BessDedError, ConfigError
from sim.model.scenario import Scenario
from sim.run.runreport import Recording
from sim.run.verdict import RunFacts


@dataclass
class LogAnalysis:
    """A log ready to analyse: the scenario it is judged against and what its run left."""

    log_path: Path
    scenario: Scenario             # as it ran: variant chosen, time scale applied
    chosen: str                    # " [variant LABEL]" or ""
    out: Path
    counters_dir: Path
    counters: dict[str, Any]       # role → the plant's/router's --counters-json document
    facts_path: Path
    known: dict[str, Any]          # the run facts file's document ({} without one)
    facts: RunFacts
    time_scale: float
    tolerance: float
    floors: dict[str, int]         # node → boot floor of the run
    keys_dir: Path
    keys: dict[str, bytes] | None  # node → key; None: secured frames taken as they are

    def describe(self) -> str:
        """One line: the log, the scenario and where counters, facts and keys came from."""
        sc = self.scenario
        return (f"bess-ded analyze: {self.log_path} as {sc.title or sc.name}{self.chosen} "
                f"({sc.n} agents)"
                + (f"; node counters from {self.counters_dir}" if self.counters else "")
                + (f"; run facts from {self.facts_path}" if self.known else "")
                + ("; signed with the public demo keys (--insecure)" if self.facts.insecure
                   else f"; frames verified with the keys in {self.keys_dir}" if self.keys
                   else "; no keys: secured frames are taken as they are"))

    def run(self, plot: bool = True) -> Recording:
        """Decode and judge the log; write metrics.json, trajectory.csv and (``plot``)
        bus_run.png into ``out``. The verdict's exit code is ``up``'s."""
        from sim.run.runreport import report

        try:
            return report(self.scenario, self.log_path, self.out, self.facts, plot=plot,
                          time_scale=self.time_scale, keys=self.keys,
                          boot_floors=self.floors or None, tolerance=self.tolerance)
        except BessDedError:
            raise
        except (ValueError, EOFError) as e:  # python-can's readers on a file of another format
            raise ConfigError(str(self.log_path), "LOG", f"expected a CAN log python-can "
                              f"reads, but got: {e}") from None


def prepare_analysis(log: Path, case: str | None = None, variant: str | None = None,
                     time_scale: float | None = None, tolerance: float | None = None,
                     out: Path | None = None, counters: Path | None = None,
                     keys: Path | None = None, say: Callable[[str], None] = print,
                     transmit: str | None = None) -> LogAnalysis:
    """Check the inputs of an analysis of ``log`` (a CAN log file, or the directory ``up``
    wrote), reading what the run left beside it. ``case``: the scenario (a case number or
    a .toml; default: the run directory's scenario.toml); ``variant``, ``time_scale``,
    ``tolerance``: as the run used them (default: the run's facts, else the first
    variant, 1, 1e-3); ``out``: default <log's directory>/<log stem>-analysis;
    ``counters``, ``keys``: directories (default: the run directory's logs/ and keys/).
    ``say`` gets the note that names a variant chosen by default; ``transmit``: with
    ``case``, how the agents sent their λ ("periodic", "event"; default the scenario's)."""
    from firmware_py import secoc
    from sim.model.scenario import scaled
    from sim.model.scenario_select import pick_variant, resolve_scenario, with_transmit
    from sim.run.keyset import derived_keys, load_key_set
    from sim.run.verdict import TOLERANCE

    log_path = log
    if log_path.is_dir():
        log_path = log_path / "run.log"
    if not log_path.is_file():
        raise ConfigError(str(log), "LOG", "expected a readable log file or the "
                          "directory of a run (with run.log), but there is no such file")
    run_dir = log_path.parent
    counters_dir = counters or run_dir / "logs"
    found = {}
    for role in ("plant", "router"):
        path = counters_dir / f"{role}.counters.json"
        if path.is_file():
            found[role] = load_node_counters(path)
    if counters is not None and not found:
        raise ConfigError(str(counters), "--counters", "expected plant.counters.json "
                          "and/or router.counters.json in it, but found neither")
    facts_path = counters_dir / "run_facts.json"
    known = _json(facts_path) if facts_path.is_file() else {}
    if not isinstance(known, dict):
        raise ConfigError(str(facts_path), "run facts", "expected a JSON object")
    try:
        facts = RunFacts.from_json(known, found or None)
        scale = time_scale or float(known.get("time_scale") or 1.0)
        tol = tolerance or float(known.get("tolerance") or TOLERANCE)
        floors = {str(k): int(v) for k, v in (known.get("boot_floors") or {}).items()}
    except (TypeError, ValueError, AttributeError) as e:
        raise ConfigError(str(facts_path), "run facts", f"expected them as `up` writes them, "
                          f"but got: {e}") from None
    if not (scale > 0 and tol > 0):
        raise ConfigError(str(facts_path), "run facts", "expected a positive time_scale and "
                          f"tolerance, but got {scale} and {tol}")
    if case is None:
        if not (run_dir / "scenario.toml").is_file():
            raise ConfigError(str(log), "--case", "expected the scenario "
                              "that ran (--case N or --case FILE); LOG is not a run "
                              "directory with its scenario.toml")
        # the scenario as it ran: variant resolved, time scale already applied
        sc, chosen = pick_variant(resolve_scenario(str(run_dir / "scenario.toml")), None,
                                  "analyze", say)
    else:
        sc, chosen = pick_variant(resolve_scenario(case), variant, "analyze", say)
        sc = scaled(with_transmit(sc, transmit), scale)
        fd = log_format(log_path)
        if fd is not None and fd != sc.fd:  # the log shows the bus the fleet ran on
            say(f"note: the log's frames are {'CAN FD' if fd else 'classic CAN'} frames: "
                f"read with the {'FD' if fd else 'classic'} DBC (the scenario says "
                f"{'FD' if sc.fd else 'classic'})")
            sc = replace(sc, fd=fd)
    keys_dir = keys or run_dir / "keys"
    if keys is not None and not keys_dir.is_dir():
        raise ConfigError(str(keys_dir), "--keys", "expected a key set directory "
                          "(bess-ded keys --fleet --out DIR)")
    node_keys = load_key_set(keys_dir) if keys_dir.is_dir() else None
    demo = derived_keys(secoc.INSECURE_MASTER, sc.n)  # node and link frame keys
    if node_keys is None and (facts.insecure or _demo_signed(log_path, sc, demo)):
        node_keys, facts.insecure = demo, True
    return LogAnalysis(log_path, sc, chosen, out or run_dir / f"{log_path.stem}-analysis",
                       counters_dir, found, facts_path, known, facts, scale, tol, floors,
                       keys_dir, node_keys)


def analyze_log(log: Path, case: str | None = None, *, plot: bool = True,
                **options: Any) -> Recording:
    """``prepare_analysis(log, case, **options)``, then ``run(plot)``: the recording's
    metrics, verdict (``verdict.exit_code`` as ``bess-ded analyze`` exits) and the files
    written."""
    return prepare_analysis(log, case, **options).run(plot)


def load_node_counters(path: Path) -> dict[str, Any]:
    """A plant's or router's --counters-json file: {"ticks": N, "counters": {name: N}},
    checked, so a truncated or foreign file is a clear error, not a traceback."""
    try:
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ConfigError(str(path), "--counters", f"expected the JSON a node writes with "
                          f"--counters-json, but got unreadable JSON ({e})") from None

    def count(x: Any) -> bool:
        return isinstance(x, int) and not isinstance(x, bool) and x >= 0

    counters = doc.get("counters", {}) if isinstance(doc, dict) else None
    if (not isinstance(counters, dict) or not count(doc.get("ticks", 0))
            or not all(isinstance(k, str) and count(v) for k, v in counters.items())):
        raise ConfigError(str(path), "--counters", "expected an object with \"ticks\": N and "
                          "\"counters\": {name: N} (N integers ≥ 0), but got "
                          f"{json.dumps(doc)[:80]}")
    return doc


FORMAT_PEEK = 200
"""Data frames ``log_format`` reads from the start of a log to tell its frame format."""


def log_format(path: Path) -> bool | None:
    """True when the first FORMAT_PEEK data frames of the log at ``path`` are all CAN FD
    frames, False when all classic; None when it has none, mixes them, or is not a log
    (``report`` then names the problem)."""
    import itertools
    from collections import Counter

    from sim.run.buslog import read_frames

    try:
        frames = [m.is_fd for m in itertools.islice(
            (m for m in read_frames(path, Counter())
             if not (m.is_error_frame or m.is_remote_frame)), FORMAT_PEEK)]
    except (OSError, ConfigError):  # report() reads it again and names it
        return None
    return frames[0] if frames and len(set(frames)) == 1 else None


def _json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise ConfigError(str(path), "JSON", f"expected a JSON file as `up` writes it, but "
                          f"got: {e}") from None


def _demo_signed(log_path: Path, sc: Any, demo: dict[str, bytes]) -> bool:
    """Do the log's secured frames verify with the public demo keys (an --insecure run)?"""
    from firmware_py.frames import FrameCodec
    from sim.run.buslog import read_log
    from sim.run.verdict import silence_ts

    try:
        log = read_log(log_path, FrameCodec(dbc_path(sc.fd, sc.lambda_tags)), n=sc.n,
                       ts=sc.ts, keys=demo,
                       silence_ts=silence_ts(sc))
    except (ValueError, EOFError):
        return False  # report() names the format problem
    return log.syncs > 0 and not log.forged
