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
    (["inject", "forge", "--target", "33"], "--target", "an agent number in 1..32, but got 33"),
    (["inject", "forge", "--rate", "0"], "--rate",
     "a finite number > 0 and ≤ 1e+06, but got 0"),
    (["inject", "forge", "--seed", "-1"], "--seed", "an integer ≥ 0, but got -1"),
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
