"""Run `bess-ded conformance --case 1 --dut 3` against a device started from the command
line it prints, as an operator would (tests/test_conformance.py, tests/vcan)."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

DEVICE_HINT = re.compile(r"start the device with its configuration and key, e\.g\.: (.*)$")
C_DEVICE_HINT = re.compile(r"or firmware_c's node program \(.*?\): (.*)$")
FIRMWARE_PY = [sys.executable, "-m", "firmware_py"]
DEVIANT = [sys.executable, str(Path(__file__).parent / "deviant_agent.py"), "BAND-2"]


def with_device(argv: Sequence[str], hint: re.Pattern[str], device: list[str],
                timeout: float = 300) -> tuple[int, str]:
    """Run the bess-ded command ``argv``; when it prints the device's command line (group
    1 of ``hint``, `bess-ded agent ...` or `bessded-agent ...`), start ``device`` with those
    arguments instead, as an operator would start theirs. The exit code and the output."""
    proc = subprocess.Popen([sys.executable, "-m", "sim.cli", *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    dut: subprocess.Popen[bytes] | None = None
    text = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            text.append(line)
            m = hint.search(line)
            if m and dut is None:
                cmd = shlex.split(m.group(1))
                program = 2 if cmd[:2] == ["bess-ded", "agent"] else 1
                assert cmd[:program] in (["bess-ded", "agent"], ["bessded-agent"]), line
                dut = subprocess.Popen([*device, *cmd[program:]], stderr=subprocess.DEVNULL)
        proc.wait(timeout=timeout)
    finally:
        for p in (proc, dut):
            if p is not None and p.poll() is None:
                p.terminate()
                p.wait(timeout=30)
    assert dut is not None, "".join(text)
    return proc.returncode, "".join(text)


def run_conformance(tmp_path: Path, device: list[str], extra: Sequence[str] = (),
                    hint: re.Pattern[str] = DEVICE_HINT) -> tuple[int, str]:
    """`bess-ded conformance --case 1 --dut 3` against ``device`` (``FIRMWARE_PY``,
    ``DEVIANT``; firmware_c's node program with ``C_DEVICE_HINT``), both real-time as on a
    HIL rig: a tester or device starved by other work plays or sees a schedule of its own
    (the tool reports how late it was)."""
    return with_device(["conformance", "--case", "1", "--dut", "3", "--out",
                        str(tmp_path / "cf"), "--junit", str(tmp_path / "junit.xml"),
                        "--rt-priority", "20", *extra], hint, device)


def assert_passed(code: int, log: str) -> None:
    """The run passed: exit 0, the PASS verdict, no requirement failed."""
    assert code == 0, log
    assert "bess-ded conformance: PASS" in log and "  FAIL  " not in log, log


@contextmanager
def stress_hog() -> Iterator[None]:
    """`stress-ng --cpu 2` running for the duration (tools/install-stress-deps)."""
    exe = shutil.which("stress-ng")
    assert exe is not None, "stress-ng is missing: run tools/install-stress-deps"
    proc = subprocess.Popen([exe, "--cpu", "2", "--quiet"])
    try:
        yield
    finally:
        proc.terminate()
        proc.wait(timeout=30)
