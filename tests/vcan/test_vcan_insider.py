"""The insider of issue 25 on real SocketCAN: agent 3's key file against the hardened fleet.

Case 1 on CAN FD (vcan1, mtu 72) with λ tags and the signed price, every node its own
process, agent 2 on firmware_c's node program (its tags and its signature check in C),
and, once every node is heard, `bess-ded inject insider --key-file keys/agent_3.key
--skip-residual` as one more process: the router's price under its genuine node key and
freshness, ISOLATE commands, the λ, setpoints, statuses and Diag pages of agents 1, 2, 4,
the plant's totals, each under the best key agent 3's file holds, and the router's syncs
of its next boot under its genuine node key (held and dropped, AUTH-35). The run must hold the
honest dispatch and report every forgery where it lands (the udp_multicast twin and the
plan: tests/test_insider.py).

Marked ``long`` (~2 min of the guest): CI's vcan step leaves it out; run it by hand:

    tools/vcan-run python3 -m pytest -m vcan tests/vcan/test_vcan_insider.py -q
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import pytest
from test_vcan_interop import _spawn, _stop, wait_for_frames
from vcanrun import FINAL_TOL, TIME_SCALE, assert_clean_exit, at, key_set, run_on_vcan

from firmware_py import contract
from firmware_py.frames import mc_name, status_name
from sim.cbind.cagent import node_program
from sim.model.cost import kkt_optimum
from sim.model.scenario import load_case, to_toml

pytestmark = [pytest.mark.vcan, pytest.mark.long]

MASTER = bytes(range(60, 76))
HONEST = (1, 2, 4)
POWER_TOL_KW = 1.0


def test_agent_3s_key_file_forges_nothing_the_hardened_fleet_takes(
        vcan_fd_channel: str, can_utils: None, tmp_path: Path) -> None:
    sc = replace(load_case(1), duration=8.0, fd=True, signed_price=True)
    (tmp_path / "hard.toml").write_text(to_toml(sc))
    keys = key_set(tmp_path, sc, MASTER)
    ch = vcan_fd_channel
    heard = wait_for_frames(ch, [contract.MC_BASE + i for i in range(1, sc.n + 1)]
                            + [contract.STATUS_BASE + 1, contract.ER_PRICE_ID])
    forge_s = 0.8 * sc.duration * TIME_SCALE
    attacker = _spawn(["sh", "-c", f"{heard} && exec {sys.executable} -m sim.cli inject "
                       f"insider --key-file {keys / 'agent_3.key'} --case "
                       f"{tmp_path / 'hard.toml'} --interface socketcan --channel {ch} "
                       f"--time-scale {TIME_SCALE:g} --start {TIME_SCALE:g} "
                       f"--duration {forge_s:g} --skip-residual"],
                      tmp_path / "attacker.txt")
    try:
        run = run_on_vcan(sc, tmp_path / "run", ch, keys=keys, c_agents=frozenset({2}),
                          c_node=node_program())
    finally:
        _stop(attacker)
    said = (tmp_path / "attacker.txt").read_text()
    assert ": 19 forgeries" in said and "refused (auth)" in said, said
    assert "held, dropped at the router's next sync" in said, said  # its syncs (AUTH-35)
    assert run.m["final_error"] < FINAL_TOL, run.m["anomalies"]
    assert run.m["verdict"]["exit_code"] == 3, run.m["verdict"]  # converged, with anomalies
    assert run.log.t_first_price is not None
    t = run.log.t_first_price + 0.9 * run.sc.duration
    optimum, _ = kkt_optimum(run.sc.batteries, sc.prices[0].rho, run.sc.load_kw)
    for i in HONEST:
        p = at(run.log.series[(status_name(i), "Power")], t)
        assert abs(p - optimum[i - 1]) < POWER_TOL_KW, (i, p, optimum[i - 1])
        states = {v for _, v in run.log.series[(mc_name(i), "State")]
                  if _ > run.log.t_first_price + TIME_SCALE}
        assert states == {contract.State.RUNNING}, (i, states)  # no forged ISOLATE, no SAFE
    named = {(a["kind"], a["node"]) for a in run.m["anomalies"]}
    assert {("unsigned_price", f"agent_{i}") for i in range(1, sc.n + 1)} <= named, named
    victims = [f"agent_{i}" for i in HONEST] + ["plant", "router"]
    assert {("auth_failed", v) for v in victims} <= named, named
    assert {("impersonation", v) for v in victims} <= named, named
    assert ("sync_jump", "bus") in named, named  # the router's syncs held and dropped
    assert not {k for k, n in named if k == "price_timeout"}, named  # none was taken
    assert_clean_exit(run)
