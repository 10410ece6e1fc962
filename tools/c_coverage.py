#!/usr/bin/env python3
"""Line coverage of the C firmware by the test suite's C tests.

Builds firmware_c with ``--coverage -O0`` into a scratch directory, runs the tests that
exercise the C code through the ctypes bindings (the controller and node vectors, the
random-traffic comparisons with firmware_py, the configuration loader) against that
build (``BESSDED_C_LIB_DIR``), then reports per-file line coverage with gcovr (text, and
JSON/HTML with ``--out``). Exit 1 if a test failed, or if a file's coverage is under
``--fail-under`` percent.

    python tools/c_coverage.py [--out DIR] [--fail-under PCT]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FIRMWARE = ROOT / "firmware_c"
TESTS = ["tests/test_c_core.py", "tests/test_c_agent.py", "tests/test_c_edges.py",
         "tests/test_c_config.py"]
MEASURED = ("controller.c", "agent.c", "agent_rx.c", "agent_rules.c", "agent_diag.c", "frames.c",
            "secoc.c", "toml.c", "config.c", "keyfile.c")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, help="write coverage.json and coverage.html here")
    p.add_argument("--fail-under", type=float, default=0.0, metavar="PCT",
                   help="exit 1 if a measured file's line coverage is below PCT")
    args = p.parse_args(argv)
    if args.out:
        args.out = args.out.resolve()   # gcovr runs in firmware_c/
    with tempfile.TemporaryDirectory(prefix="bessded-cov-") as tmp:
        build = Path(tmp)
        libs = [str(build / name) for name in ("libbessded.so", "libbessded_core.so",
                                               "libbessded_faulty.so")]
        subprocess.run(["make", "-s", "-C", str(FIRMWARE), f"BUILD={build}",
                        f"PYTHON={sys.executable}", "CFLAGS=-O0 --coverage", *libs], check=True)
        env = {**os.environ, "BESSDED_C_LIB_DIR": str(build)}
        tests = [t for t in TESTS if (ROOT / t).exists()]
        run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                              *tests], cwd=ROOT, env=env, check=False)
        report = build / "coverage.json"
        gcovr = [sys.executable, "-m", "gcovr", "--root", str(FIRMWARE), "--object-directory",
                 str(build), "--filter", str(FIRMWARE / "src"), "--json-summary",
                 str(report), "--txt", "-"]
        if args.out:
            args.out.mkdir(parents=True, exist_ok=True)
            gcovr += ["--html-details", str(args.out / "coverage.html")]
        subprocess.run(gcovr, cwd=FIRMWARE, check=True)
        summary = json.loads(report.read_text())
        if args.out:
            (args.out / "coverage.json").write_text(json.dumps(summary, indent=1))
    low = [(Path(f["filename"]).name, f["line_percent"]) for f in summary["files"]
           if Path(f["filename"]).name in MEASURED and f["line_percent"] < args.fail_under]
    for name, pct in low:
        print(f"c_coverage: {name}: {pct}% of lines, under --fail-under {args.fail_under}%",
              file=sys.stderr)
    return 1 if run.returncode != 0 or low else 0


if __name__ == "__main__":
    sys.exit(main())
