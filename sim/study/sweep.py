"""Sweeps: one lockstep run per point of a grid or a random sample, one table of results.

A sweep spec (TOML, docs/sweeps.md) names the axes: the graph (a paper case, a scenario
file, or ``random``: a random regular fleet of ``agents`` agents of ``degree`` from
``graph_seed``), the controller's kind, gains, band and dwell, the run's duration, the
rate and seed of lost neighbour frames.
``mode = "grid"`` runs every combination; ``mode = "random"`` draws ``samples`` points
(lists are sampled uniformly, ``{min, max}`` ranges uniformly or log-uniformly, integer
when both ends are) and crosses each with the ``[cross]`` axes (e.g. the same random graph
under reset-PI and PC). Every point is seeded from the spec's ``seed`` and its index, so
a sweep is the same on any machine.

A point's row (``POINT_COLUMNS`` then ``METRIC_COLUMNS``) is appended to ``results.csv``
as soon as it is done; a rerun skips the points whose ``point`` ID is already there
(resumable), and a point whose parameters a scenario refuses gets its ``error`` column
filled, not a crash. Runs go to local processes (``jobs``), or to a Ray cluster
(``sim.study.rayrun``).
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import math
import time
import tomllib
from collections.abc import Callable, Iterable, Iterator, Mapping
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from firmware_py.errors import BessDedError, ConfigError

# the axes a spec may name, with what each takes
AXES: dict[str, str] = {
    "graph": "'case1'..'case7', a scenario file, or 'random'",
    "agents": "the number of agents of a random graph (1..1000)",
    "degree": "the degree of a random regular graph",
    "graph_seed": "the seed of a random graph",
    "pinned": "how many agents of a random graph hear the price",
    "controller": "the controller's kind: pc, pi, reset, dwell",
    "k": "the proportional gain, 1/s",
    "h": "the integral gain, 1/s²",
    "band": "the reset band, cu/kWh",
    "dwell": "the dwell time, s",
    "duration": "the run's length, s",
    "loss": "the probability that a neighbour's MC frame is lost (sim.model.links)",
    "loss_seed": "the seed of the frame losses",
    "transmit": "'periodic' or 'event': when the agents send their λ (firmware-spec TX-7)",
    "event_threshold": "event mode: the λ move that triggers a frame, cu/kWh",
    "event_heartbeat": "event mode: the longest silence between frames, ticks (1..13)",
}
TRANSMIT_AXES = {"transmit": "mode", "event_threshold": "threshold",
                 "event_heartbeat": "heartbeat"}
CONTROLLER_AXES = {"controller": "kind", "k": "k", "h": "h", "band": "band", "dwell": "dwell"}
METRIC_COLUMNS = ["agents_n", "settling_time_s", "final_error", "converged", "peak_control",
                  "control_total_variation", "overshoot", "resets", "saturations", "eta_max",
                  "discrete_stable", "mc_frames", "wall_s", "error"]
CONVERGED_ERROR = 1e-3  # cu/kWh: the bus runs' verdict tolerance (docs/metrics.md)


@dataclass(frozen=True)
class SweepSpec:
    """A parsed sweep spec."""

    name: str
    mode: str                          # "grid" | "random"
    axes: Mapping[str, Any]            # axis → list of values, or a {min, max, log} range
    cross: Mapping[str, list[Any]] = field(default_factory=dict)
    samples: int = 1
    seed: int = 0
    source: str = "<spec>"

    @property
    def columns(self) -> list[str]:
        """The parameter columns of the results, in a fixed order."""
        names = set(self.axes) | set(self.cross)
        return [a for a in AXES if a in names]


SPEC_DIR = Path(__file__).resolve().parent / "specs"  # bundled specs, package data


def bundled_specs() -> list[str]:
    """The names of the sweep specs that ship with bess-ded (``bess-ded sweep NAME``)."""
    return sorted(p.stem for p in SPEC_DIR.glob("*.toml"))


def load_spec(path: str | Path) -> SweepSpec:
    """A sweep spec file, or a bundled spec by name; ConfigError naming the file and key
    on a problem."""
    src = str(path)
    if not Path(path).exists() and str(path) in bundled_specs():
        path = SPEC_DIR / f"{path}.toml"
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(src, "file", "expected a sweep spec (TOML) or one of the bundled "
                          f"specs ({', '.join(bundled_specs())}), but there is no such "
                          "file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(src, "file", f"expected a readable TOML file, but got: {e}") from None
    return parse_spec(data, src)


def parse_spec(data: Mapping[str, Any], src: str) -> SweepSpec:
    """A SweepSpec from parsed TOML ``data``; ConfigError on an unknown or bad key."""
    extra = set(data) - {"name", "mode", "samples", "seed", "axes", "cross"}
    if extra:
        raise ConfigError(src, sorted(extra)[0], "expected one of name, mode, samples, seed, "
                          "axes, cross")
    mode = data.get("mode", "grid")
    if mode not in ("grid", "random"):
        raise ConfigError(src, "mode", f"expected 'grid' or 'random', but got {mode!r}")
    axes, cross = dict(data.get("axes", {})), dict(data.get("cross", {}))
    for table, values in (("axes", axes), ("cross", cross)):
        for axis, v in values.items():
            if axis not in AXES:
                raise ConfigError(src, f"{table}.{axis}", "expected one of "
                                  f"{', '.join(AXES)}")
            ranged = isinstance(v, dict)
            if ranged and (table == "cross" or mode == "grid"):
                raise ConfigError(src, f"{table}.{axis}", "expected a list of values (a "
                                  "{min, max} range is sampled: mode = 'random', [axes])")
            if ranged and not (set(v) <= {"min", "max", "log"} and {"min", "max"} <= set(v)
                               and _real(v["min"]) and _real(v["max"])
                               and v["min"] <= v["max"]):
                raise ConfigError(src, f"{table}.{axis}", f"expected {{min, max}} numbers with "
                                  f"min ≤ max (and log = true or false), but got {v!r}")
            if not ranged and not (isinstance(v, list) and v):
                raise ConfigError(src, f"{table}.{axis}", f"expected a non-empty list of "
                                  f"values ({AXES[axis]}), but got {v!r}")
    if not axes and not cross:
        raise ConfigError(src, "axes", "expected at least one axis")
    samples, seed = data.get("samples", 1), data.get("seed", 0)
    for key, value in (("samples", samples), ("seed", seed)):
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
            raise ConfigError(src, key, f"expected an integer ≥ 0, but got {value!r}")
    return SweepSpec(name=str(data.get("name", Path(src).stem)), mode=mode, axes=axes,
                     cross=cross, samples=samples, seed=seed, source=src)


def _real(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _draw(rng: np.random.Generator, v: Any) -> Any:
    if isinstance(v, list):
        return v[int(rng.integers(len(v)))]
    lo, hi = v["min"], v["max"]
    if isinstance(lo, int) and isinstance(hi, int) and not v.get("log"):
        return int(rng.integers(lo, hi + 1))
    x = math.exp(rng.uniform(math.log(lo), math.log(hi))) if v.get("log") else \
        float(rng.uniform(lo, hi))
    return round(x) if isinstance(lo, int) and isinstance(hi, int) else x


def points(spec: SweepSpec) -> Iterator[dict[str, Any]]:
    """Every point of the sweep, in order: each a dict of axis → value."""
    crossed = [dict(zip(spec.cross, c, strict=True))
               for c in itertools.product(*spec.cross.values())]
    if spec.mode == "grid":
        for combo in itertools.product(*spec.axes.values()):
            for c in crossed:
                yield {**dict(zip(spec.axes, combo, strict=True)), **c}
        return
    for i in range(spec.samples):
        rng = np.random.default_rng([spec.seed, i])
        drawn = {axis: _draw(rng, v) for axis, v in spec.axes.items()}
        for c in crossed:
            yield {**drawn, **c}


def point_id(params: Mapping[str, Any]) -> str:
    """A point's stable ID: a hash of its parameters (what makes a rerun skip it)."""
    text = json.dumps(dict(sorted(params.items())), sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def run_point(params: Mapping[str, Any]) -> dict[str, Any]:
    """One lockstep run at ``params``: its metrics row (``error`` set, metrics empty, when
    the parameters make no valid scenario)."""
    from sim.model.lockstep import run_lockstep
    from sim.model.metrics import compute

    t0 = time.perf_counter()
    row: dict[str, Any] = dict.fromkeys(METRIC_COLUMNS, "")
    try:
        sc = scenario_of(params)
        tr = run_lockstep(sc, loss=float(params.get("loss", 0.0)),
                          loss_seed=int(params.get("loss_seed", 0)))
        m = compute(sc, tr)
    except (BessDedError, ValueError) as e:
        row.update(error=str(e), wall_s=time.perf_counter() - t0)
        return row
    settling = m["settling_time_s"]
    row.update(agents_n=sc.n, settling_time_s="" if settling is None else settling,
               final_error=m["final_error"],
               converged=int(m["final_error"] < CONVERGED_ERROR and settling is not None),
               peak_control=m.get("peak_control", ""),
               mc_frames=int(tr.mc_sent.sum()) if tr.mc_sent is not None else "",
               control_total_variation=m.get("control_total_variation", ""),
               overshoot=m["overshoot"], resets=sum(m["resets"]), saturations=m["saturations"],
               eta_max=m["eta_max"], discrete_stable=int(m["discrete_stable"]),
               wall_s=time.perf_counter() - t0)
    return row


def scenario_of(params: Mapping[str, Any]) -> Any:
    """The Scenario a point describes (ConfigError / ParameterError if it is not one)."""
    from dataclasses import replace

    from sim.model.generate import random_scenario
    from sim.model.scenario import load_case, load_scenario

    graph = str(params.get("graph", "random"))
    if graph == "random":
        sc = random_scenario(int(params.get("agents", 4)), int(params.get("degree", 3)),
                             seed=int(params.get("graph_seed", 0)),
                             pinned=int(params.get("pinned", 1)))
    elif graph.removeprefix("case").isdigit():
        sc = load_case(graph.removeprefix("case"))
    else:
        sc = load_scenario(graph)
    if "duration" in params:
        sc = replace(sc, duration=float(params["duration"]))
    tx = {field: params[axis] for axis, field in TRANSMIT_AXES.items() if axis in params}
    if tx:  # Transmit checks the values (ParameterError)
        sc = replace(sc, transmit=replace(sc.transmit, **tx))
    overrides = {field: params[axis] for axis, field in CONTROLLER_AXES.items()
                 if axis in params}
    return sc.with_controller(**overrides) if overrides else replace(sc, variants=())


@dataclass
class SweepResult:
    """What a sweep did: the points run now, skipped (done before), failed."""

    results: Path
    run: int = 0
    skipped: int = 0
    failed: int = 0
    wall_s: float = 0.0


def run_sweep(spec: SweepSpec, out: Path, jobs: int = 1, limit: int | None = None,
              progress: Callable[[int, int, int], None] | None = None,
              executor: Callable[[list[dict[str, Any]]], Iterable[tuple[dict[str, Any],
                                                                       dict[str, Any]]]]
              | None = None) -> SweepResult:
    """Run every point of ``spec`` not yet in ``out``/results.csv, appending a row each;
    only the first ``limit`` points of the sweep (a trial; a later run adds the rest);
    ``jobs`` local processes (1: in this process), or ``executor`` (params list →
    (params, row) as they finish, e.g. Ray's). ``progress(done, total, failed)``."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / "results.csv"
    header = ["point", *spec.columns, *METRIC_COLUMNS]
    done = _done_points(path, header)
    todo, seen = [], set(done)
    for p in itertools.islice(points(spec), limit):
        pid = point_id(p)
        if pid not in seen:
            seen.add(pid)
            todo.append(p)
    res = SweepResult(results=path, skipped=len(seen) - len(todo))
    t0 = time.perf_counter()
    new_file = not path.exists()
    with path.open("a", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=header)
        if new_file:
            w.writeheader()
        runs = executor(todo) if executor is not None else _local(todo, jobs)
        for params, row in runs:
            w.writerow({"point": point_id(params), **params, **row})
            f.flush()  # a killed sweep keeps every finished point
            res.run += 1
            res.failed += bool(row["error"]) or row["converged"] == 0
            if progress is not None:
                progress(res.run, len(todo), res.failed)
    res.wall_s = time.perf_counter() - t0
    return res


def _local(todo: list[dict[str, Any]], jobs: int
           ) -> Iterator[tuple[dict[str, Any], dict[str, Any]]]:
    if jobs <= 1:
        for p in todo:
            yield p, run_point(p)
        return
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = {pool.submit(run_point, p): p for p in todo}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()


def _done_points(path: Path, header: list[str]) -> set[str]:
    """The point IDs already in ``path`` (a results table of this sweep's columns)."""
    if not path.exists():
        return set()
    with path.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames != header:
            raise ConfigError(str(path), "columns", f"expected this sweep's results "
                              f"({', '.join(header)}), but the table has "
                              f"{', '.join(reader.fieldnames or [])}: another sweep's? "
                              "Use another --out")
        return {row["point"] for row in reader}


def read_results(path: Path) -> list[dict[str, Any]]:
    """The rows of a results table, numbers as floats (empty cells as NaN)."""
    with path.open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        for k, v in row.items():
            if k in ("point", "graph", "controller", "error"):
                continue
            try:
                row[k] = float(v) if v != "" else math.nan
            except ValueError:
                pass
    return rows


def summarise(rows: list[dict[str, Any]], by: str | None) -> list[str]:
    """One line per value of ``by`` (all rows if None): points, converged, and the median
    settling time and peak |u| of the converged ones."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(str(r[by]) if by else "all", []).append(r)
    lines = []
    for label, rs in sorted(groups.items()):
        good = [r for r in rs if r["converged"] == 1]
        st = [r["settling_time_s"] for r in good]
        peak = [r["peak_control"] for r in good]
        med = f"median settling {np.median(st):.3f} s, median peak |u| {np.median(peak):.3g}" \
            if good else "none converged"
        invalid = sum(1 for r in rs if r["error"])
        lines.append(f"{label}: {len(good)}/{len(rs)} converged"
                     f"{f' ({invalid} invalid)' if invalid else ''}, {med}")
    return lines
