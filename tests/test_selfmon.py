"""Issue 25, items 2 and 3: a node reports who speaks as it, and a sync cannot poison a
sender's freshness (docs/security.md, firmware-spec RX-3 and AUTH-27).

The attacker holds agent 3's key file, which lists the router's verification key (a
symmetric MAC key: it signs too). The fleet runs are case 1 on the deterministic
in-process bus (simulated clock, as tests/test_attacks.py); the transport test uses a
real udp_multicast bus, whose multicast loopback hands a node its own frames back.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from firmware_py import contract, secoc
from firmware_py.frames import FrameCodec
from firmware_py.nodeio import FleetSender
from sim.model.scenario import load_case
from sim.nodes.router import RouterNode
from sim.run.busrun import run_in_process
from sim.run.keyset import write_key_set

CASE = load_case(1)
CODEC = FrameCodec()
DURATION_S = 10.0
MASTER = bytes(range(16))
RHO_FORGED = 0.5


def _stolen_router_key(tmp: Path) -> bytes:
    """The router's key as agent 3's key file (written as `bess-ded keys` does) holds it."""
    keys = tmp / "keys"
    keys.mkdir(mode=0o700)
    write_key_set(CASE, keys, MASTER)
    return secoc.load_node_key(keys / "agent_3.key").peers["router"]


def _run(tmp: Path, inject: Callable[[float], list[can.Message]] | None = None,
         rings: dict[str, secoc.Keyring] | None = None,
         **kw: Any) -> tuple[dict[str, Any], np.ndarray, dict[str, Any]]:
    """A run of case 1; also each live node's counters at the end (observe)."""
    counters: dict[str, Any] = {}

    def observe(t: float, nodes: dict[str, Any]) -> None:
        for name, node in nodes.items():
            io = getattr(node, "io", None)
            if io is not None:
                counters[name] = dict(io.counters)

    rings = rings or secoc.Keyring.fleet(MASTER, secoc.fleet_nodes(CASE.n))
    m = run_in_process(CASE, tmp, DURATION_S, channel=f"selfmon-{tmp.name}", inject=inject,
                       observe=observe, keyrings=rings, **kw)
    tr = np.genfromtxt(tmp / "trajectory.csv", delimiter=",", names=True)
    return m, tr, counters


def _final(tr: np.ndarray) -> tuple[float, np.ndarray]:
    last = tr[-1]
    lam = np.array([last[f"lam_{i}"] for i in range(1, CASE.n + 1)])
    p = np.array([last[f"p_{i}"] for i in range(1, CASE.n + 1)])
    return float(np.max(np.abs(lam - last["rho"]))), p


def _named(m: dict[str, Any]) -> set[tuple[str, str]]:
    return {(a["kind"], a["node"]) for a in m["anomalies"]}


@pytest.fixture(scope="module")
def honest(tmp_path_factory: pytest.TempPathFactory) -> np.ndarray:
    return _final(_run(tmp_path_factory.mktemp("honest"))[1])[1]


# --------------------------------------------------------------------------- item 2


def test_own_frames_back_over_udp_multicast_are_no_impersonation_others_are(
        udp_port: int) -> None:
    """On udp_multicast a node hears its own frames (multicast loopback): the router's
    NodeIO takes them for its echo; the same ID with another payload, sent by a second
    bus instance, is `impersonation` (and foreign). Read with a timeout, no sleeps."""
    from can.interfaces.udp_multicast import UdpMulticastBus

    group = UdpMulticastBus.DEFAULT_GROUP_IPv6
    router = RouterNode(CASE, keys=secoc.Keyring.fleet(MASTER, ["router"])["router"])
    with can.Bus(interface="udp_multicast", channel=group, port=udp_port) as bus, \
            can.Bus(interface="udp_multicast", channel=group, port=udp_port) as rogue:
        sent = router.io.send("ER_Price", {"PriceValid": 1, "Rho": 1 << 23, "Segment": 0})
        bus.send(sent)
        back = bus.recv(2.0)
        assert back is not None and back.arbitration_id == sent.arbitration_id
        assert router.io.receive(back, 0.0) is None
        assert router.counters["impersonation"] == 0  # its own frame, heard back
        forged = can.Message(arbitration_id=sent.arbitration_id, is_extended_id=False,
                             data=bytes(8))
        rogue.send(forged)
        for _ in range(2):  # the rogue's frame (and, on this socket, maybe its echo)
            got = bus.recv(2.0)
            if got is not None and bytes(got.data) == bytes(8):
                router.io.receive(got, 0.0)
                break
    assert router.counters["impersonation"] == 1 and router.counters["foreign"] == 1


@pytest.mark.slow
def test_a_key_holder_speaking_as_the_router_is_named_impersonation(tmp_path: Path) -> None:
    """With the router's key from agent 3's key file, an attacker announces the router's
    price freshness a little ahead (no boot jump) and sends ρ = 0.5 price frames from
    t = 2 s: the agents cannot tell them from the router's (issue 25, item 1), but the
    router hears frames on its own IDs that it did not send, and the verdict names it:
    `impersonation [router]`, the most likely cause if the run does not converge."""
    forger = FleetSender(CODEC, keys={"router": _stolen_router_key(tmp_path)}, boot=1)
    forger.skip("ER_Price", 10_000)  # ahead of the router's count in the same boot

    def inject(t: float) -> list[can.Message]:
        k = round(t / CASE.ts)
        if t < 2.0 or k % 5:
            return []
        out = [forger.sync("ER_Price")] if k % 100 == 0 else []
        return out + [forger.frame("ER_Price", {"PriceValid": 1, "Segment": 0,
                                                "Rho": round(RHO_FORGED * (1 << 24))})]

    m, _, counters = _run(tmp_path / "run", inject)
    assert counters["router"]["impersonation"] > 0
    assert ("impersonation", "router") in _named(m), m["anomalies"]
    detail = next(a["detail"] for a in m["anomalies"]
                  if (a["kind"], a["node"]) == ("impersonation", "router"))
    assert "own IDs that it did not send" in detail
    assert ("foreign_traffic", "router") not in _named(m)  # said as what it is
    if not m["verdict"]["converged"]:
        assert m["verdict"]["cause"].startswith("impersonation [router]"), m["verdict"]


# --------------------------------------------------------------------------- item 3


def _forged_sync(key: bytes, boot: Callable[[], int], at: float, count: int = 0
                 ) -> Callable[[float], list[can.Message]]:
    """One ER_Price_Sync of boot ``boot()`` (valid MAC, count ``count``) at ``at`` s."""
    def inject(t: float) -> list[can.Message]:
        if abs(t - at) > CASE.ts / 2:
            return []
        forger = FleetSender(CODEC, keys={"router": key}, boot=boot())
        return [forger.sync_ahead("ER_Price", counts=count)]
    return inject


@pytest.mark.slow
@pytest.mark.parametrize("what", ["65535, router alive", "within the bound, router alive",
                                  "within the bound, router down",
                                  "count 2^24 - 256, router alive"])
def test_a_forged_sync_cannot_lock_the_router_out(
        what: str, honest: np.ndarray, tmp_path: Path) -> None:
    """One ER_Price_Sync forged with the router's key (from agent 3's key file):

    * boot 65535 at t = 2 s (the issue's: the fleet in SAFE for good): refused by every
      agent (`sync_jump`); the fleet keeps converging, and the router restarted at 5 s
      is heard by all;
    * boot + 8 (within the bound, taken) at 2 s: the router's next genuine sync, of the
      boot it is still in, undoes it within its sync period;
    * boot + 8 at 2.5 s while the router is down (2 s to 4 s): its restart (boot + 1)
      undoes it;
    * the router's own boot, count 2^24 − 256, at 2 s (before the count bound every
      agent took it: each later genuine price a replay, the fleet in SAFE until the
      router restarted): refused by every agent (`sync_jump`).

    Every time the fleet ends converged within 1 kW of the honest run, and the run
    reports `sync_jump`."""
    rings = secoc.Keyring.fleet(MASTER, secoc.fleet_nodes(CASE.n))
    key = _stolen_router_key(tmp_path)
    router = rings["router"]
    restarts: list[tuple[str, float, float]] = []
    if what.startswith("65535"):
        inject = _forged_sync(key, lambda: 65535, 2.0)
        restarts = [("router", 5.0, 5.2)]
    elif what.startswith("count"):
        inject = _forged_sync(key, lambda: router.boot, 2.0, (1 << 24) - 256)
    elif what.endswith("alive"):
        inject = _forged_sync(key, lambda: router.boot + secoc.SYNC_BOOT_JUMP_MAX, 2.0)
    else:
        inject = _forged_sync(key, lambda: router.boot + secoc.SYNC_BOOT_JUMP_MAX, 2.5)
        restarts = [("router", 2.0, 4.0)]
    m, tr, counters = _run(tmp_path / "run", inject, rings, restarts=restarts)
    err, p = _final(tr)
    assert err < 1e-3, (what, err)
    assert np.max(np.abs(p - honest)) < 1.0, (what, p, honest)
    assert m["verdict"]["converged"], m["verdict"]
    for i in range(1, CASE.n + 1):
        c = counters[f"agent_{i}"]
        assert c.get("sync_jump", 0) >= 1, (what, i, c)
        if what.startswith(("65535", "count")):  # refused: the price never stopped
            assert c.get("price_timeouts", 0) == 0, (what, i, c)
    assert ("sync_jump", "bus") in _named(m), m["anomalies"]
    assert not any(a["kind"] == "stale_boot" for a in m["anomalies"]), m["anomalies"]


@pytest.mark.slow
def test_without_the_bound_the_forged_sync_locks_the_fleet_out(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The control (the test above can fail): with the bound lifted, no undo and no held
    advance (the rules before AUTH-27 and AUTH-35), the one forged sync of boot 65535
    puts the fleet out of the price for good, the router's restart included, as issue 25
    found."""
    from firmware_py.nodeio import NodeIO

    monkeypatch.setattr("firmware_py.nodeio.beyond_boot_bound", lambda *_a: False)
    monkeypatch.setattr(NodeIO, "_revert", lambda *_a: False)
    monkeypatch.setattr(NodeIO, "_holds_advance", lambda *_a: False)
    key = _stolen_router_key(tmp_path)
    m, _, counters = _run(tmp_path / "run", _forged_sync(key, lambda: 65535, 2.0),
                          restarts=[("router", 5.0, 5.2)])
    assert not m["verdict"]["converged"]
    assert all(counters[f"agent_{i}"].get("price_timeouts", 0) >= 1
               for i in range(1, CASE.n + 1))


@pytest.mark.slow
def test_without_the_count_bound_one_forged_sync_puts_the_fleet_in_safe(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The control of the count case above: with AUTH-27's count bound lifted, the one
    forged sync of the router's own boot (count 2^24 − 256) makes every genuine price a
    replay: every agent's price times out and the run does not converge."""
    from firmware_py.nodeio import NodeIO

    monkeypatch.setattr(NodeIO, "_count_jump", lambda *_a: False)
    rings = secoc.Keyring.fleet(MASTER, secoc.fleet_nodes(CASE.n))
    key = _stolen_router_key(tmp_path)
    m, _, counters = _run(tmp_path / "run", _forged_sync(key, lambda: rings["router"].boot,
                                                         2.0, (1 << 24) - 256), rings)
    assert not m["verdict"]["converged"]
    assert all(counters[f"agent_{i}"].get("price_timeouts", 0) >= 1
               for i in range(1, CASE.n + 1))


def test_the_bound_and_the_undo_at_one_receiver() -> None:
    """AUTH-27 and AUTH-35 at one NodeIO (the plant's receive path is the same code): a
    sync more than SYNC_BOOT_JUMP_MAX boots ahead is `sync_jump` + `auth` and moves
    nothing; one within is held, and the sender's next sync of its boot drops it; taken
    when a forged frame verifies on it, it is undone by that sync; a genuine restart is
    taken at the sender's first frame."""
    from sim.nodes.plant import PlantNode

    rings = secoc.Keyring.fleet(MASTER, secoc.fleet_nodes(CASE.n))
    plant = PlantNode(CASE, keys=rings["plant"])
    io = plant.io
    fid = CODEC.frame_id("AGENT_1_Setpoint")
    # AUTH-28: agent 1's setpoint under its link frame key
    keys = {"AGENT_1_Setpoint": secoc.derive_frame_key(MASTER, "AGENT_1_Setpoint")}
    genuine = FleetSender(CODEC, keys=keys, boot=3)
    frames = [genuine.sync("AGENT_1_Setpoint"),
              genuine.frame("AGENT_1_Setpoint", {"Enable": 0, "PowerSetpoint": 0})]
    t = 1.0  # after the join window (opened at the first syncs() call)
    io.syncs(0.0)
    for msg in frames:
        io.receive(msg, t)
    assert io.last_freshness(fid) == contract.FRESHNESS.join(3, 0)
    too_far = FleetSender(CODEC, keys=keys, boot=3 + secoc.SYNC_BOOT_JUMP_MAX + 1)
    io.receive(too_far.sync("AGENT_1_Setpoint"), t)
    assert io.counters["sync_jump"] == 1 and io.counters["auth"] == 1
    assert io.last_freshness(fid) == contract.FRESHNESS.join(3, 0)
    near = FleetSender(CODEC, keys=keys, boot=3 + secoc.SYNC_BOOT_JUMP_MAX)
    io.receive(near.sync("AGENT_1_Setpoint"), t)
    assert io.last_freshness(fid) == contract.FRESHNESS.join(3, 0)  # held (AUTH-35)
    genuine.frame("AGENT_1_Setpoint", {"Enable": 0, "PowerSetpoint": 0})  # not heard
    io.receive(genuine.sync("AGENT_1_Setpoint"), t)  # its boot: the held advance dropped
    assert io.counters["sync_jump"] == 2 and io.counters["resyncs"] == 2
    assert io.last_freshness(fid) == contract.FRESHNESS.join(3, 2) - 1
    # a key holder that forges a frame on its track too has the advance taken (AUTH-35);
    # the sender's next sync of the boot it is in undoes it (AUTH-27)
    io.receive(near.sync("AGENT_1_Setpoint"), t)
    io.receive(near.frame("AGENT_1_Setpoint", {"Enable": 0, "PowerSetpoint": 0}), t)
    assert contract.FRESHNESS.split(io.last_freshness(fid))[0] == 3 + 8  # taken
    genuine.frame("AGENT_1_Setpoint", {"Enable": 0, "PowerSetpoint": 0})  # not heard
    io.receive(genuine.sync("AGENT_1_Setpoint"), t)
    assert io.counters["sync_jump"] == 3
    assert io.last_freshness(fid) == contract.FRESHNESS.join(3, 3) - 1  # back in boot 3
    # that sync again moves nothing; an older one of boot 3 is a replay
    io.receive(genuine.sync("AGENT_1_Setpoint"), t)
    assert io.counters["sync_jump"] == 3 and io.counters["auth"] == 1
    # a genuine restart: its sync is held, its first frame verifies on the held track
    genuine.restart()
    io.receive(genuine.sync("AGENT_1_Setpoint"), t)
    assert contract.FRESHNESS.split(io.last_freshness(fid) + 1)[0] == 3
    io.receive(genuine.frame("AGENT_1_Setpoint", {"Enable": 0, "PowerSetpoint": 0}), t)
    assert io.last_freshness(fid) == contract.FRESHNESS.join(4, 0)
    assert io.counters["sync_jump"] == 3 and io.counters["auth"] == 1
