"""The CLI's outputs stay as they are: a few runs' printed text and written files against
committed golden copies (tests/golden/cli/), so that a restructuring of the code under
the commands changes no output format (issue 21). Paths and wall-clock times are
normalised; trajectories are compared by digest (bit-exact, and kept small).

Regenerate after an intended change of an output: ``BESSDED_REGEN_GOLDEN=1 python -m
pytest tests/test_cli_golden.py`` — and review the diff."""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import pytest

from sim.cli import main
from sim.model.scenario import SCENARIO_DIR

GOLDEN = Path(__file__).resolve().parent / "golden" / "cli"
RUNS = {
    "help": ["-h"],
    "case1": ["case", "1", "--no-plot"],
    "case7": ["case", "7", "--no-plot"],
    "case3_c": ["case", "3", "--impl", "c", "--no-plot"],
    "compare2": ["compare", "2"],
    "deploy7": ["deploy", "--case", "7"],
    # event-triggered λ (issue 23): the MC frames sent, the agents' [transmit] tables
    "case7_event": ["case", "7", "--transmit", "event", "--no-plot"],
    "deploy1_event": ["deploy", "--case", "1", "--transmit", "event", "--insecure"],
}


def _normalise(text: str, out: Path) -> str:
    text = text.replace(str(out), "OUT").replace(str(SCENARIO_DIR), "SCENARIOS")
    return re.sub(r"\(\d+\.\d+ s\)", "(T s)", text)


def render(argv: list[str], out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    """Exit code, stdout, stderr and every JSON/TOML/CSV file the command wrote."""
    try:
        code = main([*argv, "--out", str(out)] if argv != ["-h"] else argv)
    except SystemExit as e:  # argparse's -h
        code = e.code
    cap = capsys.readouterr()
    parts = [f"exit {code}", "-- stdout", cap.out, "-- stderr", cap.err]
    for f in sorted(out.rglob("*")):
        rel = f.relative_to(out)
        if f.suffix == ".csv":
            parts += [f"-- {rel} sha256", hashlib.sha256(f.read_bytes()).hexdigest()]
        elif f.suffix in (".json", ".toml"):
            text = f.read_text(encoding="utf-8")
            if f.suffix == ".json":
                text = json.dumps(json.loads(text), indent=1, sort_keys=True)
            parts += [f"-- {rel}", text]
    return _normalise("\n".join(parts), out) + "\n"


@pytest.mark.parametrize("name", RUNS)
def test_the_cli_output_is_the_golden_copy(name: str, tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str],
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "80")  # argparse wraps help to the terminal's width
    got = render(RUNS[name], tmp_path / "out", capsys)
    path = GOLDEN / f"{name}.txt"
    if os.environ.get("BESSDED_REGEN_GOLDEN"):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(got, encoding="utf-8")
    assert got == path.read_text(encoding="utf-8"), (
        f"bess-ded {' '.join(RUNS[name])}: the output differs from {path} (regenerate only "
        "for an intended change: see the module docstring)")
