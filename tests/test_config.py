"""Agent configuration files: round trip, and a bad file stops the start naming the key."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from dataclasses import replace
from pathlib import Path

import pytest

from firmware_py.config import agent_configs_from_scenario, load_agent_config
from firmware_py.errors import ConfigError
from sim.model.scenario import load_case, scaled


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "agent.toml"
    p.write_text(text)
    return p


def good_text() -> str:
    return agent_configs_from_scenario(load_case(1))[1].to_toml()


def test_round_trip(tmp_path: Path) -> None:
    cfg = agent_configs_from_scenario(load_case(1))[1]
    back = load_agent_config(write(tmp_path, cfg.to_toml()))
    assert back.id == 2 and back.neighbours == cfg.neighbours
    assert back.controller == cfg.controller and back.battery == cfg.battery
    assert back.price_timeout_s == pytest.approx(0.25)
    assert back.status_timeout_s == pytest.approx(0.25) and back.fleet_size == 4


@pytest.mark.parametrize("index", [0, 1])
def test_round_trip_is_exact_through_tomli_w(tmp_path: Path, index: int) -> None:
    """Every field (floats by repr, neighbours, timeouts, fleet size) reads back equal."""
    cfg = agent_configs_from_scenario(scaled(load_case(7), 3))[index]
    text = cfg.to_toml()
    back = load_agent_config(write(tmp_path, text))
    assert replace(back, source=cfg.source) == cfg
    assert tomllib.loads(text)["timeouts"]["status_s"] == cfg.status_timeout_s
    lone = replace(cfg, neighbours=(), fleet_size=None)
    assert replace(load_agent_config(write(tmp_path, lone.to_toml())), source=cfg.source) == lone


def test_old_config_without_fleet_size_or_status_s_still_loads(tmp_path: Path) -> None:
    """fleet_size is optional (unknown: foreign IDs not checked); status_s and price_s
    default to 5 cycles of their frame at the file's Ts."""
    text = good_text().replace("fleet_size = 4\n", "").replace("status_s = 0.25\n", "")
    text = text.replace("price_s = 0.25\n", "").replace("ts = 0.01", "ts = 0.02")
    cfg = load_agent_config(write(tmp_path, text))
    assert cfg.fleet_size is None
    assert cfg.status_timeout_s == pytest.approx(0.5) == cfg.price_timeout_s


@pytest.mark.parametrize(("old", "new", "key"), [
    ("id = 2", "id = 65", "agent.id"),
    ("id = 2", 'id = "two"', "agent.id"),
    ("k = 1.0", "k = -1.0", "controller.k"),
    ("ts = 0.01", "ts = 0.0", "controller.ts"),
    ('kind = "reset"', 'kind = "fuzzy"', "controller.kind"),
    ("alpha = 0.005", "alpha = 0.0", "battery.alpha"),
    ("p_max = 100.0", "p_max = 1000.0", "battery.p_max"),
    ("[timeouts]", "[timeouts]\nbogus = 1", "timeouts.bogus"),
    ("lambda0 = 0.6", "lambda0 = 50.0", "agent.lambda0"),
    ("[[neighbour]]\nid = 1", "[[neighbour]]\nid = 2", "neighbour[1].id"),
    ("fleet_size = 4", "fleet_size = 1", "agent.fleet_size"),
    ("fleet_size = 4", "fleet_size = 65", "agent.fleet_size"),
    ("status_s = 0.25", "status_s = 0.0", "timeouts.status_s"),
    ("ts = 0.01", "ts = 1.5", "controller.ts"),          # Ts in (0, 1] s
    ("k = 1.0", "k = 250.0", "controller.k·ts"),         # k·Ts = 2.5: not Q1.30
    ("k_max = 2.0", "k_max = 16.0", "limits.k_max"),     # with ts = 0.2 (below)
])
def test_bad_config_names_the_key(tmp_path: Path, old: str, new: str, key: str) -> None:
    text = good_text()
    if key == "limits.k_max":   # k_max·ts = 3.2 ≥ 2 while k·ts = 0.2 is fine
        text = text.replace("ts = 0.01", "ts = 0.2")
    assert old in text
    with pytest.raises(ConfigError) as e:
        load_agent_config(write(tmp_path, text.replace(old, new, 1)))
    assert f"[{key}]" in str(e.value) and "agent.toml" in str(e.value)


def test_default_gain_bound_that_does_not_fit_q30_is_named(tmp_path: Path) -> None:
    """k·ts = 1.5 fits Q1.30, but the default k_max = 2·k gives k_max·ts = 3: SET_GAINS
    could not set it, so the file is refused naming limits.k_max and the default."""
    text = good_text().replace("ts = 0.01", "ts = 0.5").replace("k = 1.0", "k = 3.0")
    text = text.replace("h = 2.0", "h = 1.0")
    text = "\n".join(line for line in text.splitlines()
                     if not line.startswith(("k_max", "k_min", "h_max", "h_min")))
    with pytest.raises(ConfigError) as e:
        load_agent_config(write(tmp_path, text))
    msg = str(e.value)
    assert "[limits.k_max]" in msg and "the default 2·k" in msg and "k_max·ts = 3" in msg


def test_not_toml_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"\[file\] expected valid TOML"):
        load_agent_config(write(tmp_path, "[agent\nid = 1"))
    with pytest.raises(ConfigError, match="does not exist"):
        load_agent_config(tmp_path / "nope.toml")


def test_agent_node_refuses_a_bad_config(tmp_path: Path) -> None:
    path = write(tmp_path, good_text().replace("h = 2.0", "h = 0.0"))
    r = subprocess.run([sys.executable, "-m", "firmware_py", "--config", str(path),
                        "--insecure"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "[controller.h]" in r.stderr and "Traceback" not in r.stderr
