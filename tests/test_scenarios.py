"""Scenario files: the shipped cases load, bad files fail naming file and key, and a
user-written file runs end to end without touching code."""

from __future__ import annotations

from pathlib import Path

import pytest

from firmware_py.errors import ConfigError
from sim.model.lockstep import run_lockstep
from sim.model.metrics import compute
from sim.model.scenario import SCENARIO_DIR, case_path, load_case, load_scenario, to_toml

CASE1 = case_path(1).read_text()
TS_LINE = "ts = 0.01            # firmware sample time Ts, s\n"
EDGES = "edges = [[1, 2], [1, 3], [1, 4]]"
K_LINE = "k = 1.0\n"


@pytest.mark.parametrize("case", range(1, 8))
def test_every_case_file_loads(case: int) -> None:
    sc = load_case(case)
    assert sc.name == f"case{case}"
    assert len(sc.batteries) == len(sc.lambda0) == sc.n
    assert sc.prices[0].t == 0
    for _, run in sc.runs():
        assert run.controller.ts == sc.ts


def test_case_files_are_all_there() -> None:
    assert sorted(p.name for p in SCENARIO_DIR.glob("case*.toml")) == [
        f"case{i}.toml" for i in range(1, 8)]
    with pytest.raises(ConfigError) as e:
        load_case(9)
    assert e.value.key == "case"


def test_case_contents_match_the_paper() -> None:
    c1, c4, c5, c6, c7 = (load_case(i) for i in (1, 4, 5, 6, 7))
    assert (c1.controller.kind, c1.controller.k, c1.controller.h) == ("reset", 1.0, 2.0)
    assert c1.lambda0 == (0.3, 0.6, 1.2, 1.0) and c1.pinned == (1,)
    assert [(e.t, e.agent, e.action) for e in c4.events] == [(10, 2, "isolate"),
                                                            (20, 2, "reconnect")]
    assert [(p.t, p.rho) for p in c5.prices] == [(0, 0.8), (15, 1.0), (35, 0.6)]
    assert [r.controller.dwell for _, r in c6.runs()] == [1.0, 1.5]
    assert c7.n == 12
    labels = {label: run.controller for label, run in load_case(3).runs()}
    assert [(c.k, c.h) for c in labels.values()] == [(1, 2), (5, 2), (10, 2), (1, 6), (1, 10)]


BAD = [
    # (what, edit of case1.toml, key named in the error)
    ("missing key", lambda s: s.replace(TS_LINE, ""), "ts"),
    ("missing battery key", lambda s: s.replace("alpha = 0.0040 ", "", 1), "battery[1].alpha"),
    ("missing table", lambda s: s.replace("[controller]", "[controler]"), "controler"),
    ("unknown key", lambda s: "tss = 0.01\n" + s, "tss"),
    ("unknown key in a table", lambda s: s.replace("agents = 4", "agents = 4\nagnets = 4"),
     "graph.agnets"),
    ("unknown controller key", lambda s: s.replace(K_LINE, K_LINE + "gain = 2.0\n"),
     "controller.gain"),
    ("wrong type", lambda s: s.replace(TS_LINE, 'ts = "fast"\n'), "ts"),
    ("wrong controller type", lambda s: s.replace(K_LINE, 'k = "one"\n'), "controller.k"),
    ("wrong table type", lambda s: s.replace(EDGES, "edges = 3"), "graph.edges"),
    ("out of range", lambda s: s.replace("duration = 20.0", "duration = 1e9"), "duration"),
    ("out of range agents", lambda s: s.replace("agents = 4", "agents = 1001"), "graph.agents"),
    ("bad gain", lambda s: s.replace(K_LINE, "k = -1.0\n"), "controller.k"),
    ("bad dwell", lambda s: s.replace(K_LINE, 'k = 1.0\nkind = "dwell"\n')
     .replace('kind = "reset"       # pc | pi | reset | dwell | ft\n', ""), "controller.dwell"),
    ("bad edge agent", lambda s: s.replace(EDGES, "edges = [[1, 2], [1, 5]]"),
     "graph.edges[2]"),
    ("self loop", lambda s: s.replace(EDGES, "edges = [[1, 1]]"), "graph.edges[1]"),
    ("bad edge shape", lambda s: s.replace(EDGES, "edges = [[1, 2, 1.0, 4]]"),
     "graph.edges[1]"),
    ("nobody pinned", lambda s: s.replace("pinned = [1]", "pinned = []"), "graph.pinned"),
    ("battery count", lambda s: s.replace("agents = 4", "agents = 3")
     .replace(EDGES, "edges = [[1, 2], [1, 3]]"), "battery"),
    ("bad agent in event", lambda s: s + '\n[[event]]\nt = 5.0\nagent = 9\naction = "isolate"\n',
     "event[1].agent"),
    ("bad event action", lambda s: s + '\n[[event]]\nt = 5.0\nagent = 2\naction = "unplug"\n',
     "event[1].action"),
    ("event after the end", lambda s: s + '\n[[event]]\nt = 50.0\nagent = 2\naction = "isolate"\n',
     "event[1].t"),
    ("bad variant gain", lambda s: s + '\n[[variant]]\nlabel = "neg"\nk = -1.0\n', "variant[1].k"),
    ("bad variant key", lambda s: s + '\n[[variant]]\nlabel = "x"\nkk = 1.0\n', "variant[1].kk"),
    ("variant without label", lambda s: s + "\n[[variant]]\nk = 2.0\n", "variant[1].label"),
    ("bad variant kind", lambda s: s + '\n[[variant]]\nlabel = "x"\nkind = "lqr"\n',
     "variant[1].kind"),
    ("price not from 0", lambda s: s.replace("t = 0.0\nrho = 0.8", "t = 1.0\nrho = 0.8"), "price"),
    ("bad soc", lambda s: s.replace("soc0 = 0.60", "soc0 = 1.5"), "battery[1].soc0"),
    ("limits reversed", lambda s: s.replace("p_min = -120.0", "p_min = 130.0"), "battery[1].p_max"),
    ("not toml", lambda s: s + "\n[[[", "file"),
    ("price below rho_min", lambda s: s.replace("t = 0.0\nrho = 0.8", "t = 0.0\nrho = -6.0"),
     "price[1].rho"),
    ("price above a set rho_max", lambda s: s + "\n[limits]\nrho_max = 0.5\n", "price[1].rho"),
    ("price bounds reversed", lambda s: s + "\n[limits]\nrho_min = 1.0\nrho_max = -1.0\n",
     "limits.rho_max"),
    ("price bound beyond the λ range", lambda s: s + "\n[limits]\nrho_max = 11.0\n",
     "limits.rho_max"),
    ("unknown limit", lambda s: s + "\n[limits]\nlambda_max = 11.0\n", "limits.lambda_max"),
]


@pytest.mark.parametrize(("what", "edit", "key"), BAD, ids=[b[0] for b in BAD])
def test_bad_scenario_names_file_and_key(tmp_path: Path, what: str, edit, key: str) -> None:
    text = edit(CASE1)
    assert text != CASE1, f"the edit for {what!r} did not apply"
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_scenario(path)
    err = e.value
    assert isinstance(err, ValueError)
    assert err.key == key
    assert str(err).startswith(f"{path}: [{key}] ")
    assert "expected" in err.problem or "required" in err.problem or "unknown" in err.problem


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as e:
        load_scenario(tmp_path / "nope.toml")
    assert e.value.key == "file" and "nope.toml" in str(e.value)


def test_unknown_variant_label() -> None:
    with pytest.raises(ConfigError) as e:
        load_case(2).variant("PID")
    assert e.value.key == "variant" and "reset-PI, PC, finite-time" in str(e.value)


def test_with_controller_rejects_bad_override() -> None:
    with pytest.raises(ConfigError) as e:
        load_case(1).with_controller(band=2.0)
    assert e.value.key == "controller.band"


USER_SCENARIO = """\
# A user's own scenario: three BESSs on a line, the middle one hears the price,
# weighted edges, a price step and a plug-and-play event.
name = "line3"
title = "three on a line"
ts = 0.01
duration = 30.0
load_kw = 150.0

[graph]
agents = 3
edges = [[1, 2, 1.5], [2, 3]]
pinned = [2]

[controller]
kind = "reset"
k = 1.0
h = 1.5
band = 5e-5

[[price]]
t = 0.0
rho = 0.7

[[price]]
t = 15.0
rho = 0.9

[[event]]
t = 4.0
agent = 3
action = "isolate"

[[event]]
t = 6.0
agent = 3
action = "reconnect"

[[battery]]
lambda0 = 0.4
alpha = 0.005
beta = 0.2
m = 0.1
p_min = -80.0
p_max = 80.0

[[battery]]
lambda0 = 1.0
alpha = 0.004
beta = 0.25
m = 0.05
p_min = -100.0
p_max = 100.0

[[battery]]
lambda0 = 0.55
alpha = 0.006
beta = 0.15
m = 0.0
p_min = -60.0
p_max = 60.0
"""


def test_user_written_scenario_runs(tmp_path: Path) -> None:
    path = tmp_path / "line3.toml"
    path.write_text(USER_SCENARIO)
    sc = load_scenario(path)
    assert (sc.n, sc.pinned, sc.edges[0]) == (3, (2,), (1, 2, 1.5))
    assert sc.analysis().regular
    tr = run_lockstep(sc)
    m = compute(sc, tr)
    assert tr.lam.shape == (3001, 3)
    assert not tr.active[500, 2] and tr.active[600, 2] and tr.active[399, 2]
    assert all(s is not None for s in m["settling_times_s"])
    assert m["final_error"] < 1e-3
    assert abs(tr.lam[1499] - 0.7).max() < 1e-3     # settled at the first price, too
    assert sum(m["resets"]) > 0 and m["saturations"] == 0


def test_to_toml_round_trip(tmp_path: Path) -> None:
    sc = load_case(4)
    path = tmp_path / "again.toml"
    path.write_text(to_toml(sc))
    back = load_scenario(path)
    for field in ("ts", "duration", "load_kw", "controller", "n", "edges", "pinned",
                  "batteries", "lambda0", "prices", "events"):
        assert getattr(back, field) == getattr(sc, field), field


@pytest.mark.parametrize(("edges", "pinned", "cut"), [
    ("edges = [[1, 2], [3, 4]]", "pinned = [1]", "agents 3, 4 cannot reach a pinned agent "
     "(pinned: 1)"),
    ("edges = [[1, 2], [1, 3]]", "pinned = [1]", "agent 4 cannot reach a pinned agent"),
    ("edges = [[1, 2]]", "pinned = [4]", "agents 1, 2, 3 cannot reach a pinned agent "
     "(pinned: 4)"),
])
def test_graph_with_agents_cut_off_from_the_price_is_rejected(
        tmp_path: Path, edges: str, pinned: str, cut: str) -> None:
    path = tmp_path / "cut.toml"
    path.write_text(CASE1.replace(EDGES, edges).replace("pinned = [1]", pinned))
    with pytest.raises(ConfigError) as e:
        load_scenario(path)
    assert e.value.key == "graph"
    assert cut in str(e.value) and "expected every agent connected to one" in str(e.value)


def test_two_components_each_pinned_is_accepted(tmp_path: Path) -> None:
    path = tmp_path / "two.toml"
    path.write_text(CASE1.replace(EDGES, "edges = [[1, 2], [3, 4]]")
                    .replace("pinned = [1]", "pinned = [1, 3]"))
    assert load_scenario(path).pinned == (1, 3)


@pytest.mark.parametrize("title", ['a "quoted" title', "back\\slash \\n not a newline",
                                   "two\nlines", "tab\tand 'single' quotes", "ünïcode λ ρ"])
def test_to_toml_round_trips_any_title(tmp_path: Path, title: str) -> None:
    from dataclasses import replace

    sc = replace(load_case(5), title=title, name='we"ird\\name', variants=())
    path = tmp_path / "again.toml"
    path.write_text(to_toml(sc))
    back = load_scenario(path)
    assert (back.title, back.name) == (title, sc.name)
    assert back.prices == sc.prices and back.batteries == sc.batteries


def test_price_limits_reach_every_agent_and_round_trip(tmp_path: Path) -> None:
    """A scenario's [limits] are every agent's price plausibility limits (what `up` and
    `deploy` write); absent, the firmware's defaults, which take a negative price."""
    from firmware_py.config import RHO_MAX, RHO_MIN, agent_configs_from_scenario

    assert RHO_MIN < 0 < RHO_MAX
    assert all((c.rho_min, c.rho_max) == (RHO_MIN, RHO_MAX)
               for c in agent_configs_from_scenario(load_case(1)))
    path = tmp_path / "neg.toml"
    path.write_text(CASE1.replace("t = 0.0\nrho = 0.8", "t = 0.0\nrho = -1.5")
                    + "\n[limits]\nrho_min = -2.0\nrho_max = 1.0\nprice_step_max = 2.5\n")
    sc = load_scenario(path)
    assert (sc.rho_min, sc.rho_max, sc.price_step_max) == (-2.0, 1.0, 2.5)
    cfgs = agent_configs_from_scenario(sc)
    assert [(c.rho_min, c.rho_max, c.price_step_max) for c in cfgs] == [(-2.0, 1.0, 2.5)] * 4
    again = tmp_path / "again.toml"
    again.write_text(to_toml(sc))
    back = load_scenario(again)
    assert (back.rho_min, back.rho_max, back.price_step_max, back.prices) == \
        (sc.rho_min, sc.rho_max, sc.price_step_max, sc.prices)
