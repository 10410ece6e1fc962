"""A newcomer's first hour (issue 20): one spelling for each flag and one way to name a
scenario in every command, "did you mean" for mistypes, variants by any case,
`bess-ded deploy` writing a fleet's files without running it, and a failed `up` that
leaves an earlier run in the same directory as it was."""

from __future__ import annotations

import hashlib
import json
import os
import tomllib
from pathlib import Path

import pytest

from firmware_py import secoc
from sim.cli import build_parser, main


def _sub(command: str):  # type: ignore[no-untyped-def]
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sub.choices[command]  # type: ignore[attr-defined]


# --------------------------------------------------------------------------- spellings


@pytest.mark.parametrize("command", ["up", "restbus", "conformance", "deploy", "analyze",
                                     "keys", "plant", "router"])
def test_every_command_names_its_scenario_with_case_and_scenario_as_alias(
        command: str) -> None:
    options = {o: a.dest for a in _sub(command)._actions for o in a.option_strings}
    assert options["--case"] == options["--scenario"] == "case"


@pytest.mark.parametrize("command", ["case", "compare"])
def test_case_and_compare_take_case_as_operand_or_option(
        command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = ["--out", str(tmp_path / "o")] + (["--no-plot"] if command == "case" else [])
    assert main([command, "--case", "1", *out]) == 0
    assert (tmp_path / "o" / ("metrics.json" if command == "case" else "compare.json")).is_file()
    capsys.readouterr()
    assert main([command, "1", "--case", "2", *out]) == 2
    assert "CASE: expected one scenario, as CASE or --case CASE" in capsys.readouterr().err
    assert main([command, *out]) == 2
    assert "but got 'none'" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["case", "up", "restbus", "analyze"])
def test_no_plot_is_one_flag_with_no_plots_as_alias(command: str) -> None:
    options = {o: a.dest for a in _sub(command)._actions for o in a.option_strings}
    assert options["--no-plot"] == options["--no-plots"] == "no_plot"


def test_case_with_no_plots_alias_writes_no_figure(tmp_path: Path) -> None:
    assert main(["case", "1", "--no-plots", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "metrics.json").is_file() and not list(tmp_path.glob("*.png"))


@pytest.mark.parametrize(("argv", "hint"), [
    (["cse", "1"], "(did you mean 'case'?)"),
    (["conformence", "--case", "1"], "(did you mean 'conformance'?)"),
    (["case", "1", "--no-plotz"], "('--no-plotz': did you mean '--no-plot'?)"),
    (["up", "--case", "1", "--druation", "3"], "('--druation': did you mean '--duration'?)"),
    (["case", "1", "--controller", "rest"], "(did you mean 'reset'?)"),
    (["case", "1", "--controller", "PC"], "(did you mean 'pc'?)"),
])
def test_a_mistype_gets_a_suggestion_on_one_line(argv: list[str], hint: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: error: ") and err.count("\n") == 1, err
    assert hint in err


def test_variant_names_ignore_case(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from sim.model.scenario import load_case
    from sim.model.scenario_select import pick_variant

    sc = load_case(2)
    labels = [v.label for v in sc.variants]
    assert labels == ["reset-PI", "PC", "finite-time"]
    lower, name = pick_variant(sc, "pc")
    assert name == " [variant PC]" and lower == sc.variant("PC")
    with pytest.raises(Exception, match="expected one of"):
        sc.variant("nope")


# --------------------------------------------------------------------------- keys -h


def test_keys_help_says_what_uses_the_keys(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["keys", "-h"]) == 0
    text = capsys.readouterr().out
    assert "Nothing uses the keys yet" not in text
    assert "--keys" in text and "--key DIR/agent_3.key" in text


# --------------------------------------------------------------------------- deploy


def test_deploy_writes_every_node_file_and_runs_nothing(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "plan"
    assert main(["deploy", "--case", "2", "--variant", "pc", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    agents = sorted(p.name for p in (out / "agents").iterdir())
    assert agents == [f"agent_{i}.toml" for i in range(1, 5)]
    cfg = tomllib.loads((out / "agents" / "agent_3.toml").read_text())
    assert cfg["controller"]["kind"] == "pc"   # the variant chosen, by any case
    assert (out / "scenario.toml").is_file()
    nodes = {p.stem for p in (out / "keys").glob("*.key")}
    assert nodes == {"master", "plant", "router", *(f"agent_{i}" for i in range(1, 5))}
    assert oct(os.stat(out / "keys").st_mode & 0o777) == "0o700"
    own = secoc.load_node_key(out / "keys" / "agent_3.key")
    assert own.node == "agent_3" and own.boot_counter == 0   # no node ever ran with it
    assert not (out / "run.log").exists() and not (out / "logs").exists()
    assert f"bess-ded agent --config {out}/agents/agent_3.toml --key {out}/keys/agent_3.key " \
        "--rt-priority 10" in text
    assert f"bess-ded router --case {out}/scenario.toml" in text
    # a second deploy keeps the key set unless --force
    before = (out / "keys" / "agent_3.key").read_bytes()
    assert main(["deploy", "--case", "2", "--out", str(out)]) == 2
    assert "already holds a key set" in capsys.readouterr().err
    assert (out / "keys" / "agent_3.key").read_bytes() == before
    assert main(["deploy", "--case", "2", "--out", str(out), "--force"]) == 0
    assert (out / "keys" / "agent_3.key").read_bytes() != before


def test_deploy_with_a_key_set_or_insecure_writes_no_keys(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["keys", "--fleet", "--case", "1", "--out", str(tmp_path / "k")]) == 0
    assert main(["deploy", "--case", "1", "--keys", str(tmp_path / "k"), "--out",
                 str(tmp_path / "a")]) == 0
    assert f"--key {tmp_path}/k/agent_1.key" in capsys.readouterr().out
    assert not (tmp_path / "a" / "keys").exists()
    assert main(["deploy", "--case", "1", "--insecure", "--out", str(tmp_path / "b")]) == 0
    assert "--insecure" in capsys.readouterr().out and not (tmp_path / "b" / "keys").exists()
    assert main(["deploy", "--case", "1", "--keys", str(tmp_path / "none"), "--out",
                 str(tmp_path / "c")]) == 2
    assert not (tmp_path / "c").exists()


# --------------------------------------------------------------------------- failed up


def _digest(d: Path) -> dict[str, str]:
    """Every file's content and every directory (a new empty one counts too)."""
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest()
            if p.is_file() else "dir" for p in sorted(d.rglob("*"))}


@pytest.mark.parametrize("own_keys", [False, True])
def test_a_failed_up_leaves_the_earlier_run_intact(own_keys: bool, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """A bad --interface (exit 2) fails before `up` writes anything: the earlier run's
    outputs and its key set (fresh per run in OUT/keys, or --keys DIR with its boot
    counters) are byte for byte what they were."""
    out = tmp_path / "run"
    assert main(["deploy", "--case", "1", "--out", str(out)]) == 0
    (out / "metrics.json").write_text(json.dumps({"an": "earlier run"}))
    (out / "run.log").write_text("(0.0) vcan0 123#00\n")
    before = _digest(tmp_path)
    keys = ["--keys", str(out / "keys")] if own_keys else []
    capsys.readouterr()
    assert main(["up", "--case", "1", "--out", str(out), "--interface", "nosuchbus",
                 *keys]) == 2
    assert "cannot open CAN bus" in capsys.readouterr().err
    assert _digest(tmp_path) == before


def test_a_command_whose_module_is_missing_is_listed_and_fails_loudly(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Expected: a listed command without its module is not skipped silently: -h lists
    it as unavailable, using it exits 2 with `bess-ded: error:` naming the import
    error, and the other commands still parse."""
    import sim.cli as cli

    monkeypatch.setattr(cli, "COMMANDS", (*cli.COMMANDS, "no_such_command"))
    assert cli.main(["-h"]) == 0
    assert "no_such_command" in capsys.readouterr().out
    assert cli.main(["no_such_command"]) == 2
    err = capsys.readouterr().err
    assert "bess-ded: error:" in err and "no_such_command" in err
    assert "ModuleNotFoundError" in err
    assert cli.main(["keys", "-h"]) == 0
