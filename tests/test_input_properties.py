"""Property tests over generated inputs: scenario files, agent configurations, key files
and candump logs. Whatever the bytes, the parsers answer with a Scenario / AgentConfig /
NodeKey / LogContents or with the package's one-line error (ConfigError, KeyFileError):
never a traceback. And whatever they accept is physically possible: a battery with a
positive capacity, voltage and α, a degradation m ≥ 0, limits the setpoint frame
carries, prices inside the run, agent configurations their nodes load; the plant steps
on it without dividing by zero.

Run in-process (a subprocess per example would take minutes); a few CLI runs at the end
check the same end to end.
"""

from __future__ import annotations

import math
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_py import secoc
from firmware_py.config import agent_configs_from_scenario, parse_agent_config
from firmware_py.errors import ConfigError
from sim.model.scenario import (
    BATTERY_KEYS,
    CONTROLLER_KEYS,
    MAX_AGENT_SAMPLES,
    P_LIMIT_KW,
    SCENARIO_DIR,
    Scenario,
    load_scenario,
    parse_scenario,
)
from sim.nodes.plant import BessUnit
from sim.run import buslog

ROOT = Path(__file__).resolve().parents[1]
CASE1 = (SCENARIO_DIR / "case1.toml").read_text()
PROPS = settings(max_examples=100, deadline=None, derandomize=True,
                 suppress_health_check=[HealthCheck.function_scoped_fixture,
                                        HealthCheck.too_slow])

# values a careless user or a corrupt file puts anywhere: edges of every range, the
# non-finite floats, wrong types
EDGY = st.sampled_from([0, 0.0, -0.0, -1, 1, 1e-300, -1e-300, 1e300, -1e300, math.nan,
                        math.inf, -math.inf, 0.5, 1.0000001, 127.9, 128, 327.67, 327.68,
                        -327.68, 1e5, 1e6, 2**63, True, "", "1", [], [1, 2], {"a": 1}])
VALUE = st.one_of(EDGY, st.floats(), st.integers(-10**6, 10**6),
                  st.floats(-1e3, 1e3), st.text(max_size=4))


def base_scenario() -> dict[str, Any]:
    return tomllib.loads(CASE1)


def paths(doc: dict[str, Any]) -> list[tuple[Any, ...]]:
    """Every place a value can be put or removed in a case-1-like document."""
    out: list[tuple[Any, ...]] = [(k,) for k in ("ts", "duration", "load_kw", "name")]
    out += [("graph", k) for k in ("agents", "edges", "pinned")]
    out += [("controller", k) for k in sorted(CONTROLLER_KEYS)]
    out += [("battery", i, k) for i in range(4) for k in sorted(BATTERY_KEYS)]
    out += [("price", 0, "t"), ("price", 0, "rho"), ("price", 1, "t"), ("price", 1, "rho")]
    return out


def put(doc: dict[str, Any], path: tuple[Any, ...], value: Any) -> None:
    *head, last = path
    node: Any = doc
    for p in head:
        if isinstance(node, list):
            while len(node) <= p:
                node.append({"t": 1.0, "rho": 0.9} if head[0] == "price" else {})
        elif p not in node:
            node[p] = {}
        node = node[p]
    if value is DELETE:
        if isinstance(node, dict):
            node.pop(last, None)
    else:
        node[last] = value


DELETE = object()
MUTATION = st.tuples(st.sampled_from(paths(base_scenario())), st.one_of(VALUE, st.just(DELETE)))


def assert_physical(sc: Scenario) -> None:
    """What an accepted scenario must satisfy, whatever the file said."""
    assert 0 < sc.ts <= 1 and sc.ts <= sc.duration <= 1e5
    assert sc.n * sc.duration / sc.ts <= MAX_AGENT_SAMPLES
    assert math.isfinite(sc.load_kw)
    for b, l0 in zip(sc.batteries, sc.lambda0, strict=True):
        assert 0 < b.alpha <= 100 and 0 <= b.m <= 100 and -100 <= b.beta <= 100
        assert -P_LIMIT_KW <= b.p_min < b.p_max <= P_LIMIT_KW
        assert b.capacity_kwh > 0 and b.v_nom > 0 and 0 <= b.r_internal <= 100
        assert 0 <= b.soc0 <= 1 and math.isfinite(l0) and abs(b.beta * (1 + b.m)) < 128
    assert sc.prices[0].t == 0
    for a, b in zip(sc.prices, sc.prices[1:], strict=False):
        assert a.t < b.t
    assert all(0 <= p.t < sc.duration and math.isfinite(p.rho) for p in sc.prices)
    # the nodes take it: every agent's configuration loads, the plant steps on it
    for cfg in agent_configs_from_scenario(sc):
        parse_agent_config(tomllib.loads(cfg.to_toml()), "gen")
    for i, b in enumerate(sc.batteries, 1):
        unit = BessUnit.create(i, b)
        unit.enable, unit.stale, unit.p_set = True, False, b.p_max
        for _ in range(3):
            unit.control(set(), sc.ts)
            unit.advance(sc.ts)
        assert math.isfinite(unit.soc) and math.isfinite(unit.voltage)


@PROPS
@given(st.lists(MUTATION, min_size=1, max_size=4))
def test_generated_scenarios_are_refused_or_physical(mutations: list[tuple[Any, Any]]) -> None:
    doc = base_scenario()
    for path, value in mutations:
        put(doc, path, value)
    try:
        sc = parse_scenario(doc, "gen.toml")
    except ConfigError as e:
        assert str(e).startswith("gen.toml: [")
        return
    assert_physical(sc)


@PROPS
@given(blob=st.binary(max_size=200), at=st.integers(0, len(CASE1)))
def test_scenario_files_with_any_bytes_never_traceback(blob: bytes, at: int,
                                                       tmp_path_factory: pytest.TempPathFactory
                                                       ) -> None:
    path = tmp_path_factory.mktemp("sc") / "gen.toml"
    path.write_bytes(CASE1.encode()[:at] + blob + CASE1.encode()[at:])
    try:
        sc = load_scenario(path)
    except ConfigError as e:
        assert str(e).startswith(f"{path}: [")
        return
    assert_physical(sc)


# --------------------------------------------------------------------------- agent configs

AGENT_PATHS = ([("agent", k) for k in ("id", "lambda0", "pinned", "fleet_size")]
               + [("controller", k) for k in ("kind", "k", "h", "ts", "dwell", "band")]
               + [("battery", k) for k in ("alpha", "beta", "m", "p_min", "p_max")]
               + [("timeouts", k) for k in ("neighbour_periods", "price_s", "status_s")]
               + [("limits", k) for k in ("lambda_min", "lambda_max", "rho_min", "rho_max",
                                          "price_step_max", "k_max", "h_max", "untrusted_s")])


@PROPS
@given(st.lists(st.tuples(st.sampled_from(AGENT_PATHS), st.one_of(VALUE, st.just(DELETE))),
                min_size=1, max_size=4))
def test_generated_agent_configs_are_refused_or_sane(mutations: list[tuple[Any, Any]]) -> None:
    from sim.model.scenario import load_case

    doc = tomllib.loads(agent_configs_from_scenario(load_case(1))[1].to_toml())
    for path, value in mutations:
        put(doc, path, value)
    try:
        cfg = parse_agent_config(doc, "agent.toml")
    except ConfigError as e:
        assert str(e).startswith("agent.toml: [")
        return
    b = cfg.battery
    assert 0 < b.alpha <= 100 and 0 <= b.m <= 100 and abs(b.beta * (1 + b.m)) < 128
    assert -P_LIMIT_KW <= b.p_min < b.p_max <= P_LIMIT_KW
    assert cfg.lambda_min < cfg.lambda0 < cfg.lambda_max and cfg.rho_min < cfg.rho_max
    assert 0 < cfg.price_timeout_s <= 60 and 0 < cfg.status_timeout_s <= 60
    # what it accepted, it writes back to an equal configuration
    assert parse_agent_config(tomllib.loads(cfg.to_toml()), "agent.toml") == cfg


# --------------------------------------------------------------------------- key files

MASTER = bytes(range(16))
KEY_DOC = secoc.node_key_document("agent_1", secoc.derive_node_key(MASTER, "agent_1"),
                                  secoc.fleet_id(MASTER), 3,
                                  {"router": secoc.derive_node_key(MASTER, "router")})
KEY_PATHS = [("format",), ("node",), ("fleet_id",), ("key",), ("freshness",),
             ("freshness", "boot_counter"), ("peers",), ("peers", "router"),
             ("peers", "agent_99"), ("peers", "plant")]


@PROPS
@given(mutations=st.lists(st.tuples(st.sampled_from(KEY_PATHS),
                                    st.one_of(VALUE, st.just(DELETE))), max_size=3),
       splice=st.one_of(st.none(), st.tuples(st.integers(0, 400), st.binary(max_size=20))))
def test_generated_key_files_load_or_are_refused(mutations: list[tuple[Any, Any]],
                                                 splice: tuple[int, bytes] | None,
                                                 tmp_path_factory: pytest.TempPathFactory
                                                 ) -> None:
    import copy

    doc = copy.deepcopy(KEY_DOC)
    for path, value in mutations:
        if isinstance(doc.get(path[0]), dict) or len(path) == 1:
            put(doc, path, value)
    try:
        text = tomli_w.dumps(doc).encode()
    except (TypeError, ValueError):  # tomli-w cannot write it; then the bytes are the test
        text = b"key = 1\n"
    if splice is not None:
        text = text[:splice[0]] + splice[1] + text[splice[0]:]
    path = tmp_path_factory.mktemp("k") / "agent_1.key"
    secoc.write_private(path, "")
    path.write_bytes(text)
    try:
        k = secoc.load_node_key(path)
    except secoc.KeyFileError as e:
        assert str(e).startswith(f"{path}: ")
        return
    assert len(k.key) == 16 and 0 <= k.boot_counter <= secoc.DEFAULT_LAYOUT.max_boot
    assert all(len(v) == 16 for v in k.peers.values())


# --------------------------------------------------------------------------- logs

FRAME = "({t}) vcan0 010#{data}"
LINE = st.one_of(
    st.builds(lambda t, d: FRAME.format(t=t, data=d),
              st.one_of(st.floats(0, 1e4).map(lambda x: f"{x:.6f}"),
                        st.sampled_from(["nan", "inf", "-inf", "1e300", "-1e300", "", "x",
                                         "1e9", "0.0"])),
              st.sampled_from(["0000000000000000", "00", "ABC", "", "R", "R9", "#1AA",
                               "#Z", "GG"])),
    st.text(max_size=30).filter(lambda s: "\n" not in s and "\r" not in s),
    st.binary(max_size=30).map(lambda b: b.replace(b"\n", b"")),
)


@PROPS
@given(lines=st.lists(LINE, max_size=40), newline_at_end=st.booleans())
def test_generated_logs_are_read_with_every_line_accounted(
        lines: list[str | bytes], newline_at_end: bool,
        tmp_path_factory: pytest.TempPathFactory) -> None:
    """Every non-empty line is a frame, a skipped line counted by cause, or a frame left
    out as a timestamp outlier; the trajectory is built within its bound or refused."""
    from sim.model.scenario import load_case

    raw = b"\n".join(x if isinstance(x, bytes) else x.encode() for x in lines)
    if newline_at_end and raw:
        raw += b"\n"
    path = tmp_path_factory.mktemp("log") / "gen.log"
    path.write_bytes(raw)
    log = buslog.read_log(path, n=4, ts=0.01)
    nonempty = sum(1 for x in raw.split(b"\n") if x.strip())
    assert log.frames + sum(log.skipped_lines.values()) + len(log.time_outliers) == nonempty
    assert set(log.skipped_lines) <= set(buslog.LINE_CAUSES)
    assert all(math.isfinite(t) for t in log.time_outliers)
    if log.t_first_price is not None:
        try:
            tr = buslog.trajectory_from_log(load_case(1), log)
        except ConfigError as e:
            assert "[log] expected a recording of at most" in str(e)
        else:
            assert tr.t.size * 4 <= MAX_AGENT_SAMPLES + 4


# --------------------------------------------------------------------------- end to end

BAD_FILES = [
    ("capacity_kwh = 250.0", "capacity_kwh = 0"),
    ("m = 0.10", "m = -1"),
    ("soc0 = 0.60", "soc0 = 0.60\nv_nom = 0"),
    ("rho = 0.8", "rho = 0.8\n\n[[price]]\nt = 99.0\nrho = 1.0"),
]


@pytest.mark.parametrize(("old", "new"), BAD_FILES, ids=[n for _, n in BAD_FILES])
def test_the_installed_command_says_it_in_one_line(old: str, new: str, tmp_path: Path) -> None:
    """The same bad files through the real entry point, in a process of its own: exit 2,
    one `bess-ded: error:` line, no traceback, nothing written."""
    path = tmp_path / "bad.toml"
    path.write_text(CASE1.replace(old, new, 1))
    r = subprocess.run([sys.executable, "-m", "sim.cli", "case", str(path), "--out",
                        str(tmp_path / "o"), "--no-plots"], cwd=ROOT, capture_output=True,
                       text=True, timeout=120, check=False)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("bess-ded: error: ") and r.stderr.count("\n") == 1, r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "o").exists()
