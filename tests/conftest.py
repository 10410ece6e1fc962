"""Shared fixtures. An autouse guard fails any test that leaks a virtual bus or a child
process: a node that outlives its test is exactly the bug users would hit."""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import can.interfaces.virtual as virtual
import pytest

from firmware_py.frames import DecodedFrame, FrameCodec

# the test kit's fixtures (bess_bus, bess_keys, bess_fleet, bess_tester: docs/testing.md);
# an installed package registers them through its pytest11 entry point as well
pytest_plugins = ("sim.testkit.plugin",)

# udp_multicast runs of one test session take ports from a block of 100 of its own (by
# pid), so two sessions running at once (a developer's and CI's) never hear each other;
# pytest-xdist's workers (-n) of one session take blocks of different parity.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")[2:]
_BLOCK = ((os.getpid() % 100) * 2 + int(_WORKER) % 2 if _WORKER.isdigit()
          else os.getpid() % 200)
_ports = itertools.count(43200 + _BLOCK * 100)


def next_udp_port() -> int:
    return next(_ports)


def _children() -> set[int]:
    me = str(os.getpid())
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[1] == me and fields[0] != "Z":
            out.add(int(stat.parent.name))
    return out


@pytest.fixture(autouse=True)
def no_leaks():
    before = _children()
    yield
    with virtual.channels_lock:
        open_channels = {name: len(buses) for name, buses in virtual.channels.items() if buses}
    leaked = _children() - before
    assert not open_channels, f"test left virtual buses open: {open_channels}"
    assert not leaked, f"test left child processes running: {sorted(leaked)}"


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every realtime test belongs to the long tier too (before -m selects): the README's
    test command (-m "not vcan and not long") stays within 10 minutes on 2 idle cores."""
    for item in items:
        if item.get_closest_marker("realtime") and not item.get_closest_marker("long"):
            item.add_marker(pytest.mark.long)


@pytest.fixture
def udp_port() -> int:
    """A multicast port of its own, so concurrent runs never hear each other."""
    return next_udp_port()


@pytest.fixture(scope="session")
def udp_ports() -> Callable[[], int]:
    """The port allocator itself, for fixtures wider than one test."""
    return next_udp_port


# --------------------------------------------------------------------------- real-time runs
#
# A multi-process run on the wall clock (busrun.record) proves at any load only what the
# load cannot change: every tick is accounted for, every frame the recorder missed is
# known, and the counters add up. Rates and deadline figures belong to `bess-ded bench`;
# timing windows are asserted on the simulated clock (busrun.run_in_process).

TICK_SLACK = 3       # ticks: jitter of the first/last frame against its tick, rounding
FRAME_SLACK = 2      # frames a node may send after the recorder stopped reading


def log_frames(out: Path) -> list[tuple[float, DecodedFrame]]:
    """Every decodable frame of DIR/run.log but the ``<name>_Sync`` ones."""
    from firmware_py.contract import SYNCED_BY
    from firmware_py.errors import FrameError

    codec = _codec()
    frames = []
    for msg in can.LogReader(str(out / "run.log")):
        if msg.arbitration_id in SYNCED_BY:  # freshness syncs: not a tick's frames
            continue
        try:
            frames.append((msg.timestamp, codec.decode(msg)))
        except FrameError:
            continue
    return frames


def _codec() -> FrameCodec:
    global _CODEC
    if _CODEC is None:
        _CODEC = FrameCodec()
    return _CODEC


_CODEC: FrameCodec | None = None


def _sent(frames: list[tuple[float, DecodedFrame]]) -> int:
    """Frames a sender sent over a stretch: those recorded plus the counter gaps."""
    n, prev = 0, None
    for _, f in frames:
        n += 1 if prev is None else 1 + (f.counter - prev - 1) % 16
        prev = f.counter
    return n


def assert_every_tick_accounted(out: Path, m: dict[str, Any], ts: float) -> dict[str, Any]:
    """Every tick of every node of a real-time run is either a frame (recorded, or
    missed by the recorder and seen as a counter gap) or a deadline miss the node
    counted itself. Holds at any load: a starved node ticks less but counts the misses.

    * agent i, from its first MC frame to its last diagnostics frame reporting
      DeadlineMisses = D: MC frames sent n (one per tick) satisfy
      n ≤ span/Ts + 1 + slack and n + D ≥ span/Ts + 1 − slack;
    * plant and router (ticks and deadline_miss from their exit counters), over the span
      of their recorded frames (+ one cycle of ticks after the last one);
    * the router's price frames and the plant's status frames: recorded + counter gaps
      = the node's own count (± FRAME_SLACK per ID).
    Frames the kernel dropped at the recorder's full receive buffer (``rx_overflow``, a
    starved recorder) may hide in a counter's wrap: they count for the missing ones.
    Returns the figures (for the benchmark-style print of the caller)."""
    frames = log_frames(out)
    by_name: dict[str, list[tuple[float, DecodedFrame]]] = {}
    for t, f in frames:
        by_name.setdefault(f.name, []).append((t, f))
    agents = sorted(f.agent for t, f in frames if f.name.endswith("_MC") and f.agent)
    unrecorded = m.get("recorder_counters", {}).get("rx_overflow", 0)
    report: dict[str, Any] = {}
    for i in sorted(set(agents)):
        mc = by_name[f"AGENT_{i}_MC"]
        diag = [(t, f.raw["DeadlineMisses"]) for t, f in by_name.get(f"AGENT_{i}_Diag", [])
                if "DeadlineMisses" in f.raw]
        assert diag, f"agent {i} sent no diagnostics page with DeadlineMisses"
        t_d, misses = diag[-1]
        upto = [(t, f) for t, f in mc if t <= t_d + ts / 2]
        expected = round((t_d - upto[0][0]) / ts) + 1
        n = _sent(upto)
        report[f"agent_{i}"] = (n, misses, expected)
        assert n <= expected + TICK_SLACK, (i, n, expected)
        assert n + misses + unrecorded >= expected - TICK_SLACK, (i, n, misses, expected,
                                                                  unrecorded)
    counters = m["node_counters"]
    for role, ids in (("router", ("ER_Price", "ER_Balance", "ER_Command")),
                      ("plant", tuple(n for n in by_name if n.startswith("PLANT_")))):
        assert role in counters, f"the {role} wrote no counters at exit"
        stamps = [t for name in ids for t, _ in by_name.get(name, [])]
        assert stamps, f"no frame of the {role} recorded"
        span = round((max(stamps) - min(stamps)) / ts) + 1
        cycle = 10  # ticks: the longest cycle of its frames (ER_Balance, 100 ms)
        ticks = counters[role]["ticks"]
        misses = counters[role]["counters"].get("deadline_miss", 0)
        report[role] = (ticks, misses, span)
        assert ticks <= span + cycle + TICK_SLACK, (role, ticks, span)
        assert ticks + misses >= span - TICK_SLACK, (role, ticks, misses, span)
    price_sent = counters["router"]["counters"].get("price_frames", 0)
    price = _sent(by_name["ER_Price"])
    assert -FRAME_SLACK <= price_sent - price <= FRAME_SLACK + unrecorded, (
        price, price_sent, unrecorded)
    status = sum(_sent(v) for k, v in by_name.items() if k.startswith("PLANT_"))
    plant = counters["plant"]["counters"]  # its statuses and PLANT_Totals
    status_sent = plant.get("status_frames", 0) + plant.get("totals_frames", 0)
    n_plant = len([k for k in by_name if k.startswith("PLANT_")])
    assert (-FRAME_SLACK * n_plant <= status_sent - status
            <= FRAME_SLACK * n_plant + unrecorded), (status, status_sent, unrecorded)
    return report


def lockstep_settling_ticks(sc: Any) -> int:
    """Lockstep's settling time of the first price segment, in ticks."""
    from sim.model.lockstep import run_lockstep
    from sim.model.metrics import settling_times

    ref_st = settling_times(run_lockstep(sc))[0]
    assert ref_st is not None
    return round(ref_st / sc.ts)


def settling_ticks(out: Path, m: dict[str, Any], agent: int = 1) -> int:
    """A run's settling time counted in agent ``agent``'s own ticks (MC frames sent from
    t = 0, the first price, to the settling instant): what the control law needed,
    whatever the wall clock did meanwhile (a starved agent ticks less, not slower)."""
    from sim.run.buslog import read_log

    log = read_log(out / "run.log")
    assert m["settling_time_s"] is not None, "never settled"
    assert log.t_first_price is not None
    t0 = log.t_first_price
    t_settle = t0 + m["settling_time_s"]
    return sum(1 for t, _ in log.series[(f"AGENT_{agent}_MC", "Lambda")] if t0 <= t <= t_settle)


@pytest.fixture(scope="session")
def installed_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """This checkout as `pip install .` installs it: its wheel built (from a copy:
    setuptools writes build/ and *.egg-info into the source tree) and unpacked into a
    site directory of its own. The wheel itself is beside it (``site.parent / "wheel"``)."""
    import shutil
    import subprocess
    import sys
    import zipfile

    root = Path(__file__).resolve().parent.parent
    tmp = tmp_path_factory.mktemp("installed")
    src = tmp / "src"
    shutil.copytree(root, src, ignore=shutil.ignore_patterns(
        ".*", "build", "runs", "*.egg-info", "__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(tmp / "wheel"), str(src)], check=True,
                   capture_output=True)
    (wheel,) = (tmp / "wheel").glob("bess_ded-*.whl")
    site = tmp / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    return site
