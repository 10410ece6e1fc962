"""The C agent runtime (firmware_c/src/agent*.c) against firmware_py, bit for bit.

Every node vector (tests/vectors/node) replays through the C runtime exactly as through
firmware_py's (tests/test_node_vectors.py ``replay``): same configuration, keys, frames
and times, every frame sent byte-identical. Beyond the vectors, hypothesis drives both
runtimes with the same random traffic (valid, forged, replayed, malformed, out of
order) and compares every frame sent and every counter.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_node_vectors import VECTORS, keyring, load, replay

from dbc import dbc_path
from firmware_py import contract, pricesig, secoc
from firmware_py.config import Transmit, agent_configs_from_scenario, parse_agent_config
from firmware_py.contract import SYNCED_BY
from firmware_py.frames import FrameCodec, target_raw
from firmware_py.nodeio import FleetSender
from firmware_py.runtime import AgentRuntime
from firmware_py.secoc import (
    INSECURE_BOOT,
    INSECURE_MASTER,
    Keyring,
    _kbkdf,
    auth_data,
    cmac_aes128,
    derive_command_key,
    derive_frame_key,
    derive_node_key,
    derive_price_sign_key,
    fleet_id,
)
from sim.cbind.cagent import CAgent, keyring_from, ns, params_of, parse_config
from sim.cbind.cimpl import SOURCE_DIR as SOURCE
from sim.conformance.schedule import OTHER_FORMAT
from sim.testkit.tester import fleet_keys

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def c_agent_of(vec: dict[str, Any]) -> CAgent:
    cfg = parse_agent_config(tomllib.loads(vec["config"]), f"{vec['name']}.json")
    agent = CAgent(cfg, keyring(vec))  # None: the public --insecure keys
    tx_count = vec.get("setup", {}).get("tx_count")
    if tx_count is not None:
        agent.set_tx_count(tx_count, tx_count, tx_count)
    return agent


@pytest.mark.parametrize("path", VECTORS, ids=[p.stem for p in VECTORS])
def test_node_vector_replays_byte_exact_in_c(path) -> None:
    vec = load(path)
    assert replay(vec, c_agent_of) == len(vec["output"]) > 0


# --------------------------------------------------------------------------- random traffic

MASTER = bytes(range(16))
# AUTH-28: agent 2's link frames, under keys of their own
FRAMES = {f: derive_frame_key(MASTER, f)
          for f in ("AGENT_2_Setpoint", "PLANT_2_Status", "AGENT_2_Diag")}
COMMANDS = {"agent_2": derive_command_key(MASTER, "agent_2")}  # AUTH-30: its commands' key
ALL_FRAMES = {f: derive_frame_key(MASTER, f) for f in contract.keyed_frames()}  # the senders'
ALL_FRAMES.update({contract.command_key_name(i): derive_command_key(MASTER, f"agent_{i}")
                   for i in contract.agent_ids()})   # and the router's, per target
TS = 2.0 ** -7   # every tick time, offset and timeout is exact in binary64 and in ns
CONFIG = f"""
[agent]
id = 2
lambda0 = 0.8
pinned = true
{{fleet}}

[controller]
kind = "reset"
k = 1.0
h = 2.0
ts = {TS!r}
band = 0.001

[battery]
alpha = 0.005
beta = 0.18
m = 0.08
p_min = {{p_min}}
p_max = {{p_max}}

[limits]
price_persist = 2
untrusted_after = 3

[[neighbour]]
id = 1
weight = 1.0

[[neighbour]]
id = 3
weight = 0.5
"""
SENDER_OF = {"ER_Price": "router", "ER_Command": "router", "PLANT_2_Status": "plant",
             "AGENT_1_MC": "agent_1", "AGENT_3_MC": "agent_3", "AGENT_4_MC": "agent_4",
             "PLANT_3_Status": "plant", "AGENT_1_Setpoint": "agent_1"}
LABELS = ("router", "plant", "agent_1", "agent_3", "agent_4")
I32 = st.integers(-(1 << 31), (1 << 31) - 1)
LAMBDA = st.one_of(st.integers(10_000_000, 20_000_000), I32)   # near 0.6..1.2 cu/kWh, or any
EVENT = st.one_of(
    st.tuples(st.just("tick"), st.integers(1, 40)),              # ticks; >1: a gap
    st.tuples(st.just("price"), LAMBDA, st.booleans(), st.integers(0, 7)),
    st.tuples(st.just("mc"), st.sampled_from((1, 3, 4)), LAMBDA, st.integers(0, 3)),
    st.tuples(st.just("status"), st.integers(0, 15), st.integers(0, 200)),
    st.tuples(st.just("cmd"), st.integers(1, 3), st.integers(1, 4),
              st.sampled_from((0, 400, 500, 1000, 1500, 2000, 2001, 16383)),
              st.sampled_from((0, 900, 1000, 2000, 4000, 4001, 16383))),
    st.tuples(st.just("sync"), st.sampled_from(sorted(SENDER_OF))),
    st.tuples(st.just("restart"), st.sampled_from(LABELS)),
    st.tuples(st.just("replay"), st.integers(0, 1000)),
    st.tuples(st.just("swap"), st.sampled_from((1, 3)), LAMBDA),   # two MC frames reordered
    st.tuples(st.just("forge"), st.sampled_from(sorted(SENDER_OF)),
              st.binary(min_size=8, max_size=8)),
    st.tuples(st.just("junk"), st.integers(0, 0x7FF), st.binary(max_size=8), st.integers(0, 15)),
    st.tuples(st.just("junk"), st.sampled_from(sorted(SYNCED_BY)),
              st.binary(min_size=7, max_size=8), st.just(0)),
)
# the configuration variants: key file and fleet of 4; the setpoint clipped at ±0.5 kW;
# --insecure with no fleet size (peer syncs of any agent, keys derived on demand); the MC
# frame event-triggered (TX-7, a short heartbeat)
VARIANTS = {"base": ("fleet_size = 4", -100.0, 100.0, False, ""),
            "clipped": ("fleet_size = 4", -0.5, 0.5, False, ""),
            "insecure": ("", -100.0, 100.0, True, ""),
            "event": ("fleet_size = 4", -100.0, 100.0, False,
                      '\n[transmit]\nmode = "event"\nheartbeat = 6\n')}


# AUTH-31..33: the signed price, the router's Ed25519 key derived from MASTER as `bess-ded
# keys` derives it; agent 2's key file holds the public key
SIGNED = {"signed": ("fleet_size = 4", -100.0, 100.0, False,
                     "\n[security]\nsigned_price = true\n")}
SEED = derive_price_sign_key(MASTER)
PUBLIC = pricesig.public_key(SEED)
FLEET = fleet_id(MASTER)


# AUTH-34 (CAN FD): the λ tag keys, the KDF of AUTH-1 with the pair's label (computed here
# from the spec, not by firmware_py's derive_lambda_tag_key); the receivers each sender
# tags: agents 1 and 3 agent 2 (a neighbour of theirs), agent 4 agent 2 beside agent 5
# (a non-neighbour of agent 2 that lists it: its sync is a peer sync) and every sender
# the plant and the router
TAG_LABEL = b"bess-ded/secoc/lambda-tag-key/v1"
TAG_RX = {"agent_1": ("agent_2", "plant", "router"), "agent_3": ("agent_2", "plant", "router"),
          "agent_4": ("agent_2", "agent_5", "plant", "router")}


def tag_key(master: bytes, sender: str, receiver: str) -> bytes:
    return _kbkdf(master, TAG_LABEL, f"{sender}>{receiver}".encode(), 16)


def tag_code(node: str) -> int:
    return {"plant": 0xFE, "router": 0xFF}.get(node) or int(node.removeprefix("agent_"))


# agent 2's: its tags to its neighbours, the plant and the router; its neighbours' to it
TAGS = {f"{s}>{r}": tag_key(MASTER, s, r)
        for s, r in (("agent_2", "agent_1"), ("agent_2", "agent_3"), ("agent_2", "plant"),
                     ("agent_2", "router"), ("agent_1", "agent_2"), ("agent_3", "agent_2"))}


def tagged(msg: can.Message, fv: int, master: bytes, slots: tuple[str, ...],
           key: bytes | None = None) -> can.Message:
    """AUTH-34: an FD AGENT_j_MC or its sync (32 bytes) as agent j sends it: Mac 0, a tag
    for each of ``slots`` under the pair key of ``master`` (``key``: every tag under this
    key instead, a forgery)."""
    sender = f"agent_{(msg.arbitration_id & 0xFF)}"
    data = bytearray(msg.data)
    data[0:3] = bytes(3)
    data[8:] = bytes(len(data) - 8)
    payload = bytes((data[3] & 0xF0,)) + bytes(data[4:8])   # AUTH-7's
    for k, r in enumerate(slots):
        tk = key if key is not None else tag_key(master, sender, r)
        data[8 + 4 * k] = tag_code(r)
        data[9 + 4 * k:12 + 4 * k] = cmac_aes128(tk, auth_data(msg.arbitration_id, payload,
                                                                fv))[:3]
    return can.Message(arbitration_id=msg.arbitration_id, data=bytes(data),
                       is_extended_id=False, is_fd=True, bitrate_switch=True)


def _both(variant: str, fd: bool = False, tags: bool = True) -> tuple[AgentRuntime, CAgent]:
    fleet, p_min, p_max, insecure, extra = {**VARIANTS, **SIGNED}[variant]
    signed = variant in SIGNED
    cfg = parse_agent_config(tomllib.loads(CONFIG.format(fleet=fleet, p_min=p_min,
                                                         p_max=p_max) + extra), "random.toml")
    # AUTH-34: on CAN FD no other agent's node key, the λ tag keys instead
    tags = fd and tags
    peers = {n: derive_node_key(MASTER, n)
             for n in ("router", "plant") + (() if tags else ("agent_1", "agent_3"))}

    def ring() -> Keyring:
        if insecure:
            return Keyring.insecure_for("agent_2")
        return Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 6, lambda _b: None,
                       peers=peers, frames=FRAMES, commands=COMMANDS, fleet=FLEET,
                       price_verify=PUBLIC if signed else None, tags=TAGS if tags else None)
    return (AgentRuntime(cfg, FrameCodec(dbc_path(fd, tags)), keys=ring()),
            CAgent(cfg, ring(), fd=fd, lambda_tags=tags))


# the run starts synced and RUNNING: its first tick (its hello), every sender's sync, the
# join window (AUTH-26: 0.2 sync periods, < 30 ticks), then price, status and both
# neighbours for three ticks; the random events follow
JOIN_TICKS = 30
PREAMBLE = ([("tick", 1)] + [("sync", name) for name in sorted(SENDER_OF)]
            + [("tick", JOIN_TICKS)]
            + [("price", 13_421_773, True, 0), ("status", 0, 100), ("mc", 1, 13_000_000, 1),
               ("mc", 3, 14_000_000, 1), ("tick", 1)] * 3)
TRAFFIC = st.one_of(st.tuples(st.just("tick"), st.just(1)),
                    st.tuples(st.just("mc"), st.sampled_from((1, 3)),
                              st.integers(12_000_000, 15_000_000), st.just(1)),
                    EVENT)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(variant=st.sampled_from(sorted(VARIANTS)),
       events=st.lists(TRAFFIC, min_size=20, max_size=300))
def test_c_and_python_agents_agree_on_random_traffic(variant: str, events: list[tuple]) -> None:
    """Both runtimes get the same frames at the same times: valid and invalid prices,
    neighbours' λ, plant status and commands, syncs, sender restarts, replays of earlier
    frames, forged MACs, frames of a sender whose key the agent lacks, junk IDs, wrong
    DLCs, remote/extended/FD frames (out-of-range values come with the forged ones), and
    gaps of up to 40 ticks. Every frame either sends, the counters, the state and λ
    agree at every tick."""
    run_both(variant, PREAMBLE + events)


# AUTH-34: agent 1's λ whose tag to agent 2 is under agent 3's pair key to agent 2, agent
# 1's node key, agent 1's pair key to agent 3, or that has no slot for agent 2
LFORGE = st.tuples(st.just("lforge"), st.sampled_from(("pair_3", "node_1", "pair_1_3",
                                                       "no_slot")), LAMBDA)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(variant=st.sampled_from(sorted(VARIANTS)), tags=st.booleans(),
       events=st.lists(st.one_of(TRAFFIC, LFORGE), min_size=20, max_size=200))
def test_c_and_python_agents_agree_on_an_fd_bus(variant: str, tags: bool,
                                                events: list[tuple]) -> None:
    """GEN-1, RX-2 on a CAN FD bus: every sender's frames FD with the bit-rate switch,
    both agents send FD frames with it, and count a classic frame (the junk without the
    FD flag, the forged ones sent classic) as malformed alike. AUTH-34: the λ frames and
    their syncs 32 bytes with a tag per receiver, both agents' own tagged alike (frame for
    frame), forged λ tags among the traffic; without the tags (``--no-lambda-tags``) λ in
    8 bytes under its sender's node key, as on classic CAN."""
    py, c = run_both(variant, PREAMBLE + events + [("forge", "ER_Price", bytes(8)),
                                                   ("tick", 1)], fd=True, tags=tags)
    assert py.counters["malformed"] == c.counters["malformed"] >= 1


@pytest.mark.parametrize("variant", ["base", "insecure"])
def test_a_forged_lambda_on_fd_is_auth_in_c_and_python(variant: str) -> None:
    """AUTH-34: on CAN FD agent 1's λ to agent 2 verifies only under the pair key
    agent_1>agent_2: tagged under agent 3's key to agent 2 (agent 3's key file), under agent
    1's node key, under agent 1's key to agent 3, or without a slot for agent 2, it is
    `auth` in both runtimes and its λ is not used; the genuine frames after it are."""
    forged = []
    for how in ("pair_3", "node_1", "pair_1_3", "no_slot"):
        forged += [("lforge", how, 30_000_000), ("tick", 1), ("mc", 1, 13_100_000, 1),
                   ("tick", 1)]
    py, c = run_both(variant, PREAMBLE + forged, fd=True)
    assert c.counters["auth"] == py.counters["auth"] == 4
    assert c.counters["lost_frames"] == py.counters["lost_frames"] == 4
    assert c.state == py.state and c.lambda_q24 == py.lambda_q24


@pytest.mark.parametrize("variant", ["base", "insecure"])
def test_acceptance_filter_ids_on_fd_are_firmware_pys(variant: str) -> None:
    """GEN-5 on CAN FD (AUTH-34): a key file with no neighbour's node key (its tag keys
    instead) and derived keys both give firmware_py's acceptance IDs."""
    py, c = _both(variant, fd=True)
    assert c.accepted_ids() == sorted(py.io.accepted_ids())


def test_c_lambda_tag_key_is_auth_34s_kdf() -> None:
    """AUTH-34: bd_derive_lambda_tag_key is AUTH-1's KDF (NIST SP 800-108, CMAC) with the
    label "bess-ded/secoc/lambda-tag-key/v1" and the pair's label as context, as
    cryptography's KBKDFCMAC computes it; not a sender that is no agent."""
    import ctypes

    from sim.cbind.cagent import load

    lib = load().lib
    lib.bd_derive_lambda_tag_key.argtypes = [ctypes.c_char_p] * 4
    for s_, r in (("agent_1", "agent_3"), ("agent_64", "router"), ("agent_12", "plant")):
        out = ctypes.create_string_buffer(16)
        assert lib.bd_derive_lambda_tag_key(MASTER, s_.encode(), r.encode(), out) == 0
        assert out.raw == tag_key(MASTER, s_, r)
    assert lib.bd_derive_lambda_tag_key(MASTER, b"plant", b"agent_1", out) != 0


def test_more_than_four_neighbours_on_fd_are_refused_in_c_and_python() -> None:
    """AUTH-34: an FD agent's λ has 6 tag slots, the plant's and the router's beside its
    neighbours': 5 neighbours are a configuration error at start on CAN FD (bd_agent_init
    refuses it; firmware_py raises ConfigError), and run on classic CAN."""
    from firmware_py.errors import ConfigError

    text = CONFIG.format(fleet="", p_min=-1.0, p_max=1.0) + "".join(
        f"\n[[neighbour]]\nid = {j}\nweight = 1.0\n" for j in (4, 5, 6))
    cfg = parse_agent_config(tomllib.loads(text), "five.toml")
    assert len(cfg.neighbours) == 5
    with pytest.raises(ValueError, match="refused agent 2"):
        CAgent(cfg, fd=True)
    with pytest.raises(ConfigError):
        AgentRuntime(cfg, FrameCodec(dbc_path(True)))
    CAgent(cfg)   # classic CAN: no tags, no limit
    AgentRuntime(cfg, FrameCodec())


# AUTH-32: an ER_PriceSig transfer: the segment number's step from the last one (1500:
# back), the boot's from the router's, PriceValid, ρ, who signs (the router; another key;
# the router's with a bit flipped) and what happens to the pages on the way
SIG_EVENT = st.tuples(st.just("sig"), st.sampled_from((0, 1, 1, 2, 7, 1500)),
                      st.sampled_from((0, 0, 0, -1, 1, -3)), st.integers(0, 1),
                      st.sampled_from((13_421_773, 13_000_000, -5, 1 << 30)),
                      st.sampled_from(("router", "router", "router", "other", "flip")),
                      st.sampled_from(("whole", "whole", "whole", "drop", "dup", "tail",
                                       "no_header", "reversed", "junk", "short")),
                      st.integers(1, pricesig.SIG_PAGES))
SIGNED_TRAFFIC = st.one_of(TRAFFIC, SIG_EVENT, SIG_EVENT,
                           st.tuples(st.just("sprice"), st.booleans()))
# the first transfer: the segment the preamble's prices carry (number 0, boot 3: the
# router's), so the signed agent starts RUNNING as the others do
SIGNED_PREAMBLE = ([("tick", 1)] + [("sync", name) for name in sorted(SENDER_OF)]
                   + [("tick", JOIN_TICKS), ("sig", 0, 0, 1, 13_421_773, "router", "whole", 1)]
                   + PREAMBLE[1 + len(SENDER_OF) + 1:])


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(events=st.lists(SIGNED_TRAFFIC, min_size=20, max_size=250))
def test_c_and_python_agents_agree_on_signed_price_traffic(events: list[tuple]) -> None:
    """AUTH-31..33 in both runtimes: ER_PriceSig transfers genuine, under another key,
    with a bit flipped, of older or newer segments and boots (replays), with pages lost,
    repeated with other bytes, reordered, without their header, a last page too long,
    pages out of range and short; ER_Prices of the signed segment or not, among the
    random traffic of the other tests. Every frame sent, every counter (unsigned_price,
    bad_signature, sig_malformed by name), the state, λ and the number of signatures
    verified agree at every tick."""
    py, c = run_both("signed", SIGNED_PREAMBLE + events)
    assert py.price_sig is not None and py.price_sig.verifications >= 1


def test_signed_price_attack_is_refused_alike_in_c_and_python() -> None:
    """The forged-price attack of tests/test_pricesig.py, frame for frame on both
    runtimes: agent 3's key file forges ER_Prices under the router's node key (a valid
    MAC) and ER_PriceSig transfers under an Ed25519 key of its own, plus malformed
    pages; both agents refuse each alike and keep the signed price."""
    attack = []
    for k in range(12):
        attack += [("sig", 0, 0, 1, 50_331_648, "other", "whole", 1),   # ρ = 3 forged
                   ("price", 50_331_648, True, 0), ("price", 13_421_774 + k, True, 0),
                   ("sig", 0, 0, 1, 13_421_773, "router", "junk", 3),
                   ("sig", 0, 0, 1, 13_421_773, "router", "tail", 1),
                   ("sprice", True), ("tick", 1)]
    py, c = run_both("signed", SIGNED_PREAMBLE + attack)
    assert c.counters["unsigned_price"] == py.counters["unsigned_price"] == 24
    assert c.counters["bad_signature"] == py.counters["bad_signature"] == 12
    assert c.counters["sig_malformed"] == py.counters["sig_malformed"] >= 24
    assert c.counters.get("implausible_price", 0) == 0
    assert py.price_sig is not None and c.sig_verifications == py.price_sig.verifications == 13
    assert py.state == c.state


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_a_genuine_frame_out_of_order_is_stale_not_forged_in_both(variant: str) -> None:
    """AUTH-25: neighbour 1's two MC frames swapped on the way: the later one is used,
    the earlier one arrives behind it with a valid MAC under an older freshness value:
    `stale` in both runtimes, never `auth`; a forged MAC stays `auth`."""
    py, c = run_both(variant, PREAMBLE + [("swap", 1, 13_100_000), ("tick", 1),
                                          ("swap", 3, 13_900_000), ("tick", 1)])
    assert py.counters["stale"] == c.counters["stale"] == 2
    assert py.counters["auth"] == c.counters["auth"] == 0
    py, c = run_both(variant, PREAMBLE + [("forge", "AGENT_1_MC", bytes(8)), ("tick", 1)])
    assert py.counters["auth"] == c.counters["auth"] == 1 and py.counters["stale"] == 0


def run_both(variant: str, events: list[tuple], fd: bool = False, tags: bool = True
             ) -> tuple[AgentRuntime, CAgent]:
    """Both runtimes through the same events (EVENT's kinds; ("at", dt): the next frames
    arrive dt after the last tick, which may go back in time), frames (their format
    too), counters, state and λ compared at every tick. ``fd``: a CAN FD bus, every
    sender's frames FD (the forged ones classic: malformed there); ``tags``: with λ tags
    (AUTH-34) there, else λ in 8 bytes under its sender's node key."""
    py, c = _both(variant, fd, tags)
    codec = FrameCodec(dbc_path(fd, tags))
    tagging = fd and tags
    # AUTH-34: the senders tag their λ for TAG_RX's receivers (firmware_py's FleetSender,
    # checked below against this module's tags computed from the spec)
    receivers = {int(s.removeprefix("agent_")): rx for s, rx in TAG_RX.items()}
    pairs = {f"{s}>{r}": tag_key(MASTER, s, r) for s, rx in TAG_RX.items() for r in rx}
    if {**VARIANTS, **SIGNED}[variant][3]:   # every insecure sender: boot 1, public keys
        senders = {n: FleetSender(codec, tag_receivers=receivers) for n in LABELS}
    else:
        senders = {n: FleetSender(codec, keys={n: derive_node_key(MASTER, n), **ALL_FRAMES,
                                               **pairs}, boot=b, tag_receivers=receivers)
                   for n, b in zip(LABELS, (3, 5, 2, 4, 9), strict=True)}
    history: list[can.Message] = []
    n = 0
    t_rx = TS / 2
    signed: list[Any] = [None, 0]   # the segment the router last signed, its number
    master = INSECURE_MASTER if {**VARIANTS, **SIGNED}[variant][3] else MASTER

    def deliver(msg: can.Message) -> None:
        history.append(msg)
        py.on_frame(msg, t_rx)
        c.on_frame(msg, t_rx)

    def lam(name: str, raw: dict[str, int], key: bytes | None = None,
            slots: tuple[str, ...] | None = None) -> can.Message:
        """Agent j's MC (``name``), tagged on CAN FD (AUTH-34; ``key``, ``slots``: forged)."""
        sender = senders[SENDER_OF[name]]
        msg = sender.frame(name, raw)
        if not tagging:
            return msg
        fv = contract.FRESHNESS.join(sender.boot, sender._count[msg.arbitration_id])
        assert msg.data == tagged(msg, fv, master, TAG_RX[SENDER_OF[name]]).data
        if key is None and slots is None:
            return msg
        return tagged(msg, fv, master, slots or TAG_RX[SENDER_OF[name]], key)

    for ev in events:
        kind = ev[0]
        if kind == "tick":
            n += ev[1]
            t = n * TS
            want = [(m.arbitration_id, bytes(m.data), m.is_fd, m.bitrate_switch)
                    for m in py.tick(t)]
            got = [(m.arbitration_id, bytes(m.data), m.is_fd, m.bitrate_switch)
                   for m in c.tick(t)]
            assert got == want, f"tick {n}: frames differ"
            assert c.counters == +py.counters, f"tick {n}: counters differ"
            assert c.state == py.state and c.lambda_q24 == py.lambda_q24
            assert c.sig_verifications == (py.price_sig.verifications if py.price_sig
                                           else 0), f"tick {n}: verifications differ"
            t_rx = t + TS / 2
        elif kind == "at":
            t_rx = n * TS + ev[1]
        elif kind == "price":
            deliver(senders["router"].frame("ER_Price", {"PriceValid": int(ev[2]),
                                                         "Segment": ev[3], "Rho": ev[1]}))
        elif kind == "mc":
            deliver(lam(f"AGENT_{ev[1]}_MC", {"State": ev[3], "Resets": 0, "Lambda": ev[2]}))
        elif kind == "lforge":   # AUTH-34: agent 1's λ with agent 2's tag under another key
            _, how, value = ev
            key = {"pair_3": tag_key(master, "agent_3", "agent_2"),   # agent 3's file
                   "node_1": derive_node_key(master, "agent_1"),      # its node key
                   "pair_1_3": tag_key(master, "agent_1", "agent_3")}.get(how)  # another pair
            slots = {"no_slot": ("agent_3", "plant", "router")}.get(how)
            deliver(lam("AGENT_1_MC", {"State": 1, "Resets": 0, "Lambda": value}, key, slots))
        elif kind == "status":
            f = ev[1]
            deliver(senders["plant"].frame("PLANT_2_Status", {
                "FaultOverCurrent": f & 1, "FaultVoltage": f >> 1 & 1, "FaultSoc": f >> 2 & 1,
                "PowerLimited": f >> 3 & 1, "Power": 0, "Soc": ev[2]}))
        elif kind == "cmd":
            deliver(senders["router"].frame("ER_Command", {
                "Command": ev[1], "Target": target_raw(ev[2]), "GainK": ev[3], "GainH": ev[4]}))
        elif kind == "sync":
            msg = senders[SENDER_OF[ev[1]]].sync(ev[1])
            if tagging and ev[1].endswith("_MC"):   # AUTH-34: FV = Boot:Count of the sync
                d = int.from_bytes(msg.data[:8], "little")
                assert msg.data == tagged(msg, contract.FRESHNESS.join(
                    d >> 48, d >> 24 & 0xFFFFFF), master, TAG_RX[SENDER_OF[ev[1]]]).data
            deliver(msg)
        elif kind == "restart":
            senders[ev[1]].restart()
        elif kind == "swap":   # the later frame arrives first, the earlier one late
            name = f"AGENT_{ev[1]}_MC"
            early, late = (lam(name, {"State": 1, "Resets": 0, "Lambda": ev[2]})
                           for _ in range(2))
            deliver(late)
            deliver(early)
        elif kind == "replay" and history:
            deliver(history[ev[1] % len(history)])
        elif kind == "forge":
            fid = FrameCodec().frame_id(ev[1])
            deliver(can.Message(arbitration_id=fid, data=ev[2], is_extended_id=False))
        elif kind == "sig":
            for msg in _sig_transfer(ev, senders["router"].boot, signed, codec):
                deliver(msg)
        elif kind == "sprice" and signed[0] is not None:   # the segment last signed
            seg = signed[0]
            deliver(senders["router"].frame("ER_Price", {
                "PriceValid": seg.valid, "Segment": seg.number % pricesig.SEGMENT_LOW_MOD,
                "Rho": seg.rho if ev[1] else seg.rho + 1}))
        elif kind == "junk":
            fid, data, flags = ev[1], ev[2], ev[3]
            deliver(can.Message(arbitration_id=fid, data=data, dlc=len(data), check=False,
                                is_extended_id=bool(flags & 1), is_remote_frame=bool(flags & 2),
                                is_fd=bool(flags & 4)))
    return py, c


def _sig_transfer(ev: tuple, boot: int, signed: list[Any], codec: FrameCodec
                  ) -> list[can.Message]:
    """SIG_EVENT's ER_PriceSig pages (``signed``: [the router's last signed segment, the
    segment number], updated)."""
    _, step, dboot, valid, rho, who, how, k = ev
    number = (signed[1] + step) % pricesig.SEGMENT_MOD
    signed[1] = number
    seg = pricesig.SignedSegment(min(max(boot + dboot, 0), 0xFFFF), number, valid, rho)
    sig = pricesig.sign(SEED if who != "other" else bytes(32), FLEET, seg)
    if who == "flip":
        sig = sig[:k] + bytes([sig[k] ^ 0x10]) + sig[k + 1:]
    elif who == "router":
        signed[0] = seg
    raws = pricesig.pages(seg, sig)
    if how == "drop":
        del raws[k]
    elif how == "dup":
        raws.insert(k + 1, {**raws[k], "Signature": raws[k]["Signature"] ^ 1})
    elif how == "tail":
        raws[-1] = {**raws[-1], "Signature": raws[-1]["Signature"] | 1 << (8 * k % 56 or 8)}
    elif how == "no_header":
        raws = raws[1:]
    elif how == "reversed":
        raws = raws[:1] + raws[:0:-1]
    msgs = [codec.encode(pricesig.MESSAGE, raw, 0) for raw in raws]
    if how == "junk":   # a page beyond the DBC's range, mid-transfer
        data = bytearray(msgs[k].data)
        data[0] = (data[0] & 0xF0) | (11 + k % 5)
        msgs.insert(k, can.Message(arbitration_id=msgs[k].arbitration_id, data=bytes(data),
                                   is_extended_id=False, is_fd=msgs[k].is_fd))
    elif how == "short":   # a page of 5 bytes
        msgs.insert(k, can.Message(arbitration_id=msgs[k].arbitration_id,
                                   data=bytes(msgs[k].data[:5]), is_extended_id=False,
                                   is_fd=msgs[k].is_fd))
    return msgs


# --------------------------------------------------------------------------- edges


def _cfg(variant: str = "base") -> Any:
    fleet, p_min, p_max, _, extra = VARIANTS[variant]
    return parse_agent_config(tomllib.loads(CONFIG.format(fleet=fleet, p_min=p_min,
                                                          p_max=p_max) + extra), "edge.toml")


@pytest.mark.parametrize("peers", [("router", "plant", "agent_1", "agent_3"),
                                   ("router", "plant", "agent_1", "agent_3", "agent_4",
                                    "agent_12"), None])
def test_acceptance_filter_ids_are_firmware_pys(peers: tuple[str, ...] | None) -> None:
    """bd_agent_accepted_ids: the own IDs, the inputs and their syncs, and the peer syncs
    of key holders beyond the inputs' senders (none in insecure mode), as NodeIO's."""
    cfg = _cfg()
    if peers is None:
        ring = Keyring.insecure_for("agent_2")
        ring_c = Keyring.insecure_for("agent_2")
    else:
        keys = {n: derive_node_key(MASTER, n) for n in peers}
        ring = Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 0, lambda _b: None,
                       peers=keys, frames=FRAMES, commands=COMMANDS)
        ring_c = Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 0, lambda _b: None,
                         peers=keys, frames=FRAMES, commands=COMMANDS)
    assert CAgent(cfg, ring_c).accepted_ids() == AgentRuntime(cfg, keys=ring).io.accepted_ids()


def test_acceptance_filter_passes_the_price_signature_in_signed_mode() -> None:
    """AUTH-32: with signed_price the filter passes ER_PriceSig (0x008) too, as NodeIO's."""
    py, c = _both("signed")
    assert c.accepted_ids() == py.io.accepted_ids()
    assert FrameCodec().frame_id(pricesig.MESSAGE) in c.accepted_ids()


def test_loop_events_are_counted_and_reported_on_the_diag_frame() -> None:
    py, c = _both("base")
    for agent in (py, c):
        agent.note("deadline_miss", 3)
        agent.note("send_failure")
    assert c.counters == +py.counters
    assert [bytes(m.data) for m in c.tick(0.0)] == [bytes(m.data) for m in py.tick(0.0)]


def test_init_refuses_what_the_runtime_cannot_hold() -> None:
    cfg = _cfg()
    ring = Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 0, lambda _b: None,
                   peers={"router": derive_node_key(MASTER, "router")})
    with pytest.raises(ValueError, match="error 11"):   # no key of plant, agent_1, agent_3
        CAgent(cfg, ring)
    bad = keyring_from(Keyring.insecure_for("agent_2"))
    bad.n_peers = 1
    bad.peer_label[0].value = b"agent_99"
    with pytest.raises(ValueError, match="error 10"):
        CAgent(cfg, bad)
    params = params_of(cfg)
    params.id = 0
    with pytest.raises(ValueError, match="error 10"):
        CAgent(cfg, None, params=params)


def test_boot_is_persisted_before_use_and_a_failure_refuses_the_start() -> None:
    saved: list[int] = []
    peers = {n: derive_node_key(MASTER, n) for n in ("router", "plant", "agent_1", "agent_3")}
    ring = Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 6, saved.append,
                   peers=peers, frames=FRAMES, commands=COMMANDS)
    c = CAgent(_cfg(), ring)
    assert saved == [7] and c.boot == 7 and ring.boot == 7

    def refuse(_boot: int) -> None:
        raise OSError("disk full")
    ring = Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 6, refuse, peers=peers,
                   frames=FRAMES, commands=COMMANDS)
    with pytest.raises(ValueError, match="error 12"):
        CAgent(_cfg(), ring)
    ring = Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 65535, saved.append,
                   peers=peers, frames=FRAMES, commands=COMMANDS)
    with pytest.raises(ValueError, match="error 12"):   # the boot counter is exhausted
        CAgent(_cfg(), ring)


def _replay_alike(py: AgentRuntime, c: CAgent, script: list[can.Message]) -> None:
    """Tick both agents at t = 0, then give each frame of ``script`` one tick apart, after
    the join window (AUTH-26: its hello opened): the same frames out and the same
    counters at every tick."""
    assert [bytes(m.data) for m in py.tick(0.0)] == [bytes(m.data) for m in c.tick(0.0)]
    for k, msg in enumerate(script):
        t = (JOIN_TICKS + k) * TS
        py.on_frame(msg, t)
        c.on_frame(msg, t)
        assert [bytes(m.data) for m in py.tick(t)] == [bytes(m.data) for m in c.tick(t)]
        assert py.counters == c.counters, (k, py.counters, c.counters)


def test_a_status_under_another_agents_link_key_is_auth_alike_in_c_and_python() -> None:
    """AUTH-28, bit for bit: agent 2 (a key file's keys: the router's and its neighbours'
    node keys, its own link frame keys) takes PLANT_2_Status and its sync under
    PLANT_2_Status's key; the same sync and frames under PLANT_3_Status's key (what
    agent 3's file holds) or under the plant's node key (what every agent held before)
    are `auth` on both runtimes and change nothing; another agent's link sync
    (PLANT_3_Status_Sync, AGENT_1_Setpoint_Sync) is ignored, as on no key held."""
    peers = {n: derive_node_key(MASTER, n) for n in ("router", "agent_1", "agent_3")}

    def ring() -> Keyring:
        return Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 6, lambda _b: None,
                       peers=peers, frames=FRAMES, commands=COMMANDS)
    cfg = _cfg()
    py, c = AgentRuntime(cfg, FrameCodec(), keys=ring()), CAgent(cfg, ring())
    status = {"Soc": 100, "Power": 0, "PowerLimited": 0, "FaultSoc": 0, "FaultVoltage": 0,
              "FaultOverCurrent": 1}
    forgers = [FleetSender(FrameCodec(), keys={"PLANT_2_Status": k}, boot=5) for k in (
        ALL_FRAMES["PLANT_3_Status"], derive_node_key(MASTER, "plant"))]
    others = FleetSender(FrameCodec(), keys=ALL_FRAMES, boot=5)
    genuine = FleetSender(FrameCodec(), keys=ALL_FRAMES, boot=4)
    script = [genuine.sync("PLANT_2_Status"),
              *(m for f in forgers for m in (f.sync("PLANT_2_Status"),
                                             f.frame("PLANT_2_Status", status))),
              others.sync("PLANT_3_Status"), others.sync("AGENT_1_Setpoint"),
              genuine.frame("PLANT_2_Status", {**status, "FaultOverCurrent": 0})]
    _replay_alike(py, c, script)
    assert py.counters["auth"] == 4 and py.counters["resyncs"] == 1
    assert py.counters["plant_faults"] == 0 and py.state == c.state


def test_a_command_under_another_agents_key_is_auth_alike_in_c_and_python() -> None:
    """AUTH-30, bit for bit: agent 2 holds its own command key only. A genuine command
    for agent 3 (under agent 3's key) is not its input: ignored, uncounted. An ISOLATE
    for agent 2 under agent 3's command key (what agent 3's file holds) or the router's
    node key (what signed every command before) is `auth` on both runtimes and changes
    nothing. The genuine ISOLATE after 20 commands to others (the router's count moved
    unseen) is found by the wide search, taken, and no frame is counted lost."""
    peers = {n: derive_node_key(MASTER, n) for n in ("router", "agent_1", "agent_3")}

    def ring() -> Keyring:
        return Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 6, lambda _b: None,
                       peers=peers, frames=FRAMES, commands=COMMANDS)
    cfg = _cfg()
    py, c = AgentRuntime(cfg, FrameCodec(), keys=ring()), CAgent(cfg, ring())
    router = FleetSender(FrameCodec(), keys={"router": peers["router"], **ALL_FRAMES}, boot=4)
    isolate = {"Command": int(contract.Command.ISOLATE), "GainK": 0, "GainH": 0}
    forgers = [FleetSender(FrameCodec(), keys={contract.command_key_name(2): k}, boot=4)
               for k in (ALL_FRAMES[contract.command_key_name(3)], peers["router"])]
    script = [router.sync("ER_Command"),
              router.frame("ER_Command", {**isolate, "Target": target_raw(3)}),
              *(f.frame("ER_Command", {**isolate, "Target": target_raw(2)}, counter=2)
                for f in forgers)]
    router.skip("ER_Command", 20)
    script.append(router.frame("ER_Command", {**isolate, "Target": target_raw(2)}))
    _replay_alike(py, c, script)
    assert py.counters["auth"] == 2 and py.counters["commands"] == 1
    assert py.counters["lost_frames"] == 0 and py.state == c.state == contract.State.ISOLATED


def test_a_count_wrap_at_the_last_boot_stops_the_agent() -> None:
    """AUTH-5 with no boot left: firmware_py raises (the node ends); the C agent sends
    nothing more and reports BD_ERR_BOOT."""
    peers = {n: derive_node_key(MASTER, n) for n in ("router", "plant", "agent_1", "agent_3")}
    ring = Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 65534, lambda _b: None,
                   peers=peers, frames=FRAMES, commands=COMMANDS)
    c = CAgent(_cfg(), ring)
    c.set_tx_count((1 << 24) - 1, 0)
    assert len(c.tick(0.0)) == 6          # 3 syncs, the last MC count, setpoint, diag
    assert c.tick(TS) == [] and c.fatal == 12


def test_a_sync_below_the_boot_floor_is_refused_alike_in_c_and_python() -> None:
    """AUTH-21, bit for bit: a router sync of boot 4 (valid MAC) below the floor 5 is
    `auth` on the sync ID and sets no freshness, so the replayed price after it is
    `unsynced`; the genuine sync of boot 5 is taken, and its price. The plant's sync of
    agent 2's status below the plant's floor is `auth` too (the floor of the sender of a
    link frame, AUTH-28); its sync of agent 1's status is none of agent 2's: ignored."""
    peers = {n: derive_node_key(MASTER, n) for n in ("router", "plant", "agent_1", "agent_3")}

    def ring() -> Keyring:
        return Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 6, lambda _b: None,
                       peers=peers, floors={"router": 5, "plant": 3},
                       frames=FRAMES, commands=COMMANDS)
    cfg = _cfg()
    py, c = AgentRuntime(cfg, FrameCodec(), keys=ring()), CAgent(cfg, ring())
    old = FleetSender(FrameCodec(), boot=4,
                      keys={**{n: derive_node_key(MASTER, n) for n in peers}, **ALL_FRAMES})
    new = FleetSender(FrameCodec(), keys=old.keys, boot=5)
    price = {"PriceValid": 1, "Rho": 1 << 23, "Segment": 0}
    script = [old.sync("ER_Price"), old.frame("ER_Price", price),
              old.sync("PLANT_1_Status"), old.sync("PLANT_2_Status"),  # plant at boot 4 ok
              FleetSender(FrameCodec(), keys=old.keys, boot=2).sync("PLANT_2_Status"),
              new.sync("ER_Price"), new.frame("ER_Price", price)]
    _replay_alike(py, c, script)
    assert py.counters["auth"] == 2 and py.counters["unsynced"] == 1
    assert py.io.last_safety == ("auth", 0x682)
    assert py.price == 1 << 23 and py.state == c.state  # the genuine price only


def _agent_2_alike() -> tuple[AgentRuntime, CAgent, dict[str, bytes]]:
    """Agent 2 in firmware_py and in C, each with its own key ring (the node keys of the
    router, the plant and agents 1 and 3), and every key the tests' senders sign with."""
    peers = {n: derive_node_key(MASTER, n) for n in ("router", "plant", "agent_1", "agent_3")}

    def ring() -> Keyring:
        return Keyring("agent_2", derive_node_key(MASTER, "agent_2"), 6, lambda _b: None,
                       peers=dict(peers), frames=FRAMES, commands=COMMANDS)
    cfg = _cfg()
    return (AgentRuntime(cfg, FrameCodec(), keys=ring()), CAgent(cfg, ring()),
            peers | ALL_FRAMES)


def test_a_forged_boot_jump_is_refused_held_or_undone_alike_in_c_and_python() -> None:
    """AUTH-27 and AUTH-35, bit for bit (issue 25): with the router's key (which agent 3's
    key file holds), a price sync of boot 5 + 9 is refused (`sync_jump`, `auth`) and the
    genuine price goes on; one of boot 5 + 8 (within the bound) is held: the genuine
    price goes on, and the router's next sync of boot 5 drops it (`sync_jump`), so a
    price forged on its track is `auth`. Held again and completed by a forged price, it
    is taken; the genuine price then fails (`auth`) and the router's next sync undoes it;
    the router restarted (boot 6) is held and taken at its first price."""
    py, c, keys = _agent_2_alike()
    router = FleetSender(FrameCodec(), keys=keys, boot=5)
    far = FleetSender(FrameCodec(), keys=keys, boot=5 + 9)
    near = FleetSender(FrameCodec(), keys=keys, boot=5 + 8)
    price = {"PriceValid": 1, "Rho": 1 << 23, "Segment": 0}
    script = [router.sync("ER_Price"), router.frame("ER_Price", price),
              far.sync("ER_Price"), router.frame("ER_Price", price),  # refused; price goes on
              near.sync("ER_Price"), router.frame("ER_Price", price),  # held; price goes on
              router.sync("ER_Price"), near.frame("ER_Price", price),  # dropped; forged: auth
              near.sync("ER_Price"), near.frame("ER_Price", price),  # held, completed: taken
              router.frame("ER_Price", price),  # the genuine price fails
              router.sync("ER_Price"), router.frame("ER_Price", price)]  # undone; price
    router.restart()
    script += [router.sync("ER_Price"), router.frame("ER_Price", price)]  # held, taken
    _replay_alike(py, c, script)
    assert py.counters["sync_jump"] == 3  # refused, dropped, undone
    assert py.counters["auth"] == 3  # the far sync, the forged price, the genuine one
    assert py.counters["resyncs"] == 4  # the first, the completed advance, the undo, the restart
    assert py.io.last_freshness(FrameCodec().frame_id("ER_Price")) == \
        (6 << 24)  # the restarted router's first price frame


def test_a_held_advance_is_replaced_and_the_undo_point_is_used_once() -> None:
    """AUTH-27 and AUTH-35, bit for bit: two forged price syncs in a row (boot 5 → 9 → 13,
    each within the bound) are held, the second replacing the first; completed by a price
    forged on its track, the advance is taken, and the restarted router's first sync
    (boot 6) undoes it. The undo point is used once: a genuine boot-5 sync replayed
    after it (newer than any boot-5 frame taken) is a replay (`auth`), not an undo."""
    py, c, keys = _agent_2_alike()
    router = FleetSender(FrameCodec(), keys=keys, boot=5)
    price = {"PriceValid": 1, "Rho": 1 << 23, "Segment": 0}
    forger = FleetSender(FrameCodec(), keys=keys, boot=13)
    script = [router.sync("ER_Price"), router.frame("ER_Price", price),
              FleetSender(FrameCodec(), keys=keys, boot=9).sync("ER_Price"),
              forger.sync("ER_Price"), forger.frame("ER_Price", price)]
    router.frame("ER_Price", price)  # not heard: the router's last boot-5 frame
    replay = router.sync("ER_Price")  # a genuine boot-5 sync, newer than any frame taken
    router.restart()
    script += [router.sync("ER_Price"), router.frame("ER_Price", price), replay,
               router.frame("ER_Price", price)]
    _replay_alike(py, c, script)
    assert py.counters["sync_jump"] == 1  # the one undo
    assert py.counters["resyncs"] == 3  # the first sync, the completed advance, the undo
    assert py.counters["auth"] == 1  # the replayed boot-5 sync
    assert py.io.last_freshness(FrameCodec().frame_id("ER_Price")) == (6 << 24) + 1


# --------------------------------------------------------------------------- conformance


@pytest.mark.parametrize("case,dut,jitter,filtered,fd,trim,insecure,variant", [
    (1, 3, 0.0, False, False, 0, False, ""),
    (1, 1, 0.9, True, True, 0, False, ""),
    (7, 5, 0.5, False, False, 1, False, "persist 1"),
    (6, 3, 0.3, False, False, 0, True, ""),
    (2, 3, 0.3, False, False, 0, False, "PC"),
    (2, 2, 0.3, False, False, 0, False, "finite-time"),
    (1, 1, 0.3, False, False, 0, False, "signed price"),
    (7, 2, 0.3, False, False, 0, False, "event")])
def test_the_c_agent_passes_the_conformance_schedule(case: int, dut: int, jitter: float,
                                                     filtered: bool, fd: bool,
                                                     trim: int, insecure: bool,
                                                     variant: str) -> None:
    """`bess-ded conformance`'s whole schedule (sim.conformance: 1620 ticks, the
    requirements) played against the C agent on a simulated clock, with late ticks and
    frames, and behind its acceptance filter: every requirement passes; on a CAN FD bus
    too (``fd``: `bess-ded conformance --fd`, the C agent's --fd), with the resilient
    update on (``trim``: `--resilient 1`, WMSR-1 and WMSR-2 judged), and with the public
    keys (``insecure``: `--insecure`, AUTH-1 and AUTH-20 judged); a pc and an ft device
    (case 2's ``variant``: STEP-10, resp. STEP-11, CTRL-3 and NUM-5 judged, not the PI
    family's step); with `--price-persist 1` (``variant`` "persist 1": PRICE-5 judged);
    with `--signed-price` (``variant`` "signed price": the tester signs every price as the
    router, plays refused ones; AUTH-31..33 judged); with `--event-transmit` (``variant``
    "event": the MC frame sent event-triggered; TX-7 and CFG-9 judged)."""
    from sim import conformance as conf
    from sim.model.scenario import load_case

    persist = 1 if variant == "persist 1" else conf.PRICE_PERSIST
    sc = load_case(case).variant(variant) if variant in ("PC", "finite-time") else load_case(
        case)
    # the configuration the tester writes: the C loader reads it for the device, the
    # reference parser for the oracle (issue 22 item 4: the configuration path)
    agent = replace(agent_configs_from_scenario(sc)[dut - 1], resilient_f=trim,
                    signed_price=variant == "signed price",
                    transmit=Transmit("event" if variant == "event" else "periodic"))
    text, cfg = conf.written_config(agent, persist)
    params = parse_config(text)
    keys = fleet_keys(MASTER, sc.n)   # node keys and link frame keys (AUTH-28)
    node = f"agent_{dut}"
    seed = secoc.derive_price_sign_key(MASTER)  # signed_price: the router's (AUTH-31)
    if cfg.signed_price:  # the tester signs as the router, for the master's fleet
        keys.update({pricesig.TESTER_SIGN: seed,
                     pricesig.MONITOR_FLEET: bytes.fromhex(secoc.fleet_id(MASTER))})

    def ring() -> Keyring:
        if insecure:
            return Keyring.insecure_for(node)
        return Keyring(node, keys[node], 0, lambda _b: None, master=MASTER,
                       price_verify=pricesig.public_key(seed) if cfg.signed_price else None,
                       fleet=secoc.fleet_id(MASTER))

    codec = FrameCodec(dbc_path(fd))
    planned = (conf.plan(cfg, None, sc.prices[0].rho, boot=INSECURE_BOOT, codec=codec)
               if insecure else conf.plan(cfg, keys, sc.prices[0].rho, codec=codec))
    frames = conf.simulate(cfg, ring(), planned, jitter=jitter, seed=dut, filtered=filtered,
                           codec=codec,
                           make_dut=lambda c, _codec, k: CAgent(c, k, params=params, fd=fd))
    assert all(f.msg.is_fd == f.msg.bitrate_switch == fd for f in frames
               if f.note != OTHER_FORMAT)  # but RX-2's frame
    outcome = conf.check(cfg, ring(), ring().key, frames, codec)
    results = conf.verdict(outcome)
    assert not outcome.mismatches, outcome.mismatches[:3]
    assert not outcome.auth_errors and not outcome.problems
    assert outcome.steps_seen == {s.name for s in conf.STEPS}
    assert all(r.passed for r in results), [r for r in results if not r.passed]
    judged = {r.must for r in results}
    assert judged & {"WMSR-1", "WMSR-2"} == ({"WMSR-1", "WMSR-2"} if trim else set())
    assert judged & {"AUTH-1", "AUTH-20"} == ({"AUTH-1", "AUTH-20"} if insecure else set())
    kind_steps = {"PC": {"STEP-10"}, "finite-time": {"STEP-11", "CTRL-3", "NUM-5"},
                  "": {f"STEP-{n}" for n in range(2, 10)} | {"BAND-1", "BAND-2", "BAND-3"}}
    assert judged & set().union(*kind_steps.values()) == kind_steps.get(variant,
                                                                         kind_steps[""])
    assert ("PRICE-5" in judged) == (persist == 1)
    assert (judged >= {"AUTH-31", "AUTH-32", "AUTH-33"}) == cfg.signed_price
    assert (judged >= {"TX-7", "CFG-9"}) == cfg.transmit.event


# --------------------------------------------------------------------------- the vector runner


def dump_node_vectors(path: Path) -> dict[str, list[tuple[int, int, str]]]:
    """The text dump firmware_c/tools/node_runner.c replays (its header comment); the
    frames each vector expects, times in ns."""
    lines, expected = [], {}
    for p in VECTORS:
        vec = load(p)
        k = vec["keys"]
        lines.append(f"V {vec['name']} {vec['config'].encode().hex()}")
        if "price_verify_key" in k:   # signed_price (AUTH-31): before K, which starts it
            lines.append(f"P {k['price_verify_key']} {k['fleet_id']}")
        if k["insecure"]:
            key = derive_node_key(INSECURE_MASTER, k["node"])
            lines.append(f"K {k['node']} 1 {key.hex()} 0 0 0")
        else:
            floors = k.get("floors", {})
            peers = " ".join(f"{label} {h} {floors.get(label, 0)}"
                             for label, h in k["peers"].items())
            fk = k["frame_keys"]   # AUTH-28: the setpoint's and the status' keys
            i = k["node"].removeprefix("agent_")
            plant = 0 if "plant" in k["peers"] else floors.get("plant", 0)
            lines.append(f"K {k['node']} 0 {k['key']} {k['boot_counter']} {len(k['peers'])} "
                         f"{peers} 4 {fk[f'AGENT_{i}_Setpoint']} {fk[f'PLANT_{i}_Status']} "
                         f"{fk[f'AGENT_{i}_Diag']} {k['command_keys'][k['node']]} {plant}")
        if "tx_count" in vec.get("setup", {}):
            lines.append(f"S {vec['setup']['tx_count']}")
        for row in vec["input"]:
            if row[0] == "tick":
                lines.append(f"T {ns(row[1])}")
                continue
            flags = row[4].get("flags", "") if len(row) > 4 else ""
            bits = (1 if "ext" in flags else 0) | (2 if "rtr" in flags else 0) \
                | (4 if "fd" in flags else 0)
            lines.append(f"R {ns(row[1])} {row[2]} {bits} {row[3] or '-'}")
        lines.append("E")
        expected[vec["name"]] = [(ns(t), fid, data) for t, fid, data in vec["output"]]
    path.write_text("\n".join(lines) + "\n", encoding="ascii")
    return expected


def _replay_runner(cmd: list[str], dump: Path, expected: dict[str, list[tuple[int, int, str]]]
                   ) -> None:
    with dump.open() as stdin:
        proc = subprocess.run(cmd, stdin=stdin, capture_output=True, text=True, check=False,
                              timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    got: dict[str, list[tuple[int, int, str]]] = {}
    frames: list[tuple[int, int, str]] = []
    for line in proc.stdout.splitlines():
        parts = line.split()
        if parts[0] == "F":
            frames.append((int(parts[1]), int(parts[2]), parts[3]))
        elif parts[0] == "END":
            got[parts[1]], frames = frames, []
    assert set(got) == set(expected)
    for name, want in expected.items():
        diff = [i for i, (a, b) in enumerate(zip(got[name], want, strict=False)) if a != b]
        assert got[name] == want, (name, len(got[name]), len(want), diff[:1])


def test_node_vectors_through_the_c_runner_natively(tmp_path: Path) -> None:
    """tools/node_runner.c: the configuration through the C loader, then every vector,
    output compared frame by frame (the dump format is the one a port would use)."""
    subprocess.run(["make", "-s", "-C", str(SOURCE), f"BUILD={tmp_path}",
                    f"PYTHON={sys.executable}", "node-runner"],
                   check=True, capture_output=True)
    dump = tmp_path / "node_vectors.txt"
    _replay_runner([str(tmp_path / "node_runner")], dump, dump_node_vectors(dump))


def test_node_vectors_cross_built_for_arm_under_qemu(tmp_path: Path) -> None:
    """The same, cross-built for arm-linux-gnueabihf (32-bit: int64 arithmetic in two
    registers, mbedTLS's armhf build) and run under qemu-arm."""
    for tool in ("make", "arm-linux-gnueabihf-gcc", "qemu-arm"):
        if shutil.which(tool) is None:
            if os.environ.get("CI"):
                pytest.fail(f"{tool} is missing: tools/install-c-deps installs it")
            pytest.skip(f"{tool} is not installed (tools/install-c-deps)")
    if not Path("/usr/lib/arm-linux-gnueabihf/libmbedcrypto.a").exists():
        if os.environ.get("CI"):
            pytest.fail("libmbedtls-dev:armhf is missing: tools/install-c-deps installs it")
        pytest.skip("libmbedtls-dev:armhf is not installed (tools/install-c-deps)")
    subprocess.run(["make", "-s", "-C", str(SOURCE), f"BUILD={tmp_path}",
                    f"PYTHON={sys.executable}", "arm-node-runner"],
                   check=True, capture_output=True)
    dump = tmp_path / "node_vectors.txt"
    _replay_runner(["qemu-arm", str(tmp_path / "node_runner.arm")], dump,
                   dump_node_vectors(dump))


# --------------------------------------------------------------------------- SecOC in C


def test_c_secoc_against_firmware_py() -> None:
    """secoc.c over mbedTLS: the KDF, the fleet tag, the frame MAC and the freshness
    candidate equal firmware_py's (cryptography's CMAC); bad inputs are refused."""
    import ctypes
    import random

    from firmware_py import secoc
    from sim.cbind.cagent import load

    lib = load().lib
    rnd = random.Random(11)
    for master in (bytes(16), MASTER, bytes(rnd.randrange(256) for _ in range(16))):
        for label in ("agent_1", "agent_32", "plant", "router"):
            out = ctypes.create_string_buffer(16)
            assert lib.bd_derive_node_key(master, label.encode(), out) == 0
            assert out.raw == secoc.derive_node_key(master, label)
        for name in ("AGENT_1_Setpoint", "AGENT_32_Setpoint", "PLANT_7_Status"):  # AUTH-28
            out = ctypes.create_string_buffer(16)
            assert lib.bd_derive_frame_key(master, name.encode(), out) == 0
            assert out.raw == secoc.derive_frame_key(master, name)
        tag = ctypes.create_string_buffer(8)
        assert lib.bd_fleet_id(master, tag) == 0 and tag.raw.hex() == secoc.fleet_id(master)
    out = ctypes.create_string_buffer(16)
    assert lib.bd_derive_node_key(MASTER, b"", out) == -1
    assert lib.bd_derive_node_key(MASTER, b"a" * 33, out) == -1
    key = secoc.derive_node_key(MASTER, "agent_1")
    for _ in range(300):
        fid, fv = rnd.randrange(0x800), rnd.randrange(1 << 40)
        data = bytearray(rnd.randrange(256) for _ in range(8))
        buf = ctypes.create_string_buffer(bytes(data), 8)
        assert lib.bd_sign_frame(key, fid, buf, fv) == 0
        secoc.sign_frame(key, fid, data, fv)
        assert buf.raw == bytes(data)
        assert lib.bd_frame_verifies(key, fid, buf.raw, fv) == 1
        assert lib.bd_frame_verifies(key, fid, buf.raw, fv + 1) == 0
        bad = bytearray(buf.raw)
        bad[rnd.randrange(3)] ^= 1 << rnd.randrange(8)
        assert lib.bd_frame_verifies(key, fid, bytes(bad), fv) == 0
    verifier = secoc.FreshnessVerifier()
    got = ctypes.c_uint64()
    for _ in range(300):
        last, low = rnd.randrange(1 << 40), rnd.randrange(16)
        verifier._last["x"] = last
        want = verifier.candidate("x", low)
        rc = lib.bd_fv_candidate(last, low, 4, (1 << 40) - 1, ctypes.byref(got))
        assert (rc == 0 and got.value == want) or (rc == -1 and want is None)
    assert lib.bd_fv_candidate((1 << 40) - 1, 3, 4, (1 << 40) - 1, ctypes.byref(got)) == -1
    assert lib.bd_fv_candidate(5, 16, 4, (1 << 40) - 1, ctypes.byref(got)) == -1   # > mask
    assert lib.bd_fv_candidate(5, 0, 0, (1 << 40) - 1, ctypes.byref(got)) == -1    # 0 bits
    for _ in range(300):   # AUTH-25: the newest past value with given low bits
        last, low = rnd.choice((rnd.randrange(1 << 40), rnd.randrange(20))), rnd.randrange(16)
        verifier._last["x"] = last
        want = verifier.past("x", low)
        rc = lib.bd_fv_past(last, low, 4, ctypes.byref(got))
        assert (rc == 0 and [got.value] == want) or (rc == -1 and want == [])
    assert lib.bd_fv_past(5, 16, 4, ctypes.byref(got)) == -1   # > mask


def test_c_agent_reports_resets_and_names_every_counter() -> None:
    py, c = _both("base")
    assert c.resets == py.cstate.resets == 0
    assert c.rt.counter_names == tuple(sorted(c.rt.counter_names, key=c.rt.counter_names.index))
    assert c.rt.lib.bd_counter_name(-1) is None and c.rt.lib.bd_counter_name(99) is None
    assert set(c.rt.counter_names) >= {"dlc", "auth", "unsynced", "deadline_miss"}


def test_c_agent_in_the_python_loop_counts_inputs_that_are_not_frames() -> None:
    """LOOP-6 through the binding: run_node's GuardedBus notes not_a_frame, invalid_frame
    and rx_error by name, and the C agent has a counter of each name (the C node's own
    loop counts rx_error; the other two cannot come from a SocketCAN socket)."""
    from firmware_py.node import RX_CAUSES

    _, c = _both("base")
    for k, cause in enumerate(RX_CAUSES, start=1):
        c.note(cause, k)
    assert {cause: c.counters[cause] for cause in RX_CAUSES} == {
        cause: k for k, cause in enumerate(RX_CAUSES, start=1)}
