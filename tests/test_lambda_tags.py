"""λ tags on CAN FD (firmware-spec AUTH-34, issue 25 item 1): on an FD bus every agent's λ
and its sync carry a 24-bit tag per receiver under the key of that (sender, receiver) pair,
so no key file but the sender's own tags its λ towards anyone; `[security] lambda_tags =
false` (`--no-lambda-tags`) keeps λ under the sender's node key, 8 bytes."""

from __future__ import annotations

import tomllib
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from dbc import FD_DBC_PATH, FD_UNTAGGED_DBC_PATH, dbc_path
from firmware_py import contract, secoc
from firmware_py import fixedpoint as fx
from firmware_py.errors import ConfigError, ParameterError
from firmware_py.frames import TAG_RX_PLANT, TAG_RX_ROUTER, FrameCodec, mc_name
from firmware_py.nodeio import FleetSender, NodeIO
from sim.model.scenario import load_case, parse_scenario, to_toml
from sim.model.scenario_select import with_fd
from sim.run.busrun import run_in_process
from sim.run.keyset import write_key_set

MASTER = bytes(range(16))
FD, UNTAGGED = FrameCodec(FD_DBC_PATH), FrameCodec(FD_UNTAGGED_DBC_PATH)
CASE1_FD = replace(load_case(1), fd=True)   # a star: agent 1 hears agents 2, 3, 4
DURATION_S, ATTACK_FROM_S = 10.0, 1.0
FORGED_LAMBDA = fx.to_fixed(1.2)            # the hub's λ, 0.4 above ρ


def _io(node: str, codec: FrameCodec, rings: dict[str, secoc.Keyring],
        wanted: list[int], receivers: list[str] | None = None) -> NodeIO:
    agent = node.removeprefix("agent_")  # a receiver sends no λ here: no tags of its own
    own = ([mc_name(int(agent)) if receivers else f"AGENT_{agent}_Setpoint"]
           if node.startswith("agent_") else ["PLANT_1_Status"] if node == "plant"
           else ["ER_Price"])
    return NodeIO(codec, node, own=own, wanted=wanted, keys=rings[node], join_s=0,
                  tag_receivers=receivers or ())


def test_a_tagged_lambda_carries_one_tag_per_receiver_and_each_takes_only_its_own() -> None:
    """AUTH-34: agent 1 (neighbours 2, 3, 4) fills the slots with 2, 3, 4, the plant, the
    router, one empty; its Mac is 0; each receiver verifies its own slot under its pair
    key; a slot copied from another receiver, or a frame with no slot for it, is `auth`."""
    rings = secoc.Keyring.fleet(MASTER, secoc.fleet_nodes(4))
    tx = _io("agent_1", FD, rings, [], contract.lambda_receivers([4, 2, 3]))
    rx = {n: _io(n, FD, rings, [FD.frame_id(mc_name(1))]) for n in ("agent_2", "agent_3",
                                                                     "plant", "router")}
    syncs = tx.syncs(0.0)
    for io in rx.values():
        for s in syncs:
            io.receive(s, 0.0)
    msg = tx.send(mc_name(1), {"State": 1, "Resets": 0, "Lambda": fx.to_fixed(0.8)})
    assert msg.dlc == 32 and bytes(msg.data[0:3]) == bytes(3)
    assert list(msg.data[8:32:4]) == [2, 3, 4, TAG_RX_PLANT, TAG_RX_ROUTER, 0]
    for n, io in rx.items():
        got = io.receive(msg, 0.01)
        assert got is not None and got.raw["Lambda"] == fx.to_fixed(0.8), n
        assert io.counters["auth"] == 0
    # agent 3's slot copied into agent 2's: agent 2's tag no longer verifies
    copied = bytearray(msg.data)
    copied[8:12] = bytes([2]) + bytes(msg.data[13:16])
    fresh = tx.send(mc_name(1), {"State": 1, "Resets": 0, "Lambda": fx.to_fixed(0.8)})
    forged = can.Message(arbitration_id=fresh.arbitration_id, data=bytes(fresh.data[:8])
                         + bytes(copied[8:]), is_fd=True, bitrate_switch=True,
                         is_extended_id=False)
    assert rx["agent_2"].receive(forged, 0.02) is None
    assert rx["agent_2"].counters["auth"] == 1
    # no slot for the router: auth there too
    blank = bytearray(fresh.data)
    blank[8 + 4 * 4] = 0
    forged = can.Message(arbitration_id=fresh.arbitration_id, data=bytes(blank), is_fd=True,
                         bitrate_switch=True, is_extended_id=False)
    assert rx["router"].receive(forged, 0.02) is None
    assert rx["router"].counters["auth"] == 1


def test_more_neighbours_than_slots_is_a_config_error() -> None:
    rings = secoc.Keyring.fleet(MASTER, secoc.fleet_nodes(6))
    with pytest.raises(ConfigError, match=r"expected 1\.\.6 receivers .*\(4 neighbours at most"):
        _io("agent_1", FD, rings, [], contract.lambda_receivers([2, 3, 4, 5, 6]))


def test_an_fd_fleets_key_files_hold_no_other_agents_node_key(tmp_path: Path) -> None:
    """AUTH-34, `bess-ded keys`: on CAN FD agent 3 (a leaf of case 1's star) holds the
    router's node key and the λ tag keys of the pairs it is one of, nothing of agent 1's
    that tags its λ towards anyone else; the plant and the router hold every agent's
    pair with them, no agent's node key. A classic fleet's files are as before."""
    for sc, name in ((CASE1_FD, "fd"), (load_case(1), "classic")):
        out = tmp_path / name
        out.mkdir(mode=0o700)
        write_key_set(sc, out, MASTER)
        a3, plant, router = (secoc.load_node_key(out / f"{n}.key")
                             for n in ("agent_3", "plant", "router"))
        if name == "classic":
            assert set(a3.peers) == {"router", "agent_1"} and not a3.tags
            continue
        assert set(a3.peers) == {"router"}
        assert sorted(a3.tags) == ["agent_1>agent_3", "agent_3>agent_1", "agent_3>plant",
                                   "agent_3>router"]
        assert a3.tags["agent_1>agent_3"] == secoc.derive_lambda_tag_key(MASTER, "agent_1",
                                                                         "agent_3")
        assert set(plant.peers) == {"router"} and set(router.peers) == set()
        assert sorted(plant.tags) == [f"agent_{i}>plant" for i in range(1, 5)]
        assert sorted(router.tags) == [f"agent_{i}>router" for i in range(1, 5)]


def test_a_boot_rewrite_and_raised_floors_keep_the_tag_keys(tmp_path: Path) -> None:
    """Every start rewrites a key file's boot counter (AUTH-3) and `up` raises its floors
    (AUTH-21): both keep `[lambda_tag_keys]` (before, the first start dropped them and the
    next one was refused), and a neighbour whose λ the agent verifies by its tag may have
    a floor."""
    write_key_set(CASE1_FD, tmp_path, MASTER)
    path = tmp_path / "agent_3.key"
    before = secoc.load_node_key(path).tags
    ring = secoc.Keyring.from_file(path)
    ring.new_boot()
    secoc.save_floors(path, {"agent_1": 7, "agent_2": 9})
    after = secoc.load_node_key(path)
    assert after.tags == before and len(before) == 4 and after.boot_counter == 1
    assert after.floors == {"agent_1": 7}  # agent 2 is no neighbour of agent 3


def test_a_key_file_with_a_pair_of_others_is_refused(tmp_path: Path) -> None:
    """A file that lists a λ tag key of a pair its node is not one of would let it speak
    for another: refused at load, not trimmed."""
    doc = secoc.node_key_document("agent_3", bytes(16), "0" * 16,
                                  tags={"agent_1>agent_2": bytes(16)})
    import tomli_w
    path = tmp_path / "agent_3.key"
    secoc.write_private(path, tomli_w.dumps(doc))
    with pytest.raises(secoc.KeyFileError, match=r"lambda_tag_keys.*agent_1>agent_2"):
        secoc.load_node_key(path)


def test_lambda_tags_false_selects_the_untagged_fd_dbc_and_needs_fd() -> None:
    text = to_toml(replace(CASE1_FD, lambda_tags=False))
    assert "lambda_tags = false" in text
    sc = parse_scenario(tomllib.loads(text), "untagged.toml")
    assert (sc.fd, sc.lambda_tags) == (True, False)
    assert dbc_path(sc.fd, sc.lambda_tags) == FD_UNTAGGED_DBC_PATH
    assert dbc_path(True) == FD_DBC_PATH and UNTAGGED.tag_slots(mc_name(1)) == 0
    with pytest.raises(ConfigError, match=r"\[security\.lambda_tags\] expected it only with "
                                          r"\[bus\] fd = true"):
        parse_scenario(tomllib.loads(text.replace("fd = true", "fd = false")), "classic.toml")
    with pytest.raises(ParameterError, match="--no-lambda-tags"):
        with_fd(load_case(1), False, no_lambda_tags=True)
    assert with_fd(load_case(1), True, no_lambda_tags=True).lambda_tags is False


def _forged_hub_lambda(sender: FleetSender, sent: list[can.Message]
                       ) -> Callable[[float], list[can.Message]]:
    """An insider's forgery of agent 1's λ (the hub of case 1) at 1.2 cu/kWh: a sync one
    boot ahead (within AUTH-27's bound) every second, a frame every tick."""
    def inject(t: float) -> list[can.Message]:
        k = round(t / CASE1_FD.ts)
        if t < ATTACK_FROM_S:
            return []
        out = [sender.sync(mc_name(1))] if k % 100 == 0 else []
        out.append(sender.frame(mc_name(1), {"State": 1, "Resets": 0, "Lambda": FORGED_LAMBDA}))
        sent.extend(out)
        return out
    return inject


def _run(tmp: Path, sc: Any, inject: Callable[[float], list[can.Message]] | None = None,
         observe: Callable[[float, dict[str, Any]], None] | None = None
         ) -> tuple[dict[str, Any], np.ndarray]:
    rings = secoc.Keyring.fleet(MASTER, secoc.fleet_nodes(sc.n))
    m = run_in_process(sc, tmp, DURATION_S, channel=f"tags-{tmp.name}", inject=inject,
                       keyrings=rings, observe=observe)
    return m, np.genfromtxt(tmp / "trajectory.csv", delimiter=",", names=True)


def _powers(tr: np.ndarray) -> np.ndarray:
    return np.array([tr[-1][f"p_{i}"] for i in range(1, 5)])


@pytest.mark.slow
@pytest.mark.parametrize("lambda_tags", [True, False])
def test_agent_3s_key_file_cannot_forge_agent_1s_lambda_on_fd(lambda_tags: bool,
                                                               tmp_path: Path) -> None:
    """Issue 25's acceptance for λ: an insider with agent 3's key file alone (as `bess-ded
    keys` writes it for the FD fleet) forges agent 1's λ at 1.2 cu/kWh towards its other
    receivers (agents 2 and 4, the plant, the router), every tick, with a sync one boot
    ahead, each tag under the best key it holds (its own pair with agent 1). No receiver
    takes a frame or a sync: each is `auth` at agents 2 and 4; the dispatch ends as the
    honest FD run's (every battery within 1 kW); agent 1 sees its own ID sent by someone
    else (`impersonation`). The control, `lambda_tags = false`: agent 3's file then holds
    agent 1's node key (to verify its λ), and the same forgery bites."""
    sc = CASE1_FD if lambda_tags else replace(CASE1_FD, lambda_tags=False)
    codec = FrameCodec(dbc_path(sc.fd, sc.lambda_tags))
    keys = tmp_path / "keys"
    keys.mkdir(mode=0o700)
    write_key_set(sc, keys, MASTER)
    held = secoc.load_node_key(keys / "agent_3.key")
    others = ["agent_2", "agent_4", "plant", "router"]  # it need not lie to itself
    if lambda_tags:
        assert "agent_1" not in held.peers
        best = held.tags["agent_1>agent_3"]
        sender = FleetSender(codec, keys={secoc.pair_label("agent_1", r): best
                                          for r in others}, boot=2, tag_receivers={1: others})
    else:
        sender = FleetSender(codec, keys={"agent_1": held.peers["agent_1"]}, boot=2)
    counters: dict[str, dict[str, int]] = {}

    def observe(_t: float, nodes: dict[str, Any]) -> None:
        for n in ("agent_2", "agent_4"):
            if (node := nodes.get(n)) is not None:
                counters[n] = dict(node.io.counters)
    sent: list[can.Message] = []
    m, tr = _run(tmp_path / "attack", sc, _forged_hub_lambda(sender, sent), observe)
    _, honest = _run(tmp_path / "honest", sc)
    moved = float(np.max(np.abs(_powers(tr) - _powers(honest))))
    kinds = {a["kind"] for a in m["anomalies"]}
    if not lambda_tags:   # the control: taken, and it bites
        assert moved > 1.0, moved
        return
    assert len(sent) > 800
    for n in ("agent_2", "agent_4"):  # (the last tick's frames come after the last look)
        assert len(sent) - 1 <= counters[n].get("auth", 0) <= len(sent), (n, counters[n])
    assert moved < 1.0, moved
    assert "impersonation" in kinds and "auth_failed" in kinds, m["anomalies"]
    assert m["verdict"]["exit_code"] == 3, m["verdict"]


def test_a_sync_in_a_nodes_own_name_of_a_lambda_it_does_not_send_is_no_crash() -> None:
    """A NodeIO of agent 3 that sends only its Diag (an insider's listener,
    sim.nodes.insider) hears an AGENT_3_MC_Sync on FD: not a peer's sync (its own name),
    not taken, no exception (before the fix: SecOCError on the pair 'agent_3>agent_3')."""
    ring = secoc.Keyring.fleet(bytes(16), secoc.fleet_nodes(4))["agent_3"]
    io = NodeIO(FD, "agent 3", ["AGENT_3_Diag"], [contract.ER_PRICE_ID], fleet_size=4,
                keys=ring, join_s=0)
    tx = FleetSender(FD, keys={f"agent_3>{r}": bytes(16) for r in ("agent_1", "plant",
                                                                   "router")},
                     tag_receivers={3: ["agent_1", "plant", "router"]})
    assert io.receive(tx.sync(mc_name(3)), 0.0) is None
    assert not io.counters.get("auth")
