"""The C runtime's defensive paths, which the vectors and random traffic do not reach.

A CMAC primitive that fails (a hardware AES engine or an HSM can: firmware_py's
``cryptography`` cannot), through libbessded_faulty.so, the same sources linked with a
crypto seam that fails on demand (firmware_c/tools/crypto_faulty.c); a boot counter
exhausted at a setpoint count wrap; output and ID buffers shorter than what the agent
has; peer labels that name no node; frames that arrive out of time order; an own-ID
frame of the wrong length. Where firmware_py has the same path, both runtimes are driven
through it and compared (test_c_agent.run_both).
"""

from __future__ import annotations

import ctypes
from collections.abc import Iterator

import pytest
from test_c_agent import JOIN_TICKS, MASTER, PREAMBLE, TS, _cfg, run_both

from firmware_py.frames import FrameCodec
from firmware_py.nodeio import FleetSender
from firmware_py.secoc import Keyring, derive_command_key, derive_frame_key, derive_node_key
from sim.cbind.cagent import TICK_FRAMES_MAX, CAgent, Frame, Runtime, load_faulty

BD_ERR_PARAMS, BD_ERR_BOOT, BD_ERR_CRYPTO = 10, 12, 13   # agent.h
PEERS = ("router", "plant", "agent_1", "agent_3")


@pytest.fixture()
def faulty() -> Iterator[Runtime]:
    rt = load_faulty()
    rt.lib.bd_test_cmac_fail_after(-1)
    yield rt
    rt.lib.bd_test_cmac_fail_after(-1)


def ring(boot: int = 6) -> Keyring:
    return Keyring("agent_2", derive_node_key(MASTER, "agent_2"), boot, lambda _b: None,
                   peers={n: derive_node_key(MASTER, n) for n in PEERS},
                   frames={f: derive_frame_key(MASTER, f)   # AUTH-28, AUTH-29: its frames
                           for f in ("AGENT_2_Setpoint", "PLANT_2_Status", "AGENT_2_Diag")},
                   commands={"agent_2": derive_command_key(MASTER, "agent_2")})  # AUTH-30


JOINED = JOIN_TICKS * TS  # after the join window the first tick opened (AUTH-26)


def synced_agent(rt: Runtime) -> tuple[CAgent, dict[str, FleetSender]]:
    """A key-file agent that started (its first tick at 0), heard the router's and
    plant's syncs and took them at JOINED."""
    c = CAgent(_cfg(), ring(), runtime=rt)
    c.tick(0.0)
    senders = {n: FleetSender(keys={n: derive_node_key(MASTER, n),
                                    "PLANT_2_Status": derive_frame_key(MASTER, "PLANT_2_Status")},
                              boot=3)
               for n in ("router", "plant")}
    c.on_frame(senders["router"].sync("ER_Price"), JOINED)
    c.on_frame(senders["plant"].sync("PLANT_2_Status"), JOINED)
    assert c.counters["resyncs"] == 2 and c.fatal == 0
    return c, senders


# --------------------------------------------------------------------------- a failed CMAC


def test_the_faulty_seam_is_mbedtls_until_told_to_fail(faulty: Runtime) -> None:
    """With no failure asked for, the faulty library is the real one: frame for frame."""
    twin = CAgent(_cfg(), ring())
    c = CAgent(_cfg(), ring(), runtime=faulty)
    for k in range(3):
        assert [bytes(m.data) for m in c.tick(k * TS)] == [bytes(m.data)
                                                          for m in twin.tick(k * TS)]
    before = faulty.lib.bd_test_cmac_calls()
    faulty.lib.bd_test_cmac_fail_after(1)   # this tick's MC signs, the next one's does not
    assert [bytes(m.data) for m in c.tick(3 * TS)] == [bytes(m.data)
                                                      for m in twin.tick(3 * TS)]
    assert c.fatal == 0 and faulty.lib.bd_test_cmac_calls() == before + 1
    assert c.tick(4 * TS) == [] and c.fatal == BD_ERR_CRYPTO


def test_a_failed_key_derivation_refuses_the_start(faulty: Runtime) -> None:
    """--insecure derives every input sender's key at start (AUTH-1): a failing primitive
    refuses the start with BD_ERR_CRYPTO rather than run with a key it does not have."""
    faulty.lib.bd_test_cmac_fail_after(0)
    with pytest.raises(ValueError, match=f"error {BD_ERR_CRYPTO}"):
        CAgent(_cfg("insecure"), Keyring.insecure_for("agent_2"), runtime=faulty)


def test_a_failed_key_derivation_for_a_peer_sync_stops_the_agent(faulty: Runtime) -> None:
    """--insecure with no fleet size: agent 4's MC sync (a peer sync, AUTH-18) makes the
    agent derive agent_4's key; the primitive fails: the agent stops, nothing is sent."""
    c = CAgent(_cfg("insecure"), Keyring.insecure_for("agent_2"), runtime=faulty)
    assert len(c.tick(0.0)) == 6   # 3 syncs, MC, Setpoint, Diag
    faulty.lib.bd_test_cmac_fail_after(0)
    c.on_frame(FleetSender().sync("AGENT_4_MC"), TS / 2)
    assert c.fatal == BD_ERR_CRYPTO
    assert c.tick(TS) == [] and c.tick(2 * TS) == []
    assert c.counters["auth"] == 0   # nothing was verified: no frame is called forged


@pytest.mark.parametrize("what", ["price", "sync"])
def test_a_failed_verification_stops_the_agent_and_accuses_no_sender(faulty: Runtime,
                                                                     what: str) -> None:
    """A price (AUTH-13) or a sync (AUTH-16) arrives while the primitive fails: the frame
    is not used, not counted as forged, and the agent stops (the node exits with its
    error): a node that cannot verify must not act on its inputs."""
    c, senders = synced_agent(faulty)
    faulty.lib.bd_test_cmac_fail_after(0)
    if what == "price":
        c.on_frame(senders["router"].frame("ER_Price", {"PriceValid": 1, "Segment": 0,
                                                        "Rho": 13_421_773}), JOINED + TS)
    else:
        senders["router"].restart()
        c.on_frame(senders["router"].sync("ER_Price"), JOINED + TS)
    assert c.fatal == BD_ERR_CRYPTO
    assert c.counters["auth"] == 0 and c.counters["resyncs"] == 2
    assert c.tick(JOINED + 2 * TS) == []


def test_a_failed_signature_sends_nothing(faulty: Runtime) -> None:
    """AUTH-6: a frame whose MAC could not be computed never leaves the agent; the tick
    sends nothing at all (not the frames signed before it), and no tick after it."""
    c = CAgent(_cfg(), ring(), runtime=faulty)
    assert len(c.tick(0.0)) == 6   # 3 syncs, MC, Setpoint, Diag
    faulty.lib.bd_test_cmac_fail_after(0)
    assert c.tick(TS) == [] and c.fatal == BD_ERR_CRYPTO
    faulty.lib.bd_test_cmac_fail_after(-1)   # a primitive that recovers changes nothing
    assert c.tick(2 * TS) == [] and c.fatal == BD_ERR_CRYPTO


# --------------------------------------------------------------------------- boot, buffers


@pytest.mark.parametrize("which", ["setpoint", "diag"])
def test_a_setpoint_or_diag_count_wrap_at_the_last_boot_stops_the_agent(which: str) -> None:
    """AUTH-5 on the setpoint's or the diag's count (the MC's: test_c_agent): no boot
    left, nothing is sent and the agent reports BD_ERR_BOOT."""
    c = CAgent(_cfg(), ring(boot=65534))
    c.set_tx_count(0, 1 << 24 if which == "setpoint" else 0, 1 << 24 if which == "diag" else 0)
    assert c.tick(0.0) == [] and c.fatal == BD_ERR_BOOT


def test_a_short_output_buffer_gets_the_tick_s_first_frames() -> None:
    """bd_agent_tick(..., max): at most max frames, the first ones of the tick (a port
    with a small transmit queue); the agent's state advances as for the whole tick."""
    whole, short = CAgent(_cfg(), ring()), CAgent(_cfg(), ring())
    want = whole.tick_raw(0)
    out = (Frame * TICK_FRAMES_MAX)()
    assert len(want) == 6
    n = short.rt.lib.bd_agent_tick(short._buf, 0, out, 2)
    assert n == 2 and [(out[k].id, bytes(out[k].data)[:out[k].len]) for k in range(2)] == want[:2]
    assert short.tick_raw(int(TS * 1e9)) == whole.tick_raw(int(TS * 1e9))


def test_a_short_id_buffer_gets_some_of_the_accepted_ids_sorted() -> None:
    """bd_agent_accepted_ids(..., max): never more than max IDs, each one accepted, in
    ascending order (a CAN controller with fewer filter banks than the agent needs)."""
    c = CAgent(_cfg(), ring())
    every = c.accepted_ids()
    ids = (ctypes.c_uint32 * 4)()
    n = c.rt.lib.bd_agent_accepted_ids(c._buf, ids, 4)
    got = list(ids[:n])
    assert n == 4 < len(every) and got == sorted(got) and set(got) <= set(every)


@pytest.mark.parametrize("label", [b"gateway", b"agent_", b"agent_0", b"agent_1x",
                                   b"agent_65", b"agent_12345678901234"])
def test_a_key_file_peer_that_names_no_node_refuses_the_start(label: bytes) -> None:
    """CFG-8: a peer label is plant, router or agent_1..agent_64 (digits, no leading 0);
    anything else refuses the start (the long one would overflow a naive parser)."""
    from sim.cbind.cagent import keyring_from

    bad = keyring_from(ring())
    bad.peer_label[0].value = label
    with pytest.raises(ValueError, match=f"error {BD_ERR_PARAMS}"):
        CAgent(_cfg(), bad)


# --------------------------------------------------------------------------- against firmware_py


def test_a_neighbour_frame_from_before_the_last_one_is_one_sample_later() -> None:
    """LAM-1 with a receive time before the slot's last one (a timestamp source that
    went back): samples = max(1, rne(dt/Ts)) = 1 in both runtimes, so a jump of more
    than one lambda_step_max is implausible and a small one is not."""
    events = PREAMBLE + [("mc", 1, 13_000_000, 1), ("at", -TS / 4),
                         ("mc", 1, 21_000_000, 1), ("mc", 1, 13_000_100, 1), ("tick", 1)]
    _py, c = run_both("base", events)
    assert c.counters["implausible_lambda"] == 1


def test_an_own_id_frame_of_the_wrong_length_is_an_impersonation() -> None:
    """RX-3: a 7-byte frame on the agent's own MC ID cannot be its echo: counted as
    impersonation (and foreign traffic) in both runtimes."""
    own = FrameCodec().frame_id("AGENT_2_MC")
    _py, c = run_both("base", PREAMBLE + [("junk", own, bytes(7), 0), ("tick", 1)])
    assert c.counters["impersonation"] == 1 and c.counters["foreign"] == 1


def test_a_sync_id_with_a_streak_of_bad_frames_is_an_untrusted_source() -> None:
    """RX-13 on a sync ID: untrusted_after (3) malformed syncs in a row count one
    untrusted source and start the streak again; the sync ID itself is never blocked
    (a genuine sync after them still resynchronises), in both runtimes."""
    sync_id = FrameCodec().frame_id("ER_Price_Sync")
    bad = [("junk", sync_id, bytes(7), 0)]
    _py, c = run_both("base", PREAMBLE + bad * 4 + [("tick", 1), ("restart", "router"),
                                                    ("sync", "ER_Price"), ("tick", 1),
                                                    ("price", 13_421_773, True, 0),
                                                    ("tick", 1)])
    assert c.counters["untrusted_sources"] == 1 and c.counters["dlc"] == 4
    # the five inputs' in PREAMBLE, the router's again (held in step, AUTH-35: taken at
    # its first price)
    assert c.counters["resyncs"] == 5 + 1


def test_an_untrusted_input_is_trusted_again_when_its_time_is_up() -> None:
    """RX-13: untrusted_after (3) malformed prices make ER_Price untrusted for
    untrusted_s (100 ticks at this Ts); a valid price inside that time and one after it
    are treated alike in both runtimes, and the hold ends on time."""
    price_id = FrameCodec().frame_id("ER_Price")
    price = ("price", 13_421_773, True, 0)
    events = (PREAMBLE + [("junk", price_id, bytes(7), 0)] * 3
              + [("tick", 1), price, ("tick", 101), price, ("tick", 1)])
    _py, c = run_both("base", events)
    assert c.counters["untrusted_sources"] == 1 and c.counters["dlc"] == 3
