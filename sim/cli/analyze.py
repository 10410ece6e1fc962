"""`bess-ded analyze LOG`: metrics, trajectory, anomalies and plot from any recorded log.

LOG is a candump-format log of a fleet (``candump -L``, ``bess-ded record``, the
run.log of ``bess-ded up``, a HIL rig's capture; any format python-can's LogReader
reads by its suffix: .log, .asc, .blf, .csv, ...). The scenario says what the fleet
was meant to do; a run made with ``--time-scale F`` is analysed with the same F.
The result is what ``bess-ded up`` writes for its own runs, through the same code:
DIR/metrics.json (verdict and anomalies included), DIR/trajectory.csv, DIR/bus_run.png.
Exit codes as ``bess-ded up``'s: 0 converged without anomalies, 1 not converged,
3 converged with anomalies, 2 bad input.

LOG may be the directory `up` wrote (or its run.log): everything `up` knew is then read
back from it (DIR/keys, DIR/logs/*.counters.json, DIR/logs/run_facts.json: exit codes,
deaths, --insecure, the boot floors, --time-scale and --tolerance; DIR/scenario.toml
when neither --case nor --scenario is given), so the same run gets the same verdict
from `analyze` as from `up`. A log without keys whose frames verify with the public
demo keys is an --insecure run (insecure_keys).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from firmware_py.errors import BessDedError, ConfigError


def register(sub: argparse._SubParsersAction) -> None:
    from firmware_py.cliargs import positive_float, time_scale

    from ._common import add_case_option, add_no_plot_argument, one_line_errors

    p = one_line_errors(sub.add_parser(
        "analyze", help="metrics, anomalies and plots from a recorded CAN log",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter))
    p.add_argument("log", type=Path, metavar="LOG",
                   help="candump-format log of the fleet, or the directory `up` wrote")
    add_case_option(p, required=False)
    p.add_argument("--variant", metavar="LABEL", help="the variant that ran (cases 2, 3, 6)")
    p.add_argument("--time-scale", type=time_scale, metavar="F",
                   help="the --time-scale the run used (default: the run's, else 1)")
    p.add_argument("--tolerance", type=positive_float(), metavar="CU",
                   help="converged only if every dispatching agent's final λ is within CU "
                   "cu/kWh of ρ (default: the run's --tolerance, else 1e-3)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="output directory (default: LOG's directory/<LOG stem>-analysis)")
    p.add_argument("--counters", type=Path, metavar="DIR",
                   help="a directory with the plant's and router's counters JSON "
                   "(plant.counters.json, router.counters.json; default: LOG's "
                   "directory/logs when they are there, as `up` leaves them)")
    p.add_argument("--keys", type=Path, metavar="DIR",
                   help="the run's key set (default: LOG's directory's keys/ if there, as "
                        "`up` writes it): secured frames whose MAC does not verify are left "
                        "out and reported (auth_failed)")
    add_no_plot_argument(p, "bus_run.png")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from firmware_py import secoc

    from ..runreport import report, summary_lines
    from ..scenario import scaled
    from ..verdict import TOLERANCE, RunFacts
    from ._common import resolve_scenario
    from .keys import load_key_set
    from .up import pick_variant

    log_path: Path = args.log
    if log_path.is_dir():
        log_path = log_path / "run.log"
    if not log_path.is_file():
        raise ConfigError(str(args.log), "LOG", "expected a readable log file or the "
                          "directory of a run (with run.log), but there is no such file")
    run_dir = log_path.parent
    counters_dir = args.counters or run_dir / "logs"
    counters = {}
    for role in ("plant", "router"):
        path = counters_dir / f"{role}.counters.json"
        if path.is_file():
            counters[role] = load_node_counters(path)
    if args.counters is not None and not counters:
        raise ConfigError(str(args.counters), "--counters", "expected plant.counters.json "
                          "and/or router.counters.json in it, but found neither")
    facts_path = counters_dir / "run_facts.json"
    known = _json(facts_path) if facts_path.is_file() else {}
    if not isinstance(known, dict):
        raise ConfigError(str(facts_path), "run facts", "expected a JSON object")
    try:
        facts = RunFacts.from_json(known, counters or None)
        time_scale = args.time_scale or float(known.get("time_scale") or 1.0)
        tolerance = args.tolerance or float(known.get("tolerance") or TOLERANCE)
        floors = {str(k): int(v) for k, v in (known.get("boot_floors") or {}).items()}
    except (TypeError, ValueError, AttributeError) as e:
        raise ConfigError(str(facts_path), "run facts", f"expected them as `up` writes them, "
                          f"but got: {e}") from None
    if not (time_scale > 0 and tolerance > 0):
        raise ConfigError(str(facts_path), "run facts", "expected a positive time_scale and "
                          f"tolerance, but got {time_scale} and {tolerance}")
    spec = args.case
    if spec is None:
        if not (run_dir / "scenario.toml").is_file():
            raise ConfigError(str(args.log), "--case", "expected the scenario "
                              "that ran (--case N or --case FILE); LOG is not a run "
                              "directory with its scenario.toml")
        # the scenario as it ran: variant resolved, time scale already applied
        sc, chosen = pick_variant(resolve_scenario(str(run_dir / "scenario.toml")), None, "analyze")
    else:
        sc, chosen = pick_variant(resolve_scenario(spec), args.variant, "analyze")
        sc = scaled(sc, time_scale)
    out = args.out or run_dir / f"{log_path.stem}-analysis"
    keys_dir = args.keys or run_dir / "keys"
    if args.keys is not None and not keys_dir.is_dir():
        raise ConfigError(str(keys_dir), "--keys", "expected a key set directory "
                          "(bess-ded keys --fleet --out DIR)")
    keys = load_key_set(keys_dir) if keys_dir.is_dir() else None
    demo = {n: secoc.derive_node_key(secoc.INSECURE_MASTER, n)
            for n in secoc.fleet_nodes(sc.n)}
    if keys is None and (facts.insecure or _demo_signed(log_path, sc, demo)):
        keys, facts.insecure = demo, True
    print(f"bess-ded analyze: {log_path} as {sc.title or sc.name}{chosen} ({sc.n} agents)"
          + (f"; node counters from {counters_dir}" if counters else "")
          + (f"; run facts from {facts_path}" if known else "")
          + ("; signed with the public demo keys (--insecure)" if facts.insecure else
             f"; frames verified with the keys in {keys_dir}" if keys else
             "; no keys: secured frames are taken as they are"))
    try:
        rec = report(sc, log_path, out, facts, plot=not args.no_plot, time_scale=time_scale,
                     keys=keys, boot_floors=floors or None, tolerance=tolerance)
    except BessDedError:
        raise
    except (ValueError, EOFError) as e:  # python-can's readers on a file of another format
        raise ConfigError(str(log_path), "LOG", f"expected a CAN log python-can reads, but "
                          f"got: {e}") from None
    for line in summary_lines(rec.metrics, rec.verdict, time_scale):
        print(line)
    print(f"  wrote {', '.join(map(str, rec.written))}")
    return rec.verdict.exit_code


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


def _json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise ConfigError(str(path), "JSON", f"expected a JSON file as `up` writes it, but "
                          f"got: {e}") from None


def _demo_signed(log_path: Path, sc: Any, demo: dict[str, bytes]) -> bool:
    """Do the log's secured frames verify with the public demo keys (an --insecure run)?"""
    from ..buslog import read_log

    try:
        log = read_log(log_path, n=sc.n, ts=sc.ts, keys=demo)
    except (ValueError, EOFError):
        return False  # report() names the format problem
    return log.syncs > 0 and not log.forged
