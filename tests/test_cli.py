"""The simulation CLI end to end, in-process through sim.cli.main: case, compare, bench,
and the error contract (one line on stderr, exit code 2, no traceback)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest

from sim.cli import main
from sim.model.scenario import SCENARIO_DIR

REQUIRED_KEYS = {"settling_time_s", "settling_times_s", "overshoot", "control_total_variation",
                 "peak_control", "resets", "final_error", "eta_max", "regular", "cost",
                 "optimal_cost"}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def check_png(path: Path, min_bytes: int = 20_000) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path} is not a PNG"
    assert data[12:16] == b"IHDR"
    width, height = struct.unpack(">II", data[16:24])
    assert width >= 600 and height >= 400, f"{path}: {width}×{height}"
    assert len(data) >= min_bytes, f"{path}: only {len(data)} bytes"
    import matplotlib.image

    img = matplotlib.image.imread(path)  # decodes the whole image
    assert img.shape[:2] == (height, width)
    assert img[..., :3].std() > 0.05, f"{path} looks blank"


def test_case_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "case1"
    assert main(["case", "1", "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "settling" in stdout and str(out / "metrics.json") in stdout

    m = json.loads((out / "metrics.json").read_text())
    assert REQUIRED_KEYS <= m.keys()
    assert m["final_error"] < 1e-3
    assert m["regular"] is True
    assert m["settling_time_s"] is not None and 0 < m["settling_time_s"] < 20
    assert len(m["resets"]) == 4 and sum(m["resets"]) > 0
    assert m["cost"] == pytest.approx(m["optimal_cost"], rel=1e-6)
    assert "runs" not in m  # case 1 has no variants

    header = (out / "trajectory.csv").read_text().splitlines()[0].split(",")
    assert header[:3] == ["t", "rho", "segment"] and "lam_4" in header and "xi_1" in header
    for name in ("lambda_u_xi.png", "nu_r.png", "power.png"):
        check_png(out / name)


def test_case_from_toml_with_variants(tmp_path: Path) -> None:
    """A user's scenario file: shortened case 1 with two variants → a column each."""
    text = (SCENARIO_DIR / "case1.toml").read_text().replace("duration = 20.0", "duration = 6.0")
    text = text.replace("[[price]]", '[[variant]]\nlabel = "reset-PI"\nkind = "reset"\n\n'
                        '[[variant]]\nlabel = "PC"\nkind = "pc"\n\n[[price]]', 1)
    path = tmp_path / "mine.toml"
    path.write_text(text)
    out = tmp_path / "mine"
    assert main(["case", str(path), "--out", str(out), "--float"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert list(m["runs"]) == ["reset-PI", "PC"]
    assert m["label"] == "reset-PI" and m["arithmetic"] == "float"
    assert all(REQUIRED_KEYS <= r.keys() for r in m["runs"].values())
    assert m["runs"]["PC"]["resets"] == [0, 0, 0, 0]
    for name in ("trajectory.csv", "trajectory_reset-PI.csv", "trajectory_PC.csv"):
        assert (out / name).stat().st_size > 1000
    check_png(out / "lambda_u_xi.png")


def test_compare_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cmp"
    assert main(["compare", "2", "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    data = json.loads((out / "compare.json").read_text())
    runs = data["controllers"]
    assert list(runs) == ["reset-PI", "PC", "PI", "finite-time", "dwell Δ=1 s"]
    assert [r["controller"] for r in runs.values()] == ["reset", "pc", "pi", "ft", "dwell"]
    for label, m in runs.items():
        assert REQUIRED_KEYS <= m.keys()
        assert label in stdout
    # the paper's qualitative claims, on this discrete firmware
    assert runs["reset-PI"]["settling_time_s"] < runs["PC"]["settling_time_s"]
    assert runs["reset-PI"]["settling_time_s"] < runs["PI"]["settling_time_s"]
    assert runs["finite-time"]["control_total_variation"] > \
        10 * runs["reset-PI"]["control_total_variation"]
    check_png(out / "compare.png")


def test_bench_quick(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--quick"]) == 0
    stdout = capsys.readouterr().out
    assert "CPU" in stdout and "python" in stdout
    for kind in ("pc", "pi", "reset", "dwell", "ft"):
        assert f"\n{kind} " in stdout
    assert "case1" in stdout and "case7" in stdout
    assert "Controller step, firmware_c against firmware_py" in stdout
    assert "Agent tick, firmware_c against firmware_py" in stdout
    assert "Input checks (issue 19)" in stdout and "counted stale" in stdout
    assert "Lockstep scaling: ms per tick" in stdout and "\n1000 " in stdout


@pytest.mark.parametrize("argv", [
    ["case", "9"],
    ["case", "banana"],
    ["compare", "0"],
    ["case", "does/not/exist.toml"],
])
def test_bad_case_is_a_one_line_error(argv: list[str], tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert main([*argv, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: error: ")
    assert err.count("\n") == 1, err
    assert "Traceback" not in err
    assert not (tmp_path / "x").exists()


def test_invalid_scenario_file_names_the_key(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "bad.toml"
    path.write_text((SCENARIO_DIR / "case1.toml").read_text().replace("ts = 0.01", 'ts = "x"'))
    assert main(["case", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "[ts]" in err and str(path) in err


def test_usage_errors_return_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["case", "1", "--controller", "nope"]) == 2
    assert main([]) == 2
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for command in ("case", "compare", "bench"):
        assert command in out
