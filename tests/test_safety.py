"""The node safety model (docs/safety-model.md): every rule triggers on a crafted frame
sequence built as the real senders build it (``FleetSender``: valid MAC and freshness
unless the rule is about them), does not trigger on healthy sequences, and the paper
cases' bus runs keep every new counter at 0.

Secured frames (every frame of the DBC) that fail their MAC — forged with a wrong key,
a bit flipped, or replayed — are rejected under ``auth``, which joins the untrusted
streak; an untrusted secured ID still takes genuine frames (their MAC proves them). No
ID is ever blocked: the DBC has no E2E-only frame left (AGENT_i_Diag and ER_Balance were
the last, until the reports were signed), and the codec refuses one.

All clocks are injected (frame times and ticks are arguments): nothing sleeps."""

from __future__ import annotations

import functools
import logging
import re
from dataclasses import replace
from pathlib import Path

import can
import pytest

from firmware_py import contract
from firmware_py import fixedpoint as fx
from firmware_py.config import (
    agent_configs_from_scenario,
    load_agent_config,
    parse_agent_config,
)
from firmware_py.errors import ConfigError
from firmware_py.frames import (
    DecodedFrame,
    FrameCodec,
    diag_name,
    mc_name,
    setpoint_name,
    status_name,
    target_raw,
)
from firmware_py.nodeio import FleetSender, NodeIO
from firmware_py.runtime import DIAG_EVERY, SAFETY_CAUSES, AgentRuntime, State
from sim.model.scenario import load_case, scaled
from sim.nodes import plant as plant_module

# These drive the plant's physics with setpoints alone, no agent's MC frames to check
# them against: the plant obeys them, as told to (the check itself: tests/test_liar.py).
PlantNode = functools.partial(plant_module.PlantNode, obey_inconsistent=True)


CODEC = FrameCodec()
TS = 0.01
NEW_DIAG = ("Untrusted", "ImplausiblePrice", "ImplausibleLambda", "ImplausibleGains",
            "RejectedAuth", "Unsynced")
NEW_CAUSES = ("untrusted_sources", "implausible_price", "implausible_lambda",
              "implausible_gains", "auth", "unsynced")
PRICE_ID = CODEC.frame_id("ER_Price")

SENDER = FleetSender(CODEC)  # the genuine nodes, --insecure: boot 1, no sync needed
WRONG_KEY = bytes(16 * [9])


@pytest.fixture(autouse=True)
def _fresh_senders() -> None:
    """Every test starts with senders that just booted, as its fresh nodes expect."""
    SENDER.reset_counts()
    SENDER.boot = 1


def forger() -> FleetSender:
    """A sender that knows the layouts but not the keys: every frame it signs is forged."""
    labels = ("router", "plant", *(f"agent_{i}" for i in range(1, 9)))
    links = contract.keyed_frames(8)   # AUTH-28..30: frames and commands under their own keys
    commands = [contract.command_key_name(i) for i in range(1, 9)]
    return FleetSender(CODEC, keys=dict.fromkeys([*labels, *links, *commands], WRONG_KEY))


def tampered(msg: can.Message) -> can.Message:
    """A signed frame with one payload bit flipped (its MAC no longer verifies)."""
    data = bytearray(msg.data)
    data[7] ^= 0x01
    return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False, data=data)


def status_frame(agent: int, counter: int) -> can.Message:
    return SENDER.frame(status_name(agent), {
        "FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
        "Power": 10.0, "Soc": 50.0}, counter, phys=True)


def price_raw(rho: float) -> dict[str, int]:
    return {"PriceValid": 1, "Rho": fx.to_fixed(rho), "Segment": 0}


def price_frame(counter: int, rho: float = 0.8) -> can.Message:
    return SENDER.frame("ER_Price", price_raw(rho), counter % 16)


RHO_08 = {"Rho": fx.to_fixed(0.8)}


def taken(f: DecodedFrame | None, *signals: str) -> tuple[str, dict[str, int]] | None:
    """What a receiver took: the frame's name and the raw ``signals``; None if rejected."""
    return None if f is None else (f.name, {k: f.raw[k] for k in signals})


def mc_frame(agent: int, counter: int, lam: float, state: State = State.RUNNING) -> can.Message:
    return SENDER.frame(mc_name(agent), {"State": int(state), "Lambda": fx.to_fixed(lam),
                                         "Resets": 0}, counter % 16)


def agent(index: int = 0, case: int = 1) -> AgentRuntime:
    """Agent index+1 of a case, with a fresh plant status at t = 0."""
    a = AgentRuntime(agent_configs_from_scenario(load_case(case))[index], CODEC)
    a.on_frame(status_frame(a.cfg.id, 0), 0.0)
    return a


def running_agent() -> AgentRuntime:
    """Agent 1 (pinned) RUNNING on ρ = 0.8 at t = 0.01."""
    a = agent()
    a.on_frame(price_frame(0), 0.0)
    a.tick(0.0)
    a.tick(TS)
    assert a.state == State.RUNNING
    return a


# --------------------------------------------------------------------------- 1. untrusted


def test_untrusted_after_n_consecutive_failures_genuine_frames_still_used(
        caplog: pytest.LogCaptureFixture) -> None:
    """Five consecutive failures on ER_Price (a forged frame, a corrupted one, a replay,
    a genuine frame out of the λ range) raise the untrusted alarm for untrusted_s.

    Changed with authentication: the old counter-jump and CRC failures are now MAC
    failures (``auth``), and a secured ID is no longer blocked while untrusted: the
    genuine router's frames (valid MAC) keep being used, the forger's keep failing
    ``auth``; the alarm still expires after untrusted_s."""
    a = agent()
    assert a.cfg.untrusted_after == 5 and a.cfg.untrusted_s == pytest.approx(1.0)
    first = price_frame(0)
    a.on_frame(first, 0.0)
    a.tick(0.0)
    a.tick(TS)
    bad = forger()
    with caplog.at_level(logging.WARNING, logger="firmware_py.nodeio"):
        a.on_frame(bad.frame("ER_Price", price_raw(0.8)), 0.02)    # wrong key
        a.on_frame(tampered(price_frame(1)), 0.03)                  # one bit flipped
        a.on_frame(first, 0.04)                                     # a replay
        a.on_frame(price_frame(2, rho=20.0), 0.05)   # genuine, outside [lambda_min, lambda_max]
        assert a.counters["auth"] == 3 and a.counters["range"] == 1
        assert a.counters["untrusted_sources"] == 0 and a.io.last_safety == ("auth", PRICE_ID)
        assert "forged, replayed or corrupted" in a.last_error["auth"]
        assert a.price_rx == 0.0
        a.on_frame(bad.frame("ER_Price", price_raw(0.8)), 0.06)    # the 5th in a row
    assert a.counters["untrusted_sources"] == 1 and a.counters["auth"] == 4
    assert a.io.last_safety == ("untrusted", PRICE_ID)
    assert a.diag_values()["SafetySender"] == PRICE_ID
    assert SAFETY_CAUSES[a.diag_values()["SafetyCause"]] == "untrusted"
    assert any("untrusted for 1.000 s after 5 consecutive" in r.getMessage()
               for r in caplog.records)
    assert a.io.untrusted(PRICE_ID, 0.07)
    # untrusted, yet a genuine frame is used; a forged one is still an auth failure
    a.on_frame(price_frame(3, rho=0.8), 0.5)
    assert a.price_rx == 0.5
    assert a.io.untrusted(PRICE_ID, 0.5)     # the alarm holds for its time
    a.on_frame(bad.frame("ER_Price", price_raw(0.8)), 0.6)
    assert a.counters["auth"] == 5
    assert a.io.last_safety == ("auth", PRICE_ID) and a.price_rx == 0.5
    # the stated time is over at 0.06 + 1 s
    assert a.io._untrusted_until[PRICE_ID] == pytest.approx(1.06)
    assert not a.io.untrusted(PRICE_ID, 1.07)
    a.on_frame(price_frame(4, rho=0.8), 1.07)
    assert a.price_rx == 1.07 and PRICE_ID not in a.io._untrusted_until
    assert a.counters["untrusted_sources"] == 1
    assert a.counters["lost_frames"] == 1    # the tampered frame's freshness step


def test_a_genuine_frame_resets_the_streak() -> None:
    """4 failures, 1 genuine frame, ...: never 5 in a row, no alarm; 5 in a row then raise
    it. A plausibility rejection (a genuine but implausible price) neither ends the
    streak nor adds to it. (Failures are now forged frames, counted under ``auth``.)"""
    a = running_agent()
    bad = forger()
    ctr = 1
    for k in range(3):
        for j in range(4):
            a.on_frame(bad.frame("ER_Price", price_raw(0.8)), 0.02 + 0.1 * k + 0.01 * j)
        a.on_frame(price_frame(ctr), 0.07 + 0.1 * k)
        ctr += 1
    assert a.counters["auth"] == 12 and a.counters["untrusted_sources"] == 0
    assert a.price_rx == pytest.approx(0.27)
    for j in range(4):
        a.on_frame(bad.frame("ER_Price", price_raw(0.8)), 0.3 + 0.01 * j)
    a.on_frame(price_frame(ctr, rho=6.0), 0.34)   # genuine, > rho_max: implausible
    assert a.counters["implausible_price"] == 1 and a.counters["untrusted_sources"] == 0
    a.on_frame(bad.frame("ER_Price", price_raw(0.8)), 0.35)   # the 5th failure in a row
    assert a.counters["auth"] == 17 and a.counters["untrusted_sources"] == 1


def test_untrusted_time_stretches_with_the_time_scale_and_is_configurable() -> None:
    """The untrusted time follows the time scale (10 s at --time-scale 10) and both
    parameters are configurable. Changed with authentication: on a secured ID (ER_Price)
    the alarm no longer blocks genuine frames; nor on AGENT_1_Diag at the router, an
    E2E-only ID before the diagnostics were authenticated, where it blocked them."""
    cfg = agent_configs_from_scenario(scaled(load_case(1), 10.0))[0]
    assert cfg.untrusted_s == pytest.approx(10.0)
    a = AgentRuntime(cfg, CODEC)
    assert a.io.untrusted_s == pytest.approx(10.0)
    a.on_frame(price_frame(0), 0.0)
    bad = forger()
    for k in range(5):
        a.on_frame(bad.frame("ER_Price", price_raw(0.8)), 0.1 * (k + 1))
    assert a.counters["untrusted_sources"] == 1
    assert a.io._untrusted_until[PRICE_ID] == pytest.approx(10.5)
    assert a.io.untrusted(PRICE_ID, 10.4) and not a.io.untrusted(PRICE_ID, 10.6)

    # a secured ID, untrusted_after = 2 and untrusted_s = 0.3
    io = NodeIO(CODEC, "test", own=(mc_name(1),), wanted=(PRICE_ID,),
                untrusted_after=2, untrusted_s=0.3)
    assert taken(io.receive(price_frame(1), 0.0), "Rho") == ("ER_Price", RHO_08)
    for t in (0.01, 0.02):
        assert io.receive(bad.frame("ER_Price", price_raw(0.8)), t) is None
    assert io.counters["auth"] == 2 and io.counters["untrusted_sources"] == 1
    assert io._untrusted_until[PRICE_ID] == pytest.approx(0.32)
    assert taken(io.receive(price_frame(2), 0.2), "Rho") == ("ER_Price", RHO_08)
    assert io.untrusted(PRICE_ID, 0.31) and not io.untrusted(PRICE_ID, 0.33)

    # AGENT_1_Diag, secured like every frame: forged pages raise the alarm, the genuine
    # agent's pages still pass
    diag = CODEC.frame_id(diag_name(1))
    router = NodeIO(CODEC, "test router", own=("ER_Price",), wanted=(diag,),
                    untrusted_after=2, untrusted_s=0.3)
    page_0 = {"Page": 0, "Resets": 0, "DeadlineMisses": 0}
    assert taken(router.receive(SENDER.frame(diag_name(1), page_0), 0.0),
                 *page_0) == (diag_name(1), page_0)
    for t in (0.01, 0.02):
        assert router.receive(bad.frame(diag_name(1), page_0), t) is None
    assert router.counters["auth"] == 2 and router.counters["untrusted_sources"] == 1
    assert taken(router.receive(SENDER.frame(diag_name(1), page_0), 0.2),
                 *page_0) == (diag_name(1), page_0)


def test_plant_keeps_following_genuine_setpoints_under_forged_ones() -> None:
    """Forged AGENT_3_Setpoint frames (wrong key) are ``auth`` failures and raise the
    untrusted alarm after 5 in a row. Changed with authentication: they no longer silence
    the genuine agent 3 — the plant keeps taking its setpoints
    and never uses a forged one, even at 5× the genuine rate. Forged frames before the
    first genuine one are ``unsynced`` (the insecure plant waits for the sender), not
    forgeries."""
    plant = PlantNode(load_case(1))
    u = plant.unit(3)
    name = setpoint_name(3)
    bad = forger()

    def forged() -> can.Message:
        return bad.frame(name, {"Enable": 1, "PowerSetpoint": -9000})

    plant.on_frame(forged(), 0.0)
    assert plant.counters["unsynced"] == 1 and plant.counters["auth"] == 0
    assert u.setpoint_rx is None
    plant.on_frame(SENDER.frame(name, {"Enable": 1, "PowerSetpoint": 5000}, 0), 0.001)
    assert u.p_set == 50.0
    for k in range(5):
        plant.on_frame(forged(), 0.002 + 0.001 * k)
    assert plant.counters["auth"] == 5 and plant.counters["untrusted_sources"] == 1
    assert plant.io.untrusted(CODEC.frame_id(name), 0.01)
    plant.on_frame(SENDER.frame(name, {"Enable": 1, "PowerSetpoint": 6000}, 1), 0.01)
    assert u.setpoint_rx == 0.01 and u.p_set == 60.0
    # 1 s of genuine setpoints every 50 ms, 5 forged ones in between each
    refs = []
    for k in range(1, 101):
        t = 0.01 + k * TS
        if k % 5 == 0:
            plant.on_frame(SENDER.frame(name, {"Enable": 1, "PowerSetpoint": 6000}), t)
        plant.on_frame(forged(), t + 0.005)
        plant.tick(t)
        refs.append(u.p_ref)
        assert u.p_set == 60.0 and not u.stale, t
    assert plant.counters["setpoints"] == 2 + 20
    # each genuine frame ends a streak; the 5 forged ones after it raise the alarm again
    # (1 before the loop, then every period but the first, whose streak is only 4)
    assert plant.counters["auth"] == 105 and plant.counters["untrusted_sources"] == 1 + 19
    assert min(refs) >= 0.0 and refs[-1] == pytest.approx(60.0)


# --------------------------------------------------------------------------- 2. price


def test_price_outside_bounds_rejected() -> None:
    a = running_agent()
    a.on_frame(price_frame(1, rho=6.0), 0.02)     # inside the DBC and lambda range, > rho_max
    a.on_frame(price_frame(2, rho=-5.5), 0.03)    # < rho_min (a negative price is no fault)
    assert a.counters["implausible_price"] == 2 and a.price == fx.to_fixed(0.8)
    assert "rho_min/rho_max" in a.last_error["implausible_price"]
    assert a.counters["range"] == 0


def test_price_step_rejected_until_it_persists_for_k_frames() -> None:
    a = running_agent()
    t = TS
    for n in range(1, 3):  # 0.8 → 1.5 (Δ 0.7 > 0.5): frames 1 and 2 rejected
        t += 0.05
        a.tick(t)
        a.on_frame(price_frame(n, rho=1.5), t)
        assert a.price == fx.to_fixed(0.8), n
    assert a.counters["implausible_price"] == 2
    t += 0.05
    a.tick(t)
    a.on_frame(price_frame(3, rho=1.5), t)         # the 3rd in a row: a new level
    assert a.price == fx.to_fixed(1.5) and a.counters["price_steps_accepted"] == 1
    assert a.counters["implausible_price"] == 2


def test_price_step_candidate_must_repeat_exactly() -> None:
    """A stream alternating two far levels (or drifting in big steps) never persists. With
    authentication such a stream must carry the router's MAC (a compromised router or a
    holder of its key): only the safety model bounds it."""
    a = running_agent()
    for n in range(1, 11):
        a.tick(TS + 0.05 * n)
        a.on_frame(price_frame(n, rho=2.0 if n % 2 else 2.5), TS + 0.05 * n)
    assert a.price == fx.to_fixed(0.8) and a.counters["implausible_price"] == 10
    assert a.counters["price_steps_accepted"] == 0


def test_paper_price_steps_pass() -> None:
    """Case 5's steps 0.8 → 1.0 → 0.6 (≤ 0.4) are accepted at once."""
    a = running_agent()
    for n, rho in enumerate((1.0, 1.0, 0.6, 0.6), start=1):
        a.tick(TS + 0.05 * n)
        a.on_frame(price_frame(n, rho=rho), TS + 0.05 * n)
        assert a.price == fx.to_fixed(rho)
    assert not any(a.counters[c] for c in NEW_CAUSES)


# --------------------------------------------------------------------------- 3. neighbour λ


def neighbour_setup() -> tuple[AgentRuntime, int, float]:
    a = running_agent()
    j = a.cfg.neighbours[0].id
    return a, j, a.cfg.lambda_step_max or 0.0


def test_neighbour_lambda_step_rejected_last_good_kept() -> None:
    a, j, step = neighbour_setup()
    assert step == pytest.approx(0.1)  # 10·k·Ts
    t = 2 * TS
    a.on_frame(mc_frame(j, 0, 0.80), t)
    a.tick(t)
    t += TS
    a.on_frame(mc_frame(j, 1, 0.85), t)   # 0.05 per sample: fine
    a.tick(t)
    t += TS
    a.on_frame(mc_frame(j, 2, 5.0), t)    # forged jump
    slot = next(s for s in a.neighbours.values() if s.id == j)
    assert a.counters["implausible_lambda"] == 1 and slot.lam == fx.to_fixed(0.85)
    assert SAFETY_CAUSES[a.diag_values()["SafetyCause"]] == "implausible_lambda"
    assert a.diag_values()["SafetySender"] == CODEC.frame_id(mc_name(j))
    # two samples since the last accepted frame: up to 2 × step
    a.tick(t)
    t += TS
    a.on_frame(mc_frame(j, 3, 0.85 + 1.9 * step), t)
    assert a.counters["implausible_lambda"] == 1
    assert slot.lam == fx.to_fixed(0.85 + 1.9 * step)


def test_isolate_jump_and_reconnect_not_counted() -> None:
    """An isolated neighbour jumps to its idle MC with State ISOLATED, comes back through
    INIT: none of it is a RUNNING→RUNNING step."""
    a, j, _ = neighbour_setup()
    t = 2 * TS
    for ctr, (lam, st) in enumerate([(1.2, State.RUNNING), (0.1944, State.ISOLATED),
                                     (0.1944, State.ISOLATED), (0.1944, State.INIT),
                                     (0.1944, State.RUNNING), (0.2, State.RUNNING),
                                     (1.0, State.SAFE), (1.0, State.RUNNING)]):
        a.on_frame(mc_frame(j, ctr, lam, st), t)
        a.tick(t)
        t += TS
    assert a.counters["implausible_lambda"] == 0


def test_timed_out_neighbour_is_accepted_afresh() -> None:
    a, j, _ = neighbour_setup()
    a.on_frame(mc_frame(j, 0, 0.8), 0.02)
    a.tick(0.02)
    a.tick(0.2)   # silent for 18 samples: timed out
    a.on_frame(mc_frame(j, 1, 2.0), 0.2)
    assert a.counters["implausible_lambda"] == 0


# --------------------------------------------------------------------------- 4. commands


def command(counter: int, cmd: int, target: int = 1, k: int = 0, h: int = 0) -> can.Message:
    return SENDER.frame("ER_Command", {"Command": cmd, "Target": target_raw(target), "GainK": k,
                                        "GainH": h}, counter)


def test_set_gains_outside_bounds_rejected_inside_accepted() -> None:
    """The gains are 14 bits now (0..16.383): the issue's attack is their DBC maximum."""
    a = running_agent()
    assert (a.cfg.k_min, a.cfg.k_max, a.cfg.h_min, a.cfg.h_max) == (0.5, 2.0, 1.0, 4.0)
    assert CODEC.raw_range("ER_Command", "GainK") == (0, 16383)
    a.on_frame(command(0, 3, k=16383, h=16383), 0.02)   # the DBC maximum (the attack)
    a.on_frame(command(1, 3, k=1000, h=4500), 0.03)     # h just above h_max
    assert a.counters["implausible_gains"] == 2
    assert (a.ctrl.config.k, a.ctrl.config.h) == (1.0, 2.0)
    assert a.diag_values()["ImplausibleGains"] == 2
    a.on_frame(command(2, 3, k=1500, h=3000), 0.04)
    assert (a.ctrl.config.k, a.ctrl.config.h) == (1.5, 3.0)
    assert a.counters["implausible_gains"] == 2


def test_isolate_and_reconnect_logged_and_counted(caplog: pytest.LogCaptureFixture) -> None:
    a = running_agent()
    with caplog.at_level(logging.WARNING, logger="firmware_py.runtime"):
        a.on_frame(command(0, 1), 0.02)
        a.on_frame(command(1, 1), 0.03)   # the router repeats each command (a new FV each)
        a.on_frame(command(2, 2), 0.04)
        a.on_frame(command(3, 1, target=2), 0.05)   # not for agent 1
    assert a.counters["commands_isolate"] == 2 and a.counters["commands_reconnect"] == 1
    sender = f"0x{CODEC.frame_id('ER_Command'):03X}"
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert sum("ISOLATE from claimed sender " + sender in m for m in msgs) == 2
    assert sum("RECONNECT from claimed sender " + sender in m for m in msgs) == 1
    # the same bytes again are a replay, not a repeat: rejected before the command logic
    replayed = command(4, 1)
    a.on_frame(replayed, 0.06)
    a.on_frame(replayed, 0.07)
    assert a.counters["commands_isolate"] == 3 and a.counters["auth"] == 1


# --------------------------------------------------------------------------- 5. plant ramp


def test_plant_ramp_limits_a_setpoint_jump() -> None:
    plant = PlantNode(load_case(1))
    u = plant.unit(3)
    rate = max(abs(u.battery.p_min), u.battery.p_max) / 0.25
    assert u.ramp_kw_s == pytest.approx(rate)
    refs = []
    for k in range(40):
        if k % 5 == 0:
            plant.on_frame(SENDER.frame(setpoint_name(3), {
                "Enable": 1, "PowerSetpoint": round(100 * u.battery.p_max)}, k // 5), k * TS)
        plant.tick(k * TS)
        refs.append(u.p_ref)
    steps = [b - a for a, b in zip(refs, refs[1:], strict=False)]
    assert max(steps) <= rate * TS + 1e-9
    assert refs[-1] == pytest.approx(u.battery.p_max)
    assert refs[10] < 0.5 * u.battery.p_max
    assert plant.counters["setpoint_ramp_limited"] == 1
    # disabling goes to 0 at once (the safe direction)
    plant.on_frame(SENDER.frame(setpoint_name(3), {"Enable": 0, "PowerSetpoint": 0}, 8), 0.4)
    plant.tick(0.4)
    assert u.p_ref == 0.0


def test_plant_ramp_configurable_and_off() -> None:
    plant = PlantNode(load_case(1), ramp_full_s=0)
    plant.on_frame(SENDER.frame(setpoint_name(1), {"Enable": 1, "PowerSetpoint": 9000}, 0), 0.0)
    plant.tick(0.0)
    assert plant.unit(1).p_ref == 90.0 and plant.counters["setpoint_ramp_limited"] == 0


# --------------------------------------------------------------------------- 6. diag pages


def test_diag_pages_carry_the_safety_counters() -> None:
    """Pages 9..11 carry the safety counters and the last cause; pages 11 and 12 the MAC
    failures (RejectedAuth), Unsynced and Resyncs."""
    a = running_agent()
    a.on_frame(forger().frame("ER_Price", price_raw(0.8)), 0.014)
    a.on_frame(price_frame(1, rho=9.0), 0.015)
    a.on_frame(command(0, 3, k=9000, h=9000), 0.016)
    pages = {}
    for k in range(2, 2 + len(a.DIAG_PAGES) * DIAG_EVERY):
        for msg in a.tick(k * TS):
            if msg.arbitration_id == CODEC.frame_id(diag_name(1)):
                f = CODEC.decode(msg)
                pages[f.raw["Page"]] = f.raw
    assert pages[9]["ImplausiblePrice"] == 1 and pages[9]["Untrusted"] == 0
    assert pages[10]["ImplausibleGains"] == 1
    assert pages[11]["SafetySender"] == CODEC.frame_id("ER_Command")
    assert SAFETY_CAUSES[pages[11]["SafetyCause"]] == "implausible_gains"
    assert pages[11]["RejectedAuth"] == 1 and pages[12]["Unsynced"] == 0
    assert pages[12]["Resyncs"] == 0
    decoded = CODEC.database.decode_message(CODEC.frame_id(diag_name(1)), CODEC.encode(
        diag_name(1), {"Page": 11, **{s: pages[11][s] for s in a.DIAG_PAGES[11]}}, 0).data)
    assert decoded["SafetyCause"] == "IMPLAUSIBLE_GAINS"
    choices = CODEC.database.get_message_by_name(diag_name(1)).get_signal_by_name(
        "SafetyCause").choices
    assert choices is not None
    assert [str(v) for v in choices.values()] == [c.upper() for c in SAFETY_CAUSES]


# --------------------------------------------------------------------------- config


def test_limits_round_trip_and_bad_values(tmp_path: Path) -> None:
    cfg = replace(agent_configs_from_scenario(load_case(1))[1], rho_max=3.0, price_persist=4,
                  lambda_step_max=0.2, k_max=3.0, untrusted_after=7, untrusted_s=2.0)
    path = tmp_path / "a.toml"
    path.write_text(cfg.to_toml())
    assert replace(load_agent_config(path), source=cfg.source) == cfg
    data = {"agent": {"id": 1, "lambda0": 0.5}, "controller": {"kind": "reset"},
            "battery": {"alpha": 0.005, "beta": 0.18, "m": 0.08, "p_min": -100, "p_max": 100}}
    for limits, key in (({"rho_min": 2.0, "rho_max": 1.0}, "limits.rho_max"),
                        ({"k_min": 3.0}, "limits.k_max"),
                        ({"price_persist": 0}, "limits.price_persist"),
                        ({"untrusted_after": 1.5}, "limits.untrusted_after"),
                        ({"lambda_step_max": 0}, "limits.lambda_step_max")):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            parse_agent_config({**data, "limits": limits}, "test")


# --------------------------------------------------------------------------- healthy runs


@pytest.mark.parametrize("case", [1, 4, 5, pytest.param(7, marks=pytest.mark.long)])
def test_paper_case_bus_run_keeps_safety_counters_at_zero(tmp_path: Path, case: int) -> None:
    from sim.run.busrun import run_in_process

    sc = load_case(case)
    m = run_in_process(sc, tmp_path, sc.duration)
    assert m["anomalies"] == [], m["anomalies"]
    assert m["verdict"]["converged"]
    for name, d in m["node_diagnostics"].items():
        for sig in NEW_DIAG:
            assert d.get(sig, 0) == 0, (name, sig)
            assert sig in d, (name, sig)  # the page was recorded
    for node in ("plant", "router"):
        c = m["node_counters"][node]["counters"]
        for cause in NEW_CAUSES:
            assert c.get(cause, 0) == 0, (node, cause)


def test_implausible_prices_on_the_bus_are_alarms_and_the_dispatch_holds(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every 4th ER_Price from t = 2 s carries ρ = 4.0, signed by the router itself (a
    faulty or compromised router: its MAC and freshness are valid, so authentication
    cannot stop it): every agent rejects each as implausible (the genuine frames in
    between keep the new level from persisting), the dispatch holds at ρ = 0.8, and the
    rejections are anomalies in the metrics."""
    from sim.nodes.router import RouterNode
    from sim.run.busrun import run_in_process

    real = RouterNode._price_raw
    sent = [0]

    def forged(self: RouterNode) -> dict[str, int]:
        raw = real(self)
        sent[0] += 1
        if self._now_rel >= 2.0 and sent[0] % 4 == 0:
            raw["Rho"] = fx.to_fixed(4.0)
        return raw

    real_advance = RouterNode._advance

    def advance(self: RouterNode, t: float) -> tuple[float, float]:
        dt, t_rel = real_advance(self, t)
        self._now_rel = t_rel
        return dt, t_rel

    monkeypatch.setattr(RouterNode, "_price_raw", forged)
    monkeypatch.setattr(RouterNode, "_advance", advance)
    sc = replace(load_case(1), duration=8.0)
    m = run_in_process(sc, tmp_path, sc.duration)
    # the agents' own λ (the recorder's ρ includes the forged frames, so the log's
    # final_error is measured against them and the verdict says "not converged")
    found = [re.search(r"λ=([-0-9.]+)", s) for s in m["node_summaries"] if s.startswith("agent")]
    lams = [float(f.group(1)) for f in found if f is not None]
    assert len(lams) == 4 and max(abs(lam - 0.8) for lam in lams) < 1e-3, lams
    kinds = {(a["kind"], a["node"]) for a in m["anomalies"]}
    assert kinds == {("implausible_frames", f"agent_{i}") for i in range(1, 5)}, m["anomalies"]
    # each alarm names the claimed sender and the cause of the last rejection
    assert all("claimed to come from ER_Price, 0x010 (implausible_price)" in a["detail"]
               for a in m["anomalies"]), m["anomalies"]
    for i in range(1, 5):
        d = m["node_diagnostics"][f"agent_{i}"]
        assert d["ImplausiblePrice"] >= 20 and d["Untrusted"] == 0, d
        assert d["RejectedAuth"] == 0, d
