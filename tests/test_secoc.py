"""firmware_py.secoc: CMAC, KDF, authenticator layout, freshness, key files."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import can
import pytest
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_py import secoc
from firmware_py.frames import FrameCodec
from firmware_py.nodeio import FleetSender, NodeIO
from firmware_py.secoc import (
    FreshnessLayout,
    FreshnessVerifier,
    KeyFileError,
    SecOCError,
    authenticator,
    derive_node_key,
    frame_verifies,
    verify,
)

# NIST SP 800-38B, Appendix D.1 (CMAC-AES-128; the same vectors are RFC 4493 §4).
NIST_KEY = bytes.fromhex("2b7e151628aed2a6abf7158809cf4f3c")
NIST_M = bytes.fromhex(
    "6bc1bee22e409f96e93d7e117393172a" "ae2d8a571e03ac9c9eb76fac45af8e51"
    "30c81c46a35ce411e5fbc1191a0a52ef" "f69f2445df4f9b17ad2b417be66c3710")
NIST_CASES = [  # (message length in bytes, tag)
    (0, "bb1d6929e95937287fa37d129b756746"),
    (16, "070a16b46b4d4144f79bdd9dd04a287c"),
    (40, "dfa66747de9ae63030ca32611497c827"),
    (64, "51f0bebf7e3b9d92fc49741779363cfe"),
]


def _reference_cmac(key: bytes, msg: bytes) -> bytes:
    """A second, independent code path for the test only: CMAC written out from
    SP 800-38B §6.1-6.2 on top of raw AES-ECB (not used by the firmware)."""
    def aes(block: bytes) -> bytes:
        enc = Cipher(algorithms.AES(key), modes.ECB()).encryptor()
        return enc.update(block) + enc.finalize()

    def dbl(b: bytes) -> bytes:
        v = int.from_bytes(b, "big") << 1
        if v >> 128:
            v = (v & ((1 << 128) - 1)) ^ 0x87
        return v.to_bytes(16, "big")

    k1 = dbl(aes(bytes(16)))
    k2 = dbl(k1)
    n = max(1, -(-len(msg) // 16))
    last = msg[16 * (n - 1):]
    if len(last) == 16:
        last = bytes(a ^ b for a, b in zip(last, k1, strict=True))
    else:
        padded = last + b"\x80" + bytes(15 - len(last))
        last = bytes(a ^ b for a, b in zip(padded, k2, strict=True))
    c = bytes(16)
    for i in range(n - 1):
        c = aes(bytes(a ^ b for a, b in zip(c, msg[16 * i:16 * i + 16], strict=True)))
    return aes(bytes(a ^ b for a, b in zip(c, last, strict=True)))


@pytest.mark.parametrize(("length", "tag"), NIST_CASES)
def test_cmac_nist_vectors_both_code_paths(length: int, tag: str) -> None:
    msg = NIST_M[:length]
    assert secoc.cmac_aes128(NIST_KEY, msg).hex() == tag
    assert _reference_cmac(NIST_KEY, msg).hex() == tag


@pytest.mark.parametrize(("length", "tag"), [c for c in NIST_CASES if c[0] in (16, 40)])
def test_nist_vectors_through_the_authenticator(length: int, tag: str) -> None:
    """The NIST message split into data ID (2 bytes) ‖ payload ‖ FV (8 bytes)."""
    msg = NIST_M[:length]
    data_id = int.from_bytes(msg[:2], "big")
    payload = msg[2:-8]
    fv = int.from_bytes(msg[-8:], "big")
    assert secoc.auth_data(data_id, payload, fv) == msg
    assert authenticator(NIST_KEY, data_id, payload, fv, bits=128) == int(tag, 16)
    assert authenticator(NIST_KEY, data_id, payload, fv) == int(tag[:6], 16)  # 24 bits
    assert authenticator(NIST_KEY, data_id, payload, fv, bits=32) == int(tag[:8], 16)
    assert verify(NIST_KEY, data_id, payload, fv, int(tag[:6], 16))


def test_truncation_keeps_the_leading_bits() -> None:
    full = authenticator(NIST_KEY, 0x123, b"\x01\x02", 7, bits=128)
    for bits in (1, 8, 24, 28, 64, 127):
        assert authenticator(NIST_KEY, 0x123, b"\x01\x02", 7, bits=bits) == full >> (128 - bits)
        assert authenticator(NIST_KEY, 0x123, b"\x01\x02", 7, bits=bits) < 1 << bits
    for bad in (0, 129):
        with pytest.raises(SecOCError):
            authenticator(NIST_KEY, 0, b"", 0, bits=bad)


def test_layout_errors() -> None:
    with pytest.raises(SecOCError):
        secoc.auth_data(1 << 16, b"", 0)
    with pytest.raises(SecOCError):
        secoc.auth_data(0, b"", 1 << 64)
    with pytest.raises(SecOCError):
        authenticator(b"short", 0, b"", 0)
    assert not verify(NIST_KEY, 1, b"", 0, 1 << 24)  # a MAC wider than its bits
    assert not verify(NIST_KEY, 1, b"", 0, -1)


def test_equals_cantools_compute_authenticator() -> None:
    """cantools.autosar.secoc packs u16 data ID ‖ payload ‖ u{freshness_bit_length}
    and hands that to the MAC function: with a 64-bit freshness it is our layout."""
    from cantools.autosar.secoc import apply_authenticator, compute_authenticator
    from cantools.database.can.formats.arxml import (
        AutosarMessageSpecifics,
        AutosarSecOCProperties,
    )
    from cantools.database.can.message import Message

    payload = bytes.fromhex("a1b2c3d4")
    spec = AutosarMessageSpecifics()
    spec._secoc = AutosarSecOCProperties(
        auth_algorithm_name="CMAC-AES-128", freshness_algorithm_name="bess-ded",
        payload_length=len(payload), data_id=0x0231, auth_tx_bit_length=24,
        freshness_bit_length=64, freshness_tx_bit_length=8)
    msg = Message(frame_id=0x231, name="X", length=8, signals=[], autosar_specifics=spec)
    key = derive_node_key(NIST_KEY, "agent_2")

    def mac_fn(dbmsg: object, data: bytes | bytearray, fv: int) -> bytes:
        return secoc.cmac_aes128(key, bytes(data))

    for fv in (0, 1, 0x0001_000000, 0x12_3456_789A, (1 << 40) - 1):
        theirs = compute_authenticator(payload, msg, mac_fn, fv)
        assert int.from_bytes(theirs, "big") == authenticator(key, 0x0231, payload, fv, 128)
        frame = apply_authenticator(payload + bytes(4), msg, mac_fn, fv)
        assert frame[4] == secoc.truncate(fv, 8)
        assert int.from_bytes(frame[5:8], "big") == authenticator(key, 0x0231, payload, fv)


# --------------------------------------------------------------------------- KDF


def _reference_kbkdf(master: bytes, label: bytes, context: bytes, length: int) -> bytes:
    """SP 800-108 §5.1 written out, with the CMAC of the other code path."""
    out = b""
    i = 1
    while len(out) < length:
        out += _reference_cmac(master, i.to_bytes(4, "big") + label + b"\x00" + context
                               + (8 * length).to_bytes(4, "big"))
        i += 1
    return out[:length]


def test_kdf_deterministic_separated_and_as_documented() -> None:
    master = bytes(range(16))
    nodes = secoc.fleet_nodes(7)
    keys = {n: derive_node_key(master, n) for n in nodes}
    assert len(set(keys.values())) == len(nodes)  # different nodes → different keys
    assert all(len(k) == 16 for k in keys.values())
    assert keys == {n: derive_node_key(master, n) for n in nodes}  # deterministic
    for n in nodes:
        assert keys[n] == _reference_kbkdf(master, secoc.NODE_KEY_LABEL, n.encode(), 16)
    other = derive_node_key(bytes(16), "agent_1")
    assert other != keys["agent_1"]  # another master, another key
    assert secoc.fleet_id(master) == _reference_kbkdf(master, secoc.FLEET_ID_LABEL, b"",
                                                      8).hex()
    assert secoc.fleet_id(master) != secoc.fleet_id(bytes(16))
    assert nodes == ["agent_1", "agent_2", "agent_3", "agent_4", "agent_5", "agent_6",
                     "agent_7", "plant", "router"]


def test_frame_key_kdf_as_documented_and_separated() -> None:
    """AUTH-28: a link frame's key is AUTH-1's KDF with its own label over the message
    name: one per frame, none equal to a node key or to another frame's."""
    from firmware_py import contract

    master = bytes(range(16))
    names = contract.link_frames(4)
    keys = {f: secoc.derive_frame_key(master, f) for f in names}
    for f, k in keys.items():
        assert k == _reference_kbkdf(master, secoc.FRAME_KEY_LABEL, f.encode(), 16)
    nodes = {derive_node_key(master, n) for n in secoc.fleet_nodes(4)}
    assert len(set(keys.values())) == len(names) and not nodes & set(keys.values())
    assert secoc.derive_frame_key(bytes(16), names[0]) != keys[names[0]]
    assert contract.parties_of("AGENT_1_Setpoint") == {"agent_1", "plant"}
    # the router's ledger takes PLANT_Totals (a report: the plant's and the router's key)
    assert contract.parties_of("PLANT_1_Status") == {"plant", "agent_1"}
    assert contract.parties_of("PLANT_Totals") == {"plant", "router"}
    assert "PLANT_Totals" in contract.REPORT_FRAMES
    assert "ER_Price" not in contract.LINK_FRAMES and "AGENT_1_MC" not in contract.LINK_FRAMES
    assert "ER_Command" not in contract.LINK_FRAMES and "AGENT_1_Diag" not in contract.LINK_FRAMES
    for bad in ("", "plant_1_status", "A" * 33, "PLANT 1"):
        with pytest.raises(SecOCError):
            secoc.derive_frame_key(master, bad)


def test_command_key_kdf_as_documented_and_separated() -> None:
    """AUTH-30: the key of the commands to agent i is AUTH-1's KDF with its own label over
    the target's label: one per agent, none equal to a node key or a frame key; only the
    router and the target hold it (a fleet keyring derives it for them only)."""
    from firmware_py import contract

    master = bytes(range(16))
    keys = {i: secoc.derive_command_key(master, f"agent_{i}") for i in range(1, 33)}
    for i, k in keys.items():
        assert k == _reference_kbkdf(master, secoc.COMMAND_KEY_LABEL, f"agent_{i}".encode(), 16)
    others = {derive_node_key(master, n) for n in secoc.fleet_nodes(32)}
    others |= {secoc.derive_frame_key(master, f) for f in contract.keyed_frames()}
    assert len(set(keys.values())) == 32 and not others & set(keys.values())
    rings = secoc.Keyring.fleet(master, secoc.fleet_nodes(4))
    assert rings["agent_1"].key_for("ER_Command") == keys[1]
    assert rings["router"].key_for("ER_Command", target=3) == keys[3]
    assert rings["agent_3"].key_for("ER_Command", target=1) is None
    assert rings["plant"].key_for("ER_Command", target=1) is None
    assert rings["agent_3"].key_for("ER_Command_Sync") == derive_node_key(master, "router")
    for bad in ("", "router", "plant", "agent_0", "agent_1x"):
        with pytest.raises(SecOCError):
            secoc.derive_command_key(master, bad)


@pytest.mark.parametrize("bad", ["", "Agent_1", "agent 1", "1agent", "a" * 33, "agent-1"])
def test_bad_node_names(bad: str) -> None:
    with pytest.raises(SecOCError):
        derive_node_key(bytes(16), bad)


def test_bad_master_key() -> None:
    with pytest.raises(SecOCError, match="16 bytes"):
        derive_node_key(bytes(15), "plant")


# --------------------------------------------------------------------------- freshness
#
# Sender side: Keyring.new_boot (the persisted boot counter) and NodeIO's per-ID counts;
# receiver side: NodeIO with FreshnessVerifier. Exercised on real frames (FleetSender
# signs as a fleet node does) through the node's own receive path.

KEYS = {n: derive_node_key(NIST_KEY, n) for n in ("router", "agent_1", "agent_2")}


def _receiver(join_s: float | None = 0.0) -> NodeIO:
    """Agent 1's view of ER_Price (secured), with the real keys of NIST_KEY's fleet;
    ``join_s``: its join window (AUTH-26; 0: none, it takes the first sync at once)."""
    ring = secoc.Keyring("agent_1", KEYS["agent_1"], 0, lambda _b: None,
                         peers={"router": KEYS["router"]})
    return NodeIO(FrameCodec(), "agent 1", own=["AGENT_1_MC"], wanted=[0x010],
                  keys=ring, untrusted_after=10**9, join_s=join_s)


def _price(sender: FleetSender, i: int) -> can.Message:
    return sender.frame("ER_Price", {"PriceValid": 1, "Rho": i, "Segment": 0})


def _rho(rx: NodeIO, msg: can.Message, t: float) -> int | None:
    """The raw Rho of ``msg`` as ``rx`` took it (its own price sequence number in these
    tests), None when rejected."""
    f = rx.receive(msg, t)
    return None if f is None else f.raw["Rho"]


def _synced() -> tuple[FleetSender, NodeIO]:
    sender, rx = FleetSender(FrameCodec(), keys=KEYS, boot=7), _receiver()
    rx.receive(sender.sync("ER_Price"), 0.0)
    assert rx.counters["resyncs"] == 1
    return sender, rx


def test_boot_counter_is_persisted_before_use_and_only_moves_on() -> None:
    persisted: list[int] = []
    ring = secoc.Keyring("agent_1", KEYS["agent_1"], 4, persisted.append)
    assert ring.new_boot() == 5 and persisted == [5]
    assert ring.new_boot() == 6 and persisted == [5, 6]

    def fail(boot: int) -> None:
        raise OSError("disk full")

    with pytest.raises(OSError):
        secoc.Keyring("agent_1", KEYS["agent_1"], 3, fail).new_boot()
    with pytest.raises(SecOCError, match="exhausted"):
        secoc.Keyring("agent_1", KEYS["agent_1"], secoc.DEFAULT_LAYOUT.max_boot,
                      persisted.append).new_boot()


def test_a_node_starts_a_boot_and_a_count_wrap_starts_another() -> None:
    """Each NodeIO is one boot; a message count about to pass 2^24 starts the next boot
    (persisted), restarts every count at 0 and makes the syncs due at once."""
    persisted: list[int] = []
    ring = secoc.Keyring("agent_1", KEYS["agent_1"], 0, persisted.append,
                         peers={"router": KEYS["router"]})
    io = NodeIO(FrameCodec(), "agent 1", own=["AGENT_1_MC"], wanted=[], keys=ring)
    assert io.boot == 1 and persisted == [1]
    assert [m.arbitration_id for m in io.syncs(0.0)] == [0x501]
    assert io.syncs(0.5) == []
    io._tx_count[0x101] = (1 << 24) - 1
    raw = {"State": 1, "Resets": 0, "Lambda": 0}
    last = io.send("AGENT_1_MC", raw)
    first = io.send("AGENT_1_MC", raw)
    assert io.boot == 2 and persisted == [1, 2] and io._tx_count[0x101] == 1
    assert frame_verifies(KEYS["agent_1"], 0x101, last.data, 1 << 24 | (1 << 24) - 1)
    assert frame_verifies(KEYS["agent_1"], 0x101, first.data, 2 << 24 | 0)
    assert len(io.syncs(0.6)) == 1  # the new boot is announced at once


def test_the_join_window_keeps_the_newest_sync_and_takes_no_frame() -> None:
    """AUTH-26: a sync replayed from earlier in the sender's current boot, heard first at
    the receiver's start, is kept only until the sender's newer sync (its answer to the
    hello) replaces it; no frame is taken in the window; at the first frame after it the
    newest sync is taken, the ID marked lost (the frames of the window were skipped), so
    the replayed frames fail and the genuine one is accepted. Without the window (the
    control) the replayed frame would be taken."""
    sender = FleetSender(FrameCodec(), keys=KEYS, boot=7)
    for i in range(3):
        _price(sender, i)
    early_sync = sender.sync("ER_Price")                 # count 3: captured by an attacker
    early = [_price(sender, i) for i in range(3, 6)]
    for i in range(6, 40):
        _price(sender, i)
    genuine_sync = sender.sync("ER_Price")               # count 40: the answer to the hello

    control = _receiver(join_s=0.0)
    control.receive(early_sync, 0.01)
    assert _rho(control, early[0], 0.02) == 3           # what the window prevents

    rx = _receiver(join_s=None)
    assert rx.join_s == pytest.approx(0.2)
    rx.syncs(0.0)                                        # its hello: the window until 0.2 s
    rx.receive(early_sync, 0.01)
    assert rx.receive(early[0], 0.02) is None and rx.counters["joining"] == 1
    rx.receive(genuine_sync, 0.05)
    rx.receive(early_sync, 0.06)                         # older than one already heard
    assert rx.counters["auth"] == 1 and rx.counters["resyncs"] == 0
    assert rx.last_freshness(0x010) is None                    # nothing taken yet
    for i, m in enumerate(early[1:]):  # after the window: below the newest sync, they fail
        assert rx.receive(m, 0.21 + 0.01 * i) is None
    # taken at the first frame after the window; lost, so a failure waits for a frame
    # that verifies (AUTH-14: unsynced, not auth)
    assert rx.counters["resyncs"] == 1 and rx.last_freshness(0x010) == (7 << 24 | 39)
    assert rx.counters["unsynced"] == 2 and rx.counters["auth"] == 1
    sender.skip("ER_Price", 20)  # frames the receiver never heard: the wider window (AUTH-13)
    assert _rho(rx, _price(sender, 60), 0.25) == 60
    assert rx.counters["lost_frames"] == 20
    assert rx.receive(early[2], 0.26) is None and rx.counters["auth"] == 2  # no longer lost


def test_a_sync_overtaken_by_its_tick_s_frame_is_stale_not_forged() -> None:
    """AUTH-16/AUTH-25: a sender's sync and the frame of the same tick swapped on the way
    (a loaded vcan host does this): the frame is taken, the sync then announces a value
    one behind what was taken: `stale`, not a replayed sync; one from 16 or more frames
    ago still is `auth`."""
    sender, rx = _synced()
    for i in range(20):
        rx.receive(_price(sender, i), 0.0)
    old = sender.sync("ER_Price")                        # announces count 20 ...
    for i in range(20):
        rx.receive(_price(sender, i), 0.0)
    sync = sender.sync("ER_Price")                       # ... and count 40
    assert _rho(rx, _price(sender, 40), 0.0) == 40   # the tick's frame first
    rx.receive(sync, 0.0)
    assert rx.counters["stale"] == 1 and rx.counters["auth"] == 0
    rx.receive(old, 0.0)
    assert rx.counters["auth"] == 1 and rx.counters["stale"] == 1


def test_round_trip_and_replay_rejected() -> None:
    sender, rx = _synced()
    frames = [_price(sender, i) for i in range(40)]
    for i, m in enumerate(frames):
        assert _rho(rx, m, 0.0) == i
    last = rx.last_freshness(0x010)
    for m in frames:  # replay of every old frame: its freshness is spent
        assert rx.receive(m, 0.0) is None
    # every one was accepted before: a replay, not a late frame (AUTH-25)
    assert rx.counters["auth"] == 40 and rx.counters["stale"] == 0
    assert rx.last_freshness(0x010) == last  # state unchanged
    assert _rho(rx, _price(sender, 99), 0.0) == 99


def test_a_late_genuine_frame_is_stale_not_forged() -> None:
    """Frames 1..5 arrive as 1, 3, 2, 5, 4 (a loaded host): 2 and 4 carry a valid MAC
    under a freshness value below the last accepted: counted stale, never used, no auth
    failure and no untrusted streak; a forged frame in between is still auth."""
    sender, rx = _synced()
    f = [_price(sender, i) for i in range(6)]
    got = [_rho(rx, f[i], 0.0) for i in (0, 1, 3, 2, 5, 4)]
    assert got == [0, 1, 3, None, 5, None]
    assert rx.counters["stale"] == 2 and rx.counters["auth"] == 0
    assert rx.counters["lost_frames"] == 2 and rx._streak[0x010] == 0
    for i in (4, 5):  # again: a late frame already seen, an accepted one: replays
        assert rx.receive(f[i], 0.0) is None
    assert rx.counters["stale"] == 2 and rx.counters["auth"] == 2
    rx.counters["auth"] = 0
    bad = bytearray(_price(sender, 6).data)
    bad[0] ^= 0x5A
    assert rx.receive(can.Message(arbitration_id=0x010, data=bad, is_extended_id=False),
                      0.0) is None
    assert rx.counters["auth"] == 1 and rx.counters["stale"] == 2


def test_a_frame_later_than_one_window_is_auth() -> None:
    """STALE_WINDOWS bounds the look back (one CMAC): a frame 16 or more behind the last
    accepted one verifies in no window tried and counts as auth."""
    sender, rx = _synced()
    old = _price(sender, 0)
    for i in range(1, 17):
        assert _rho(rx, _price(sender, i), 0.0) == i
    assert rx.receive(old, 0.0) is None
    assert rx.counters["auth"] == 1 and rx.counters["stale"] == 0


def test_past_values_of_the_verifier() -> None:
    v = FreshnessVerifier(tx_bits=4, initial={"s": 0x123})
    assert v.past("s", 0x3) == [0x123] and v.past("s", 0x4) == [0x114]
    assert v.past("s", 0x4, windows=3) == [0x114, 0x104]   # beyond SEEN_BITS: spent
    assert v.accept("s", 0x125) and v.accept("s", 0x127, frame=False)
    assert v.past("s", 0x5) == [] and v.past("s", 0x7) == [0x127]   # 0x125 was accepted
    v.mark("s", 0x127)
    assert v.past("s", 0x7) == [] and v.past("s", 0x6) == [0x126]
    assert FreshnessVerifier(initial={"s": 2}).past("s", 5, windows=4) == []
    assert FreshnessVerifier().past("s", 1) == [] and v.past("s", 16) == []


def test_replay_one_window_later_rejected() -> None:
    sender, rx = _synced()
    old = _price(sender, 1)
    assert _rho(rx, old, 0.0) == 1
    for i in range(16):  # exactly one window later the truncated value repeats
        f = _price(sender, 2 + i)
        assert _rho(rx, f, 0.0) == 2 + i
    assert f.data[3] & 0x0F == old.data[3] & 0x0F
    assert rx.receive(old, 0.0) is None and rx.counters["auth"] == 1


def test_truncated_freshness_wraps_and_lost_frames_are_counted() -> None:
    sender, rx = _synced()
    for i in range(100):
        f = _price(sender, i)
        if i % 7 == 3:
            continue  # lost on the bus
        assert _rho(rx, f, 0.0) == i
    assert rx.counters["lost_frames"] == len([i for i in range(100) if i % 7 == 3])
    for i in range(15):  # 15 lost frames: the edge of the window
        _price(sender, i)
    assert _rho(rx, _price(sender, 0), 0.0) == 0
    for i in range(16):  # 16 lost: outside the window → fails until a sync
        _price(sender, i)
    assert rx.receive(_price(sender, 0), 0.0) is None and rx.counters["auth"] == 1
    assert rx.receive(sender.sync("ER_Price"), 0.0) is None and rx.counters["resyncs"] == 2
    assert _rho(rx, _price(sender, 0), 0.0) == 0


def test_a_timed_out_sender_gets_a_wider_window_then_waits_for_its_sync() -> None:
    sender, rx = _synced()
    assert _rho(rx, _price(sender, 0), 0.0) == 0
    rx.sender_lost(0x010)  # the receiver's timeout fired
    for i in range(100):  # 100 frames lost: within LOST_WINDOWS · 16
        _price(sender, i)
    assert _rho(rx, _price(sender, 1), 1.0) == 1
    assert rx.counters["auth"] == 0 and rx.counters["lost_frames"] == 100
    rx.sender_lost(0x010)
    for i in range(200):  # beyond the wider window: unsynced, not a forgery
        _price(sender, i)
    assert rx.receive(_price(sender, 1), 2.0) is None
    assert rx.counters["unsynced"] == 1 and rx.counters["auth"] == 0


def test_restarted_sender_needs_its_sync_and_an_old_sync_cannot_rewind() -> None:
    sender, rx = FleetSender(FrameCodec(), keys=KEYS, boot=7), _receiver()
    assert rx.receive(_price(sender, 0), 0.0) is None and rx.counters["unsynced"] == 1
    first_sync = sender.sync("ER_Price")
    rx.receive(first_sync, 0.0)
    for i in range(20):
        assert _rho(rx, _price(sender, i), 0.0) == i
    sender.restart()  # boot 8
    assert rx.receive(_price(sender, 0), 0.0) is None and rx.counters["auth"] == 1
    rx.receive(first_sync, 0.0)  # a replayed old sync: refused, the state stays
    assert rx.counters["resyncs"] == 1
    rx.receive(sender.sync("ER_Price"), 0.0)  # in step: held (AUTH-35)
    assert rx.counters["resyncs"] == 1
    assert _rho(rx, _price(sender, 1), 0.0) == 1  # verifies on it: taken
    assert rx.counters["resyncs"] == 2 and rx.counters["sync_jump"] == 0


def test_wrong_key_and_other_sender_rejected() -> None:
    sender, rx = _synced()
    forger = FleetSender(FrameCodec(), keys={"router": KEYS["agent_2"]}, boot=7)
    assert rx.receive(_price(forger, 0), 0.0) is None and rx.counters["auth"] == 1
    assert _rho(rx, _price(sender, 0), 0.0) == 0


def test_candidate_at_the_end_of_the_layout() -> None:
    layout = FreshnessLayout(boot_bits=1, counter_bits=8)
    v = FreshnessVerifier(tx_bits=8, layout=layout, initial={"s": layout.max_value - 1})
    assert v.candidate("s", 0xFF) == layout.max_value
    assert v.candidate("s", 0x00) is None  # would run past the layout
    assert v.candidate("s", 0x100) is None  # not a truncated value
    with pytest.raises(SecOCError):
        FreshnessVerifier(tx_bits=0)
    assert not v.accept("s", layout.max_value - 1)  # not strictly greater


@settings(max_examples=300, deadline=None, derandomize=True)  # a 2^-24 fluke stays out
@given(data_id=st.integers(0, 0xFFFF), payload=st.binary(min_size=0, max_size=8),
       which=st.sampled_from(["payload", "id", "freshness", "mac"]),
       bit=st.integers(0, 63), start=st.integers(0, (1 << 40) - 2))
def test_any_single_bit_flip_is_rejected(data_id: int, payload: bytes, which: str,
                                         bit: int, start: int) -> None:
    key = derive_node_key(NIST_KEY, "agent_1")
    v = FreshnessVerifier(tx_bits=4, initial={"agent_1": start})
    fv = v.candidate("agent_1", (start + 1) & 0xF)
    assert fv == start + 1
    tfv, mac = secoc.truncate(fv, 4), authenticator(key, data_id, payload, fv)
    if which == "payload":
        if not payload:
            payload = b"\x00"  # flipping the length instead: one more byte
        else:
            b = bit % (8 * len(payload))
            payload = (int.from_bytes(payload, "big") ^ (1 << b)).to_bytes(len(payload), "big")
    elif which == "id":
        data_id ^= 1 << (bit % 16)
    elif which == "freshness":
        tfv ^= 1 << (bit % 4)
    else:
        mac ^= 1 << (bit % 24)
    candidate = v.candidate("agent_1", tfv)
    assert candidate is None or not verify(key, data_id, payload, candidate, mac)
    assert v.last("agent_1") == start


# --------------------------------------------------------------------------- key files


def _write_key_file(path: Path, mode: int = 0o600, boot: int = 0) -> bytes:
    import tomli_w

    key = derive_node_key(NIST_KEY, "agent_3")
    doc = secoc.node_key_document("agent_3", key, secoc.fleet_id(NIST_KEY), boot)
    secoc.write_private(path, secoc.KEY_FILE_HEADER + tomli_w.dumps(doc))
    os.chmod(path, mode)
    return key


def test_load_node_key_and_persist_boot_counter(tmp_path: Path) -> None:
    path = tmp_path / "agent_3.key"
    key = _write_key_file(path)
    nk = secoc.load_node_key(path)
    assert (nk.node, nk.key, nk.boot_counter) == ("agent_3", key, 0)
    assert key.hex() not in repr(nk)
    assert secoc.Keyring.from_file(path).new_boot() == 1
    assert secoc.load_node_key(path).boot_counter == 1
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert secoc.Keyring.from_file(path).new_boot() == 2
    assert secoc.load_node_key(path).boot_counter == 2
    with pytest.raises(SecOCError, match="go back"):
        secoc.save_boot_counter(path, 1)
    assert not list(tmp_path.glob(".*tmp"))


@pytest.mark.parametrize("mode", [0o640, 0o604, 0o644, 0o660, 0o700 | 0o004])
def test_load_node_key_refuses_open_permissions(tmp_path: Path, mode: int) -> None:
    path = tmp_path / "agent_3.key"
    _write_key_file(path, mode)
    with pytest.raises(KeyFileError, match="too open"):
        secoc.load_node_key(path)


@pytest.mark.parametrize(("text", "match"), [
    ("format = 'other'\n", "format"),
    ("not toml at all [", "TOML"),
    (f"format = '{secoc.KEY_FILE_FORMAT}'\nnode = 'Bad'\n", "node"),
    (f"format = '{secoc.KEY_FILE_FORMAT}'\nnode = 'plant'\nfleet_id = '00'\n", "fleet_id"),
    (f"format = '{secoc.KEY_FILE_FORMAT}'\nnode = 'plant'\nfleet_id = '{'0' * 16}'\n"
     "freshness = {boot_counter = -1}\n", "boot_counter"),
    (f"format = '{secoc.KEY_FILE_FORMAT}'\nnode = 'plant'\nfleet_id = '{'0' * 16}'\n"
     "key = 'zz'\nfreshness = {boot_counter = 0}\n", "hex"),
])
def test_load_node_key_malformed(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "k.key"
    secoc.write_private(path, text)
    with pytest.raises(KeyFileError, match=match):
        secoc.load_node_key(path)


def test_load_node_key_missing(tmp_path: Path) -> None:
    with pytest.raises(KeyFileError, match="cannot read"):
        secoc.load_node_key(tmp_path / "none.key")
    with pytest.raises(KeyFileError, match="regular file"):
        secoc.load_node_key(tmp_path)


def test_master_key_file_formats(tmp_path: Path) -> None:
    import tomli_w

    p = tmp_path / "m.key"
    secoc.write_private(p, tomli_w.dumps(secoc.master_key_document(NIST_KEY)))
    assert secoc.load_master_key(p) == NIST_KEY
    secoc.write_private(p, NIST_KEY.hex() + "\n")
    assert secoc.load_master_key(p) == NIST_KEY
    secoc.write_private(p, "abc\n")
    with pytest.raises(KeyFileError, match="hex digits"):
        secoc.load_master_key(p)
    os.chmod(p, 0o644)
    with pytest.raises(KeyFileError, match="too open"):
        secoc.load_master_key(p)
