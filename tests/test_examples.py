"""examples/: the three tests docs/testing.md offers users to copy must pass as they are,
with the kit's plugin as an installed package loads it (pytest11 entry point; here -p,
since the environment's bess-ded may be another checkout's editable install). They run
node processes on the wall clock and assert only what holds at any load."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]

pytestmark = [pytest.mark.slow, pytest.mark.realtime]


def test_the_examples_pass_as_a_user_runs_them(tmp_path: Path) -> None:
    examples = sorted((ROOT / "examples").glob("test_*.py"))
    assert len(examples) == 3
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("PYTEST_ADDOPTS", None)
    out = subprocess.run([sys.executable, "-m", "pytest", "-p", "sim.testkit.plugin", "-q",
                          "-p", "no:cacheprovider", "--basetemp", str(tmp_path / "t"),
                          "examples"], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=1200)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert "3 passed" in out.stdout, out.stdout[-2000:]
