"""Interop with Debian's can-utils on vcan0, during one case-1 run (every node a process).

One run serves all three checks (a scenario run costs ~1.5 min in the QEMU guest):

(a) the price comes from can-utils, not from the router: the router runs muted for the whole
    run (``--silent``), and can-utils speak for it with its key from the run's key set (the
    frames are signed here with ``FleetSender``, as any tool holding the key would). Once
    all four agents and the plant are heard (``candump -n 1`` each, on 11-bit data frames
    only), ``cansend`` injects ``ER_Price_Sync`` (the freshness of boot 5) and the first
    ER_Price frame (ρ = 0.9, not case 1's 0.8), which takes the agents out of INIT, and
    ``canplayer`` then plays the next frames at the price cycle (by the file's timestamps),
    each with its own freshness value (a loop would replay spent values: rejected). (A
    ``cansend`` per frame would do too on a host, but in the emulated guest each one costs
    ~0.3-0.6 s of CPU: a stream of them starved the nodes and let the price lapse past the
    agents' 1.25 s timeout.) The agents must converge to ρ = 0.9. Every 50th frame of the
    file is followed by a tampered copy of a price frame (one payload bit flipped) and a
    frame of DLC 5: every agent counts them under RejectedAuth / RejectedDlc, at most as
    many as ``candump`` saw.
(b) ``candump -L`` records the run (kernel filters: standard IDs only, joined with an
    inverse filter that drops the 0x7F0 noise) and every line decodes with
    ``python3 -m cantools decode`` against the DBC.
(c) two ``cangen`` generators add random traffic on IDs the DBC does not define
    (0x7F0 with random DLC and payload; random 29-bit IDs), ~50 frames/s in all. It
    must not disturb convergence. Agents 1 and 2 run with ``--no-acceptance-filter``
    and count it (AGENT_i_Diag RejectedUnknownId > 0); agents 3 and 4 keep the default
    kernel acceptance filter, which stops it before the firmware (RejectedUnknownId = 0).

Case 1 is shortened to 8 s (dataclasses.replace; lockstep is at 1.4e-4 at 8 s) and
stretched by vcanrun.TIME_SCALE in the guest.
"""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest
from vcanrun import (
    FINAL_TOL,
    TIME_SCALE,
    Run,
    assert_clean_exit,
    assert_decodes_with_cantools,
    key_set,
    run_on_vcan,
)

from firmware_py import contract, secoc
from firmware_py import fixedpoint as fx
from firmware_py.frames import FrameCodec
from firmware_py.nodeio import FleetSender
from sim.model.scenario import load_case

pytestmark = pytest.mark.vcan

RHO = 0.9
UNFILTERED = (1, 2)  # agents that see every frame; 3 and 4 keep the kernel filter
PRICE_CYCLE_S = 0.05  # ER_Price's GenMsgCycleTime at Ts = 10 ms
FEEDER_BOOT = 5    # the boot the can-utils "router" announces: within AUTH-27's 8 of the floor 1
PRICE_FRAMES = 2000   # more than the run needs at the price cycle
BAD_EVERY = 50        # a tampered and a short frame after every 50th price frame
MASTER = bytes(range(16))


def _hex(m: object) -> str:
    return f"{m.arbitration_id:03X}#{bytes(m.data).hex().upper()}"  # type: ignore[attr-defined]


def price_stream(router_key: bytes) -> tuple[str, list[str]]:
    """(ER_Price_Sync, then ER_Price frames for ρ = 0.9 with counts 0, 1, 2, ...) signed
    with the router's key at boot FEEDER_BOOT, in cansend's ID#DATA form."""
    sender = FleetSender(FrameCodec(), keys={"router": router_key}, boot=FEEDER_BOOT)
    sync = _hex(sender.sync("ER_Price"))
    raw = {"PriceValid": 1, "Rho": fx.to_fixed(RHO), "Segment": 0}
    return sync, [_hex(sender.frame("ER_Price", raw)) for _ in range(PRICE_FRAMES)]


def tampered(frame: str) -> str:
    """One payload bit flipped (ρ's top byte): the MAC no longer verifies."""
    head, data = frame.split("#")
    return f"{head}#{data[:14]}{int(data[14:], 16) ^ 0x40:02X}"


def play_file(path: Path, channel: str, frames: list[str], gap_s: float) -> None:
    """A candump -L file that ``canplayer -I`` plays one frame every ``gap_s`` (by its
    timestamps: with -t, canplayer sends the whole file at once, then sleeps -g)."""
    path.write_text("".join(f"({k * gap_s:.6f}) {channel} {f}\n"
                            for k, f in enumerate(frames)))


def wait_for_frames(channel: str, ids: list[int]) -> str:
    """A shell command that returns once a frame of each ID was heard (``candump -n 1``
    each; mask C00007FF matches 11-bit data frames only: 7FF alone would also pass
    cangen's 29-bit IDs that end in the same bits)."""
    return " && ".join(f"candump -n 1 {channel},{fid:03X}:C00007FF >/dev/null"
                       for fid in ids)


def _spawn(argv: list[str], out: Path) -> subprocess.Popen[bytes]:
    with out.open("wb") as f:
        return subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)


def _stop(p: subprocess.Popen[bytes]) -> None:
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGTERM)
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


@pytest.fixture(scope="module")
def interop(vcan_channel: str, can_utils: None,
            tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Run, Path]]:
    for tool in ("cangen", "canplayer"):
        if subprocess.run(["sh", "-c", f"command -v {tool}"], capture_output=True).returncode:
            pytest.fail(f"{tool} missing (tools/install-vcan-deps)")
    out = tmp_path_factory.mktemp("interop")
    ch = vcan_channel
    sc = replace(load_case(1), duration=8.0)
    keys = key_set(out, sc, MASTER)
    sync, good = price_stream(secoc.derive_node_key(MASTER, "router"))
    # after cansend's first frame (count 0): counts 1, 2, ...; each bad frame takes one
    # slot, so the good ones around it are 3 cycles apart (< the agents' 25 Ts timeout)
    played = []
    for k, frame in enumerate(good[1:], start=1):
        played.append(frame)
        if k % BAD_EVERY == 0:
            played += [tampered(frame), frame[:4 + 10]]  # + a tampered copy, DLC 5
    play_file(out / "price.log", ch, played, PRICE_CYCLE_S * TIME_SCALE)
    # an AGENT_i_MC frame from every agent, and the plant's status (the agents leave INIT
    # on a price and a status)
    wait_nodes = wait_for_frames(ch, [contract.MC_BASE + i for i in range(1, sc.n + 1)]
                                 + [contract.STATUS_BASE + 1])
    feeder = (f"{wait_nodes} && cansend {ch} {sync} && cansend {ch} {good[0]} && "
              f"exec canplayer -I {out / 'price.log'}")
    capture = out / "candump.log"
    procs = [
        # j: both filters must match (CAN_RAW_JOIN_FILTERS): 11-bit IDs, and not 0x7F0..7FF
        _spawn(["candump", "-L", f"{ch},0:80000000,7F0~7F0,j"], capture),
        _spawn(["cangen", ch, "-g", "40", "-I", "7F0", "-L", "r", "-D", "r"],
               out / "cangen-std.txt"),
        _spawn(["cangen", ch, "-g", "40", "-e", "-I", "r", "-L", "r", "-D", "r"],
               out / "cangen-ext.txt"),
        _spawn(["sh", "-c", feeder], out / "feeder.txt"),
    ]
    try:
        # the router's price is muted for the whole run: ER_Price comes from can-utils only
        run = run_on_vcan(sc, out / "run", ch, keys=keys, extra={
            "router": ["--silent", "0:1000000"],
            **{f"agent_{i}": ["--no-acceptance-filter"] for i in UNFILTERED}})
    finally:
        for p in reversed(procs):
            _stop(p)
    yield run, capture


def test_agents_follow_the_price_sent_with_cansend(interop: tuple[Run, Path]) -> None:
    run, capture = interop
    # the run's t = 0 is the frame cansend injected (count 0), after its sync
    first = next(ln.split()[2] for ln in capture.read_text().splitlines()
                 if ln.split()[2].startswith("010#"))
    assert first == price_stream(secoc.derive_node_key(MASTER, "router"))[1][0], first
    prices = {round(v, 6) for _, v in run.log.series[("price", "Rho")]}
    assert prices == {round(fx.to_float(fx.to_fixed(RHO)), 6)}, prices
    assert run.m["final_error"] < FINAL_TOL, {k: run.m[k] for k in (
        "final_error", "settling_times_s", "deadline_misses", "anomalies",
        "node_diagnostics", "node_counters")}
    for i in range(1, run.sc.n + 1):
        lam = run.log.series[(f"AGENT_{i}_MC", "Lambda")][-1][1]
        assert abs(lam - RHO) < FINAL_TOL, (i, lam)
    assert_clean_exit(run)


def test_candump_capture_decodes_with_cantools(interop: tuple[Run, Path]) -> None:
    run, capture = interop
    lines = capture.read_text().splitlines()
    # the capture saw the run: every node's frames, far more than the start-up tail
    assert len(lines) > run.m["frames_recorded"] // 2, (len(lines), run.m["frames_recorded"])
    ids = {ln.split()[2].split("#")[0] for ln in lines}
    assert {"010", "101", "104", "281", "301"} <= ids, sorted(ids)
    assert_decodes_with_cantools(capture, len(lines))


def test_random_traffic_on_other_ids_is_counted_not_followed(
        interop: tuple[Run, Path]) -> None:
    run, _ = interop
    # the recorder saw the noise (it records everything) ...
    assert run.m["frames_undecodable"].get("unknown_id", 0) > 100, run.m["frames_undecodable"]
    # (and the short price frames of test_bad_price_frames_...; the tampered ones decode,
    # and fail their MAC: auth_failed)
    assert set(run.m["frames_undecodable"]) == {"unknown_id", "dlc"}, \
        run.m["frames_undecodable"]
    # ... the unfiltered agents rejected it under unknown_id, the filtered ones never
    # saw it, and none rejected anything else
    for i in range(1, run.sc.n + 1):
        d = run.m["node_diagnostics"][f"agent_{i}"]
        if i in UNFILTERED:
            assert d["RejectedUnknownId"] > 0, (i, d)
        else:
            assert d["RejectedUnknownId"] == 0, (i, d)
        assert d["RejectedRange"] == d["RejectedImpersonation"] == 0, (i, d)


def test_bad_price_frames_from_canplayer_are_counted_by_cause(
        interop: tuple[Run, Path]) -> None:
    run, capture = interop
    price = [ln.split()[2] for ln in capture.read_text().splitlines()
             if ln.split()[2].startswith("010#")]
    good = set(price_stream(secoc.derive_node_key(MASTER, "router"))[1])
    sent = {"RejectedAuth": sum(len(f) == 4 + 16 and f not in good for f in price),
            "RejectedDlc": sum(len(f) == 4 + 10 for f in price)}
    assert all(v >= 2 for v in sent.values()), sent  # at least two bad pairs were played
    for i in range(1, run.sc.n + 1):
        d = run.m["node_diagnostics"][f"agent_{i}"]
        for cause, n in sent.items():
            assert 1 <= d[cause] <= n, (i, cause, d[cause], n)
    assert ("auth_failed", "bus") in {(a["kind"], a["node"]) for a in run.m["anomalies"]}
