"""`bess-ded inject insider` (sim/nodes/insider.py): what one node's key file forges, and
a fleet under that attack (issue 25, acceptance: "with agent 3's key file alone, a forged
price, sync, command, plant status, or another agent's λ is accepted by no node").

* The plan, per scheme: which of the forgeries use the key that really signs the
  message (the residual risk docs/security.md lists) and which a stand-in; it names
  the same residual as `bess-ded bench --auth`'s `insider_forges`.
* On udp_multicast, every node a process (`bess-ded up`), the insider a process of its
  own with a copy of agent 3's key file: on the hardened fleet (CAN FD with λ tags, the
  signed price) every forged price, command, plant status, setpoint, λ and Diag of
  another node is refused by every receiver and reported, and the honest batteries end
  where the honest run puts them. The in-process twins, one forgery kind at a time and
  each with its control, are tests/test_attacks.py, test_lambda_tags.py,
  test_pricesig.py and test_selfmon.py (syncs); the vcan twin of this run is
  tests/vcan/test_vcan_insider.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dbc import dbc_path
from firmware_py import contract, secoc
from firmware_py.config import agent_configs_from_scenario
from firmware_py.frames import FrameCodec
from sim.bench import auth
from sim.model.cost import kkt_optimum
from sim.model.scenario import Scenario, load_case, to_toml
from sim.nodes import insider
from sim.run.keyset import write_key_set

MASTER = bytes(range(40, 56))
HONEST = (1, 2, 4)       # agent 3 is the compromised node
POWER_TOL_KW = 1.0


def hardened(duration: float = 10.0) -> Scenario:
    """Case 1 on the recommended configuration: CAN FD, λ tags, the signed price."""
    return replace(load_case(1), fd=True, signed_price=True, duration=duration)


def _plan(sc: Scenario, tmp: Path, node: str = "agent_3") -> insider.InsiderPlan:
    keys = tmp / "keys"
    keys.mkdir(mode=0o700)
    write_key_set(sc, keys, MASTER)
    codec = FrameCodec(dbc_path(sc.fd, sc.lambda_tags))
    receivers = {c.id: contract.lambda_receivers([n.id for n in c.neighbours])
                 for c in agent_configs_from_scenario(sc)}
    return insider.plan(sc, secoc.load_node_key(keys / f"{node}.key"), codec, receivers)


@pytest.mark.parametrize("sc, genuine_keys, residual", [
    (load_case(1), {"ER_Price", "AGENT_1_MC"}, {"ER_Price", "AGENT_1_MC"}),
    (hardened(), {"ER_Price"}, set())],
    ids=["classic", "fd-tagged-signed"])
def test_the_plan_names_the_residual_risk(sc: Scenario, genuine_keys: set[str],
                                          residual: set[str], tmp_path: Path) -> None:
    """Agent 3's file, case 1: every secured message of another node is forged, each
    under the genuine key where the file holds it, else a stand-in. On classic CAN the
    genuine ones are exactly what `bench --auth` computes for today's scheme (`a`: its
    frames, not their syncs) and all are taken; on the hardened fleet the price is under
    the genuine key but must be the signed one, and nothing remains forgeable: agent 3's
    own battery's status has one receiver, agent 3 (the router's ledger takes the
    plant's PLANT_Totals), so it is not in the plan at all. Both add the router's syncs
    under its genuine node key, which receivers hold and drop (AUTH-35): not residual."""
    p = _plan(sc, tmp_path)
    names = {f.name for f in p.forgeries}
    assert {"ER_Price", "ER_Command", "AGENT_1_MC", "AGENT_1_Setpoint", "AGENT_1_Diag",
            "PLANT_1_Status", "PLANT_Totals"} <= names
    assert "PLANT_3_Status" not in names  # its one receiver is agent 3 itself
    assert not any(f.name.startswith("AGENT_3_") for f in p.forgeries)  # not its own
    assert sum(f.name == "ER_Command" for f in p.forgeries) == 3         # agents 1, 2, 4
    assert {f.name for f in p.forgeries if f.genuine and not f.held} == genuine_keys
    assert {f.name for f in p.forgeries if f.residual} == residual
    # the router's syncs of its next boot, under its genuine node key: held (AUTH-35)
    assert {f.name for f in p.forgeries if f.held} == {"ER_Price_Sync", "ER_Command_Sync"}
    assert all(f.genuine and not f.residual for f in p.forgeries if f.held)
    if not sc.fd:
        today = next(s for s in auth.SCHEMES if s.key == "a")
        assert genuine_keys == {n for n in auth.insider_forges(today, sc)
                                if not n.endswith("_Sync")}
    text = "\n".join(insider.describe(insider.without_residual(p)))
    assert "FORGEABLE" not in text and "refused (auth)" in text


@pytest.mark.parametrize("node, residual", [
    ("plant", set()),
    ("router", {f"AGENT_{i}_Diag" for i in range(1, 5)})])
def test_the_hubs_key_files_on_the_hardened_fleet(node: str, residual: set[str],
                                                  tmp_path: Path) -> None:
    """The plant's file forges nothing a receiver takes (the setpoints' one receiver is
    the plant: not forged at all); the router's, the Diag pages it reads (no status: it
    holds none of their keys, its ledger takes PLANT_Totals, which it receives itself)."""
    p = _plan(hardened(), tmp_path, node)
    assert not any(f.name.endswith("_Setpoint") for f in p.forgeries) or node != "plant"
    assert {f.name for f in p.forgeries if f.residual} == residual


def test_inject_insider_without_its_key_file_is_a_usage_error(capsys: pytest.CaptureFixture[str]
                                                              ) -> None:
    from sim.cli import main

    assert main(["inject", "insider", "--case", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: error: inject insider: expected --key-file FILE"), err


def _final_powers(out: Path) -> np.ndarray:
    rows = np.genfromtxt(out / "trajectory.csv", delimiter=",", names=True)
    return np.array([rows[f"p_{i}"][-1] for i in HONEST])


@pytest.mark.realtime
def test_agent_3s_key_file_forges_nothing_the_hardened_fleet_takes(tmp_path: Path,
                                                                  udp_port: int) -> None:
    """`bess-ded up` (case 1, CAN FD, λ tags, signed price) on udp_multicast and, once
    it runs, `bess-ded inject insider --key-file keys/agent_3.key --skip-residual` beside
    it for 8 s: 19 forgeries, each at its cycle (the plan has no residual left:
    PLANT_3_Status's one receiver is agent 3, and the router's ledger takes the plant's
    PLANT_Totals, forged here too; the router's syncs of its next boot, under its genuine
    node key, every second: held and dropped, AUTH-35). At any load: the run converges (exit 3: with
    anomalies), agents 1, 2 and 4 never leave RUNNING and end within 1 kW of the KKT
    optimum at ρ; every forgery is reported where it lands: `unsigned_price` at every
    agent (the price, under the router's genuine node key and freshness, is not the
    signed one), `auth_failed` at agents 1, 2 and 4, the plant and the router (commands,
    λ tags, setpoints, statuses, totals, Diag), `impersonation` at every node it spoke
    for, `sync_jump` on the bus (the recorder drops the held syncs as the agents do) and
    no price timeout at any honest agent (a taken sync would have stopped its price)."""
    sc = hardened()
    (tmp_path / "hard.toml").write_text(to_toml(sc))
    keys = tmp_path / "keys"
    keys.mkdir(mode=0o700)
    write_key_set(sc, keys, MASTER)
    bus = ["--interface", "udp_multicast", "--bus-config", json.dumps({"port": udp_port})]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    out = tmp_path / "run"
    fleet = subprocess.Popen([sys.executable, "-m", "sim.cli", "up", "--case",
                              str(tmp_path / "hard.toml"), "--keys", str(keys), *bus,
                              "--no-plot", "--out", str(out)],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             env=env)
    try:
        deadline = time.monotonic() + 120
        while not (out / "logs" / "router.log").exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        attack = subprocess.run([sys.executable, "-m", "sim.cli", "inject", "insider",
                                 "--key-file", str(keys / "agent_3.key"), "--case",
                                 str(tmp_path / "hard.toml"), *bus, "--start", "1",
                                 "--duration", "8", "--skip-residual"],
                                capture_output=True, text=True, timeout=120, env=env)
        stdout, _ = fleet.communicate(timeout=300)
    finally:
        fleet.kill()
    assert attack.returncode == 0, attack.stdout + attack.stderr
    assert ": 19 forgeries" in attack.stdout and "sent" in attack.stdout
    assert "held, dropped at the router's next sync" in attack.stdout
    assert "FORGEABLE" not in attack.stdout  # nothing left for --skip-residual to skip
    m = json.loads((out / "metrics.json").read_text())
    assert fleet.returncode == 3, stdout[-3000:]
    assert m["final_error"] < 1e-3, m["final_error"]
    optimum, _ = kkt_optimum(sc.batteries, sc.prices[0].rho, sc.load_kw)
    p = _final_powers(out)
    assert np.max(np.abs(p - np.array([optimum[i - 1] for i in HONEST]))) < POWER_TOL_KW, p
    named = {(a["kind"], a["node"]) for a in m["anomalies"]}
    assert {("unsigned_price", f"agent_{i}") for i in range(1, 5)} <= named, named
    victims = [f"agent_{i}" for i in HONEST] + ["plant", "router"]
    assert {("auth_failed", v) for v in victims} <= named, named
    assert {("impersonation", v) for v in victims} <= named, named
    assert ("sync_jump", "bus") in named, named
    honest_trouble = {(k, n) for k, n in named
                      if k in ("agent_safe", "agent_isolated", "plant_fault", "price_timeout")
                      and n in {f"agent_{i}" for i in HONEST}}
    assert not honest_trouble, honest_trouble
