"""The verdict of a bus run and the anomalies behind it (sim/run/verdict.py, docs/runs.md).

Most cases are deterministic: a fleet on the in-process virtual bus stepped on a
simulated clock (``busrun.run_in_process``), or a recorded log edited frame by frame
and judged by ``bess-ded analyze``. The multi-process runs at the end assert only what
holds at any load (no foreign traffic between concurrent runs, a dead router named).
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import can
import pytest

from firmware_py.frames import FrameCodec
from sim.cli import main
from sim.model.scenario import load_case
from sim.run import busrun
from sim.run.verdict import EXIT_ANOMALIES, EXIT_NOT_CONVERGED, EXIT_OK

ROOT = Path(__file__).resolve().parents[1]


def kinds(m: dict) -> set[tuple[str, str]]:
    return {(a["kind"], a["node"]) for a in m["anomalies"]}


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """Case 1 for 10 s on the virtual bus: the reference every edited log starts from."""
    out = tmp_path_factory.mktemp("clean")
    m = busrun.run_in_process(replace(load_case(1), duration=10.0), out, duration=10.0,
                              channel="verdict-clean")
    return out / "run.log", m


def test_a_clean_run_converges_without_anomalies(clean_run: tuple[Path, dict]) -> None:
    _, m = clean_run
    assert m["anomalies"] == []
    assert m["verdict"] == {"converged": True, "reasons": [], "interrupted": False,
                            "exit_code": EXIT_OK, "ok": True, "cause": None}
    assert m["final_error"] < 1e-3
    # the router's own ledger is reported next to the cost recomputed from the powers
    ledger = m["router_ledger"]
    assert ledger["cost"] > 0 and ledger["cost"] >= ledger["optimal_cost"] * 0.999
    assert ledger["cost_rate"] == pytest.approx(m["cost"], abs=0.1)  # 0.1 cu/h resolution


def test_router_gone_for_good_is_not_convergence(tmp_path: Path) -> None:
    """The router falls silent at 4 s and never comes back: every agent ends in SAFE
    with its λ held near ρ, which the old summary called converged (error ≈ 0)."""
    m = busrun.run_in_process(replace(load_case(1), duration=8.0), tmp_path, duration=8.0,
                              channel="verdict-router-gone", router_silent=((4.0, 100.0),))
    assert not m["verdict"]["converged"]
    assert m["verdict"]["exit_code"] == EXIT_NOT_CONVERGED
    assert all(f"agent_{i} ended in SAFE" in m["verdict"]["reasons"] for i in range(1, 5))
    found = kinds(m)
    assert ("node_silent", "router") in found
    assert {("agent_safe_at_end", f"agent_{i}") for i in range(1, 5)} <= found
    silent = next(a for a in m["anomalies"] if a["kind"] == "node_silent")
    assert "ER_Price" in silent["detail"] and 3.85 <= silent["t"] < 4.0  # its last frame


def test_a_router_outage_that_ends_is_reported_but_converges(tmp_path: Path) -> None:
    m = busrun.run_in_process(replace(load_case(1), duration=10.0), tmp_path, duration=10.0,
                              channel="verdict-router-outage", router_silent=((4.0, 6.0),))
    assert m["verdict"]["converged"] and m["verdict"]["exit_code"] == EXIT_ANOMALIES
    safe = [a for a in m["anomalies"] if a["kind"] == "agent_safe"]
    assert {a["node"] for a in safe} == {f"agent_{i}" for i in range(1, 5)}
    # SAFE from the price timeout (0.25 s) after the last price frame to its return
    assert all(4.2 <= a["t"] <= 4.4 for a in safe), safe


def test_a_dead_plant_puts_its_agents_in_safe(tmp_path: Path) -> None:
    """The plant stops at 4 s for good: within the documented status timeout (5 status
    cycles, 0.25 s) plus a sample of transport, every agent is SAFE with its setpoint
    disabled; the verdict names the silent plant and the agents' status timeouts."""
    from firmware_py.contract import State, timeout_s

    sc = replace(load_case(1), duration=6.0)
    m = busrun.run_in_process(sc, tmp_path, duration=6.0, channel="verdict-plant-dead",
                              restarts=[("plant", 4.0, float("inf"))])
    assert m["verdict"]["exit_code"] == EXIT_NOT_CONVERGED
    limit = timeout_s("PLANT_1_Status", sc.ts)
    codec = FrameCodec()
    last_status = max(f.timestamp for f in can.LogReader(str(tmp_path / "run.log"))
                      if f.arbitration_id == codec.frame_id("PLANT_1_Status"))
    for i in range(1, 5):
        frames = [(f.timestamp, codec.decode(f)) for f in can.LogReader(str(tmp_path / "run.log"))
                  if f.arbitration_id in (codec.frame_id(f"AGENT_{i}_MC"),
                                          codec.frame_id(f"AGENT_{i}_Setpoint"))]
        safe = min(t for t, f in frames if f.name.endswith("_MC")
                   and f.raw["State"] == State.SAFE)
        assert limit < safe - last_status <= limit + 2 * sc.ts + 1e-9, (i, safe, last_status)
        assert all(f.raw["Enable"] == 0 for t, f in frames
                   if f.name.endswith("_Setpoint") and t > safe)
        assert m["node_diagnostics"][f"agent_{i}"]["StatusTimeouts"] == 1
    found = kinds(m)
    assert ("node_silent", "plant") in found
    assert {("status_timeout", f"agent_{i}") for i in range(1, 5)} <= found
    assert {("agent_safe_at_end", f"agent_{i}") for i in range(1, 5)} <= found


def analyze(log: Path, out: Path, *extra: str) -> tuple[int, dict]:
    rc = main(["analyze", str(log), "--case", "1", "--out", str(out), "--no-plot", *extra])
    return rc, json.loads((out / "metrics.json").read_text())


def test_analyze_reproduces_the_run(clean_run: tuple[Path, dict], tmp_path: Path) -> None:
    log, m = clean_run
    rc, again = analyze(log, tmp_path)
    assert rc == EXIT_OK
    for key in ("settling_times_s", "final_error", "resets", "anomalies", "router_ledger",
                "frames_recorded", "cost"):
        assert again[key] == m[key], key


def rewrite(src: Path, dst: Path, edit) -> Path:
    """Copy a candump log through ``edit(msg) -> [msgs]``."""
    with can.Logger(str(dst)) as writer:
        for msg in can.LogReader(str(src)):
            for out in edit(msg):
                writer.on_message_received(out)
    return dst


def test_forged_reports_in_a_log_are_left_out_with_the_keys(clean_run: tuple[Path, dict],
                                                            tmp_path: Path) -> None:
    """`analyze --keys` of a log with forged AGENT_2_Diag pages (every counter 999) and
    forged ER_Balance pages (ten times the cost) beside the genuine ones: the report's
    diagnostics and ledger are the clean run's, the forgeries are auth_failed on their
    messages. Without the keys the same log shows the forged values: only the MAC tells
    them apart."""
    codec = FrameCodec()
    diag_id, balance_id = codec.frame_id("AGENT_2_Diag"), codec.frame_id("ER_Balance")
    forged = {"diag": 0, "balance": 0}

    def edit(msg: can.Message) -> list[can.Message]:
        out = [msg]
        if msg.timestamp - 2.0 < 0 or msg.arbitration_id not in (diag_id, balance_id):
            return out
        d = codec.decode(msg)
        page = d.raw["Page"]
        if msg.arbitration_id == diag_id:
            sigs = codec.pages("AGENT_2_Diag")[page]
            raw = {s: min(999, codec.raw_range("AGENT_2_Diag", s)[1]) for s in sigs}
            forged["diag"] += 1
        else:
            raw = {s: 10 * v for s, v in d.raw.items()
                   if s not in ("Mac", "Counter", "Page")}
            forged["balance"] += 1
        f = codec.encode(d.name, {"Page": page, **raw}, (d.counter + 1) % 16)
        f.data[0:3] = bytes([0x5A, 0xA5, 0x3C])  # a guessed MAC
        f.timestamp = msg.timestamp + 1e-4
        return [*out, f]

    log = rewrite(clean_run[0], tmp_path / "forged.log", edit)
    keys = str(clean_run[0].parent / "keys")
    rc, m = analyze(log, tmp_path / "a", "--keys", keys)
    assert rc == EXIT_ANOMALIES
    clean = clean_run[1]
    assert m["node_diagnostics"] == clean["node_diagnostics"]
    assert m["router_ledger"] == clean["router_ledger"]
    auth = {a["detail"].split(":")[0]: a["detail"] for a in m["anomalies"]
            if a["kind"] == "auth_failed" and a["node"] == "bus"}
    assert set(auth) == {"AGENT_2_Diag", "ER_Balance"}, m["anomalies"]
    assert auth["AGENT_2_Diag"].startswith(f"AGENT_2_Diag: {forged['diag']} frames")
    assert auth["ER_Balance"].startswith(f"ER_Balance: {forged['balance']} frames")
    _, blind = analyze(log, tmp_path / "b")  # no keys: the forgeries read as the run's
    assert blind["node_diagnostics"]["agent_2"]["RejectedAuth"] == 999
    assert blind["router_ledger"]["cost"] > 2 * clean["router_ledger"]["cost"]


def test_foreign_traffic_in_a_log(clean_run: tuple[Path, dict], tmp_path: Path) -> None:
    """A second sender on AGENT_2_MC (its own counter sequence), frames of an agent the
    4-agent run does not have, and diagnostics frames of 5 bytes: each reported by
    cause. Without the run's keys the forged MC frames show as a second counter
    sequence; with them (`analyze --keys`) they fail their MAC, are left out of the
    analysis and reported as auth_failed."""
    codec = FrameCodec()
    forged = {"n": 0}

    def edit(msg: can.Message) -> list[can.Message]:
        out = [msg]
        if msg.arbitration_id == 0x102 and 3.0 < msg.timestamp < 4.0:
            forged["n"] += 1
            f = codec.encode("AGENT_2_MC", {"State": 1, "Lambda": 5 << 24, "Resets": 0},
                             (forged["n"] * 7) % 16)
            f.timestamp = msg.timestamp + 1e-4
            out.append(f)
        if msg.arbitration_id == 0x010 and msg.timestamp < 1.0:
            g = codec.encode("AGENT_9_MC", {"State": 1, "Lambda": 0, "Resets": 0}, 0)
            g.timestamp = msg.timestamp
            bad = can.Message(arbitration_id=0x301, data=bytes(5), is_extended_id=False,
                              timestamp=msg.timestamp)
            out += [g, bad]
        return out

    log = rewrite(clean_run[0], tmp_path / "forged.log", edit)
    rc, m = analyze(log, tmp_path / "a")
    assert rc == EXIT_ANOMALIES
    details = [a["detail"] for a in m["anomalies"] if a["kind"] == "foreign_traffic"]
    assert details == [
        f"AGENT_2_MC: {forged['n']} frames out of its counter sequence (a second sender on "
        "the ID, or a replay)",
        "20 frames of messages outside this 4-agent run (AGENT_9_MC: 20)"], m["anomalies"]
    assert ("malformed_frames", "bus") in kinds(m)
    assert m["frames_outside_run"] == {"AGENT_9_MC": 20}
    assert m["frames_undecodable"] == {"dlc": 20}
    rc, m = analyze(log, tmp_path / "b", "--keys", str(clean_run[0].parent / "keys"))
    assert rc == EXIT_ANOMALIES
    forged_mc = [a["detail"] for a in m["anomalies"] if a["kind"] == "auth_failed"]
    assert forged_mc == [f"AGENT_2_MC: {forged['n']} frames whose MAC does not verify with "
                         "its sender's key (forged, or replayed from an earlier window or "
                         "run); the analysis left them out"], m["anomalies"]
    assert m["final_error"] == clean_run[1]["final_error"]  # λ = 5 never entered it


def test_recorder_misses_are_counted(clean_run: tuple[Path, dict], tmp_path: Path) -> None:
    """Three AGENT_1_MC frames missing from the log: counted from the counter jumps."""
    dropped = {"n": 0}

    def edit(msg: can.Message) -> list[can.Message]:
        if msg.arbitration_id == 0x101 and msg.timestamp >= 2.0 and dropped["n"] < 3:
            dropped["n"] += 1
            return []
        return [msg]

    rc, m = analyze(rewrite(clean_run[0], tmp_path / "gappy.log", edit), tmp_path / "a")
    assert rc == EXIT_ANOMALIES
    assert m["frames_missed_by_recorder"] == 3
    assert kinds(m) == {("recorder_missed_frames", "recorder")}


def test_a_bus_silence_is_one_anomaly(clean_run: tuple[Path, dict], tmp_path: Path) -> None:
    """Nothing at all for 0.1 s (10 Ts): one bus silence, not a node gone."""
    rc, m = analyze(rewrite(clean_run[0], tmp_path / "quiet.log",
                            lambda msg: [] if 5.0 <= msg.timestamp < 5.1 else [msg]),
                    tmp_path / "a")
    assert rc == EXIT_ANOMALIES
    silence = [a for a in m["anomalies"] if a["kind"] == "bus_silence"]
    assert len(silence) == 1 and silence[0]["t"] == pytest.approx(4.99, abs=0.011)
    assert not [a for a in m["anomalies"] if a["kind"] == "node_silent"]


def test_analyze_rejects_what_it_cannot_read(tmp_path: Path, capsys) -> None:
    assert main(["analyze", str(tmp_path / "nope.log"), "--case", "1"]) == 2
    assert "expected a readable log file" in capsys.readouterr().err
    (tmp_path / "x.log").write_text("")
    assert main(["analyze", str(tmp_path / "x.log")]) == 2  # no scenario named


def test_a_log_without_a_price_is_judged_too(clean_run: tuple[Path, dict],
                                             tmp_path: Path) -> None:
    log = rewrite(clean_run[0], tmp_path / "noprice.log",
                  lambda m: [] if m.arbitration_id == 0x010 else [m])
    rc, m = analyze(log, tmp_path / "a")
    assert rc == EXIT_NOT_CONVERGED
    assert ("no_price", "router") in kinds(m)
    assert not (tmp_path / "a" / "trajectory.csv").exists()


# ------------------------------------------------------------------- inputs of `up`


@pytest.mark.parametrize("argv, says", [
    (["--duration", "-1"], "--duration: expected a finite number > 0 and ≤ 100000, but got -1"),
    (["--duration", "0"], "--duration: expected a finite number > 0 and ≤ 100000, but got 0"),
    (["--duration", "nan"], "--duration: expected a finite number > 0 and ≤ 100000, but got nan"),
    (["--time-scale", "0"], "--time-scale: expected a factor in [1, 1000], but got 0"),
    (["--interface", "virtual"], "exists inside one process only"),
    (["--variant", "PC"], "has no variants"),
    (["--bus-config", "[1]"], "expected a JSON object"),
])
def test_up_refuses_bad_input_at_once(argv: list[str], says: str, capsys) -> None:
    assert main(["up", "--case", "1", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: error: ") and says in err and err.count("\n") == 1


def test_up_names_unknown_cases_and_variants(capsys) -> None:
    assert main(["up", "--case", "9"]) == 2
    assert "expected a case number" in capsys.readouterr().err
    assert main(["up", "--case", "2", "--variant", "nope"]) == 2
    assert "expected one of reset-PI" in capsys.readouterr().err


def test_private_port_only_where_needed() -> None:
    bus, port = busrun.private_port(busrun.BusOptions("udp_multicast", None, None))
    assert port is not None and busrun.PRIVATE_PORTS[0] <= port < busrun.PRIVATE_PORTS[1]
    assert bus.resolved()["port"] == port
    assert port not in busrun.bound_udp_ports()
    named = busrun.BusOptions("udp_multicast", None, '{"port": 43999}')
    assert busrun.private_port(named) == (named, None)
    vcan = busrun.BusOptions("socketcan", "vcan0", None)
    assert busrun.private_port(vcan) == (vcan, None)


# ------------------------------------------------------------- multi-process runs


@pytest.mark.slow
@pytest.mark.realtime
def test_concurrent_up_runs_do_not_hear_each_other(tmp_path: Path) -> None:
    """Two `bess-ded up --case 1` with no bus flags at once: each on a private port, each
    with its own handful of resets and no foreign traffic. (Deadline misses and bus
    silences may be reported on a loaded host: they are not asserted. Nor is the
    verdict's "converged": CI once starved both runs for 0.3 s at their very end, beside
    stress-ng, and an agent rightly went SAFE on a status timeout; another time 14
    processes on 2 CPUs beside stress-ng left the error at 1.11e-3 after 8 s, above the
    1e-3 tolerance. A NOT CONVERGED verdict must then come with the starvation's
    evidence.)"""
    procs = [subprocess.Popen([sys.executable, "-m", "sim.cli", "up", "--case", "1",
                               "--duration", "8", "--no-plot", "--out", str(tmp_path / f"r{i}")],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=ROOT)
             for i in range(2)]
    outs = [p.communicate(timeout=300)[0].decode() for p in procs]
    ports = set()
    for i, (p, out) in enumerate(zip(procs, outs, strict=True)):
        m = json.loads((tmp_path / f"r{i}" / "metrics.json").read_text())
        assert p.returncode in (EXIT_OK, EXIT_ANOMALIES, EXIT_NOT_CONVERGED), out
        if not m["verdict"]["converged"]:
            kinds = {a["kind"] for a in m["anomalies"]}
            assert kinds & {"bus_silence", "node_silent", "deadline_misses", "price_timeout",
                            "status_timeout", "host_overloaded"}, out
        assert max(m["resets"]) <= 20, out
        assert not [a for a in m["anomalies"] if a["kind"] in ("foreign_traffic",
                                                               "malformed_frames")], out
        assert m["frames_out_of_sequence"] == {} and m["frames_outside_run"] == {}
        ports.add(next(line for line in out.splitlines() if "private to this run" in line))
    assert len(ports) == 2


@pytest.mark.slow
@pytest.mark.realtime
def test_router_killed_mid_run_is_named(tmp_path: Path, udp_port: int) -> None:
    sc = replace(load_case(1), duration=6.0)

    def kill_router(specs: list[busrun.NodeSpec], _logdir: Path) -> None:
        proc = next(s for s in specs if s.name == "router").proc
        assert proc is not None
        proc.kill()

    bus = busrun.BusOptions("udp_multicast", None, json.dumps({"port": udp_port}))
    rec = busrun.record(sc, tmp_path, bus, quiet=True, plot=False,
                        actions=[(3.0, kill_router)])
    m = rec.metrics
    assert rec.verdict.exit_code == EXIT_NOT_CONVERGED
    assert any(r.startswith("router died (exit code -9)") for r in m["verdict"]["reasons"])
    found = kinds(m)
    assert ("node_died", "router") in found and ("node_silent", "router") in found
    assert {("agent_safe_at_end", f"agent_{i}") for i in range(1, 5)} <= found


@pytest.mark.realtime
def test_record_captures_a_bus_for_analyze(tmp_path: Path, udp_port: int) -> None:
    """`bess-ded record` on a udp_multicast port until SIGINT: every frame sent lands in
    a candump log that python-can and `cantools decode` read back; the datagrams between
    them that are no frame (13 bytes of garbage, a standard frame with ID 0x800) end
    neither the recording nor a frame: they are counted by cause and reported."""
    import signal

    from can.interfaces.udp_multicast.utils import pack_message

    log = tmp_path / "bus.log"
    config = json.dumps({"port": udp_port})
    p = subprocess.Popen([sys.executable, "-m", "sim.cli", "record", "--interface",
                          "udp_multicast", "--bus-config", config, "--out", str(log)],
                         stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert p.stderr is not None
        assert p.stderr.readline().startswith("bess-ded record:")  # the bus is open
        codec = FrameCodec()
        with can.Bus(interface="udp_multicast", port=udp_port, fd=False) as bus:
            wide = can.Message(arbitration_id=0x800, is_extended_id=False, data=bytes(8),
                               check=False)
            for k in range(50):
                bus._multicast.send(bytes(range(13)) if k % 2 else pack_message(wide))
                bus.send(codec.encode("ER_Price", {"PriceValid": 1, "Rho": k << 20,
                                                   "Segment": 0}, k % 16))
        # loopback delivery is synchronous: the frames wait in record's socket, which it
        # drains before it closes
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 0, err
    assert "50 frames" in err
    assert "anomaly: 25 not_a_frame, 25 invalid_frame" in err, err
    frames = list(can.LogReader(str(log)))
    assert [codec.decode(f).raw["Rho"] for f in frames] == [k << 20 for k in range(50)]


def test_up_refuses_a_scenario_that_leaves_agents_unpinned(tmp_path: Path, capsys) -> None:
    """Agents 3 and 4 share no edge with the pinned agent 1: they could never reach ρ."""
    text = (ROOT / "sim/scenarios/case1.toml").read_text()
    lines = [("edges = [[1, 2], [3, 4]]" if line.startswith("edges") else line)
             for line in text.splitlines()]
    path = tmp_path / "split.toml"
    path.write_text("\n".join(lines) + "\n")
    assert main(["up", "--case", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "agents 3, 4 cannot reach a pinned agent" in err


def test_a_capture_received_out_of_order_is_judged_in_bus_order(
        clean_run: tuple[Path, dict], tmp_path: Path) -> None:
    """vcan on two CPUs can hand a capture socket one sender's frame after later ones
    (the kernel stamped it when it was sent): every 50th AGENT_1_MC frame written three
    frames late, timestamp kept. The analysis takes frames in timestamp order, so with
    the run's keys nothing is forged, nothing is out of sequence, and the run is judged
    as recorded in order; ``reordered`` says how many came late."""
    from sim.run import buslog

    held: list[can.Message] = []
    seen = {"n": 0, "late": 0}

    def edit(msg: can.Message) -> list[can.Message]:
        if msg.arbitration_id != 0x101 or seen["n"] >= 903:
            return [msg]
        seen["n"] += 1
        if seen["n"] % 50 == 0:
            held.append(msg)
            return []
        if held and seen["n"] % 50 == 3:
            seen["late"] += 1
            return [msg, held.pop()]
        return [msg]

    log = rewrite(clean_run[0], tmp_path / "late.log", edit)
    keys = clean_run[0].parent / "keys"
    rc, m = analyze(log, tmp_path / "a", "--keys", str(keys))
    assert rc == EXIT_OK, m["anomalies"]
    assert m["final_error"] == clean_run[1]["final_error"]
    assert seen["late"] == 18 and buslog.read_log(log).reordered == 18


def test_a_replayed_sync_below_the_run_s_boot_floor_is_a_stale_boot(tmp_path: Path) -> None:
    """A monitor with no freshness state takes the first sync that verifies: a sync and a
    price replayed from the router's previous boot, ahead of its genuine ones, pass a
    monitor without the run's boot floors. With them (busrun.record reads them from the
    key files before the nodes start), the old sync is a stale boot of the router (its MAC
    verifies: not forged, AUTH-21) and the old price never verifies; the genuine frames
    after them do."""
    from firmware_py.nodeio import FleetSender
    from sim.run import buslog

    key = bytes(range(16))
    old, new = (FleetSender(keys={"router": key}, boot=b) for b in (3, 4))
    frames = [old.sync("ER_Price"),
              old.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": 5 << 23}),
              new.sync("ER_Price"),
              new.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": 8 << 23})]
    path = tmp_path / "replay.log"
    with can.Logger(str(path)) as writer:
        for t, f in enumerate(frames):
            f.timestamp = 100.0 + 0.01 * t
            writer.on_message_received(f)
    blind = buslog.read_log(path, keys={"router": key})
    assert not blind.forged and [v for _, v in blind.series[("price", "Rho")]] == [2.5, 4.0]
    floored = buslog.read_log(path, keys={"router": key}, boot_floors={"router": 4})
    assert not floored.forged and floored.unverified == {"ER_Price": 1}
    assert floored.stale_boot == {"router": (3, 4)}
    assert floored.stale_boot_syncs == {"ER_Price_Sync": 1}   # left out, and counted
    assert [v for _, v in floored.series[("price", "Rho")]] == [4.0]


def _ground_truth_log(path: Path) -> tuple[int, int, int]:
    """A recording with a known truth, built with the real SecOC code: 300 ticks of four
    senders' genuine secured frames (their syncs first), every genuine λ/ρ/power in a
    range no forged frame uses; genuine AGENT_1_MC frames swapped with their successor
    every 7th tick and AGENT_2_MC frames delayed 3.5 cycles every 11th (late: behind newer
    ones); a flood of 20 forged frames per tick (an attacker's key, every counter) and
    replays every tick of a genuine frame 2 ticks old (price or status: frames already
    accepted, so not late) and of one 50 ticks old. (genuine, late, attacker) frames."""
    import random

    from firmware_py.nodeio import FleetSender
    from firmware_py.secoc import derive_frame_key, derive_node_key

    rnd = random.Random(19)
    master = bytes(range(16))
    labels = ("router", "plant", "agent_1", "agent_2")
    links = ("PLANT_1_Status",)   # AUTH-28: under its own link frame key
    honest = FleetSender(keys={**{n: derive_node_key(master, n) for n in labels},
                               **{f: derive_frame_key(master, f) for f in links}}, boot=5)
    attacker = FleetSender(keys={n: bytes(rnd.randrange(256) for _ in range(16))
                                 for n in (*labels, *links)}, boot=5)
    ts, frames, genuine, late, attack = 0.01, [], [], 0, 0

    def honest_frames(k: int) -> list[can.Message]:
        return [honest.frame("ER_Price", {"PriceValid": 1, "Segment": 0,
                                          "Rho": 13_000_000 + k}),
                honest.frame("AGENT_1_MC", {"State": 1, "Resets": 0, "Lambda": 13_000_000 + k}),
                honest.frame("AGENT_2_MC", {"State": 1, "Resets": 0, "Lambda": 13_000_000 + k}),
                honest.frame("PLANT_1_Status", {"FaultOverCurrent": 0, "FaultVoltage": 0,
                                                "FaultSoc": 0, "PowerLimited": 0,
                                                "Power": 100 + k, "Soc": 100})]

    for j, name in enumerate(("ER_Price", "AGENT_1_MC", "AGENT_2_MC", "PLANT_1_Status")):
        s = honest.sync(name)
        s.timestamp = 1.0 + j * 1e-4
        frames.append(s)
    for k in range(300):
        t = 1.01 + k * ts
        batch = honest_frames(k)
        for j, f in enumerate(batch):
            f.timestamp = t + j * 1e-4
        if k % 7 == 6:     # AGENT_1_MC of this tick overtakes the previous one
            prev = next(f for f in reversed(genuine) if f.arbitration_id == 0x101)
            prev.timestamp, batch[1].timestamp = batch[1].timestamp, prev.timestamp
            late += 1
        if k % 11 == 5:    # AGENT_2_MC delivered after the next three of its sender's
            batch[2].timestamp += 3.5 * ts
            late += 1
        genuine += batch
        for _ in range(20):
            name = rnd.choice(("ER_Price", "AGENT_1_MC", "AGENT_2_MC", "PLANT_1_Status"))
            raw = ({"PriceValid": 1, "Segment": 0, "Rho": 30_000_000 + attack}
                   if name == "ER_Price" else
                   {"State": 1, "Resets": 0, "Lambda": 30_000_000 + attack}
                   if name.endswith("_MC") else
                   {"FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0,
                    "PowerLimited": 0, "Power": 5_000 + attack % 1000, "Soc": 100})
            f = attacker.frame(name, raw, counter=rnd.randrange(16))
            f.timestamp = t + rnd.uniform(0, ts)
            frames.append(f)
            attack += 1
        if k >= 2:         # a replay of a genuine price or status frame of 2 ticks ago
            old = genuine[4 * (k - 2) + rnd.choice((0, 3))]
            frames.append(can.Message(arbitration_id=old.arbitration_id, data=old.data,
                                      is_extended_id=False, timestamp=t + 0.3 * ts))
            attack += 1
        if k >= 50:        # a replay of one of the genuine frames of 50 ticks ago
            old = genuine[4 * (k - 50) + rnd.randrange(4)]
            frames.append(can.Message(arbitration_id=old.arbitration_id, data=old.data,
                                      is_extended_id=False, timestamp=t + 0.5 * ts))
            attack += 1
    # candump lines in any order (can.Logger would clamp a timestamp that goes back)
    path.write_text("".join(f"({f.timestamp:.6f}) vcan0 {f.arbitration_id:03X}#"
                            f"{bytes(f.data).hex().upper()}\n"
                            for f in sorted(genuine + frames, key=lambda f: rnd.random())))
    return len(genuine), late, attack


def test_the_recorder_tells_late_genuine_frames_from_a_flood_of_forged_ones(
        tmp_path: Path) -> None:
    """Issue 19, "late is not forged": against a known ground truth (``_ground_truth_log``)
    the recorder accepts no forged frame, calls no genuine frame forged, and counts
    exactly the reordered genuine frames as stale; the verdict says stale_frames only
    above its threshold and never auth_failed for them."""
    from firmware_py.secoc import derive_frame_key, derive_node_key
    from sim.run import buslog, verdict

    path = tmp_path / "truth.log"
    n_genuine, n_late, n_attack = _ground_truth_log(path)
    keys = {n: derive_node_key(bytes(range(16)), n)
            for n in ("router", "plant", "agent_1", "agent_2")}
    keys["PLANT_1_Status"] = derive_frame_key(bytes(range(16)), "PLANT_1_Status")
    log = buslog.read_log(path, keys=keys, ts=0.01)
    assert sum(log.forged.values()) == n_attack            # every attacker frame, no more
    assert sum(log.stale.values()) == n_late > 0           # every late genuine frame
    assert log.stale == {"AGENT_1_MC": 300 // 7, "AGENT_2_MC": len(range(5, 300, 11))}
    assert not log.unverified
    used = {key: [v for _, v in log.series[key]] for key in (
        ("price", "Rho"), ("AGENT_1_MC", "Lambda"), ("AGENT_2_MC", "Lambda"),
        ("PLANT_1_Status", "Power"))}
    assert sum(map(len, used.values())) == n_genuine - n_late   # all the others were used
    # ... and only genuine values: 13e6 + k (ρ, λ: < 0.8 cu/kWh), 1.00..3.99 kW; forged
    # ones are ≥ 30e6 (1.79 cu/kWh) and ≥ 50 kW
    assert all(0.77 < v < 0.8 for key in list(used)[:3] for v in used[key])
    assert all(1.0 <= v < 4.0 for v in used[("PLANT_1_Status", "Power")])
    assert used[("price", "Rho")] == sorted(used[("price", "Rho")])  # in the sender's order
    assert not log.out_of_sequence                         # the late ones never reached it
    out: list[verdict.Anomaly] = []
    verdict._recording(load_case(1), log, out)
    kinds_ = [a.kind for a in out]
    assert kinds_.count("auth_failed") == 4 and "stale_frames" not in kinds_  # 69 late of 7752
    log.stale["AGENT_1_MC"] += 100                          # many late: a load anomaly
    out.clear()
    verdict._recording(load_case(1), log, out)
    assert [a.kind for a in out].count("stale_frames") == 1


def test_the_recorder_looks_ahead_only_as_far_as_the_elapsed_time_allows() -> None:
    """A frame right after its sender's last one gets one freshness window (a forgery in
    a flood: one chance in 2^24, as at a node, not eight); after the recorder missed
    frames for a while, as many as 4 frames per cycle would need, up to MAX_WINDOWS
    (2.3 s of silence: 58 windows, beyond a node's LOST_WINDOWS)."""
    from firmware_py.nodeio import LOST_WINDOWS
    from sim.run import monitor

    mon = monitor.Monitor({}, None, lambda name: 0.01)
    f = FrameCodec().decode(FrameCodec().encode("AGENT_1_MC", {"State": 1, "Resets": 0,
                                                               "Lambda": 0}, 0))
    assert mon.windows(f, 5.0) == LOST_WINDOWS              # nothing known yet
    mon.t_last[f.frame_id] = 5.0
    assert [mon.windows(f, 5.0 + dt)
            for dt in (0.002, 0.01, 0.039, 0.045, 0.2, 2.3, 9.0, 60.0)] == [
        1, 1, 1, 2, 6, 58, 226, mon.MAX_WINDOWS]


def test_a_node_s_stale_frames_are_a_load_anomaly_above_one_percent_never_auth() -> None:
    """The plant's and router's `stale` counters (late genuine frames, AUTH-25): 5 in
    1000 ticks is what a loaded host does (nothing); 50 is `stale_frames`, not auth."""
    from sim.run import buslog, verdict

    facts = verdict.RunFacts(node_counters={
        "plant": {"counters": {"stale": 5}, "ticks": 1000},
        "router": {"counters": {"stale": 50}, "ticks": 1000}})
    out: list[verdict.Anomaly] = []
    verdict._counters(load_case(1), buslog.LogContents(), facts, out)
    assert [(a.kind, a.node) for a in out] == [("stale_frames", "router")]
    assert out[0].detail.startswith("50 genuine secured frames arrived late")
