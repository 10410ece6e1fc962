"""Every numeric option of the commands is checked before anything runs, and the CAN
config's keys against what the chosen python-can interface takes: exit code 2 and an
"expected X, but got Y" line, never a traceback or a silently ignored value."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from firmware_py import __main__ as agent_main
from firmware_py.cliargs import RT_PRIORITY, float_in, int_in, nonnegative_float, positive_float
from firmware_py.node import BusConfigError, accepted_bus_keys, bus_kwargs
from sim.cli import main

NODE = ["--case", "1", "--interface", "virtual", "--insecure"]
AGENT = ["--config", "agent_1.toml", "--insecure"]  # never read: the options fail first

BAD = [
    # (argv, option, the expectation the message states)
    (["case", "1", "--band", "-1"], "--band", "a finite number ≥ 0, but got -1"),
    (["case", "1", "--band", "nan"], "--band", "a finite number ≥ 0, but got nan"),
    (["case", "1", "--dwell", "0"], "--dwell", "a finite number > 0, but got 0"),
    (["case", "1", "--dwell", "soon"], "--dwell", "a finite number > 0, but got 'soon'"),
    (["agent", *AGENT, "--duration", "-1"], "--duration",
     "a finite number > 0 and ≤ 100000, but got -1"),
    (["agent", *AGENT, "--rt-priority", "100"], "--rt-priority",
     "a SCHED_FIFO priority in 1..99 or 0, but got 100"),
    (["agent", *AGENT, "--inject-rx-loss", "1.5"], "--inject-rx-loss",
     "a probability in [0, 1], but got 1.5"),
    (["agent", *AGENT, "--inject-rx-delay", "-0.1"], "--inject-rx-delay",
     "a finite number in [0, 60], but got -0.1"),
    (["agent", *AGENT, "--inject-rx-jitter", "inf"], "--inject-rx-jitter",
     "a finite number in [0, 60], but got inf"),
    (["agent", *AGENT, "--inject-seed", "-3"], "--inject-seed", "an integer ≥ 0, but got -3"),
    (["plant", *NODE, "--period", "0"], "--period",
     "a finite number > 0 and ≤ 1000, but got 0"),
    (["plant", *NODE, "--duration", "-5"], "--duration",
     "a finite number > 0 and ≤ 100000, but got -5"),
    (["router", *NODE, "--period", "-0.01"], "--period",
     "a finite number > 0 and ≤ 1000, but got -0.01"),
    (["router", *NODE, "--rt-priority", "-1"], "--rt-priority",
     "a SCHED_FIFO priority in 1..99 or 0, but got -1"),
    (["inject", "forge", "--count", "0"], "--count", "an integer ≥ 1, but got 0"),
    (["inject", "forge", "--count", "1.5"], "--count", "an integer ≥ 1, but got '1.5'"),
    (["inject", "forge", "--target", "65"], "--target", "an agent number in 1..64, but got 65"),
    (["inject", "forge", "--rate", "0"], "--rate",
     "a finite number > 0 and ≤ 1e+06, but got 0"),
    (["inject", "forge", "--seed", "-1"], "--seed", "an integer ≥ 0, but got -1"),
    (["bench", "--capacity-only", "--fleet-transmit", "sometimes"], "--fleet-transmit",
     "periodic, event or periodic,event, but got 'sometimes'"),
]


@pytest.mark.parametrize(("argv", "option", "expected"), BAD,
                         ids=[f"{a[0]} {o} {a[-1]}" for a, o, _ in BAD])
def test_bad_numeric_option_is_exit_2(argv: list[str], option: str, expected: str,
                                      tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                      ) -> None:
    if argv[0] == "case":
        argv = [*argv, "--out", str(tmp_path / "x")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == (f"bess-ded: error: {option}: expected {expected} (usage: bess-ded "
                   f"{argv[0]} -h)\n")
    assert not (tmp_path / "x").exists()


def test_the_agent_entry_point_checks_the_same(capsys: pytest.CaptureFixture[str]) -> None:
    assert agent_main.main([*AGENT, "--duration", "0"]) == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last == ("python -m firmware_py: error: argument --duration: expected a finite "
                    "number > 0 and ≤ 100000, but got 0")


def test_good_values_parse() -> None:
    p = argparse.ArgumentParser()
    agent_main.add_arguments(p)
    args = p.parse_args([*AGENT, "--duration", "2.5", "--rt-priority", "0",
                         "--inject-rx-loss", "1", "--inject-rx-delay", "0"])
    assert (args.duration, args.rt_priority, args.inject_rx_loss) == (2.5, 0, 1.0)
    assert p.parse_args([*AGENT, "--rt-priority", "99"]).rt_priority == 99


def test_type_factories() -> None:
    assert positive_float()("1e-3") == 1e-3
    assert nonnegative_float()("0") == 0.0
    assert float_in(-1, 1)("-1") == -1.0
    assert int_in(1, 32)("32") == 32
    assert RT_PRIORITY("0") == 0 and RT_PRIORITY("1") == 1
    for conv, text in ((positive_float(), "0"), (positive_float(), "-inf"),
                       (float_in(-1, 1), "1.01"), (int_in(1, 32), "0"), (RT_PRIORITY, "x")):
        with pytest.raises(argparse.ArgumentTypeError, match="expected .*, but got"):
            conv(text)


# --------------------------------------------------------------------------- --bus-config


def test_accepted_keys_come_from_the_bus_class() -> None:
    udp = accepted_bus_keys("udp_multicast")
    assert udp is not None and {"channel", "port", "hop_limit", "fd", "can_filters"} <= set(udp)
    sock = accepted_bus_keys("socketcan")
    assert sock is not None and {"local_loopback", "ignore_rx_error_frames"} <= set(sock)
    virt = accepted_bus_keys("virtual")
    assert virt is not None and {"rx_queue_size", "preserve_timestamps"} <= set(virt)
    assert "bitrate" not in udp + sock + virt  # all three would ignore it
    assert accepted_bus_keys("pcan") is None   # reads **kwargs itself: not checked


@pytest.mark.parametrize(("interface", "config", "message"), [
    ("udp_multicast", '{"prot": 43200}', "CAN config: udp_multicast accepts channel, port, "
     "hop_limit, receive_own_messages, fd, can_filters, config_context, ignore_config; but "
     "got unknown key 'prot' (did you mean 'port'?)"),
    ("socketcan", '{"bitrate": 500000}', "unknown key 'bitrate' (socketcan's bitrate is the "
     "kernel's"),
    ("virtual", '{"interface": "socketcan"}', "unknown key 'interface' (give the interface "
     "with --interface"),
])
def test_unknown_bus_config_key_is_rejected(interface: str, config: str, message: str) -> None:
    with pytest.raises(BusConfigError) as e:
        bus_kwargs(interface, None, config)
    assert message in str(e.value)


def test_known_bus_config_keys_pass() -> None:
    assert bus_kwargs("udp_multicast", None, '{"port": 43200, "hop_limit": 2}')["port"] == 43200
    assert bus_kwargs("virtual", "x", {"rx_queue_size": 10})["rx_queue_size"] == 10
    assert bus_kwargs("pcan", None, {"f_clock_mhz": 80})["f_clock_mhz"] == 80  # unchecked


def test_child_nodes_get_only_the_bus_settings_they_do_not_take_by_themselves() -> None:
    """firmware_c's node program takes no --bus-config: a socketcan bus's own fd = True
    (every node reads FD frames to count them) is not passed on, a setting given is."""
    from sim.run.busrun import BusOptions

    assert BusOptions("socketcan", "vcan0").argv() == [
        "--interface", "socketcan", "--channel", "vcan0"]
    assert BusOptions("socketcan", "vcan0", '{"fd": false}').argv()[-2:] == [
        "--bus-config", '{"fd": false}']
    assert BusOptions("udp_multicast", None, '{"port": 43111}').argv()[-2:] == [
        "--bus-config", '{"port": 43111}']


def test_bus_config_from_the_environment_is_checked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CAN_CONFIG", '{"hoplimit": 2}')
    with pytest.raises(BusConfigError, match="unknown key 'hoplimit'"):
        bus_kwargs("udp_multicast")


def test_bad_bus_config_through_the_cli(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["inject", "forge", "--interface", "virtual", "--bus-config",
                 '{"rx_queu_size": 3}']) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: error: CAN config: virtual accepts ") and \
        err.count("\n") == 1
    assert "but got unknown key 'rx_queu_size' (did you mean 'rx_queue_size'?)" in err


# --------------------------------------------------------------------------- upper bounds

@pytest.mark.parametrize(("argv", "option", "expected"), [
    (["up", "--case", "1", "--duration", "1e300"], "--duration",
     "a finite number > 0 and ≤ 100000, but got 1e300"),
    (["up", "--case", "1", "--time-scale", "0.5"], "--time-scale",
     "a factor in [1, 1000], but got 0.5"),
    (["up", "--case", "1", "--time-scale", "1e9"], "--time-scale",
     "a factor in [1, 1000], but got 1e9"),
    (["record", "--duration", "1e300"], "--duration",
     "a finite number > 0 and ≤ 100000, but got 1e300"),
    (["restbus", "--case", "1", "--dut", "agent_2", "--wait", "1e300"], "--wait",
     "a finite number > 0 and ≤ 100000, but got 1e300"),
    (["plant", *NODE, "--time-scale", "inf"], "--time-scale", "a factor in [1, 1000], but got inf"),
    (["plant", *NODE, "--period", "1e300"], "--period",
     "a finite number > 0 and ≤ 1000, but got 1e300"),
    (["analyze", "x.log", "--case", "1", "--time-scale", "1e300"], "--time-scale",
     "a factor in [1, 1000], but got 1e300"),
    (["inject", "forge", "--rate", "1e300"], "--rate",
     "a finite number > 0 and ≤ 1e+06, but got 1e300"),
], ids=lambda x: " ".join(x) if isinstance(x, list) else None)
def test_absurdly_large_values_are_refused(argv: list[str], option: str, expected: str,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """`--duration 1e300` ran until killed: every duration, wait, period, rate and time
    scale has an upper bound."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bess-ded: error: {option}: expected {expected}"), err


def test_up_refuses_a_duration_its_log_could_not_be_analysed_for(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["up", "--case", "1", "--duration", "30000", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err == ("bess-ded: error: --duration: expected at most 25000 s for 4 agents at Ts "
                   "= 0.01 s (the analysis holds 1e+07 agent-samples), but got 30000.0\n")
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------- scenario files

CASE1 = (Path(__file__).resolve().parents[1] / "sim" / "scenarios" / "case1.toml").read_text()


def edited(old: str, new: str) -> str:
    assert old in CASE1, old
    return CASE1.replace(old, new, 1)


BAD_SCENARIOS = [
    # (name, file text, the key named, what the message says)
    ("capacity 0", edited("capacity_kwh = 250.0", "capacity_kwh = 0"), "battery[1].capacity_kwh",
     "expected a value in (0, 1e+06], but got 0"),
    ("capacity < 0", edited("capacity_kwh = 250.0", "capacity_kwh = -5.0"),
     "battery[1].capacity_kwh", "expected a value in (0, 1e+06], but got -5.0"),
    ("v_nom 0", edited("soc0 = 0.60", "soc0 = 0.60\nv_nom = 0"), "battery[1].v_nom",
     "expected a value in (0, 10000], but got 0"),
    ("r < 0", edited("soc0 = 0.60", "soc0 = 0.60\nr_internal = -0.1"), "battery[1].r_internal",
     "expected a value in [0, 100], but got -0.1"),
    ("m = -1", edited("m = 0.10", "m = -1"), "battery[1].m",
     "expected a value in [0, 100], but got -1"),
    ("alpha huge", edited("alpha = 0.0040", "alpha = 1e300"), "battery[1].alpha",
     "expected a value in (0, 100], but got 1e+300"),
    ("p_max beyond the frame", edited("p_max = 120.0", "p_max = 400.0"), "battery[1].p_max",
     "expected a value in [-327.67, 327.67], but got 400.0"),
    ("soc0 nan", edited("soc0 = 0.60", "soc0 = nan"), "battery[1].soc0",
     "expected a number, but got nan"),
    ("idle MC", edited("beta = 0.20", "beta = 100.0").replace("m = 0.10", "m = 0.5", 1),
     "battery[1].beta", "expected an idle marginal cost β·(1+m) within ±128 cu/kWh"),
    ("price after the end", edited("rho = 0.8", "rho = 0.8\n\n[[price]]\nt = 25.0\nrho = 1.0"),
     "price[2].t", "expected a time before the scenario's end (duration = 20 s), but got 25"),
    ("price at the end", edited("rho = 0.8", "rho = 0.8\n\n[[price]]\nt = 20.0\nrho = 1.0"),
     "price[2].t", "expected a time before the scenario's end"),
    ("too many samples", edited("duration = 20.0", "duration = 90000.0"), "duration",
     "expected at most 1e+07 agent-samples (graph.agents × duration / ts = 4 × 90000 / 0.01)"),
    ("duration inf", edited("duration = 20.0", "duration = inf"), "duration",
     "expected a number, but got inf"),
]


@pytest.mark.parametrize(("text", "key", "says"), [b[1:] for b in BAD_SCENARIOS],
                         ids=[b[0] for b in BAD_SCENARIOS])
def test_physically_impossible_scenarios_are_exit_2(text: str, key: str, says: str,
                                                    tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """capacity_kwh = 0 and v_nom = 0 crashed the plant (ZeroDivisionError), a negative
    capacity was taken, m = -1 ran to a wrong cost: each is refused before anything runs."""
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert main(["case", str(path), "--out", str(tmp_path / "o"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bess-ded: error: {path}: [{key}] {says}"), err
    assert err.count("\n") == 1 and not (tmp_path / "o").exists()


@pytest.mark.parametrize("blob", [b"\xff\xfe\x00garbage", CASE1.encode() + b"\n# \xc3\x28\n",
                                  b"ts = 0.01\n\x00\x01\x02"])
def test_binary_bytes_in_a_scenario_are_exit_2(blob: bytes, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """Was a UnicodeDecodeError traceback."""
    path = tmp_path / "bin.toml"
    path.write_bytes(blob)
    assert main(["case", str(path), "--out", str(tmp_path / "o"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bess-ded: error: {path}: [file] expected ") and \
        err.count("\n") == 1, err


def test_binary_bytes_in_an_agent_config_are_exit_2(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "agent_1.toml"
    path.write_bytes(b"[agent]\nid = 1\n\xff\xff\n")
    assert agent_main.main(["--config", str(path), "--insecure"]) == 2
    err = capsys.readouterr().err
    assert f"error: {path}: [file] expected a UTF-8 text file, but byte 15 is 0xff, not text" in err


def test_the_bundled_scenarios_still_load() -> None:
    from sim.model.scenario import SCENARIO_DIR, load_scenario

    for path in sorted(SCENARIO_DIR.glob("case*.toml")):
        assert load_scenario(path).n >= 1


# --------------------------------------------------------------------------- logs and analyze

@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Case 1 for 8 s (converged to the tolerance) on the virtual bus (simulated clock):
    a run.log, its keys."""
    from dataclasses import replace

    from sim.model.scenario import load_case
    from sim.run import busrun

    out = tmp_path_factory.mktemp("run")
    busrun.run_in_process(replace(load_case(1), duration=8.0), out, duration=8.0,
                          channel="inputs-clean")
    return out


def analyze(log: Path, out: Path, *extra: str) -> tuple[int, dict]:
    import json

    rc = main(["analyze", str(log), "--case", "1", "--out", str(out), "--no-plot", *extra])
    return rc, (json.loads((out / "metrics.json").read_text()) if rc != 2 else {})


def damaged(run_dir: Path, tmp_path: Path, lines: list[str], tail: str = "") -> Path:
    """The run's log with ``lines`` inserted after its 100th line and ``tail`` appended
    without a newline; with the run's keys beside it, as `up` leaves them."""
    import shutil

    text = (run_dir / "run.log").read_text().splitlines(keepends=True)
    d = tmp_path / "d"
    d.mkdir()
    shutil.copytree(run_dir / "keys", d / "keys")
    (d / "run.log").write_text("".join(text[:100] + [ln + "\n" for ln in lines] + text[100:])
                               + tail)
    return d / "run.log"


def test_damaged_lines_are_skipped_counted_and_reported(
        run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A NaN timestamp (was dropped without a word), garbage, bytes that are not text, an
    odd hex digit and a last line cut off (made the whole log unreadable): each skipped,
    counted by cause in metrics.json and warned about in the summary; the rest of the
    log gives the verdict the clean log gives."""
    rc0, clean = analyze(run_dir / "run.log", tmp_path / "clean")
    log = damaged(run_dir, tmp_path, ["(nan) inputs-clean 010#0000000000000000 R",
                                      "(inf) inputs-clean 010#0000000000000000 R",
                                      "this is not a frame", "(1.5) inputs-clean 010#ABC R"],
                  tail="(2.99) inputs-clean 10")
    text = log.read_bytes().replace(b"this is not a frame", b"\xff\xfe not text")
    log.write_bytes(text)
    capsys.readouterr()
    rc, m = analyze(log, tmp_path / "a")
    out = capsys.readouterr().out
    assert rc == rc0 == 0
    assert m["log_lines_skipped"] == {"bad_timestamp": 2, "not_text": 1, "malformed": 1,
                                      "truncated": 1}
    assert m["frames_recorded"] == clean["frames_recorded"]
    assert m["anomalies"] == clean["anomalies"] == []
    assert ("  warning: skipped 5 log line(s) that hold no frame: 2 with a timestamp that is "
            "not a finite number; 1 not in candump -L format; 1 with bytes that are not text; "
            "1 truncated last line (no newline at the end: the capture was cut off)") in out


def test_a_far_future_timestamp_is_reported_and_the_log_still_analysed(
        run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """One frame stamped 31 years on (and a price frame at a far-past time) tried to
    allocate a Ts grid of 5.8 TiB: they are left out and listed, the rest is analysed."""
    lines = (run_dir / "run.log").read_text().splitlines()
    price = next(ln for ln in lines if " 010#" in ln)
    late = "(1000000000.000000)" + price.split(")", 1)[1]
    early = "(-1000000000.000000)" + price.split(")", 1)[1]
    rc0, clean = analyze(run_dir / "run.log", tmp_path / "clean")
    capsys.readouterr()
    rc, m = analyze(damaged(run_dir, tmp_path, [late, early]), tmp_path / "a")
    out = capsys.readouterr().out
    assert rc == rc0 == 0
    assert m["timestamp_outliers"] == [-1e9, 1e9]
    assert m["final_error"] == clean["final_error"] and m["frames_recorded"] == \
        clean["frames_recorded"]
    assert ("warning: left out 2 frame(s) whose timestamp lies more than 360000 Ts away from "
            "the rest of the recording (t = -1000000000.000000, 1000000000.000000)") in out


def test_a_log_too_long_to_analyse_is_exit_2(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Frames every 50 s for 3 days (no gap long enough to be an outlier): refused with
    the bound, not by exhausting memory."""
    log = tmp_path / "long.log"
    log.write_text("".join(f"({t:.6f}) vcan0 010#0000000000000000\n"
                           for t in range(0, 3 * 86400, 50)))
    assert main(["analyze", str(log), "--case", "1", "--out", str(tmp_path / "a"),
                 "--no-plot"]) == 2
    err = capsys.readouterr().err
    assert "[log] expected a recording of at most 1e+07 agent-samples (4 agents × its span " \
        "/ Ts = 0.01 s), but it spans 259150 s from the first price" in err


@pytest.mark.parametrize(("content", "says"), [
    (b'{"ticks": 12, "counters": {"deadl', "expected the JSON a node writes with "
     "--counters-json, but got unreadable JSON (Unterminated string"),
    (b"\xff\xfe", "but got unreadable JSON ('utf-8' codec can't decode"),
    (b"[1, 2]", 'expected an object with "ticks": N and "counters": {name: N} (N integers ≥ '
     '0), but got [1, 2]'),
    (b'{"ticks": -1}', 'but got {"ticks": -1}'),
    (b'{"counters": {"deadline_miss": "many"}}', "but got {\"counters\": {\"deadline_miss\""),
])
def test_a_bad_counters_json_is_exit_2(content: bytes, says: str, run_dir: Path,
                                       tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    """A truncated counters JSON was a JSONDecodeError traceback."""
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "plant.counters.json").write_bytes(content)
    assert main(["analyze", str(run_dir / "run.log"), "--case", "1", "--counters",
                 str(tmp_path / "c"), "--out", str(tmp_path / "a"), "--no-plot"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bess-ded: error: {tmp_path / 'c' / 'plant.counters.json'}: "
                          "[--counters] ") and says in err and err.count("\n") == 1, err


# --------------------------------------------------------------------------- key files

def key_set(tmp_path: Path) -> Path:
    keys = tmp_path / "keys"
    assert main(["keys", "--fleet", "--case", "1", "--out", str(keys)]) == 0
    return keys


def bump_boot(path: Path, boot: int) -> None:
    from firmware_py import secoc

    k = secoc.load_node_key(path)
    import tomli_w

    secoc.write_private(path, secoc.KEY_FILE_HEADER + tomli_w.dumps(
        secoc.node_key_document(k.node, k.key, k.fleet_id, boot, k.peers, k.floors,
                                k.frames)))


def test_up_checks_every_key_file_before_starting_a_node(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A node refusing its key file (boot counter exhausted, a peer's key missing) made
    `up` exit 2 or 1 "not converged" depending on timing: now every file is checked
    before anything starts, exit 2 naming the file and the cause; no run directory."""
    import shutil

    import tomli_w

    from firmware_py import secoc

    keys = key_set(tmp_path)
    out = tmp_path / "o"
    capsys.readouterr()

    def up() -> str:
        assert main(["up", "--case", "1", "--keys", str(keys), "--out", str(out)]) == 2
        assert not out.exists()
        err = capsys.readouterr().err
        assert err.startswith("bess-ded: error: --keys: expected ") and err.count("\n") == 1
        return err

    saved = tmp_path / "saved"
    shutil.copytree(keys, saved)
    bump_boot(keys / "agent_3.key", secoc.DEFAULT_LAYOUT.max_boot)
    assert (f"agent_3.key with a boot counter below {secoc.DEFAULT_LAYOUT.max_boot}"
            f" (each start uses the next; re-provision with bess-ded keys --fleet ... --force),"
            f" but got '{secoc.DEFAULT_LAYOUT.max_boot}, exhausted'") in up()

    shutil.copy2(saved / "agent_3.key", keys / "agent_3.key")
    k = secoc.load_node_key(keys / "agent_2.key")
    secoc.write_private(keys / "agent_2.key", secoc.KEY_FILE_HEADER + tomli_w.dumps(
        secoc.node_key_document(k.node, k.key, k.fleet_id, 0,
                                {p: v for p, v in k.peers.items() if p != "agent_1"},
                                None, k.frames)))
    assert ("agent_2.key with the keys of the nodes it receives from (router, "
            "agent_1), but got 'none for agent_1'") in up()
    secoc.write_private(keys / "agent_2.key", secoc.KEY_FILE_HEADER + tomli_w.dumps(
        secoc.node_key_document(k.node, k.key, k.fleet_id, 0, k.peers, None,
                                {f: v for f, v in k.frames.items() if f != "PLANT_2_Status"})))
    assert ("agent_2.key with the keys of its link frames and reports (AUTH-28, AUTH-29: "
            "AGENT_2_Setpoint, PLANT_2_Status, AGENT_2_Diag), but got 'none for "
            "PLANT_2_Status'") in up()

    shutil.copy2(saved / "agent_2.key", keys / "agent_2.key")
    (keys / "plant.key").unlink()
    assert "a key set with plant.key" in up()

    shutil.copy2(saved / "plant.key", keys / "plant.key")
    keys.chmod(0o755)
    assert f"a directory only its owner may access (chmod 700 {keys}), but got " \
        f"'{keys} with mode 0755'" in up()


def test_a_key_file_through_a_symlink_is_refused(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Key directories' permissions are checked, so a link out of one is refused, not
    followed (docs/security.md): by the loader, `up --keys` and the agent's --key."""
    from firmware_py import secoc

    keys = key_set(tmp_path)
    elsewhere = tmp_path / "elsewhere.key"
    (keys / "agent_1.key").rename(elsewhere)
    (keys / "agent_1.key").symlink_to(elsewhere)
    with pytest.raises(secoc.KeyFileError, match="expected the node key file itself, but got "
                       "a symbolic link"):
        secoc.load_node_key(keys / "agent_1.key")
    capsys.readouterr()
    assert main(["up", "--case", "1", "--keys", str(keys), "--out", str(tmp_path / "o")]) == 2
    assert "a symbolic link" in capsys.readouterr().err
    cfg = tmp_path / "agent_1.toml"
    from firmware_py.config import agent_configs_from_scenario
    from sim.model.scenario import load_case

    cfg.write_text(agent_configs_from_scenario(load_case(1))[0].to_toml())
    assert agent_main.main(["--config", str(cfg), "--key", str(keys / "agent_1.key"),
                            "--interface", "virtual"]) == 2
    assert "a symbolic link" in capsys.readouterr().err
    assert secoc.load_node_key(elsewhere).boot_counter == 0  # nothing written through it


def test_a_scenario_its_agents_would_refuse_is_exit_2(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    """λ(0) = 50 passed the scenario's own range but not the agent's limits: `up` then
    lost that node at its start. Every agent's configuration is loaded as the node would."""
    path = tmp_path / "l50.toml"
    path.write_text(edited("lambda0 = 0.3 ", "lambda0 = 50.0 "))
    assert main(["case", str(path), "--out", str(tmp_path / "o"), "--no-plots"]) == 2
    assert capsys.readouterr().err == (
        f"bess-ded: error: {path}: [agent 1] expected values agent 1's configuration takes, "
        "but its [agent.lambda0] expected a value inside limits [-10.0, 10.0], but got 50.0\n")


def test_every_bundled_variant_writes_configs_its_agents_accept() -> None:
    """Case 3's k = 10 derived k_max = 20, beyond what SET_GAINS carries (16.383): the
    agent refused the file `up` wrote. The default bound is capped there."""
    import tomllib

    from firmware_py.config import GAIN_MAX, agent_configs_from_scenario, parse_agent_config
    from sim.model.scenario import load_case

    for label, sc in load_case(3).runs():
        for cfg in agent_configs_from_scenario(sc):
            back = parse_agent_config(tomllib.loads(cfg.to_toml()), label)
            assert back.k_max == min(2 * sc.controller.k, GAIN_MAX)


def test_a_time_scale_the_controller_cannot_take_is_exit_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["up", "--case", "1", "--time-scale", "200", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "[time_scale] expected a factor that keeps the controller valid (Ts·F ≤ 1 s: F ≤ " \
        "100 here), but got 200" in err and err.count("\n") == 1


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".csv", ".db", ".txt"])
def test_a_garbage_log_of_any_format_is_exit_2(suffix: str, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """python-can's readers fail each its own way (struct.error, sqlite3.DatabaseError,
    UnicodeDecodeError): all are the one-line error."""
    log = tmp_path / f"g{suffix}"
    log.write_bytes(b"\x00\xffgarbage\nmore,1,2\n")
    assert main(["analyze", str(log), "--case", "1", "--out", str(tmp_path / "a"),
                 "--no-plot"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bess-ded: error: {log}: [LOG] expected a CAN log python-can "
                          "reads, but got: ") and err.count("\n") == 1, err


def test_a_bus_silent_for_minutes_is_judged_whole_not_left_out(
        run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Only stamps an hour (at Ts = 10 ms) off the rest are outliers: a fleet whose bus
    stalled for two minutes is analysed whole, and the stall is an anomaly."""
    lines = (run_dir / "run.log").read_text().splitlines()
    half = len(lines) // 2

    def shifted(line: str) -> str:
        t, rest = line[1:].split(")", 1)
        return f"({float(t) + 120:.6f}){rest}"

    log = tmp_path / "stalled.log"
    log.write_text("\n".join(lines[:half] + [shifted(x) for x in lines[half:]]) + "\n")
    rc, m = analyze(log, tmp_path / "a")
    assert m["timestamp_outliers"] == [] and m["frames_recorded"] == len(lines)
    assert rc != 0 and {"bus_silence", "node_silent"} & {a["kind"] for a in m["anomalies"]}
