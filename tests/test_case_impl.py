"""`bess-ded case N --impl c`: the lockstep simulator on firmware_c's C core writes the
same trajectories as on firmware_py, byte for byte (issue 11's acceptance: cases 1 and 7;
here every case and every variant)."""

from __future__ import annotations

from pathlib import Path

import pytest

from sim.cli import main


@pytest.mark.parametrize("case", range(1, 8))
def test_c_and_py_write_identical_trajectories(case: int, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = {}
    for impl in ("py", "c"):
        out[impl] = tmp_path / impl
        assert main(["case", str(case), "--impl", impl, "--no-plots", "--out",
                     str(out[impl])]) == 0
        assert ("firmware_c (the C core)" in capsys.readouterr().out) == (impl == "c")
    csvs = sorted(p.name for p in out["py"].glob("trajectory*.csv"))
    assert "trajectory.csv" in csvs
    assert csvs == sorted(p.name for p in out["c"].glob("trajectory*.csv"))
    for name in csvs:
        assert (out["c"] / name).read_bytes() == (out["py"] / name).read_bytes(), name


def test_impl_c_is_fixed_point_only(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["case", "1", "--impl", "c", "--float", "--no-plots"]) == 2
    assert "bess-ded: error: --impl c: expected --fixed" in capsys.readouterr().err
