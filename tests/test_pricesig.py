"""The router's signed price (``[security] signed_price``; issue 25, item 1, step d-min;
docs/security.md, firmware-spec AUTH-31..33).

Real parts only: the DBC's ER_PriceSig through the codec, Ed25519 from `cryptography`, the
key files `bess-ded keys` writes, and whole runs of case 1 on the in-process bus with a
simulated clock (an insider with agent 3's key file sends on a bus instance of its own).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from test_attacks import _final  # max|λ−ρ| and the powers at the end of a case-1 run

from firmware_py import contract, pricesig, secoc
from firmware_py.frames import FrameCodec
from firmware_py.nodeio import FleetSender
from firmware_py.pricesig import PriceSigReceiver, SignedSegment
from sim.model.scenario import load_case, parse_scenario, to_toml
from sim.run.busrun import run_in_process
from sim.run.keyset import check_key_set, write_key_set

CASE = dataclasses.replace(load_case(1), signed_price=True)
CODEC = FrameCodec()
MASTER = bytes(range(16))
DURATION_S = 10.0
FLEET = secoc.fleet_id(MASTER)
SEED = secoc.derive_price_sign_key(MASTER)
PUBLIC = pricesig.public_key(SEED)
SIG_ID = CODEC.frame_id(pricesig.MESSAGE)
ROUTER_NEXT = [0]  # the router's next ER_Price count (observe), for a forger in step with it


def _pages(seg: SignedSegment, signature: bytes) -> list[can.Message]:
    return [CODEC.encode(pricesig.MESSAGE, raw, 0) for raw in pricesig.pages(seg, signature)]


def _feed(rx: PriceSigReceiver, msgs: list[can.Message]) -> list[str]:
    return [bad[0] for m in msgs if (bad := rx.take(CODEC.decode(m).raw)) is not None]


# --------------------------------------------------------------------------- the frames


def test_er_price_sig_pages_golden() -> None:
    """Page 0 carries the signed segment, pages 1..10 the signature 7 bytes each (the last
    one byte), Intel order, no MAC: the bytes on the wire, fixed here."""
    seg = SignedSegment(boot=3, number=0x15A, valid=1, rho=round(0.8 * (1 << 24)))
    signature = bytes(range(64))
    msgs = _pages(seg, signature)
    assert [m.arbitration_id for m in msgs] == [0x008] * 11 and all(m.dlc == 8 for m in msgs)
    # Page 0 | PriceValid << 4 | Segment (0x15A & 7 = 2) << 5; Rho LE; Boot LE; 0x15A >> 3
    assert msgs[0].data.hex(" ") == "50 cd cc cc 00 03 00 2b"
    assert msgs[1].data.hex(" ") == "01 00 01 02 03 04 05 06"
    assert msgs[10].data.hex(" ") == "0a 3f 00 00 00 00 00 00"
    assert CODEC.kind(0x008) == "transfer" and 0x008 not in contract.SECURED_IDS
    # the signed bytes: label, fleet, boot, number, valid, ρ (AUTH-31)
    assert seg.message(FLEET) == (pricesig.SIG_LABEL + bytes.fromhex(FLEET) + b"\x00\x03"
                                  + b"\x01\x5a" + b"\x01" + b"\x00\xcc\xcc\xcd")


def test_a_signature_verifies_once_and_binds_the_price() -> None:
    rx = PriceSigReceiver(PUBLIC, FLEET)
    seg = SignedSegment(1, 0, 1, round(0.8 * (1 << 24)))
    price = {"PriceValid": 1, "Rho": seg.rho, "Segment": 0}
    assert rx.check(price) is not None  # nothing signed yet
    assert _feed(rx, _pages(seg, pricesig.sign(SEED, FLEET, seg))) == []
    assert rx.current == seg and rx.verifications == 1
    assert rx.check(price) is None
    assert rx.check({**price, "Rho": seg.rho + 1}) is not None
    assert rx.check({**price, "Segment": 1}) is not None
    assert rx.check({**price, "PriceValid": 0}) is not None
    # the once-a-second repeat costs no verify
    assert _feed(rx, _pages(seg, pricesig.sign(SEED, FLEET, seg))) == []
    assert rx.verifications == 1
    # a newer segment replaces it; the older one replayed is refused (bad_signature)
    seg2 = SignedSegment(1, 1, 1, seg.rho + 100)
    assert _feed(rx, _pages(seg2, pricesig.sign(SEED, FLEET, seg2))) == []
    assert _feed(rx, _pages(seg, pricesig.sign(SEED, FLEET, seg))) == ["bad_signature"]
    assert rx.current == seg2
    # a signature of an earlier boot than the router's known one: a replay
    seg0 = SignedSegment(0, 9, 1, seg.rho)
    assert [b[0] for m in _pages(seg0, pricesig.sign(SEED, FLEET, seg0))
            if (b := rx.take(CODEC.decode(m).raw, min_boot=1))] == ["bad_signature"]


def test_bad_and_malformed_signatures_are_counted_never_raised() -> None:
    rx = PriceSigReceiver(PUBLIC, FLEET)
    seg = SignedSegment(1, 0, 1, 1 << 24)
    good = pricesig.sign(SEED, FLEET, seg)
    # another key's signature (e.g. an agent's own Ed25519 key), and a bit flipped
    other = pricesig.sign(bytes(32), FLEET, seg)
    assert _feed(rx, _pages(seg, other)) == ["bad_signature"]
    flipped = bytes([good[0] ^ 1]) + good[1:]
    assert _feed(rx, _pages(seg, flipped)) == ["bad_signature"]
    # a valid signature of one segment under another's header
    lie = SignedSegment(1, 0, 1, 2 << 24)
    assert _feed(rx, _pages(lie, good)) == ["bad_signature"]
    assert rx.current is None
    msgs = _pages(seg, good)
    # a page without its header; a page repeated with other bytes; a last page too long
    assert _feed(rx, msgs[1:3]) == ["sig_malformed", "sig_malformed"]
    other_page = CODEC.encode(pricesig.MESSAGE, {"Page": 2, "Signature": 12345}, 0)
    assert _feed(rx, [msgs[0], msgs[1], msgs[2], other_page]) == ["sig_malformed"]
    long_last = CODEC.encode(pricesig.MESSAGE, {"Page": 10, "Signature": 0x1FF}, 0)
    assert _feed(rx, [msgs[0], long_last]) == ["sig_malformed"]
    assert rx.current is None
    assert _feed(rx, msgs) == [] and rx.current == seg  # the genuine transfer still works


# --------------------------------------------------------------------------- keys


def test_keys_give_the_router_alone_the_signing_key(tmp_path: Path) -> None:
    """`bess-ded keys` for a signed_price scenario: the router's file holds the Ed25519
    private key, every other file only its public key; an unsigned scenario's files have
    neither (as before). Rotation keeps them; `up --keys` checks them."""
    keys = tmp_path / "keys"
    keys.mkdir(mode=0o700)
    write_key_set(CASE, keys, MASTER)
    router = secoc.load_node_key(keys / "router.key")
    assert router.price_sign == SEED and router.price_verify is None
    for node in secoc.fleet_nodes(CASE.n)[:-1]:
        k = secoc.load_node_key(keys / f"{node}.key")
        assert k.price_sign is None and k.price_verify == PUBLIC
        assert SEED.hex() not in (keys / f"{node}.key").read_text()
    ring = secoc.Keyring.from_file(keys / "agent_3.key")
    assert ring.price_sign is None and ring.price_verify == PUBLIC
    # every rewrite of a file (a start's boot counter, `up`'s floors) keeps them
    secoc.Keyring.from_file(keys / "router.key").new_boot()
    secoc.save_floors(keys / "agent_3.key", {"router": 2})
    assert secoc.load_node_key(keys / "router.key").price_sign == SEED
    assert secoc.load_node_key(keys / "agent_3.key").price_verify == PUBLIC
    check_key_set(keys, CASE.n, CASE)
    plain = tmp_path / "plain"
    plain.mkdir(mode=0o700)
    write_key_set(load_case(1), plain, MASTER)
    assert "price_signature" not in (plain / "router.key").read_text()
    with pytest.raises(Exception, match="price signing key"):
        check_key_set(plain, CASE.n, CASE)
    # the scenario switch round-trips through its TOML, and reaches every agent's file
    assert parse_scenario(__import__("tomllib").loads(to_toml(CASE)), "x").signed_price
    from firmware_py.config import agent_configs_from_scenario, parse_agent_config
    cfg = agent_configs_from_scenario(CASE)[2]
    assert "[security]\nsigned_price = true" in cfg.to_toml()
    assert parse_agent_config(__import__("tomllib").loads(cfg.to_toml()), "x").signed_price


# --------------------------------------------------------------------------- runs


def _stolen(tmp: Path) -> secoc.NodeKey:
    keys = tmp / "keys"
    keys.mkdir(mode=0o700)
    write_key_set(CASE, keys, MASTER)
    return secoc.load_node_key(keys / "agent_3.key")


def _run(tmp: Path, inject: Callable[[float], list[can.Message]] | None = None,
         signed: bool = True, c_agents: tuple[int, ...] = ()
         ) -> tuple[dict[str, Any], np.ndarray, dict[str, dict[str, int]]]:
    counters: dict[str, dict[str, int]] = {}

    def observe(t: float, nodes: dict[str, Any]) -> None:
        for name, node in nodes.items():
            counters[name] = dict(node.counters)
        ROUTER_NEXT[0] = nodes["router"].io._tx_count[contract.ER_PRICE_ID]

    sc = CASE if signed else load_case(1)
    rings = secoc.Keyring.fleet(MASTER, secoc.fleet_nodes(CASE.n), signed_price=signed)
    m = run_in_process(sc, tmp, DURATION_S, channel=f"pricesig-{tmp.name}",
                       inject=inject, observe=observe, keyrings=rings, c_agents=c_agents)
    return m, np.genfromtxt(tmp / "trajectory.csv", delimiter=",", names=True), counters


@pytest.fixture(scope="module")
def honest(tmp_path_factory: pytest.TempPathFactory) -> np.ndarray:
    """A healthy signed run of case 1: converged, exit 0, no rejection of any kind."""
    m, tr, counters = _run(tmp_path_factory.mktemp("honest"))
    assert m["verdict"]["exit_code"] == 0 and m["verdict"]["converged"], m["verdict"]
    assert m["anomalies"] == []
    for i in range(1, CASE.n + 1):
        c = counters[f"agent_{i}"]
        assert not any(c.get(k) for k in pricesig.CAUSES), c
    assert counters["router"]["price_signatures"] == len({p.rho for p in CASE.prices})
    assert counters["router"]["signature_frames"] >= 11 * DURATION_S
    return _final(tr)[1]


def test_a_healthy_signed_run_converges_with_no_rejection(honest: np.ndarray) -> None:
    assert honest.shape == (CASE.n,)


def _ramp(forger: FleetSender, forged: list[can.Message]) -> list[can.Message]:
    """The forged price ramp's frame of this sample: from ρ = 0.8 at 2 s towards 3
    cu/kWh, +0.05 per price cycle, under the router's node key with the freshness value
    of the router's next frame (what an unsigned receiver takes)."""
    k = len(forged)
    rho = min(3.0, 0.8 + 0.05 * k)
    forger._count[contract.ER_PRICE_ID] = ROUTER_NEXT[0] - 1
    forged.append(forger.frame("ER_Price", {"PriceValid": 1, "Segment": 1,
                                            "Rho": round(rho * (1 << 24))}))
    return [forged[-1]]


def _attack(tmp: Path, c_agents: tuple[int, ...] = ()) -> tuple[
        dict[str, Any], np.ndarray, dict[str, dict[str, int]], list[can.Message],
        FleetSender, secoc.NodeKey]:
    """The insider of issue 25 with agent 3's key file: an ER_Price ramp towards ρ = 3
    under the router's node key (a valid MAC), and ER_PriceSig transfers signed with an
    Ed25519 key of its own (its file has the router's public key only), plus malformed
    pages (``c_agents``: the agents on firmware_c's runtime)."""
    tmp.mkdir(parents=True, exist_ok=True)
    stolen = _stolen(tmp)
    assert stolen.price_sign is None
    forger = FleetSender(CODEC, keys={"router": stolen.peers["router"]}, boot=1)
    forged: list[can.Message] = []
    fake = SignedSegment(1, 1, 1, 3 << 24)
    fake_pages = _pages(fake, pricesig.sign(secoc.derive_price_sign_key(bytes(16)),
                                            stolen.fleet_id, fake))
    junk = [CODEC.encode(pricesig.MESSAGE, {"Page": 7, "Signature": 1}, 0),
            can.Message(arbitration_id=SIG_ID, is_extended_id=False, data=b"\x00\x01")]

    def inject(t: float) -> list[can.Message]:
        k = round(t / CASE.ts)
        if t < 2.0:
            return []
        out: list[can.Message] = []
        if k % 100 == 0:
            out += fake_pages + junk
        if k % 5 == 0:
            out += _ramp(forger, forged)
        return out

    m, tr, counters = _run(tmp / "run", inject, c_agents=c_agents)
    return m, tr, counters, forged, forger, stolen


def test_agent_3s_key_file_cannot_forge_a_signed_price(tmp_path: Path,
                                                       honest: np.ndarray) -> None:
    """The insider of issue 25 (_attack). Every agent refuses every forged price
    (unsigned_price) and every forged signature (bad_signature, sig_malformed), nothing
    crashes, the dispatch is the honest run's, and the verdict names the anomalies."""
    m, tr, counters, forged, forger, stolen = _attack(tmp_path)
    # each forged price carries a MAC under the router's node key and the freshness
    # value the router's next frame takes (boot 1 in this key set's first run)
    last = forged[-1]
    fv = contract.FRESHNESS.join(1, forger._count[contract.ER_PRICE_ID])
    assert secoc.frame_verifies(stolen.peers["router"], contract.ER_PRICE_ID, last.data, fv)
    for i in range(1, CASE.n + 1):
        c = counters[f"agent_{i}"]
        assert c["unsigned_price"] >= 150 and c["bad_signature"] >= 8, c
        assert c["sig_malformed"] >= 16, c
        assert c.get("implausible_price", 0) == 0  # refused before the safety model
    err, p = _final(tr)
    assert err < 1e-3
    assert np.max(np.abs(p - honest)) < 1.0, (p, honest)
    named = {(a["kind"], a["node"]) for a in m["anomalies"]}
    assert {("unsigned_price", f"agent_{i}") for i in range(1, CASE.n + 1)} <= named
    assert {("bad_signature", f"agent_{i}") for i in range(1, CASE.n + 1)} <= named
    assert ("unsigned_price", "bus") in named and ("impersonation", "router") in named
    assert m["verdict"]["converged"] and m["verdict"]["exit_code"] != 0, m["verdict"]
    for line in m["node_summaries"][:CASE.n]:  # each agent's exit summary says it too
        assert "bad_signature=8" in line and "unsigned_price=" in line, line


def test_c_agents_refuse_the_forgery_bit_for_bit_as_the_python_agents(tmp_path: Path) -> None:
    """The same attack with every agent on firmware_c's runtime (libsodium verifying the
    signatures; sim.cbind.cagent through run_in_process): the run is the Python agents'
    one sample for sample (the same trajectory, the same frames on the bus), every agent
    counts the same unsigned_price, bad_signature and sig_malformed, the verdict names
    the same anomalies and the C agents' exit summaries say it."""
    py = _attack(tmp_path / "py")
    c = _attack(tmp_path / "c", c_agents=tuple(range(1, CASE.n + 1)))
    assert np.array_equal(c[1], py[1])
    for i in range(1, CASE.n + 1):
        want = {k: v for k, v in py[2][f"agent_{i}"].items() if v}
        assert c[2][f"agent_{i}"] == want, (i, c[2][f"agent_{i}"], want)
        assert c[2][f"agent_{i}"]["bad_signature"] >= 8
    assert c[0]["verdict"] == py[0]["verdict"]
    assert c[0]["anomalies"] == py[0]["anomalies"]
    assert [f.data for f in c[3]] == [f.data for f in py[3]]
    for line in c[0]["node_summaries"][:CASE.n]:
        assert "(C)" in line and "bad_signature=8" in line and "unsigned_price=" in line, line


ROUTER_NOW: list[tuple[int, dict[str, int]]] = []  # (boot, the price it sends), observe


def _lock_out(stolen: secoc.NodeKey) -> Callable[[float], list[can.Message]]:
    """Two hops of agent 3's key file against the router's price, from 2 s: a price sync
    8 boots ahead (under the router's node key, which the file holds) with the router's
    genuine signed price replayed on its track twice, then one 16 boots ahead with the
    same, all within 50 ms (well inside the router's sync period)."""
    key = stolen.peers["router"]

    def inject(t: float) -> list[can.Message]:
        k = round((t - 2.0) / CASE.ts)
        if not 0 <= k <= 4 or not ROUTER_NOW:
            return []
        boot, price = ROUTER_NOW[-1]
        hop = FleetSender(CODEC, keys={"router": key}, boot=boot + (8 if k < 2 else 16))
        if k in (0, 2):
            return [hop.sync("ER_Price"), hop.frame("ER_Price", price)]
        hop.follow("ER_Price", hop.boot, 0)
        return [hop.frame("ER_Price", price)]
    return inject


@pytest.mark.parametrize("vouch", ["signature of the boot", "signature of the boot, in C",
                                   "control: MAC alone"])
def test_a_held_price_advance_needs_a_signature_of_its_boot(
        vouch: str, tmp_path: Path, honest: np.ndarray,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """AUTH-33 with AUTH-35: a genuine price frame's ρ passes AUTH-33, so agent 3's key file
    could complete a held advance of the router's price with it. Taken twice within the
    router's sync period (the control, the vouch lifted), the second hop moves AUTH-27's
    undo point past the router's boot: every agent loses the price for good (its
    restarts would have to pass 9 boots). With the vouch, no signature of those boots
    exists: the replayed frames are `unsynced`, no advance is taken (the second hop is
    beyond the bound from the boot the agents are in), the router's next sync drops the
    held one, and the dispatch is the honest run's; the same with every agent on
    firmware_c's runtime."""
    from firmware_py.runtime import AgentRuntime

    stolen = _stolen(tmp_path)
    ROUTER_NOW.clear()

    def observe(t: float, nodes: dict[str, Any]) -> None:
        router = nodes["router"]
        ROUTER_NOW.append((router.io.boot, router._price_raw()))

    if vouch.startswith("control"):
        monkeypatch.setattr(AgentRuntime, "_signed_boot", lambda self, boot: True)
    rings = secoc.Keyring.fleet(MASTER, secoc.fleet_nodes(CASE.n), signed_price=True)
    counters: dict[str, dict[str, int]] = {}

    def watch(t: float, nodes: dict[str, Any]) -> None:
        observe(t, nodes)
        for name, node in nodes.items():
            counters[name] = dict(node.counters)

    c_agents = tuple(range(1, CASE.n + 1)) if vouch.endswith("in C") else ()
    m = run_in_process(CASE, tmp_path / "run", DURATION_S, channel=f"lockout-{tmp_path.name}",
                       inject=_lock_out(stolen), observe=watch, keyrings=rings,
                       c_agents=c_agents)
    err, p = _final(np.genfromtxt(tmp_path / "run" / "trajectory.csv", delimiter=",",
                                  names=True))
    timeouts = [counters[f"agent_{i}"].get("price_timeouts", 0) for i in range(1, CASE.n + 1)]
    if vouch.startswith("control"):
        assert all(timeouts) and not m["verdict"]["converged"], (timeouts, m["verdict"])
        return
    assert not any(timeouts), timeouts
    for i in range(1, CASE.n + 1):
        c = counters[f"agent_{i}"]
        assert c["unsynced"] >= 2 and c["sync_jump"] >= 2, c  # the held one dropped
    assert err < 1e-3 and np.max(np.abs(p - honest)) < 1.0, (p, honest)
    assert m["verdict"]["converged"], m["verdict"]
    assert ("impersonation", "router") in {(a["kind"], a["node"]) for a in m["anomalies"]}


def test_price_sign_key_kdf_as_documented() -> None:
    """AUTH-31: the seed is AUTH-1's KDF for 256 bits (two CMAC blocks, counters 1 and 2)
    under its own label, and its public key is what every other file holds."""
    fixed = b"bess-ded/price-sign-key/v1" + b"\x00" + b"router" + (256).to_bytes(4, "big")
    blocks = [secoc.cmac_aes128(MASTER, i.to_bytes(4, "big") + fixed) for i in (1, 2)]
    assert SEED == b"".join(blocks)
    assert SEED[:16] not in {secoc.derive_node_key(MASTER, n)
                             for n in secoc.fleet_nodes(CASE.n)}
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    assert PUBLIC == Ed25519PrivateKey.from_private_bytes(SEED).public_key().public_bytes_raw()


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_each_price_segment_is_signed_before_its_first_price(tmp_path: Path, fd: bool) -> None:
    """Case 1 with case 5's price steps (0.8, 1.0 at 3 s, 0.6 at 6 s): the router signs
    each segment once and sends it before that segment's first ER_Price, so no agent
    refuses a genuine price at a step, and the run converges at the last price; on
    classic CAN and on the FD twin (the same 8-byte pages as FD frames)."""
    sc = dataclasses.replace(CASE, fd=fd, prices=(
        dataclasses.replace(CASE.prices[0]), *(dataclasses.replace(CASE.prices[0], t=t, rho=r)
                                              for t, r in ((3.0, 1.0), (6.0, 0.6)))))
    counters: dict[str, dict[str, int]] = {}

    def observe(t: float, nodes: dict[str, Any]) -> None:
        for name, node in nodes.items():
            counters[name] = dict(node.counters)

    rings = secoc.Keyring.fleet(MASTER, secoc.fleet_nodes(sc.n), signed_price=True)
    m = run_in_process(sc, tmp_path, DURATION_S, channel=f"pricesig-steps-{tmp_path.name}",
                       observe=observe, keyrings=rings)
    assert m["verdict"]["exit_code"] == 0, (m["verdict"], m["anomalies"])
    assert counters["router"]["price_signatures"] == 3
    for i in range(1, sc.n + 1):
        assert not any(counters[f"agent_{i}"].get(k) for k in pricesig.CAUSES)
    err, _ = _final(np.genfromtxt(tmp_path / "trajectory.csv", delimiter=",", names=True))
    assert err < 1e-3


def test_without_signed_price_the_same_ramp_is_taken(tmp_path: Path,
                                                     honest: np.ndarray) -> None:
    """The control: the same forged ramp against an unsigned fleet (the default) is taken
    by the agents (its MAC and freshness hold), and the batteries leave the honest
    dispatch by far more than 1 kW (issue 25's forged price)."""
    stolen = _stolen(tmp_path)
    forger = FleetSender(CODEC, keys={"router": stolen.peers["router"]}, boot=1)
    forged: list[can.Message] = []

    def inject(t: float) -> list[can.Message]:
        return _ramp(forger, forged) if t >= 2.0 and round(t / CASE.ts) % 5 == 0 else []

    _, tr, counters = _run(tmp_path / "run", inject, signed=False)
    assert not any(counters["agent_1"].get(k) for k in pricesig.CAUSES)
    _, p = _final(tr)
    assert np.max(np.abs(p - honest)) > 10.0, (p, honest)


def test_process_runs_carry_the_agents_signature_counters_to_the_verdict(
        tmp_path: Path) -> None:
    """`up` starts each agent of a signed scenario (Python or C) with --counters-dir
    DIR/logs (no Diag slot carries these counters); the files it writes at exit are read
    back with the plant's and router's, and the verdict names the causes per agent. An
    unsigned scenario's argv is as before."""
    import json

    from firmware_py.__main__ import _write_counters
    from firmware_py.config import agent_configs_from_scenario
    from firmware_py.runtime import AgentRuntime
    from sim.run.buslog import LogContents
    from sim.run.busopts import BusOptions
    from sim.run.nodeprocs import node_specs, sim_node_counters
    from sim.run.verdict import RunFacts, _counters

    bus = BusOptions("udp_multicast")
    logs = tmp_path / "logs"
    logs.mkdir()
    signed = node_specs(CASE, tmp_path / "s.toml", tmp_path, bus, rt_priority=0)
    plain = node_specs(load_case(1), tmp_path / "s.toml", tmp_path, bus, rt_priority=0)
    for spec in signed:
        assert ("--counters-dir" in spec.argv) == spec.name.startswith("agent_"), spec
    assert not any("--counters-dir" in spec.argv for spec in plain)
    # a C agent (bessded-agent) writes the same file (firmware_c/src/main_agent.c)
    mixed = node_specs(CASE, tmp_path / "s.toml", tmp_path, bus, rt_priority=0,
                       c_agents=frozenset({2}), c_node=Path("/opt/bessded-agent"))
    c_spec = next(spec for spec in mixed if spec.name == "agent_2")
    assert c_spec.argv[0] == "/opt/bessded-agent"
    assert c_spec.argv[-2:] == ["--counters-dir", str(tmp_path / "logs")]
    ring = secoc.Keyring.fleet(MASTER, ["agent_2"], signed_price=True)["agent_2"]
    agent = AgentRuntime(agent_configs_from_scenario(CASE)[1], CODEC, keys=ring)
    agent.counters["unsigned_price"] += 7
    agent.counters["auth"] += 1  # a Diag counter: not written (the Diag carries it)
    _write_counters([agent], str(logs))
    read = sim_node_counters(tmp_path)
    assert read == {"agent_2": {"ticks": 0, "counters": {"unsigned_price": 7}}}
    assert json.loads((logs / "agent_2.counters.json").read_text())["ticks"] == 0
    found: list[Any] = []
    _counters(CASE, LogContents(), RunFacts(node_counters=read), found)
    assert [(a.kind, a.node) for a in found] == [("unsigned_price", "agent_2")]
