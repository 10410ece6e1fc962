"""`bess-ded sweep` (issue 24, deliverable 4): a grid or a random sample of lockstep runs,
one table, resumable, plotted; local processes or Ray's own local cluster; bad specs and
bad points reported, never a crash."""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

import pytest
from test_cli import check_png

from firmware_py.errors import ConfigError
from sim.cli import main
from sim.model.lockstep import run_lockstep
from sim.model.metrics import compute
from sim.model.scenario import load_case
from sim.study.sweep import (
    METRIC_COLUMNS,
    load_spec,
    parse_spec,
    point_id,
    points,
    read_results,
    run_sweep,
)

GRID = """
name = "gains"
mode = "grid"
[axes]
graph = ["case1"]
k = [1.0, 2.0]
h = [2.0, 4.0]
duration = [6.0]
"""
RANDOM = """
name = "graphs"
mode = "random"
samples = 3
seed = 7
[axes]
graph = ["random"]
agents = {min = 5, max = 12}
degree = [4]
graph_seed = {min = 0, max = 1000}
duration = [15.0]
[cross]
controller = ["reset", "pc"]
"""


def _spec(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "spec.toml"
    path.write_text(text)
    return path


def _rows(path: Path) -> dict[str, dict[str, str]]:
    with path.open() as f:
        return {r["point"]: r for r in csv.DictReader(f)}


def test_a_grid_runs_every_combination_and_each_row_is_the_case_runs_metrics(
        tmp_path: Path) -> None:
    """2 × 2 gains on case 1: four rows; the row of k = 1, h = 2 carries exactly the
    metrics of the lockstep run of case 1 (6 s) that `bess-ded case` computes."""
    spec = load_spec(_spec(tmp_path, GRID))
    res = run_sweep(spec, tmp_path / "out")
    assert (res.run, res.skipped, res.failed) == (4, 0, 0)
    rows = _rows(res.results)
    assert sorted((r["k"], r["h"]) for r in rows.values()) == [
        ("1.0", "2.0"), ("1.0", "4.0"), ("2.0", "2.0"), ("2.0", "4.0")]
    sc = replace(load_case(1), duration=6.0)
    m = compute(sc, run_lockstep(sc))
    row = rows[point_id({"graph": "case1", "k": 1.0, "h": 2.0, "duration": 6.0})]
    assert float(row["settling_time_s"]) == m["settling_time_s"]
    assert float(row["final_error"]) == m["final_error"]
    assert int(row["resets"]) == sum(m["resets"]) and row["converged"] == "1"


def test_a_rerun_skips_what_is_done_and_a_cut_sweep_resumes(tmp_path: Path) -> None:
    """The second run of the same spec runs nothing; a table cut after two points (a
    killed sweep) gets the other two, the same rows as an uncut run."""
    spec = load_spec(_spec(tmp_path, GRID))
    whole = run_sweep(spec, tmp_path / "whole")
    assert run_sweep(spec, tmp_path / "whole").run == 0
    cut = tmp_path / "cut"
    cut.mkdir()
    lines = whole.results.read_text().splitlines(keepends=True)
    (cut / "results.csv").write_text("".join(lines[:3]))
    res = run_sweep(spec, cut)
    assert (res.run, res.skipped) == (2, 2)
    drop = {"wall_s"}
    strip = lambda rows: {p: {k: v for k, v in r.items() if k not in drop}  # noqa: E731
                          for p, r in rows.items()}
    assert strip(_rows(cut / "results.csv")) == strip(_rows(whole.results))


def test_a_random_sample_is_seeded_crossed_and_the_same_in_two_processes(
        tmp_path: Path) -> None:
    """3 random graphs × {reset, pc}: 6 points, the same draw every time, each graph under
    both controllers; two worker processes give the rows one process gives."""
    spec = load_spec(_spec(tmp_path, RANDOM))
    drawn = list(points(spec))
    assert drawn == list(points(spec)) and len(drawn) == 6
    assert [p["controller"] for p in drawn] == ["reset", "pc"] * 3
    assert drawn[0]["graph_seed"] == drawn[1]["graph_seed"]
    one = _rows(run_sweep(spec, tmp_path / "one").results)
    two = _rows(run_sweep(spec, tmp_path / "two", jobs=2).results)
    assert one.keys() == two.keys()
    for p in one:
        assert {k: v for k, v in one[p].items() if k != "wall_s"} == \
            {k: v for k, v in two[p].items() if k != "wall_s"}


def test_a_point_without_a_valid_scenario_is_a_row_with_its_error(tmp_path: Path) -> None:
    """A degree that no regular graph on 5 agents has, and a dwell below Ts: rows whose
    error column says why, metrics empty, the rest of the sweep run."""
    spec = parse_spec({"mode": "grid", "axes": {
        "graph": ["random"], "agents": [5], "degree": [3, 4], "duration": [2.0]}}, "<t>")
    res = run_sweep(spec, tmp_path / "out")
    rows = read_results(res.results)
    bad = [r for r in rows if r["error"]]
    assert len(rows) == 2 and len(bad) == 1 and res.failed >= 1
    assert "n·degree even" in bad[0]["error"] and bad[0]["final_error"] != bad[0]["final_error"]


@pytest.mark.parametrize(("text", "key"), [
    ('mode = "grid"\n[axes]\nbanana = [1]\n', "axes.banana"),
    ('mode = "grid"\n[axes]\nk = {min = 1, max = 2}\n', "axes.k"),
    ('mode = "random"\n[axes]\nk = {min = 2, max = 1}\n', "axes.k"),
    ('mode = "lattice"\n[axes]\nk = [1]\n', "mode"),
    ('mode = "grid"\n', "axes"),
    ('mode = "random"\nsamples = -1\n[axes]\nk = [1]\n', "samples"),
    ('mode = "grid"\n[axes]\nk = []\n', "axes.k"),
])
def test_a_bad_spec_names_its_key(tmp_path: Path, text: str, key: str) -> None:
    with pytest.raises(ConfigError, match=rf"\[{key}\] expected"):
        load_spec(_spec(tmp_path, text))


def test_the_cli_prints_a_summary_plots_and_refuses_another_sweeps_table(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The summary per controller, sweep.png, and exit 2 (nothing overwritten) when --out
    holds a table of other columns; a missing spec is exit 2 too."""
    out = tmp_path / "out"
    assert main(["sweep", str(_spec(tmp_path, RANDOM)), "--out", str(out), "--jobs", "1"]) == 0
    stdout = capsys.readouterr().out
    assert "sweep graphs: 6 points run, 0 done before" in stdout
    assert "  pc: " in stdout and "  reset: " in stdout
    check_png(out / "sweep.png")
    before = (out / "results.csv").read_bytes()
    assert main(["sweep", str(_spec(tmp_path, GRID)), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: error: ") and "another sweep's" in err
    assert (out / "results.csv").read_bytes() == before
    assert main(["sweep", str(tmp_path / "none.toml")]) == 2
    assert "no such file" in capsys.readouterr().err


@pytest.mark.long  # Ray's local cluster takes ~20 s to start and stop on 2 cores
def test_ray_local_mode_and_parquet_give_the_same_table(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    """--ray local (Ray's own local cluster) runs the points as Ray tasks: the rows of a
    local run; --parquet writes them as a Parquet table too."""
    import pyarrow.parquet as pq

    spec = _spec(tmp_path, GRID)
    assert main(["sweep", str(spec), "--out", str(tmp_path / "ray"), "--ray", "local",
                 "--parquet", "--no-plot"]) == 0
    assert "parquet: " in capsys.readouterr().out
    local = _rows(run_sweep(load_spec(spec), tmp_path / "local").results)
    remote = _rows(tmp_path / "ray" / "results.csv")
    assert {p: r["final_error"] for p, r in remote.items()} == \
        {p: r["final_error"] for p, r in local.items()}
    table = pq.read_table(tmp_path / "ray" / "results.parquet")
    assert table.num_rows == 4 and set(METRIC_COLUMNS) <= set(table.column_names)


def test_the_example_study_is_a_valid_spec_of_a_thousand_paired_graphs() -> None:
    """examples/sweep_reset_vs_pc.toml: 1,000 random 4-regular graphs of 5–64 agents, each
    under reset-PI and PC (2,000 points), all with valid sizes."""
    spec = load_spec("reset-vs-pc")  # bundled; examples/sweep_reset_vs_pc.toml links to it
    assert load_spec(Path(__file__).parents[1] / "examples" / "sweep_reset_vs_pc.toml") == \
        replace(spec, source=str(Path(__file__).parents[1] / "examples" /
                                  "sweep_reset_vs_pc.toml"))
    drawn = list(points(spec))
    assert len(drawn) == 2000 and spec.samples == 1000
    assert {p["controller"] for p in drawn} == {"reset", "pc"}
    assert min(p["agents"] for p in drawn) >= 5 and max(p["agents"] for p in drawn) <= 64
    assert len({p["graph_seed"] for p in drawn}) > 990
