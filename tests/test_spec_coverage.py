"""The MUSTs of docs/firmware-spec.md that no other test pins exactly (section 16).

Each test's docstring names the requirement IDs it covers. Deterministic: fixed
timestamps, a simulated clock for the run loop, no wall-clock rates."""

from __future__ import annotations

import copy
import inspect
import random
import re
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest
import tomli_w

from firmware_py import contract
from firmware_py import fixedpoint as fx
from firmware_py.config import agent_configs_from_scenario, parse_agent_config
from firmware_py.controllers import (
    ControllerConfig,
    FixedArithmetic,
    consensus_error,
    make_controller,
)
from firmware_py.errors import ConfigError, ParameterError
from firmware_py.frames import FrameCodec, mc_name, status_name, target_raw
from firmware_py.node import run_node
from firmware_py.nodeio import FleetSender
from firmware_py.runtime import AgentRuntime, State
from firmware_py.secoc import (
    KEY_FILE_HEADER,
    Keyring,
    derive_command_key,
    derive_frame_key,
    derive_node_key,
    fleet_id,
    node_key_document,
    write_private,
)
from sim.model.scenario import load_case, scaled
from sim.testkit.tester import fleet_keys

CODEC = FrameCodec()
SENDER = FleetSender(CODEC)  # the other nodes, --insecure: boot 1, no sync needed


@pytest.fixture(autouse=True)
def _fresh_senders() -> None:
    SENDER.reset_counts()
    SENDER.boot = 1


def base() -> dict[str, Any]:
    """Agent 2 of case 1 as a TOML document (a dict to edit)."""
    return tomllib.loads(agent_configs_from_scenario(load_case(1))[1].to_toml())


def parse(doc: dict[str, Any]) -> Any:
    return parse_agent_config(doc, "agent.toml")


def refused(doc: dict[str, Any], key: str) -> str:
    with pytest.raises(ConfigError) as e:
        parse(doc)
    assert f"[{key}]" in str(e.value), str(e.value)
    return str(e.value)


def status_frame(agent: int, fault: int = 0) -> can.Message:
    return SENDER.frame(status_name(agent), {
        "FaultOverCurrent": fault, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
        "Power": 0.0, "Soc": 50.0}, phys=True)


def price_frame(rho: float) -> can.Message:
    return SENDER.frame("ER_Price", {"PriceValid": 1, "Rho": fx.to_fixed(rho), "Segment": 0})


def mc_frame(agent: int, lam_raw: int, state: int = 1) -> can.Message:
    return SENDER.frame(mc_name(agent), {"State": state, "Lambda": lam_raw, "Resets": 0})


def command(cmd: int, target: int) -> can.Message:
    return SENDER.frame("ER_Command", {"Command": cmd, "Target": target_raw(target), "GainK": 0,
                                       "GainH": 0})


def running(doc: dict[str, Any], rho: float = 0.8) -> AgentRuntime:
    """An agent of ``doc`` with a fresh status and price at t = 0 (RUNNING at its first
    tick)."""
    a = AgentRuntime(parse(doc), CODEC)
    a.on_frame(status_frame(a.cfg.id), 0.0)
    a.on_frame(price_frame(rho), 0.0)
    return a


def diag(a: AgentRuntime, signal: str) -> int:
    """``signal`` as the agent's Diag page that carries it would send it now."""
    (page,) = [k for k, sigs in enumerate(a.DIAG_PAGES) if signal in sigs]
    raw = CODEC.decode(a._diag_frame(page)).raw
    assert raw["Page"] == page
    return raw[signal]


# --------------------------------------------------------------------------- numbers


def test_mulq_rounds_ties_toward_plus_infinity() -> None:
    """NUM-2: mulq = (a·b + 2^23) >> 24, ties toward +∞ (not away from zero, not to
    even), exact product, floor shift; the spec's examples, and the same ties inside ξ."""
    assert fx.mul(3, 1 << 23) == 2 and fx.mul(-3, 1 << 23) == -1
    assert fx.mul(167772, 1 << 21) == 20972 and fx.mul(-167772, 1 << 21) == -20971
    assert fx.mul(5, 1 << 23) == 3 and fx.mul(-5, 1 << 23) == -2   # not to even (2, -2)
    assert fx.mul(1, 1 << 23) == 1 and fx.mul(-1, 1 << 23) == 0    # not away from zero
    big = (1 << 31) - 1
    assert fx.mul(big, (1 << 32) - 1) == (big * ((1 << 32) - 1) + (1 << 23)) >> 24  # exact
    assert fx.mul(fx.ONE, -12345) == -12345
    ar = FixedArithmetic()
    half = 1 << 23    # a weight of 0.5
    # ξ = mulq(W, Λ − λ_j): Λ − λ_j = ±3 LSB gives ±1.5 → 2 and −1
    assert consensus_error(ar, 10, [(half, 7)], 0, 0) == (2, False)
    assert consensus_error(ar, 7, [(half, 10)], 0, 0) == (-1, False)
    # two individually rounded terms: −1.5 → −1 each, the sum −2 (not rne(−3) = −3 or −4)
    assert consensus_error(ar, 7, [(half, 10), (half, 10)], 0, 0) == (-2, False)


def test_q24_and_q30_round_ties_to_even() -> None:
    """NUM-4 (and NUM-6's ties): configuration values go through q24 = rne(x·2^24), ties
    to even, unlike mulq; exact ties; a value outside int32 is a ParameterError; the
    limits and weights an agent starts with are q24 of its configuration."""
    assert fx.to_fixed(0.01) == 167772 and fx.to_fixed(1e-4) == 1678
    assert fx.to_fixed(0.8) == 13421773
    assert fx.to_fixed(2.5 * 2.0 ** -24) == 2 and fx.to_fixed(3.5 * 2.0 ** -24) == 4
    assert fx.to_fixed(-2.5 * 2.0 ** -24) == -2 and fx.to_fixed(-3.5 * 2.0 ** -24) == -4
    assert fx.to_fixed(0.5 * 2.0 ** -24) == 0 and fx.to_fixed(1.5 * 2.0 ** -24) == 2
    assert fx.to_q30(2.5 * 2.0 ** -30) == 2 and fx.to_q30(3.5 * 2.0 ** -30) == 4
    with pytest.raises(ParameterError):
        fx.to_fixed(128.0)
    assert fx.to_fixed(-128.0) == -(1 << 31)
    doc = base()
    doc["limits"].update(lambda_min=-2.5 * 2.0 ** -24 - 1, lambda_max=1 + 2.5 * 2.0 ** -24,
                         rho_max=3.5 * 2.0 ** -24 + 2)
    a = AgentRuntime(parse(doc), CODEC)
    assert a.lam_min == -(1 << 24) - 2 and a.lam_max == (1 << 24) + 2
    assert a.rho_max == (2 << 24) + 4


# --------------------------------------------------------------------------- configuration


def test_unknown_table_is_refused_naming_it() -> None:
    """CFG-1: only agent, controller, neighbour, battery, timeouts, limits; timeouts and
    limits optional."""
    doc = base()
    doc["plant"] = {"x": 1}
    msg = refused(doc, "plant")
    assert "unknown table" in msg
    doc = base()
    del doc["timeouts"], doc["limits"]
    assert parse(doc).id == 2
    for table in ("agent", "controller", "battery"):
        doc = base()
        del doc[table]
        refused(doc, table)
    doc = base()
    doc["neighbour"] = {"id": 1}
    refused(doc, "neighbour")


def test_agent_table_rules() -> None:
    """CFG-2: id 1..64 (the DBC's agents) required; lambda0 in [−100, 100] required and
    strictly inside (lambda_min, lambda_max); pinned boolean, default false; fleet_size
    id..64, optional."""
    for key in ("id", "lambda0"):
        doc = base()
        del doc["agent"][key]
        refused(doc, f"agent.{key}")
    for ident, ok in ((0, False), (1, True), (64, True), (65, False), (True, False)):
        doc = base()
        doc["agent"]["id"] = ident
        doc["neighbour"] = []
        doc["agent"].pop("fleet_size")
        if ok:
            assert parse(doc).id == ident
        else:
            refused(doc, "agent.id")
    doc = base()
    doc["limits"].update(lambda_min=-200.0)
    refused(doc, "limits.lambda_min")
    for lam0, ok in ((-10.0, False), (10.0, False), (-9.999, True), (9.999, True)):
        doc = base()
        doc["agent"]["lambda0"] = lam0
        if ok:
            assert parse(doc).lambda0 == lam0
        else:
            refused(doc, "agent.lambda0")
    doc = base()
    doc["limits"].update(lambda_min=-127.0, lambda_max=127.0)
    doc["agent"]["lambda0"] = 100.5
    refused(doc, "agent.lambda0")
    doc["agent"]["lambda0"] = 100
    assert parse(doc).lambda0 == 100.0
    doc = base()
    doc["agent"]["pinned"] = 1
    refused(doc, "agent.pinned")
    del doc["agent"]["pinned"]
    assert parse(doc).pinned is False
    doc = base()
    doc["agent"]["fleet_size"] = 2
    assert parse(doc).fleet_size == 2
    del doc["agent"]["fleet_size"]
    assert parse(doc).fleet_size is None


def test_neighbour_rules() -> None:
    """CFG-4: neighbour id 1..64, not the own, each at most once; weight in
    [0.001, 100], default 1.0; no neighbours is allowed."""
    doc = base()
    doc["neighbour"] = [{"id": 1, "weight": 1.0}, {"id": 3}, {"id": 1, "weight": 0.5}]
    msg = refused(doc, "neighbour")
    assert "duplicates" in msg
    for w, ok in ((0.001, True), (100, True), (0.000999, False), (100.001, False),
                  (0.0, False), (-1.0, False), ("1", False)):
        doc = base()
        doc["neighbour"] = [{"id": 1, "weight": w}]
        if ok:
            assert parse(doc).neighbours[0].weight == w
        else:
            refused(doc, "neighbour[1].weight")
    doc = base()
    doc["neighbour"] = [{"id": 65}]
    refused(doc, "neighbour[1].id")
    doc["neighbour"] = [{"id": 3}]
    assert parse(doc).neighbours[0].weight == 1.0
    doc["neighbour"] = []
    assert parse(doc).neighbours == ()
    del doc["neighbour"]
    assert parse(doc).neighbours == ()


@pytest.mark.parametrize(("key", "value", "named"), [
    ("alpha", 1e-9 * 0.99, "battery.alpha"),
    ("alpha", None, "battery.alpha"),
    ("beta", None, "battery.beta"),
    ("beta", "0.1", "battery.beta"),
    ("beta", float("inf"), "battery.beta"),
    ("m", -1e-9, "battery.m"),
    ("m", None, "battery.m"),
    ("p_min", None, "battery.p_min"),
    ("p_max", None, "battery.p_max"),
    ("p_max", 327.68, "battery.p_max"),
])
def test_battery_rules(key: str, value: Any, named: str) -> None:
    """CFG-5: alpha ≥ 1e-9, beta finite, m ≥ 0, p_min < p_max within ±327.67, all
    required; each bad value is refused naming its key."""
    doc = base()
    if value is None:
        del doc["battery"][key]
    else:
        doc["battery"][key] = value
    refused(doc, named)


def test_battery_limits_that_are_allowed_and_p_min_rules() -> None:
    """CFG-5: the edges are accepted (alpha = 1e-9 and 100, m = 0 and 100, beta ±100,
    ±327.67), beyond them refused; p_min ≥ p_max is refused naming p_max (the pair's
    second key), p_min < −327.67 naming p_min."""
    doc = base()
    doc["battery"].update(alpha=1e-9, m=0.0, beta=-100.0, p_min=-327.67, p_max=327.67)
    b = parse(doc).battery
    assert (b.alpha, b.m, b.beta, b.p_min, b.p_max) == (1e-9, 0.0, -100.0, -327.67, 327.67)
    doc["battery"].update(alpha=100.0, m=100.0, beta=1.0)
    assert parse(doc).battery.m == 100.0
    for key, value in (("alpha", 100.01), ("m", 100.01), ("beta", 100.01), ("beta", -101.0)):
        refused({**doc, "battery": {**doc["battery"], key: value}}, f"battery.{key}")
    doc["battery"].update(p_min=5.0, p_max=5.0)
    refused(doc, "battery.p_max")
    doc["battery"].update(p_min=-327.68, p_max=5.0)
    refused(doc, "battery.p_min")


def test_neighbour_periods_is_truncated_and_timeouts_are_bounded() -> None:
    """CFG-6, LIVE-2: neighbour_periods in [1, 100] truncated to an integer (3.9 → 3:
    a neighbour 3.5 periods old is not alive); price_s, status_s in [0.01, 60],
    default 5·(5·ts)."""
    doc = base()
    doc["timeouts"] = {"neighbour_periods": 3.9}
    cfg = parse(doc)
    assert cfg.neighbour_timeout_periods == 3
    assert cfg.price_timeout_s == 5 * (5 * 0.01) == cfg.status_timeout_s
    a = running(doc)
    a.on_frame(mc_frame(1, fx.to_fixed(0.6)), 0.0)
    a.tick(0.0)
    assert a.neighbours_alive == 1
    a.tick(0.035)   # 3.5 periods: alive under 3.9, not under 3
    assert a.neighbours_alive == 0 and a.counters["neighbour_timeouts"] == 1
    doc["timeouts"] = {"neighbour_periods": 4}
    b = running(doc)
    b.on_frame(mc_frame(1, fx.to_fixed(0.6)), 0.0)
    b.tick(0.0)
    b.tick(0.035)
    assert b.neighbours_alive == 1
    for key, bad in (("neighbour_periods", 0.99), ("neighbour_periods", 100.5),
                     ("price_s", 0.009), ("price_s", 60.5), ("status_s", 0.009),
                     ("status_s", 61), ("neighbour_periods", True)):
        doc["timeouts"] = {key: bad}
        refused(doc, f"timeouts.{key}")
    doc["timeouts"] = {"neighbour_periods": 100, "price_s": 60, "status_s": 0.01}
    cfg = parse(doc)
    assert (cfg.neighbour_timeout_periods, cfg.price_timeout_s, cfg.status_timeout_s) == \
        (100, 60.0, 0.01)
    doc["controller"]["ts"] = 0.02
    del doc["timeouts"]
    assert parse(doc).price_timeout_s == 5 * (5 * 0.02) == parse(doc).status_timeout_s


@pytest.mark.parametrize(("key", "bad"), [
    ("lambda_min", -127.5), ("lambda_max", 127.5), ("rho_min", -128.0), ("rho_max", 128.0),
    ("price_step_max", 0.9e-6), ("price_step_max", 127.5), ("price_persist", 0),
    ("price_persist", 101), ("price_persist", 2.0), ("lambda_step_max", 0.9e-6),
    ("lambda_step_max", 128.0), ("k_min", -0.1), ("k_max", 16.384), ("h_min", -0.1),
    ("h_max", 16.384), ("untrusted_after", 0), ("untrusted_after", 1001),
    ("untrusted_s", -1.0), ("untrusted_s", 3600.5),
])
def test_each_limit_is_range_checked(key: str, bad: Any) -> None:
    """CFG-7: every [limits] key's range, refused naming it."""
    doc = base()
    doc["limits"][key] = bad
    refused(doc, f"limits.{key}")


def test_limits_order_defaults_and_q24() -> None:
    """CFG-7: rho_min < rho_max, k_min ≤ k_max, h_min ≤ h_max; the defaults (−10, 10,
    −5, 5, 0.5, 3, (10·k)·ts, 0.5·k, 2·k, 0.5·h, 2·h, 5, (1.0·ts)/0.01); h_max·ts must fit
    Q1.30 like k_max·ts; the Q24 limits are q24 of the values."""
    doc = base()
    doc["limits"].update(rho_min=2.0, rho_max=2.0)
    refused(doc, "limits.rho_max")
    doc = base()
    doc["limits"].update(k_min=2.0, k_max=1.5)
    refused(doc, "limits.k_max")
    doc = base()
    doc["limits"].update(h_min=3.0, h_max=2.5)
    refused(doc, "limits.h_max")
    doc = base()
    doc["controller"].update(k=3.0, h=4.0, ts=0.3)
    del doc["limits"]
    msg = refused(doc, "limits.h_max")    # 2·h·ts = 2.4: not Q1.30
    assert "the default 2·h" in msg
    doc["controller"].update(h=3.0)     # 2·h·ts = 1.8 fits; 2·k·ts = 1.8 too
    cfg = parse(doc)
    k, h, ts = 3.0, 3.0, 0.3
    assert (cfg.lambda_min, cfg.lambda_max, cfg.rho_min, cfg.rho_max) == (-10, 10, -5, 5)
    assert (cfg.price_step_max, cfg.price_persist, cfg.untrusted_after) == (0.5, 3, 5)
    assert cfg.lambda_step_max == (10 * k) * ts
    assert (cfg.k_min, cfg.k_max, cfg.h_min, cfg.h_max) == (0.5 * k, 2 * k, 0.5 * h, 2 * h)
    assert cfg.untrusted_s == (1.0 * ts) / 0.01
    a = AgentRuntime(cfg, CODEC)
    assert (a.lam_min, a.lam_max) == (fx.to_fixed(-10.0), fx.to_fixed(10.0))
    assert a.lambda_step_max == round((10 * k) * ts * 2 ** 24)
    assert a.price_step_max == 8388608


def write_key_file(path: Path, node: str, peers: list[str],
                   frames: list[str] | None = None, commands: bool = True) -> Path:
    """A key file of case 1's fleet: ``node``'s key, its ``peers``' node keys and the keys
    of ``frames`` (None: every link frame and report of agents 1..4 it is a party of,
    AUTH-28, AUTH-29), and its command keys (AUTH-30)."""
    master = bytes(range(16))
    if frames is None:
        frames = [f for f in contract.keyed_frames(4) if node in contract.parties_of(f)]
    targets = ([f"agent_{i}" for i in range(1, 5)] if node == "router"
               else [node] if node.startswith("agent_") else []) if commands else []
    doc = node_key_document(node, derive_node_key(master, node), fleet_id(master), 0,
                            {p: derive_node_key(master, p) for p in peers}, None,
                            {f: derive_frame_key(master, f) for f in frames},
                            {t: derive_command_key(master, t) for t in targets})
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
    return path


def test_a_key_file_lacking_a_senders_key_stops_the_start(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """CFG-8, AUTH-28..30: agent 2 of case 1 takes ER_Price (router), AGENT_1_MC
    (agent_1), PLANT_2_Status (its link frame key) and the commands to it (its command
    key), and signs AGENT_2_Setpoint and AGENT_2_Diag (their own keys): a key file without
    any one of them stops the start naming it (the agent's command exits 2 before it
    opens a bus); with all of them it starts (and persists its new boot, AUTH-3)."""
    from firmware_py.__main__ import main

    cfg = agent_configs_from_scenario(load_case(1))[1]
    conf = tmp_path / "agent.toml"
    conf.write_text(cfg.to_toml())
    every = ["router", "agent_1"]
    links = ["AGENT_2_Setpoint", "PLANT_2_Status", "AGENT_2_Diag"]
    path = write_key_file(tmp_path / "no_status.toml", "agent_2", every,
                          [f for f in links if f != "PLANT_2_Status"])
    capsys.readouterr()
    assert main(["--config", str(conf), "--key", str(path), "--interface", "virtual",
                 "--channel", "cfg8-never-opened", "--duration", "0.01"]) == 2
    err = capsys.readouterr().err
    assert "verification key of PLANT_2_Status" in err and "Traceback" not in err
    for missing in every:
        path = write_key_file(tmp_path / f"no_{missing}.toml", "agent_2",
                              [p for p in every if p != missing], links)
        with pytest.raises(ConfigError) as e:
            AgentRuntime(cfg, CODEC, keys=Keyring.from_file(path))
        assert f"(sent by {missing})" in str(e.value)
    for missing in links:
        path = write_key_file(tmp_path / f"no_{missing}.toml", "agent_2", every,
                              [f for f in links if f != missing])
        with pytest.raises(ConfigError) as e:
            AgentRuntime(cfg, CODEC, keys=Keyring.from_file(path))
        assert f"key of {missing}" in str(e.value)
    path = write_key_file(tmp_path / "no_command.toml", "agent_2", every, links, commands=False)
    with pytest.raises(ConfigError, match="verification key of ER_Command"):
        AgentRuntime(cfg, CODEC, keys=Keyring.from_file(path))
    path = write_key_file(tmp_path / "all.toml", "agent_2", every, links)
    a = AgentRuntime(cfg, CODEC, keys=Keyring.from_file(path))
    assert a.io.boot == 1 and Keyring.from_file(path).boot == 1


def test_weights_and_pin_are_quantised_from_the_config() -> None:
    """CTRL-5: W_j = q24(weight_j) (ties to even), PIN = ONE if pinned else 0."""
    doc = base()
    doc["neighbour"] = [{"id": 1, "weight": 1 + 2.0 ** -25}, {"id": 3, "weight": 0.3},
                        {"id": 4, "weight": 1 + 3 * 2.0 ** -25}]
    a = AgentRuntime(parse(doc), CODEC)
    weights = {s.id: s.weight for s in a.neighbours.values()}
    assert weights == {1: 16777216, 3: round(0.3 * 2 ** 24), 4: 16777218}
    assert weights[3] == 5033165 and a.pin == 0
    doc["agent"]["pinned"] = True
    assert AgentRuntime(parse(doc), CODEC).pin == fx.ONE


# --------------------------------------------------------------------------- runtime


def saturating_agent() -> AgentRuntime:
    """Agent 2, not pinned, one neighbour (agent 1) of weight 100 at λ = −127 while its
    own λ(0) = 100: ξ = 100·227 saturates; the controller itself does not."""
    doc = base()
    doc["agent"]["lambda0"] = 100.0
    doc["limits"].update(lambda_min=-127.0, lambda_max=127.0)
    doc["neighbour"] = [{"id": 1, "weight": 100.0}]
    doc["timeouts"] = {"neighbour_periods": 100, "price_s": 60, "status_s": 60}
    a = running(doc)
    a.on_frame(mc_frame(1, fx.to_fixed(-127.0)), 0.0)
    return a


def test_xi_saturation_is_counted_in_saturations_not_in_ctrl_sats() -> None:
    """XI-3, DIAG-3 (sat_xi part), DIAG-1 page 5: each tick's clamped ξ adds 1 to the
    runtime count, reported in Saturations; ctrl_sats stays 0."""
    a = saturating_agent()
    for k in range(31):
        a.tick(k * 0.01)
    assert a.state == State.RUNNING and a.neighbours_alive == 1
    assert a.counters["saturations"] == 31 and a.cstate.saturations == 0
    assert diag(a, "Saturations") == 31


def test_saturations_is_the_sum_and_isolate_resets_the_controller_counters() -> None:
    """DIAG-3, STATE-7, DIAG-2 (internal counts go on): Saturations = sat_xi + ctrl_sats;
    an ISOLATE at once replaces the controller state by the initial state of
    q24(β·(1+m)) with resets = ctrl_sats = 0, so Saturations and Resets go down; an
    ISOLATE while ISOLATED changes nothing."""
    a = saturating_agent()
    for k in range(3):
        a.tick(k * 0.01)
    a.cstate = a.cstate.__class__(lam=a.cstate.lam, nu=12345 << 30, xi_prev=-7, armed=False,
                                  since_reset=9, resets=6, saturations=4)
    assert diag(a, "Saturations") == 3 + 4 and diag(a, "Resets") == 6
    a.on_frame(command(1, 2), 0.025)
    assert a.state == State.ISOLATED        # at once, before any tick
    b = a.cfg.battery
    idle = fx.to_fixed(b.beta * (1 + b.m))
    assert a.cstate == a.cstate.__class__(lam=idle << 30, nu=0, xi_prev=0, armed=True,
                                          since_reset=0, resets=0, saturations=0)
    assert diag(a, "Saturations") == 3 and diag(a, "Resets") == 0
    before = a.cstate
    a.on_frame(command(1, 2), 0.026)
    assert a.cstate is before and a.state == State.ISOLATED
    frames = a.tick(0.03)
    mc = next(CODEC.decode(m) for m in frames if m.arbitration_id == 0x102)
    assert mc.raw["Lambda"] == idle and mc.raw["State"] == int(State.ISOLATED)


def test_diag_counters_saturate_on_the_wire_and_keep_counting() -> None:
    """DIAG-2: a u16 counter above 65535 is sent as 65535 while the internal counter
    keeps counting; Resets on the Diag page saturates, on the MC frame it is mod 4
    (TX-1)."""
    a = running(base())
    a.tick(0.0)
    a.counters["unknown_id"] = 65534
    for _ in range(3):   # three real rejections: 65535, 65536, 65537
        a.on_frame(can.Message(arbitration_id=0x7F0, data=bytes(8), is_extended_id=False),
                   0.001)
    assert a.counters["unknown_id"] == 65537
    assert diag(a, "RejectedUnknownId") == 65535
    a.on_frame(can.Message(arbitration_id=0x7F0, data=bytes(8), is_extended_id=False), 0.002)
    assert a.counters["unknown_id"] == 65538 and diag(a, "RejectedUnknownId") == 65535
    a.cstate = a.cstate.__class__(lam=a.cstate.lam, resets=70001)
    assert diag(a, "Resets") == 65535
    mc = next(CODEC.decode(m) for m in a.tick(0.01) if m.arbitration_id == 0x102)
    assert mc.raw["Resets"] == 70001 % 4


def test_own_lambda_is_not_clamped_to_the_limits() -> None:
    """STEP-12: the own λ is limited only by sat54: a step that takes it beyond
    lambda_max is sent as it is (pc, k·ts = 1.6, ρ = 0.9, λ(0) = 0, lambda_max = 1)."""
    doc = base()
    doc["controller"].update(kind="pc", k=8.0, h=2.0, ts=0.2)
    doc["limits"].update(lambda_min=-1.0, lambda_max=1.0, k_max=8.0, k_min=4.0)
    doc["limits"].pop("lambda_step_max")
    doc["agent"].update(lambda0=0.0, pinned=True)
    doc["neighbour"] = []
    a = running(doc, rho=0.9)
    frames = a.tick(0.0)
    kts = fx.to_q30(8.0 * 0.2)
    xi = 0 - fx.to_fixed(0.9)
    expected = ((-(kts * xi)) + (1 << 29)) >> 30
    assert expected > fx.to_fixed(1.0)
    mc = next(CODEC.decode(m) for m in frames if m.arbitration_id == 0x102)
    assert mc.raw["Lambda"] == expected == a.lambda_q24
    assert a.counters["saturations"] == 0 and a.cstate.saturations == 0


def test_setpoint_clips_are_counted_only_in_running() -> None:
    """SP-2, SP-3, DIAG-5: each Setpoint frame whose P(λ) is clipped adds 1 to
    setpoint_limited (not on the Diag frame); outside RUNNING nothing is counted."""
    doc = base()
    doc["battery"].update(p_min=-1.0, p_max=1.0)   # P(0.6) ≈ 2 kW: clipped at 1 kW
    a = AgentRuntime(parse(doc), CODEC)
    for k in range(10):          # INIT: setpoints disabled, nothing counted
        a.tick(k * 0.01)
    assert a.state == State.INIT and a.counters["setpoint_limited"] == 0
    a.on_frame(status_frame(2), 0.1)
    a.on_frame(price_frame(0.8), 0.1)
    sent = []
    for k in range(10, 20):      # RUNNING: setpoints at ticks 10 and 15
        sent += a.tick(k * 0.01)
    sps = [CODEC.decode(m).raw for m in sent if m.arbitration_id == 0x202]
    assert len(sps) == 2 and all(s["Enable"] == 1 for s in sps)
    assert all(s["PowerSetpoint"] in (-100, 100) for s in sps)
    assert a.counters["setpoint_limited"] == 2
    assert "setpoint_limited" not in " ".join(a.diag_values())
    doc["battery"].update(p_min=-100.0, p_max=100.0)
    b = running(doc)
    for k in range(10):
        b.tick(k * 0.01)
    assert b.counters["setpoint_limited"] == 0


def test_counters_off_the_diag_frame_are_kept_and_printed() -> None:
    """DIAG-5: malformed, commands, commands_isolate, commands_reconnect,
    price_steps_accepted, setpoint_limited exist, count their events, are not on the Diag
    frame and are printed by summary()."""
    doc = base()
    doc["battery"].update(p_min=-1.0, p_max=1.0)
    doc["limits"]["price_persist"] = 1
    a = running(doc)
    a.tick(0.0)
    a.on_frame(can.Message(arbitration_id=0x010, is_remote_frame=True, dlc=8,
                           is_extended_id=False), 0.001)
    a.on_frame(price_frame(2.0), 0.002)      # a step of 1.2 > 0.5, accepted at once
    a.on_frame(command(1, 2), 0.003)
    a.on_frame(command(2, 2), 0.004)
    expected = {"malformed": 1, "commands": 2, "commands_isolate": 1,
                "commands_reconnect": 1, "price_steps_accepted": 1, "setpoint_limited": 1}
    assert {k: a.counters[k] for k in expected} == expected
    names = set(a.diag_values())
    assert not names & set(expected)
    line = a.summary()
    for k, v in expected.items():
        assert f"{k}={v}" in line


def test_unrepresentable_idle_mc_is_refused_at_start() -> None:
    """CMD-3, LOOP-5: β·(1+m) = 130 (β = 100, m = 0.3) does not fit Q24: the configuration
    is refused naming battery.beta, as firmware_c refuses it, instead of the node's loop
    ending at the first ISOLATE (was Open point 6); 127 is accepted and isolates."""
    doc = base()
    doc["battery"].update(beta=100.0, m=0.3)
    refused(doc, "battery.beta")
    doc["battery"].update(beta=127.0 / 1.5, m=0.5)
    a = running(doc)
    a.tick(0.0)
    a.on_frame(command(1, 2), 0.001)
    assert a.state == State.ISOLATED


# --------------------------------------------------------------------------- run loop

T = 2.0 ** -6   # a binary-exact sample time: every release r_n = n·T exactly


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class FakeBus:
    """recv waits on the simulated clock: it returns the next scheduled frame if it is
    delivered within the timeout (the clock jumps to its delivery time), else advances
    the clock by the timeout. send may fail."""

    def __init__(self, clock: Clock, frames: list[tuple[float, can.Message]] | None = None,
                 fail: Callable[[int], bool] = lambda n: False) -> None:
        self.clock = clock
        self.queue = sorted(frames or [], key=lambda f: f[0])
        self.sent: list[tuple[float, can.Message]] = []
        self.fail = fail
        self.attempts = 0

    def recv(self, timeout: float | None = None) -> can.Message | None:
        assert timeout is not None
        if self.queue and self.queue[0][0] <= self.clock.t + timeout:
            t, msg = self.queue.pop(0)
            self.clock.t = max(self.clock.t, t)
            return msg
        self.clock.t += timeout
        return None

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.attempts += 1
        if self.fail(self.attempts):
            raise can.CanOperationError("no buffer space")
        self.sent.append((self.clock.t, msg))


class Recorder:
    """A node that records what the loop does; tick n costs cost.get(n, 0) periods of
    the simulated clock."""

    period = T

    def __init__(self, clock: Clock, cost: dict[int, float] | None = None) -> None:
        self.clock = clock
        self.cost = cost or {}
        self.events: list[tuple[str, float]] = []
        self.counters: dict[str, int] = {}

    def on_frame(self, msg: can.Message, t: float) -> None:
        self.events.append(("rx", t))

    def tick(self, t: float) -> list[can.Message]:
        n = sum(e == "tick" for e, _ in self.events)
        self.events.append(("tick", t))
        self.clock.t += self.cost.get(n, 0.0) * T
        return [can.Message(arbitration_id=0x101, data=bytes(8), is_extended_id=False)]

    def note(self, event: str, count: int = 1) -> None:
        self.counters[event] = self.counters.get(event, 0) + count

    def ticks(self) -> list[float]:
        return [t for e, t in self.events if e == "tick"]


def msg() -> can.Message:
    return can.Message(arbitration_id=0x010, data=bytes(8), is_extended_id=False)


def test_run_loop_releases_and_receive_times() -> None:
    """LOOP-1, LOOP-3: releases r_{n+1} = r_n + Ts from the start; between releases each
    frame is handled at once with t_rx = the clock at delivery; ticks at the clock."""
    clock = Clock()
    clock.t = 5.0
    bus = FakeBus(clock, [(5.0 + 1.5 * T, msg()), (5.0 + 3.25 * T, msg())])
    node = Recorder(clock)
    run_node(node, bus, duration=6 * T, clock=clock)
    assert node.ticks() == [5.0 + n * T for n in range(6)]
    assert node.events[2] == ("rx", 5.0 + 1.5 * T) and node.events[3][0] == "tick"
    assert node.events[5] == ("rx", 5.0 + 3.25 * T)
    assert node.counters == {}
    assert [t for t, _ in bus.sent] == node.ticks()


def test_deadline_misses_are_counted_exactly_and_periods_skipped() -> None:
    """LOOP-2: late = now − r; late > Ts/2 is a miss: deadline_miss += 1 + floor(late/Ts),
    r += floor(late/Ts)·Ts, tick at now; late = Ts/2 exactly is not a miss; frames queued
    during an overrun are handled before the late tick."""
    clock = Clock()
    # tick 3 (at 3T) takes 2.7 periods: at 5.7T the release 4T is 1.7T late: 2 misses,
    # r = 5T, tick at 5.7T, next release 6T. Tick 7 (at 8T) takes 1.5 periods: at 9.5T
    # the release 9T is 0.5T late: no miss. Tick 9 (at 10T) takes 3 periods: at 13T the
    # release 11T is 2T late: 3 misses, r = 13T, tick at 13T.
    node = Recorder(clock, {3: 2.7, 7: 1.5, 9: 3.0})
    bus = FakeBus(clock, [(4.5 * T, msg()), (5.0 * T, msg())])
    run_node(node, bus, duration=15 * T, clock=clock)
    late = 3 * T + 2.7 * T
    assert node.ticks() == [0, T, 2 * T, 3 * T, late, 6 * T, 7 * T, 8 * T, 9.5 * T,
                            10 * T, 13 * T, 14 * T]
    assert node.counters == {"deadline_miss": 2 + 3}
    i = node.events.index(("tick", late))
    assert [e for e, _ in node.events[i - 2:i]] == ["rx", "rx"]


def test_run_loop_uses_the_monotonic_clock_by_default() -> None:
    """LOOP-3: the clock is monotonic (time.monotonic unless a test injects one)."""
    assert inspect.signature(run_node).parameters["clock"].default is time.monotonic


def test_failed_sends_and_bad_frames_are_counted_and_the_loop_goes_on() -> None:
    """LOOP-4, LOOP-5: a failing send adds 1 to send_failure and the loop goes on (the
    next frames of the same tick and later ticks are sent); an error frame adds 1 to
    error_frame and is not handled; rejected frames are counted drops."""
    cfg = agent_configs_from_scenario(load_case(1))[1]
    agent = AgentRuntime(cfg, CODEC)
    clock = Clock()
    frames = [(0.0, status_frame(2)), (0.0, price_frame(0.8)),
              (0.003, can.Message(is_error_frame=True, arbitration_id=0x20000004,
                                  data=bytes(8))),
              (0.004, can.Message(arbitration_id=0x7F0, data=bytes(8), is_extended_id=False)),
              (0.005, can.Message(arbitration_id=0x010, data=bytes(7), dlc=7,
                                  is_extended_id=False)),
              (0.006, copy.copy(price_frame(0.8)))]
    bad = frames[-1][1]
    bad.data = bytearray(bad.data)
    bad.data[0] ^= 1   # MAC no longer verifies
    bus = FakeBus(clock, frames, fail=lambda n: n in (1, 3, 4, 9))
    run_node(agent, bus, duration=0.1 - 1e-9, clock=clock)
    assert agent.counters["send_failure"] == 4
    assert agent.counters["error_frame"] == 1
    assert (agent.counters["unknown_id"], agent.counters["dlc"], agent.counters["auth"]) == \
        (1, 1, 1)
    assert agent.ticks == 10 and bus.attempts == len(bus.sent) + 4
    ids = [m.arbitration_id for _, m in bus.sent]
    # attempts 1, 3, 4: tick 0's MC_Sync, MC, Setpoint; attempt 9: tick 4's MC
    assert ids.count(0x102) == 10 - 2 and ids.count(0x502) == 0 and ids.count(0x602) == 1
    assert agent.state == State.RUNNING


class RaisingBus(FakeBus):
    """A FakeBus whose scheduled items may be exceptions: recv raises them at their time,
    as python-can does for a datagram it cannot read; from ``failing`` on, every recv
    fails at once (an interface down), with no time passing."""

    def __init__(self, clock: Clock, items: list[tuple[float, Any]],
                 failing: tuple[float, float] = (1.0, 1.0)) -> None:
        super().__init__(clock, items)
        self.failing = failing
        self.calls = 0

    def recv(self, timeout: float | None = None) -> can.Message | None:
        self.calls += 1
        if self.failing[0] <= self.clock.t < self.failing[1]:  # as python-can raises it
            raise can.CanOperationError("Failed to wait for IP/UDP socket: [Errno 100] "
                                        "Network is down") from OSError(100, "Network is down")
        if self.queue and isinstance(self.queue[0][1], BaseException):
            assert timeout is not None
            if self.queue[0][0] <= self.clock.t + timeout:
                t, exc = self.queue.pop(0)
                self.clock.t = max(self.clock.t, t)
                raise exc
        return super().recv(timeout)


def unreadable(data: bytes) -> can.CanOperationError:
    """What python-can's udp_multicast raises for ``data`` (its own unpacking)."""
    from can.interfaces.udp_multicast.utils import unpack_message

    try:
        unpack_message(data, replace={"timestamp": 0.0}, check=True)
    except Exception as e:
        err = can.CanOperationError("could not unpack received message")
        err.__cause__ = e
        return err
    raise AssertionError(f"{data!r} unpacks")


def test_inputs_that_are_not_frames_are_counted_and_the_loop_keeps_its_schedule() -> None:
    """LOOP-6: a datagram that is no message (not_a_frame), a message no CAN bus carries
    (invalid_frame: an 11-bit frame with ID 0x800, a float ID that python-can's own check
    lets pass) and failing receives (rx_error) are counted, the frames between them are
    handled, and every release is kept (no miss). A receive that keeps failing pauses
    (GuardedBus.sleep) instead of spinning: at most one failed recv per pause."""
    import msgpack
    from can.interfaces.udp_multicast.utils import pack_message

    from firmware_py.node import GuardedBus

    cfg = agent_configs_from_scenario(load_case(1))[1]
    agent = AgentRuntime(cfg, CODEC)
    clock = Clock()
    wide = can.Message(arbitration_id=0x800, is_extended_id=False, data=bytes(8),
                       check=False)
    items: list[tuple[float, Any]] = [
        (0.0, status_frame(2)), (0.001, unreadable(bytes(13))),
        (0.002, unreadable(pack_message(wide))),
        (0.003, can.Message(arbitration_id=0x10, is_extended_id=False, data=bytes(8))),
        (0.004, unreadable(msgpack.packb([1, 2, 3]))), (0.005, price_frame(0.8))]
    items[3][1].arbitration_id = 16.5   # a float ID in a datagram passes python-can
    bus = RaisingBus(clock, items, failing=(0.052, 0.071))
    pauses: list[float] = []

    def sleep(s: float) -> None:
        pauses.append(s)
        clock.t += s

    guarded = GuardedBus(bus, agent.note, clock, sleep=sleep)
    run_node(agent, guarded, duration=0.1 - 1e-9, clock=clock)
    assert (agent.counters["not_a_frame"], agent.counters["invalid_frame"]) == (2, 2)
    assert agent.counters["rx_error"] == len(pauses) >= 2
    assert sum(pauses) == pytest.approx(0.071 - 0.052, abs=T)
    assert agent.ticks == 10 and agent.counters["deadline_miss"] == 0
    assert agent.price is not None and agent.state == State.RUNNING   # the frames got in


# --------------------------------------------------------------------------- peer syncs


def agent_with(keys: Keyring) -> AgentRuntime:
    a = AgentRuntime(agent_configs_from_scenario(load_case(1))[1], CODEC, keys=keys)
    assert a.tick(0.0)[0].arbitration_id == 0x502   # the first syncs
    return a


def hello_after(a: AgentRuntime, sync: can.Message) -> bool:
    """Deliver ``sync`` at 0.5 s; True if the agent re-announces its syncs at the next
    tick (before sync_s = 1 s elapsed)."""
    a.tick(0.4)
    a.on_frame(sync, 0.5)
    return any(m.arbitration_id in (0x502, 0x602) for m in a.tick(0.5))


@pytest.mark.parametrize("sync_of", ["AGENT_3_MC", "AGENT_4_Setpoint", "PLANT_3_Status",
                                     "AGENT_1_Setpoint"])
def test_insecure_and_in_memory_keyrings_take_every_fleet_sync_as_a_peer_sync(
        sync_of: str, tmp_path: Path) -> None:
    """AUTH-19, RX-5, AUTH-18, AUTH-28: insecure and in-memory fleet keyrings hold every
    node key, so any fleet node's restart sync of a broadcast (here agent 3's MC, not a
    neighbour of agent 2) makes a hello pending; other agents' link frames (AGENT_j_
    Setpoint, PLANT_j_Status) are under keys agent 2 does not hold: ignored, even in
    those modes. A key-file agent holding only the router's and agent 1's node keys and
    its own link frame keys has no peer syncs: it ignores all four."""
    restarted = FleetSender(CODEC, boot=2)
    ring = Keyring.insecure_for("agent_2")
    broadcast = sync_of == "AGENT_3_MC"
    assert hello_after(agent_with(ring), restarted.sync(sync_of)) == broadcast
    master = bytes(range(16))
    fleet = Keyring.fleet(master, ["agent_2"])["agent_2"]
    keyed = FleetSender(CODEC, keys=fleet_keys(master, 4), boot=2)
    a = agent_with(fleet)
    assert hello_after(a, keyed.sync(sync_of)) == broadcast
    path = write_key_file(tmp_path / "a2.toml", "agent_2", ["router", "agent_1"])
    b = agent_with(Keyring.from_file(path))
    assert not hello_after(b, keyed.sync(sync_of))
    assert a.counters["auth"] == b.counters["auth"] == 0


# --------------------------------------------------------------------------- time scale


@pytest.mark.parametrize("kind", ["pi", "reset", "dwell", "pc", "ft"])
def test_a_scaled_agent_steps_as_the_unscaled_one_up_to_quantisation(kind: str) -> None:
    """SCALE-1: sim.model.scenario.scaled gives ts·F, k/F, h/F², dwell·F; per sample the fixed
    controller of the scaled config follows the unscaled one within quantisation (a few
    Q24 LSB over 300 samples of the same ξ), not bit for bit."""
    F = 4
    base_cfg = agent_configs_from_scenario(load_case(1))[1].controller
    base_cfg = ControllerConfig(kind=kind, k=base_cfg.k, h=base_cfg.h, ts=base_cfg.ts,
                                dwell=0.03 if kind == "dwell" else 0.0, band=base_cfg.band)
    sc = scaled(load_case(1), F)
    sc_cfg = agent_configs_from_scenario(sc)[1].controller
    one = agent_configs_from_scenario(load_case(1))[1].controller
    assert sc_cfg.ts == one.ts * F and sc_cfg.k == one.k / F and sc_cfg.h == one.h / F ** 2
    other = ControllerConfig(kind=kind, k=base_cfg.k / F, h=base_cfg.h / F ** 2,
                             ts=base_cfg.ts * F, dwell=base_cfg.dwell * F, band=base_cfg.band)
    a, b = make_controller(base_cfg), make_controller(other)
    assert a.dwell_samples == b.dwell_samples
    assert abs(a.kts - b.kts) <= 1 and a.ts_q * F - b.ts_q in range(-F, F + 1)
    sa, sb = a.initial_state(0.6), b.initial_state(0.6)
    rng = random.Random(7)
    worst: float = 0
    resets = 0
    for n in range(300):
        xi = rng.randint(-3 << 20, 3 << 20) if n % 50 else 0
        sa, oa = a.step(sa, xi)
        sb, ob = b.step(sb, xi)
        assert oa.reset == ob.reset
        resets += oa.reset
        worst = max(worst, abs(a.wire_lambda(sa) - b.wire_lambda(sb)))
    assert worst <= 2, worst
    # the same reset samples in both (the loop checks each one), and as many as the seeded
    # ξ give: the reset controllers reset, the others never do
    assert resets == {"reset": 107, "dwell": 80}.get(kind, 0)
    # h/F instead of h/F² would be far off: the check can fail
    wrong = make_controller(ControllerConfig(kind=kind, k=base_cfg.k / F, h=base_cfg.h / F,
                                             ts=base_cfg.ts * F, dwell=base_cfg.dwell * F,
                                             band=base_cfg.band))
    if kind not in ("pc", "ft"):   # they do not use h
        sw, sa2 = wrong.initial_state(0.6), a.initial_state(0.6)
        rng = random.Random(7)
        off: float = 0
        for n in range(300):
            xi = rng.randint(-3 << 20, 3 << 20) if n % 50 else 0
            sw, _ = wrong.step(sw, xi)
            sa2, _ = a.step(sa2, xi)
            off = max(off, abs(a.wire_lambda(sa2) - wrong.wire_lambda(sw)))
        assert off > 1000


def test_acceptance_filters_pass_the_syncs_of_the_keys_held(tmp_path: Path) -> None:
    """AUTH-19, GEN-5, AUTH-28 (key files, case 1): the agent's filter passes the syncs of
    what it takes (not its peer syncs); the router's also passes every agent's MC frames
    and syncs (it takes the MC frames for the pinned-agent failover; not the setpoints'
    syncs, under link frame keys it does not hold), the plant's the router's
    (ER_Price_Sync, ER_Command_Sync)."""
    from sim.nodes.plant import PlantNode
    from sim.nodes.router import RouterNode

    agents = [f"agent_{j}" for j in range(1, 5)]
    ring = Keyring.from_file(write_key_file(tmp_path / "a2.toml", "agent_2",
                                            ["router", "agent_1"]))
    a = AgentRuntime(agent_configs_from_scenario(load_case(1))[1], CODEC, keys=ring)
    syncs = {i for i in a.io.accepted_ids() if i >= 0x400}
    assert syncs == {0x410, 0x420, 0x501, 0x502, 0x602, 0x682, 0x702}  # 0x702: its own
    # the reports' syncs are nobody's peer syncs (RX-5): not even the router's
    assert not {0x701, 0x703} & set(a.io.accepted_ids())
    router = RouterNode(load_case(1), keys=Keyring.from_file(
        write_key_file(tmp_path / "r.toml", "router", agents)))
    # the router takes every agent's MC frames (the pinned-agent failover, docs/faults.md):
    # their syncs are its own, and an agent's restart shows on them (no peer syncs needed)
    assert {0x101, 0x102, 0x103, 0x104, 0x501, 0x502, 0x503, 0x504} <= \
        set(router.io.accepted_ids())
    assert not {0x601, 0x602, 0x603, 0x604} & set(router.io.accepted_ids())
    no_failover = RouterNode(load_case(1), failover=False, keys=Keyring.from_file(
        write_key_file(tmp_path / "r2.toml", "router", agents)))
    # without it the router takes no MC frame, but still the agents' MC syncs (peer syncs)
    assert {0x501, 0x502, 0x503, 0x504} <= set(no_failover.io.accepted_ids())
    assert not {0x101, 0x102, 0x103, 0x104, 0x601, 0x602, 0x603, 0x604} & \
        set(no_failover.io.accepted_ids())
    assert not {0x701, 0x702, 0x703, 0x704} & set(router.io.accepted_ids())
    plant = PlantNode(load_case(1), keys=Keyring.from_file(
        write_key_file(tmp_path / "p.toml", "plant", [*agents, "router"])))
    assert {0x410, 0x420} <= set(plant.io.accepted_ids())
    # the plant takes every agent's MC frames too (each setpoint is checked against the λ
    # its agent publishes, sim/nodes/consistency.py), so their syncs are its own, not peer syncs
    assert {0x501, 0x502, 0x503, 0x504} <= set(plant.io.accepted_ids())
    assert not {0x500, 0x505} & set(plant.io.accepted_ids())


def test_a_late_tick_first_drains_at_most_256_queued_frames() -> None:
    """LOOP-2: at a release the frames already queued are handled first, up to 256, each
    at the clock of its delivery; the rest wait for the time before the next release."""
    clock = Clock()
    node = Recorder(clock, {0: 2.0})     # tick 0 overruns: 300 frames queue meanwhile
    bus = FakeBus(clock, [(0.5 * T, msg()) for _ in range(300)])
    run_node(node, bus, duration=3.25 * T, clock=clock)
    kinds = [e for e, _ in node.events]
    assert kinds[:258] == ["tick"] + ["rx"] * 256 + ["tick"]
    assert kinds[258:] == ["rx"] * 44 + ["tick"]
    assert all(t == 2 * T for e, t in node.events[1:] if e == "rx")
    assert node.ticks() == [0, 2 * T, 3 * T]
    assert node.counters == {"deadline_miss": 2}


# --------------------------------------------------------------------------- the table

SPEC = Path(__file__).resolve().parent.parent / "docs" / "firmware-spec.md"


def coverage_rows() -> tuple[str, dict[str, tuple[str, str]]]:
    text = SPEC.read_text(encoding="utf-8")
    sec = text[text.index("## 16. Coverage"):text.index("## 17. ")]
    rows = {m[0]: (m[1], m[2]) for m in re.findall(
        r"^\| ([A-Z]+-\d+) \| ([a-z ]+) \| (.*) \|$", sec, flags=re.M)}
    return sec, rows


def test_coverage_table_is_complete_and_its_totals_and_conformance_steps_agree() -> None:
    """Section 16: one row per requirement of sections 1..14, the Totals line counts the
    rows, the `conformance:` column is sim.conformance.STEPS, and every test named in
    this file's rows exists."""
    from sim.conformance import STEPS

    text = SPEC.read_text(encoding="utf-8")
    defined = set(re.findall(r"^- \*\*([A-Z]+-\d+)\*\*", text[:text.index("## 15. ")],
                             flags=re.M))
    sec, rows = coverage_rows()
    assert set(rows) == defined
    counts = {s: sum(st == s for st, _ in rows.values()) for s in ("covered", "partial",
                                                                   "not yet")}
    assert (f"Totals: {counts['covered']} covered, {counts['partial']} partial, "
            f"{counts['not yet']} not yet (of {len(rows)}).") in sec
    steps: dict[str, list[str]] = {}
    for step in STEPS:
        for must in step.musts:
            steps.setdefault(must, [])
            if step.name not in steps[must]:
                steps[must].append(step.name)
    for rid, (_, cell) in rows.items():
        m = re.search(r"; conformance: ([^|]*)$", cell)
        assert (m[1].split(", ") if m else []) == steps.get(rid, []), rid
    here = set(re.findall(r"^def (test_\w+)", Path(__file__).read_text(), flags=re.M))
    for rid, (_, cell) in rows.items():
        for part in cell.split("; "):
            if part.startswith("test_spec_coverage.py::"):
                names = re.findall(r"(?:::|, ::)(test_\w+)", part)
                assert names and set(names) <= here, (rid, names)


# --------------------------------------------------------------------------- the details
# that some "covered" rows listed as not asserted


def pinned_alone(**timeouts: float) -> dict[str, Any]:
    doc = base()
    doc["agent"]["pinned"] = True
    doc["neighbour"] = []
    doc["timeouts"] = {"status_s": 60.0, **timeouts}
    return doc


def mc_of(frames: list[can.Message], agent: int = 2) -> dict[str, int]:
    return next(CODEC.decode(m).raw for m in frames if m.arbitration_id == 0x100 + agent)


def test_safe_and_running_entries_zero_nu_and_xiprev_and_step_at_once() -> None:
    """STATE-3, STATE-4, STATE-6, TX-1, TICK-1: a stale price at a tick → SAFE with
    ν := 0, ξprev := 0 and the rest of the state kept, λ held; a fresh price → RUNNING
    at the next tick, whose step (from ν = 0, ξprev = 0) already shows on that tick's MC
    frame; a tick's frames go out syncs, MC, Setpoint, Diag."""
    a = running(pinned_alone())
    first = a.tick(0.0)
    assert [m.arbitration_id for m in first] == [0x502, 0x602, 0x702, 0x102, 0x202, 0x302]
    for k in range(1, 5):
        a.tick(k * 0.01)
    s = a.cstate
    assert s.nu != 0 and s.xi_prev != 0
    frames = a.tick(0.3)                  # the price of t = 0 is 0.3 s old > 0.25
    assert a.state == State.SAFE and a.counters["price_timeouts"] == 1
    assert a.cstate == s.__class__(lam=s.lam, nu=0, xi_prev=0, armed=s.armed,
                                   since_reset=s.since_reset, resets=s.resets,
                                   saturations=s.saturations)
    mc = mc_of(frames)
    assert (mc["State"], mc["Lambda"], mc["Resets"]) == (int(State.SAFE), fx.narrow(int(s.lam)),
                                                         s.resets % 4)
    a.tick(0.31)
    assert a.cstate.lam == s.lam            # held while SAFE
    a.on_frame(price_frame(0.8), 0.315)
    frames = a.tick(0.32)
    xi = fx.narrow(int(s.lam)) - fx.to_fixed(0.8)            # mulq(ONE, x) = x
    lam = s.lam - a.ctrl.kts * xi                        # NU24 = 0: ν was zeroed
    assert a.state == State.RUNNING
    assert (a.cstate.lam, a.cstate.nu, a.cstate.xi_prev) == (lam, a.ctrl.ts_q * xi, xi)
    assert a.cstate.resets == s.resets and a.cstate.since_reset == s.since_reset + 1
    mc = mc_of(frames)
    assert (mc["State"], mc["Lambda"]) == (int(State.RUNNING), fx.narrow(lam))


def test_set_gains_zeroes_nu_and_keeps_the_rest_in_any_state() -> None:
    """CMD-5: an accepted SET_GAINS recomputes KTS = (2·GainK·TSQ + 1000) div 2000 and
    HTS = (2·GainH·TSQ + 1000) div 2000 in integers (TSQ = q30(ts); not q30(k·ts), which
    differs by an LSB: h = 3, ts = 0.01), sets ν := 0 and keeps λ (all its bits), ξprev,
    armed, since_reset, resets, ctrl_sats; it applies in ISOLATED too."""
    a = running(pinned_alone())
    for k in range(5):
        a.tick(k * 0.01)
    s = a.cstate
    a.on_frame(SENDER.frame("ER_Command", {"Command": 3, "Target": target_raw(2), "GainK": 1500,
                                           "GainH": 3000}), 0.045)
    tsq = fx.to_q30(0.01)
    assert (a.ctrl.kts, a.ctrl.hts) == ((2 * 1500 * tsq + 1000) // 2000,
                                         (2 * 3000 * tsq + 1000) // 2000)
    assert a.ctrl.hts == fx.to_q30(3000 * 0.001 * 0.01) - 1   # the one-LSB difference
    assert a.cstate == s.__class__(lam=s.lam, nu=0, xi_prev=s.xi_prev, armed=s.armed,
                                   since_reset=s.since_reset, resets=s.resets,
                                   saturations=s.saturations)
    a.on_frame(command(1, 2), 0.046)
    a.on_frame(SENDER.frame("ER_Command", {"Command": 3, "Target": target_raw(2), "GainK": 700,
                                           "GainH": 1100}), 0.047)
    assert a.state == State.ISOLATED and a.ctrl.kts == (2 * 700 * tsq + 1000) // 2000
    assert a.cfg.k_min == 0.5 and a.cfg.k_max == 2.0   # the bounds do not move


def test_plant_fault_flags() -> None:
    """RX-11: FaultOverCurrent or FaultVoltage is a fault (false → true counts once in
    plant_faults); FaultSoc and PowerLimited have no effect on the agent."""
    a = running(pinned_alone())
    a.tick(0.0)

    def status(**flags: int) -> can.Message:
        raw = {"FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
               "Power": 0.0, "Soc": 50.0, **flags}
        return SENDER.frame(status_name(2), raw, phys=True)

    a.on_frame(status(FaultSoc=1, PowerLimited=1), 0.005)
    a.tick(0.01)
    assert a.state == State.RUNNING and a.counters["plant_faults"] == 0
    a.on_frame(status(FaultVoltage=1), 0.015)
    a.on_frame(status(FaultVoltage=1, FaultOverCurrent=1), 0.016)
    a.tick(0.02)
    assert a.state == State.SAFE and a.counters["plant_faults"] == 1
    a.on_frame(status(), 0.025)
    a.tick(0.03)
    assert a.state == State.RUNNING
    a.on_frame(status(FaultOverCurrent=1), 0.035)
    assert a.counters["plant_faults"] == 2


def test_first_price_is_bounds_checked_only_and_a_stale_last_price_still_counts() -> None:
    """PRICE-3: the very first price is checked against the bounds only (a far first
    price is accepted); the step rule uses the last accepted price even after it went
    stale."""
    a = AgentRuntime(parse(pinned_alone()), CODEC)
    a.on_frame(price_frame(4.0), 0.0)      # 4.0 − nothing: no step rule
    assert a.price == fx.to_fixed(4.0) and a.counters["implausible_price"] == 0
    a.tick(0.0)
    a.tick(0.3)                             # stale (0.3 > 0.25), still the last price
    assert not a.price_ok
    a.on_frame(price_frame(1.0), 0.31)     # a step of 3 > 0.5 from the stale 4.0
    assert a.counters["implausible_price"] == 1 and a.price == fx.to_fixed(4.0)


def test_an_agent_sends_only_its_six_frames_classic_standard_dlc8() -> None:
    """GEN-1, GEN-2: over 250 ticks (syncs twice) every frame an agent sends is one of
    AGENT_i_MC, _Setpoint, _Diag, _MC_Sync, _Setpoint_Sync, _Diag_Sync: classic CAN,
    11-bit, DLC 8, not remote."""
    a = running(pinned_alone(price_s=60.0))
    sent = [m for k in range(250) for m in a.tick(k * 0.01)]
    assert {m.arbitration_id for m in sent} == {0x102, 0x202, 0x302, 0x502, 0x602, 0x702}
    assert all(not m.is_extended_id and not m.is_fd and not m.is_remote_frame
               and not m.is_error_frame and m.dlc == 8 and len(m.data) == 8 for m in sent)
    assert sum(m.arbitration_id == 0x502 for m in sent) == 3   # t = 0, 1, 2 s


def test_generated_parts_of_the_table_are_current() -> None:
    """tools/spec_coverage.py (the conformance column, the Totals line) has nothing to
    change."""
    import importlib.util

    path = SPEC.parent.parent / "tools" / "spec_coverage.py"
    spec = importlib.util.spec_from_file_location("spec_coverage", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    text = SPEC.read_text(encoding="utf-8")
    assert mod.refreshed(text) == text
    broken = text.replace("; conformance: commands |", " |", 1)
    assert broken != text and mod.refreshed(broken) == text


def test_setpoint_map_worked_example_bit_exact() -> None:
    """SP-1: G = rne(6553600/(((1+m)·2)·α)), O = rne((100·β)/(2·α)), lo/hi = rne(100·p);
    P(λ) = ((λ·G + 2^39) >> 40) − O clipped (section 9.1's example)."""
    from firmware_py.runtime import SetpointMap

    b = parse(base()).battery
    assert (b.alpha, b.beta, b.m, b.p_min, b.p_max) == (0.005, 0.18, 0.08, -100.0, 100.0)
    sp = SetpointMap(b)
    assert (sp.gain, sp.offset, sp.lo, sp.hi) == (606814815, 1800, -10000, 10000)
    assert sp(10015998) == (3728, False)
    lam = 10015998 * 606814815
    assert lam == 6077855973410370 and (lam + (1 << 39)) >> 40 == 5528
    assert sp(fx.to_fixed(10.0)) == (10000, True) and sp(fx.to_fixed(-10.0)) == (-10000, True)
    assert sp(-1) == (((-606814815 + (1 << 39)) >> 40) - 1800, False)


def test_xi_uses_alive_running_neighbours_and_the_pin() -> None:
    """XI-1, XI-2: ξ = mulq(PIN, Λ − ρ) + Σ mulq(W_j, Λ − λ_j) over the slots alive and
    RUNNING; an alive INIT neighbour and a silent one do not count (ξprev' = ξ)."""
    doc = pinned_alone()
    doc["neighbour"] = [{"id": 1, "weight": 0.5}, {"id": 3, "weight": 2.0},
                        {"id": 4, "weight": 1.0}]
    a = running(doc, rho=0.7)
    a.on_frame(mc_frame(1, fx.to_fixed(0.9)), 0.0)
    a.on_frame(mc_frame(3, fx.to_fixed(0.1), state=0), 0.0)     # alive, INIT
    lam = fx.narrow(int(a.cstate.lam))
    a.tick(0.0)
    assert a.neighbours_alive == 1
    xi = (lam - fx.to_fixed(0.7)) + fx.mul(1 << 23, lam - fx.to_fixed(0.9))
    assert a.cstate.xi_prev == xi


def test_reconnect_runs_at_the_next_tick() -> None:
    """STATE-8: RECONNECT in ISOLATED → INIT at once, controller state unchanged; at the
    next tick with fresh price and status the agent is RUNNING and that tick's MC frame
    carries RUNNING and a stepped λ; RECONNECT in another state changes nothing."""
    a = running(pinned_alone())
    a.tick(0.0)
    a.on_frame(command(2, 2), 0.001)
    assert a.state == State.RUNNING
    a.on_frame(command(1, 2), 0.002)
    a.tick(0.01)
    s = a.cstate
    a.on_frame(command(2, 2), 0.015)
    assert a.state == State.INIT and a.cstate is s
    mc = mc_of(a.tick(0.02))
    assert mc["State"] == int(State.RUNNING) and mc["Lambda"] != fx.narrow(int(s.lam))
    assert mc["Lambda"] == fx.narrow(int(a.cstate.lam))


def test_only_accepted_mc_frames_refresh_a_slot() -> None:
    """LIVE-1: an accepted MC frame sets λ_j, state_j and last_rx_j = t_rx; a rejected one
    (bad MAC, out-of-range λ) changes nothing in the slot."""
    doc = pinned_alone()
    doc["neighbour"] = [{"id": 1}]
    a = running(doc)
    slot = next(iter(a.neighbours.values()))
    assert (slot.lam, slot.state, slot.last_rx, slot.alive) == (None, State.INIT, None,
                                                                False)
    a.on_frame(mc_frame(1, fx.to_fixed(0.9)), 0.004)
    assert (slot.lam, slot.state, slot.last_rx) == (fx.to_fixed(0.9), State.RUNNING, 0.004)
    bad = mc_frame(1, fx.to_fixed(0.8))
    bad.data = bytearray(bad.data)
    bad.data[1] ^= 0x40
    a.on_frame(bad, 0.006)
    a.on_frame(mc_frame(1, fx.to_fixed(11.0)), 0.007)    # beyond lambda_max = 10
    assert (slot.lam, slot.state, slot.last_rx) == (fx.to_fixed(0.9), State.RUNNING, 0.004)
    assert a.counters["auth"] == 1 and a.counters["range"] == 1


def test_an_old_sync_is_an_auth_failure_with_a_key_file() -> None:
    """AUTH-16, AUTH-17: with real keys a sync whose FV − 1 is 16 or more below `last` is
    a replay: `auth` on the sync ID, `last_safety` = (auth, sync ID), `last` does not move
    back (less than 16 below: `stale`, tests/test_secoc.py)."""
    master = bytes(range(16))
    ring = Keyring.fleet(master, ["agent_2"])["agent_2"]
    a = AgentRuntime(parse(pinned_alone()), CODEC, keys=ring)
    router = FleetSender(CODEC, keys={"router": derive_node_key(master, "router")}, boot=5)
    a.tick(0.0)  # its hello: the join window (AUTH-26) until 0.2 s
    t0 = 0.25
    first = router.sync("ER_Price")
    a.on_frame(first, t0)
    assert a.counters["resyncs"] == 1
    for k in range(20):
        a.on_frame(router.frame("ER_Price", {"PriceValid": 1, "Rho": fx.to_fixed(0.8),
                                             "Segment": 0}), t0 + 0.0004 * k)
    assert a.counters["auth"] == 0 and a.price == fx.to_fixed(0.8)
    a.on_frame(first, t0 + 0.01)
    assert a.counters["auth"] == 1 and a.io.last_safety == ("auth", 0x410)
    assert a.counters["resyncs"] == 1
    a.on_frame(router.frame("ER_Price", {"PriceValid": 1, "Rho": fx.to_fixed(0.8),
                                         "Segment": 0}), t0 + 0.02)
    assert a.counters["auth"] == 1 and a.counters["lost_frames"] == 0
