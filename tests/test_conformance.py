"""`bess-ded conformance`: the schedule, the oracle and the verdict per requirement.

In process, the schedule is played against firmware_py's agent on a simulated clock
(``sim.conformance.simulate``), with ticks and frames as late as a loaded host makes
them: firmware_py must pass every requirement at any such timing, and every known
deviation must fail, naming its requirement. On udp_multicast the command drives a
separately started agent process, as a vendor would drive their device.
"""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest
from conformance_run import (
    C_DEVICE_HINT,
    DEVIANT,
    DEVICE_HINT,
    FIRMWARE_PY,
    assert_passed,
    run_conformance,
)

from dbc import FD_DBC_PATH
from firmware_py import fixedpoint as fx
from firmware_py.config import AgentConfig, agent_configs_from_scenario
from firmware_py.contract import ER_COMMAND_ID, State
from firmware_py.frames import FrameCodec
from firmware_py.runtime import AgentRuntime
from firmware_py.secoc import Keyring
from sim import conformance as conf
from sim.cbind.cagent import node_program
from sim.cli import main
from sim.conformance.schedule import OTHER_FORMAT
from sim.model.scenario import load_case
from sim.testkit.tester import fleet_keys

MASTER = bytes(range(16))
FD_CODEC = FrameCodec(FD_DBC_PATH)
KEYS = fleet_keys(MASTER, 12)  # node keys and link frame keys (AUTH-28)


def _setup(case: int, dut: int, fd: bool = False
           ) -> tuple[AgentConfig, Callable[[], Keyring], list[conf.Planned]]:
    sc = load_case(case)
    # the configuration the tester writes, as the reference parser reads it
    _, cfg = conf.written_config(agent_configs_from_scenario(sc)[dut - 1])
    node = f"agent_{dut}"

    def ring() -> Keyring:  # its peers' floors at boot 2, as `up` writes them (AUTH-21)
        return Keyring(node, KEYS[node], 0, lambda _b: None, master=MASTER,
                       floors={n: 2 for n in KEYS if n != node})

    return cfg, ring, conf.plan(cfg, KEYS, sc.prices[0].rho, boot=2,
                                codec=FD_CODEC if fd else None)


def _judge(cfg: AgentConfig, ring: Callable[[], Keyring], frames: list[conf.Frame],
           codec: FrameCodec | None = None) -> tuple[conf.Outcome, list[conf.Result]]:
    key = KEYS[f"agent_{cfg.id}"]
    outcome = conf.check(cfg, ring(), key, frames, codec)
    conf.explain(cfg, ring(), key, frames, outcome, codec)
    return outcome, conf.verdict(outcome)


@pytest.mark.parametrize("fd", [True, False])
def test_a_device_sending_the_other_frame_format_fails_gen_1_alone(fd: bool) -> None:
    """A DUT that sends classic frames on a CAN FD bus (or FD frames on a classic one)
    fails GEN-1, once, naming the first such frame; its frames are judged by their
    content otherwise, so nothing else fails, and the checker does not crash on them."""
    cfg, ring, planned = _setup(1, 3, fd)
    codec = FD_CODEC if fd else None

    def other_format(rt: AgentRuntime) -> None:
        send = rt.io.send

        def wrong(name: str, raw: dict[str, int], *a: Any, **k: Any) -> can.Message:
            msg = send(name, raw, *a, **k)
            msg.is_fd = msg.bitrate_switch = not fd
            return msg

        rt.io.send = wrong  # type: ignore[method-assign]

    frames = conf.simulate(cfg, ring(), planned, other_format, codec=codec)
    outcome, results = _judge(cfg, ring, frames, codec)
    assert [r.must for r in results if r.failed] == ["GEN-1"], \
        [r for r in results if r.failed]
    detail = next(r.detail for r in results if r.must == "GEN-1")
    assert ("but got a classic CAN frame" if fd else "but got a CAN FD frame") in detail
    assert "more frames in the wrong format" in detail


@pytest.mark.parametrize("case,dut,jitter,seed,fd", [(1, 3, 0.0, 0, False),
                                                     (1, 1, 0.95, 2, True),
                                                     (7, 5, 0.5, 1, False),
                                                     (6, 3, 0.3, 3, False)])
def test_firmware_py_passes_every_requirement_at_any_timing(
        case: int, dut: int, jitter: float, seed: int, fd: bool) -> None:
    """Expected: with the device's ticks and the tester's frames each up to 0.95 Ts late,
    every requirement passes and the whole schedule was checked (the oracle found the
    order of events that explains every frame); on a CAN FD bus too (``fd``: every
    frame of the schedule, the hand-made ones included, an FD frame with the bit-rate
    switch)."""
    cfg, ring, planned = _setup(case, dut, fd)
    codec = FD_CODEC if fd else None
    assert all(p.msg.is_fd == p.msg.bitrate_switch == fd for p in planned
               if p.note != OTHER_FORMAT)  # but RX-2's frame
    frames = conf.simulate(cfg, ring(), planned, jitter=jitter, seed=seed, codec=codec)
    outcome, results = _judge(cfg, ring, frames, codec)
    assert not outcome.mismatches, outcome.mismatches[:3]
    assert not outcome.auth_errors and not outcome.problems
    assert outcome.steps_seen == {s.name for s in conf.STEPS}
    assert all(r.passed for r in results), [r for r in results if not r.passed]
    assert outcome.ticks >= conf.STEPS[-1].end - 5
    # a dwell device's own requirements are in its verdict only (case 6: kind dwell),
    # AUTH-34 in an FD run's (λ tags); the PI family's step in every one of these (reset
    # and dwell devices), pc's and ft's in none
    own = {r.must for r in results} & set(conf.ONLY_ON)
    assert own == ({"AUTH-34"} if fd else set()) | (
        {m for m, on in conf.ONLY_ON.items() if on == "dwell"} if case == 6 else set()) | {
        m for m, on in conf.ONLY_ON.items() if on == "pi family"}, own


def test_a_dwell_device_meets_crossings_at_its_dwell_and_only_it_is_judged_on_them() -> None:
    """Expected: on a device of kind dwell (case 6, D = ceil(7.2) = 8 samples in the
    tester's file) the band step ends with a crossing after SAFE and crossings D − 1 and
    D samples after a reset; a device whose dwell lets a crossing reset only once
    since_reset > D (not ≥: the set's ``dwell_strict``) fails DWELL-1 first. A reset
    device's plan has no such crossing, nor a pinned dwell device's (no band
    trajectory: its verdict has no DWELL-1)."""
    import conformance_faults as cf

    cfg, ring, planned = _setup(6, 3)
    assert cfg.controller.kind == "dwell" and cfg.controller.dwell_samples == 8
    notes = [p.note for p in planned if p.step == "band" and "samples after a reset" in p.note]
    assert [n.split(" (")[0] for n in notes] == [
        "a crossing D or more samples after a reset, SAFE between",
        "a crossing D − 1 samples after a reset", "a crossing D samples after a reset"]
    strict = cf.BY_NAME["dwell_strict"].apply
    _, faulty = _judge(cfg, ring, conf.simulate(cfg, ring(), planned, strict, jitter=0.3))
    assert [r.must for r in faulty if r.failed][:1] == ["DWELL-1"], faulty[:3]
    # (a healthy dwell device passes them: test_firmware_py_passes_every_requirement_…)
    _, _, planned1 = _setup(1, 3)
    assert not any("samples after a reset" in p.note for p in planned1)
    # a pinned dwell device (case 6's hub): no band trajectory, so no dwell edges either
    _, hub = conf.written_config(agent_configs_from_scenario(load_case(6))[0])
    assert hub.controller.kind == "dwell" and conf.kind_exercised(hub) == ""


@pytest.mark.parametrize("prev", [0.37e-2, 9.2453, 14.000000000123, 15.9949])
def test_exactly_after_puts_two_times_a_tie_apart_in_binary64_and_in_whole_ns(
        prev: float) -> None:
    """Expected: the exact-timing run's pair (``Planned.after``) is 2.5 periods apart as
    firmware_py divides it (binary64: a tie of rne) and as firmware_c subtracts it (its
    ns clock, round(t·1e9): a remainder of exactly half its period), the first time moved
    by at most 2 ns."""
    from sim.conformance.drive import _exactly_after

    cfg, _, _ = _setup(1, 3)
    ts = cfg.controller.ts
    a, b = _exactly_after(prev, 2.5 * ts, ts)
    assert abs(a - prev) <= 2e-9
    assert (b - a) / ts == 2.5
    period_ns = round(ts * 1e9)
    dt = round(b * 1e9) - round(a * 1e9)
    assert dt // period_ns == 2 and 2 * (dt % period_ns) == period_ns


@pytest.mark.parametrize("filtered_first", [False, True])
def test_a_device_filtering_foreign_ids_passes_judged_with_the_filter(
        filtered_first: bool) -> None:
    """Expected: a DUT whose CAN controller passes only its acceptance IDs (GEN-5: it
    never counts the unknown and extended IDs of the content step) passes, and the
    outcome says it filters; whichever model is tried first."""
    cfg, ring, planned = _setup(1, 3)
    frames = conf.simulate(cfg, ring(), planned, filtered=True, jitter=0.3)
    outcome = conf.check(cfg, ring(), KEYS["agent_3"], frames, filtered_first=filtered_first)
    assert not outcome.mismatches and outcome.filtered
    unfiltered = conf.check(cfg, ring(), KEYS["agent_3"], conf.simulate(cfg, ring(), planned),
                            filtered_first=filtered_first)
    assert not unfiltered.mismatches and not unfiltered.filtered


@pytest.mark.parametrize("must,case,dut", [("BAND-2", 1, 3), ("BAND-2", 7, 5),
                                           ("BAND-1", 4, 2)])
def test_a_known_deviation_fails_naming_its_requirement(must: str, case: int,
                                                        dut: int) -> None:
    """Expected: an agent with the deviation fails exactly that requirement; the rest of
    the schedule, checked with the deviation modelled, passes."""
    cfg, ring, planned = _setup(case, dut)
    frames = conf.simulate(cfg, ring(), planned, conf.MUTANTS[must][1], jitter=0.3)
    outcome, results = _judge(cfg, ring, frames)
    failed = [r for r in results if not r.passed]
    assert [r.must for r in failed] == [must], failed
    assert conf.MUTANTS[must][0] in failed[0].detail
    assert outcome.explained_by == {must: conf.MUTANTS[must][0]}


def test_an_unknown_deviation_fails_the_requirements_of_its_signal_and_step() -> None:
    """Expected: a device that does not count rejected MACs on Diag page 8 fails the
    authentication requirements of that counter, in the step that forges frames."""
    cfg, ring, planned = _setup(1, 3)

    def no_auth_count(rt: AgentRuntime) -> None:
        values = rt.diag_values
        rt.diag_values = lambda: {**values(), "RejectedAuth": 0}  # type: ignore[method-assign]

    frames = conf.simulate(cfg, ring(), planned, no_auth_count)
    outcome, results = _judge(cfg, ring, frames)
    # the earlier run's sync played first (AUTH-21) is the first auth failure: named first
    failed = [r.must for r in results if not r.passed]
    assert failed[0] == "AUTH-21", failed
    assert set(failed) <= {"AUTH-10", "AUTH-11", "AUTH-12", "AUTH-14", "AUTH-16", "AUTH-17",
                           "AUTH-21", "AUTH-25", "RX-8"}, failed
    assert "first divergence at step" in results[0].detail
    # RejectedAuth's page (11 of 13) goes out every 130 ticks: the first after the
    # earlier run's sync at the start
    assert outcome.mismatches[0].step in ("price-only", "running")
    assert outcome.mismatches[0].signal == "RejectedAuth"
    assert not outcome.explained_by


def test_a_device_ignoring_its_boot_floors_fails_auth_21() -> None:
    """Expected: a device that takes the earlier run's price sync played first (AUTH-21:
    below its floor) counts it as a resync, not as an auth failure: it fails, and the
    requirements named include AUTH-21."""
    cfg, ring, planned = _setup(1, 3)
    assert planned[0].note == "an earlier run's price sync (AUTH-21)"

    def no_floors(rt: AgentRuntime) -> None:
        rt.io.keys.floors.clear()

    frames = conf.simulate(cfg, ring(), planned, no_floors)
    _, results = _judge(cfg, ring, frames)
    failed = {r.must for r in results if not r.passed}
    assert "AUTH-21" in failed, failed


def test_the_schedule_does_what_its_steps_say() -> None:
    """Expected: played against firmware_py, the device goes through INIT, RUNNING,
    ISOLATED and SAFE, and counts each rejection and timeout the steps provoke."""
    cfg, ring, planned = _setup(1, 3)
    dut = AgentRuntime(cfg, FrameCodec(), keys=ring())
    states = []
    pins = {dut.pin}
    real_tick = dut.tick

    def tick(t: float) -> list:
        frames = real_tick(t)
        pins.add(dut.pin)
        if not states or states[-1] != dut.state.name:
            states.append(dut.state.name)
        return frames

    dut.tick = tick  # type: ignore[method-assign]
    t0 = 12.5 * cfg.controller.ts
    nxt = 0
    for k in range(int(t0 / cfg.controller.ts) + conf.STEPS[-1].end + 3):
        t = (k + 0.37) * cfg.controller.ts
        while nxt < len(planned) and t0 + planned[nxt].at < t:
            dut.on_frame(planned[nxt].msg, t0 + planned[nxt].at)
            nxt += 1
        dut.tick(t)
    # ... and in the limits, freshness and states steps: SAFE on PriceValid = 0 frames only,
    # ISOLATE in SAFE, RECONNECT with the price stale (INIT), ISOLATE in INIT, RECONNECT;
    # the band step's ISOLATE and RECONNECT (its known start), its plant fault and back
    assert states == ["INIT", "RUNNING", "ISOLATED", "RUNNING", "SAFE", "RUNNING", "SAFE",
                      "RUNNING", "SAFE", "ISOLATED", "INIT", "ISOLATED", "RUNNING",
                      "ISOLATED", "RUNNING", "SAFE", "RUNNING"]
    c = dut.counters
    # 5 in the authentication step and the late frame again (seen: a replay, AUTH-25),
    # untrusted_after forged commands, one fewer forged prices (untrusted_after = 6 in
    # the configuration the tester writes)
    assert cfg.untrusted_after == 6 and cfg.price_persist == 5
    # untrusted: the forged commands, and untrusted_after DLC errors on one ID (RX-13);
    # AUTH-27: three key holders' syncs refused (a boot 9 on, counts 17 and 129 on);
    # untrusted_after − 1 forged statuses, valid ones, one more (RX-10: no verdict)
    assert c["auth"] == 5 + 1 + 2 + 6 + 5 + 3 + 1 and c["untrusted_sources"] == 2
    assert c["sync_jump"] == 3 + 1  # AUTH-35: the held price sync 8 boots on, dropped
    assert c["dlc"] == cfg.untrusted_after and c["impersonation"] == 1
    assert c["stale"] == 1   # the genuine frame delivered late (AUTH-25), not auth
    assert c["unsynced"] == 1  # the command before its sync (AUTH-11)
    # SET_GAINS at the bounds pass; one LSB beyond each of the four bounds is refused
    assert c["unknown_id"] == 2 and c["implausible_gains"] == 1 + 4
    # content: a price above rho_max, a persistent step there and back (price_persist − 1
    # candidates each); the step one LSB above the bound: price_persist − 1 candidates,
    # accepted the price_persist-th time
    assert c["implausible_price"] == 1 + 4 + 4 + 4 and c["price_steps_accepted"] == 2 + 1
    assert c["implausible_lambda"] == 2 + 1  # one LSB above LAM-1's bound
    # the neighbour lost on the bus; the PriceValid = 0 outage and the one while ISOLATED
    assert c["neighbour_timeouts"] == 2 and c["price_timeouts"] == 3
    assert c["plant_faults"] == 3  # the second while ISOLATED, the third in the band step
    assert c["saturations"] >= 1  # ξ past int32 in the extremes step (XI-3)
    assert c["commands_isolate"] == 5 and c["commands_reconnect"] == 6
    # in-step syncs are no resyncs; lost: 3, 5 forged statuses (and 1: the one more,
    # RX-10), a price 16 values on (15),
    # the neighbour's 25 frames lost on the bus (not the 6 forged commands' counts nor the
    # PIN refused before authentication: no lost_frames on ER_Command, AUTH-30); the two
    # forgeries of the timeouts step (a neighbour's, the price's) skip a value each, and so
    # does the content step's FD frame (malformed, RX-2)
    # (the neighbour's 25 lost frames and 94 values more: its next frame is 120 on)
    # (resyncs: + the router's price sync 16 values on, AUTH-27's taken side)
    assert c["resyncs"] == 5 and c["lost_frames"] == 3 + 5 + 1 + 15 + 25 + 94 + 2 + 1
    assert c["malformed"] == 1
    assert c["range"] == 1  # the PIN whose GainK is neither way (CMD-7, RX-7)
    assert pins == {0, fx.ONE} and dut.pin == (fx.ONE if cfg.pinned else 0)  # and back
    assert dut.cstate.resets >= 1  # after ISOLATE's reset of the count: resets still happen


def test_every_requirement_named_exists_in_the_spec() -> None:
    from sim.conformance import results as res

    spec = set(conf.spec_requirements())
    named = {m for s in conf.STEPS for m in s.musts} | set(conf.MUTANTS)
    named |= {m for v in conf.SIGNAL_MUSTS.values() for m in v}
    for table in (res.MOMENTS, res.TRANSITIONS, res.STATE_RULES, res.EDGES):
        named |= {m for v in table.values() for m in v}
    assert named <= spec, named - spec
    assert len(spec) > 100


def _mm(message: str, signal: str, expected: object, got: object, tick: int = 100,
        step: str = "control", moment: tuple[str, ...] = (),
        transition: tuple[str, ...] = (), follows: int | None = None) -> conf.Mismatch:
    return conf.Mismatch(tick * 0.01, tick, step, message, signal, expected, got,
                         moment=moment, transition=transition, follows=follows,
                         raw=(expected, got))


def test_a_difference_names_what_the_step_exercises_at_that_moment() -> None:
    """Expected: a λ difference after a SET_GAINS names CMD-5, a State difference after
    an ISOLATE STATE-7 and after an ISOLATE for another agent CMD-1; a λ one LSB off names
    a rounding (the gains', λ(0)'s or the wire's: NUM-8, in no signal's list), a missed
    reset at ξ = 0 the crossing rule (STEP-2), unless the tester just led it there; a
    counter names its own cause, narrowed by the moment where they meet; without a
    moment, the signal's requirements narrowed by the step's."""
    a = conf.attribute
    assert a(_mm("MC", "Lambda", 1000, 5000, step="commands",
                 moment=("SET_GAINS in bounds",)))[0] == "CMD-5"
    assert a(_mm("MC", "State", "RUNNING", "ISOLATED", step="commands",
                 moment=("ISOLATE",)))[0] == "STATE-7"
    assert a(_mm("MC", "State", "RUNNING", "ISOLATED", step="commands",
                 moment=("ISOLATE for another agent",))) == ("CMD-1",)
    # one LSB off: the gains' rounding right after a SET_GAINS, λ(0)'s before any
    # control step, else the wire λ's
    assert a(_mm("MC", "Lambda", 1000, 1001, moment=("SET_GAINS in bounds",))) == (
        "CMD-5", "NUM-8")
    assert a(_mm("MC", "Lambda", 1000, 1001, step="start")) == ("NUM-4", "NUM-8")
    # (pc's and ft's step first: the verdict judges them on those devices only)
    assert a(_mm("MC", "Lambda", 1000, 1001, moment=("ISOLATE",))) == (
        "STEP-10", "STEP-11", "NUM-8")
    assert a(_mm("MC", "Resets", 2, 1, transition=("ξ = 0 after ξprev ≠ 0",))) == ("STEP-2",)
    # what the tester just did comes before the edge it led the controller to
    assert a(_mm("MC", "Resets", 2, 1, moment=("a neighbour alive but INIT (not in ξ)",),
                 transition=("ξ = 0 after ξprev ≠ 0",)))[0] == "XI-1"
    # ISOLATED expected: with the idle λ on the wire the ISOLATE was taken (STATE-7) and
    # the state not kept (STATE-9); with another λ too, the ISOLATE was not taken
    isolated = _mm("MC", "State", "ISOLATED", "SAFE", step="states",
                   moment=("ISOLATE in SAFE",))
    assert a(isolated)[0] == "STATE-9"
    assert a(isolated, alongside=[isolated, _mm("MC", "Lambda", 1000, 5000)])[0] == "STATE-7"
    assert a(_mm("MC", "State", "INIT", "SAFE", step="start"))[0] == "STATE-5"
    assert a(_mm("Diag", "ImplausibleGains", 1, 0, step="commands",
                 moment=("ISOLATE", "SET_GAINS out of bounds"))) == ("CMD-5",)
    assert a(_mm("Diag", "RejectedDlc", 1, 0, step="commands",
                 moment=("ISOLATE",))) == ("RX-7",)
    assert a(_mm("Diag", "PriceTimeouts", 0, 1, step="price-only")) == ("TMO-3",)
    # (WMSR-1: the resilient update's, judged on a --resilient run only: ONLY_ON; the
    # controller kinds' steps on a device of that kind only)
    assert a(_mm("MC", "Lambda", 1000, 5000)) == (
        "STEP-10", "STEP-11", "XI-2", "STEP-6", "STEP-7", "STEP-8", "TX-1", "WMSR-1",
        "CTRL-3", "NUM-5")
    step = conf.Step("x", 0, 10, "", ("NUM-1",), moments=(("my note", ("NUM-1",)),))
    assert a(_mm("MC", "Lambda", 1000, 5000, step="x", moment=("my note",)),
             [*conf.STEPS, step]) == ("NUM-1",)


def test_a_difference_where_a_state_rule_decides_names_that_rule() -> None:
    """Expected: a λ that differs where the oracle held it outside RUNNING (not entered at
    that tick) names STATE-10 first, whatever frame the tester had just sent (a sync
    moves no λ); a reset counted at the entry to RUNNING names STATE-6; a State that did
    not follow the oracle's health (SAFE kept where the oracle went RUNNING, or the other
    way) names the definition of health, STATE-2, then the transition's rule; a λ
    difference at that entry still names the entry's rules, not STATE-2, and another
    signal where λ is held its own rules, not STATE-10 (nor does its report mention it)."""
    a = conf.attribute
    held = (conf.oracle.LAMBDA_HELD,)
    assert a(_mm("MC", "Lambda", 1000, 1014, step="price-only", moment=("sync of ER_Command",),
                 transition=held))[0] == "STATE-10"
    # ... of a λ only (the oracle gives the edge to a λ difference alone): INIT gone SAFE
    # is still its own rule's
    assert a(_mm("MC", "State", "INIT", "SAFE", step="start"))[0] == "STATE-5"
    assert a(_mm("MC", "Resets", 0, 1, step="running",
                 transition=("INIT → RUNNING",)))[0] == "STATE-6"
    assert a(_mm("MC", "State", "RUNNING", "SAFE", step="timeouts",
                 transition=("SAFE → RUNNING",)))[:2] == ("STATE-2", "STATE-4")
    assert a(_mm("MC", "State", "SAFE", "RUNNING", step="timeouts",
                 transition=("RUNNING → SAFE",)))[:2] == ("STATE-2", "STATE-3")
    assert a(_mm("MC", "Lambda", 1000, 5000, step="running",
                 transition=("INIT → RUNNING",)))[0] == "STATE-4"
    # the report says where the oracle was: a state change, or an edge (λ held for λ only)
    why = [r.detail for r in conf.verdict(conf.Outcome(ticks=200, mismatches=[
        _mm("Sync", "frames", "no sync", "a sync", step="start")]))]
    assert "the oracle" not in why[0], why[0]
    why = [r.detail for r in conf.verdict(conf.Outcome(ticks=200, mismatches=[
        _mm("MC", "Lambda", 1000, 1014, step="price-only", transition=held)]))]
    assert "the oracle at λ held outside RUNNING" in why[0], why[0]
    why = [r.detail for r in conf.verdict(conf.Outcome(ticks=200, mismatches=[
        _mm("MC", "State", "RUNNING", "SAFE", transition=("SAFE → RUNNING",))]))]
    assert "the oracle going SAFE → RUNNING" in why[0], why[0]
    # a command's own rule still comes first where the tester just sent one
    assert a(_mm("MC", "State", "INIT", "RUNNING", step="states",
                 moment=("RECONNECT, the price stale",),
                 transition=("ISOLATED → INIT",)))[0] == "STATE-8"


def test_the_oracle_gives_lambda_held_to_a_lambda_difference_only() -> None:
    """Expected: a device that goes SAFE from INIT (the oracle holds λ there: the edge
    LAMBDA_HELD) fails its own rule first, STATE-5, not STATE-10: the oracle marks only a
    λ difference with the edge, so neither the attribution nor the report gives it to a
    State."""
    import conformance_faults as cf

    s = cf.score(cf.BY_NAME["init_goes_safe"])
    assert s.failed[:1] == ["STATE-5"], s.failed
    assert "λ held" not in s.first_mismatch, s.first_mismatch


def test_a_device_that_does_not_act_on_a_command_is_named_by_that_command() -> None:
    """Expected: a device that takes SET_GAINS only in RUNNING (the states step sends one
    while it is ISOLATED) is explained by not acting on that one command: CMD-5 alone,
    the report saying which command it ignored."""
    cfg, ring, planned = _setup(1, 3)

    class GainsOnlyRunning(AgentRuntime):
        def on_frame(self, msg: can.Message, t: float) -> None:
            kept = self.ctrl, self.cstate
            super().on_frame(msg, t)
            if (msg.arbitration_id == ER_COMMAND_ID and self.state != State.RUNNING
                    and self.ctrl is not kept[0]):  # a SET_GAINS taken: undone
                self.ctrl, self.cstate = kept

    def gains_only_running(rt: AgentRuntime) -> None:
        rt.__class__ = GainsOnlyRunning

    frames = conf.simulate(cfg, ring(), planned, gains_only_running)
    outcome, results = _judge(cfg, ring, frames)
    failed = [r.must for r in results if not r.passed]
    assert failed == ["CMD-5"], failed
    assert "does not act on the tester's command 'SET_GAINS outside RUNNING" in (
        results[0].detail), results[0].detail


def test_the_verdict_names_the_first_divergence_first_and_one_cause_per_episode() -> None:
    """Expected: the FAIL lines in the order of the evidence, not the spec's; the
    differences that follow a divergence (its episode) fail nothing more; the first FAIL
    line names the step, the tick, the signal, both values and the requirement; a check
    that went to the end fails no requirement as "not exercised"."""
    first = _mm("MC", "Lambda", 1000, 5000, tick=603, step="commands",
                moment=("SET_GAINS in bounds",))
    follow = [_mm("MC", "Lambda", 1000 + k, 5000, tick=603 + k, step="commands",
                  follows=603) for k in range(1, 30)]
    later = _mm("Diag", "RejectedDlc", 1, 0, tick=700, step="commands")
    outcome = conf.Outcome(ticks=900, mismatches=[first, *follow, later],
                           steps_seen={s.name for s in conf.STEPS})
    results = conf.verdict(outcome)
    failed = [r for r in results if not r.passed]
    assert [r.must for r in failed] == ["CMD-5", "CMD-2", "RX-7"], failed
    detail = failed[0].detail
    for part in ("step commands", "tick 603", "SET_GAINS in bounds", "MC.Lambda = 5000",
                 "expected 1000", "CMD-5", "29 more differences"):
        assert part in detail, (part, detail)
    assert all(r.passed for r in results[3:])


def test_junit_has_one_case_per_requirement_and_the_failures(tmp_path: Path) -> None:
    results = [conf.Result("STEP-1", True, "steps control"),
               conf.Result("BAND-2", False, "the DUT behaves as if ...")]
    conf.junit(results, tmp_path / "j.xml", "conformance case1 agent_3")
    suite = ET.parse(tmp_path / "j.xml").getroot().find("testsuite")
    assert suite is not None
    assert suite.get("tests") == "2" and suite.get("failures") == "1"
    cases = {c.get("name"): c for c in suite.iter("testcase")}
    assert cases["STEP-1"].find("failure") is None
    failure = cases["BAND-2"].find("failure")
    assert failure is not None and "behaves as if" in (failure.text or "")


@pytest.mark.parametrize("argv,message", [
    (["--dut", "9"], "--dut: expected an agent number in 1..4, but got '9'"),
    (["--dut", "3", "--interface", "virtual"], "--interface: expected a bus that connects "
     "processes"),
    (["--dut", "3", "--case", "99"], "expected a case number"),
])
def test_bad_input_is_refused(argv: list[str], message: str, tmp_path: Path,
                              capsys: pytest.CaptureFixture[str]) -> None:
    base = ["conformance", "--case", "1", "--out", str(tmp_path)]
    assert main(base + argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: error: ") and message in err


def test_no_device_is_a_failure_naming_the_frame(udp_port: int, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["conformance", "--case", "1", "--dut", "2", "--wait", "1", "--out",
                 str(tmp_path), "--bus-config", f'{{"port": {udp_port}}}']) == 1
    out, err = capsys.readouterr()
    assert "FAIL: no 0x302 frame of the device under test in 1 s" in err
    # the device's command: real-time as `up` runs its nodes (busrun.RT_PRIORITY) ...
    (hint,) = [m.group(1) for m in map(DEVICE_HINT.search, out.splitlines()) if m]
    assert hint.startswith("bess-ded agent --config ") and hint.endswith("--rt-priority 10")
    # ... and the same device as firmware_c's node program takes it (its own bus flags)
    (c_hint,) = [m.group(1) for m in map(C_DEVICE_HINT.search, out.splitlines()) if m]
    assert c_hint.startswith("bessded-agent --config ") and c_hint.endswith("--rt-priority 10")
    assert "--interface udp_multicast --channel ff15:" in c_hint
    assert f"--port {udp_port} " in c_hint and "--bus-config" not in c_hint


def test_the_device_command_has_the_testers_rt_priority(udp_port: int, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    """... or at the tester's own --rt-priority N."""
    assert main(["conformance", "--case", "1", "--dut", "2", "--wait", "0.2", "--out",
                 str(tmp_path), "--bus-config", f'{{"port": {udp_port}}}',
                 "--rt-priority", "30"]) == 1
    (hint,) = [m.group(1) for m in map(DEVICE_HINT.search, capsys.readouterr().out
                                       .splitlines()) if m]
    assert hint.endswith("--rt-priority 30"), hint


def test_the_requirement_list_shipped_with_sim_is_the_specs() -> None:
    """`bess-ded conformance` reads the requirement IDs from package data
    (sim/conformance/spec_requirements.txt: docs/ is not installed); it must be
    docs/firmware-spec.md's list, in order (regenerate: python tools/gen_spec_ids.py)."""
    spec = Path(__file__).resolve().parents[1] / "docs" / "firmware-spec.md"
    ids = list(dict.fromkeys(re.findall(r"^- \*\*([A-Z]+-\d+)\*\*", spec.read_text(), re.M)))
    assert list(conf.spec_requirements()) == ids, "stale: run python tools/gen_spec_ids.py"
    assert conf.REQUIREMENTS_FILE.parent == Path(conf.__file__).parent  # package data


@pytest.mark.realtime
def test_firmware_py_agent_process_passes_on_udp_multicast(tmp_path: Path) -> None:
    """Expected (any load): exit 0, every requirement PASS, JUnit without failures; on
    CAN FD (`--fd`: the device is started with --fd, every frame on the bus, the
    tester's and the device's, is FD with the bit-rate switch). The classic bus runs in
    tools/wheel-check's conformance and in the next test."""
    code, log = run_conformance(tmp_path, FIRMWARE_PY, ["--fd"])
    assert_passed(code, log)
    assert "FAIL" not in log  # nowhere in the output, as before the helper
    assert "CAN FD frames" in log and " --fd " in log
    frames = list(can.LogReader(str(tmp_path / "cf" / "conformance.log")))
    assert frames and all(f.is_fd and f.bitrate_switch for f in frames)
    suite = ET.parse(tmp_path / "junit.xml").getroot().find("testsuite")
    assert suite is not None and suite.get("failures") == "0"
    # case 1's agent is a reset device (no dwell) and runs with a key file: of the
    # requirements exercised on some runs only, the PI family's and λ tags' (AUTH-34)
    # are in its verdict
    _, cfg = conf.written_config(agent_configs_from_scenario(load_case(1))[2])
    on = conf.exercised_on(cfg, lambda_tags=True, insecure=False)
    assert on == {"reset", "pi family", "lambda tags"}
    judged = {m for s in conf.STEPS for m in s.musts if conf.ONLY_ON.get(m, "") in on | {""}}
    assert int(suite.get("tests") or 0) == len(judged)


@pytest.mark.realtime
@pytest.mark.long  # CI's real-time step only (beside stress-ng), not the README suite too
def test_firmware_c_node_program_passes_on_udp_multicast(tmp_path: Path) -> None:
    """Expected (any load): firmware_c's node program, started from the command line the
    tool prints for it, passes every requirement on the classic udp_multicast bus."""
    code, log = run_conformance(tmp_path, [str(node_program())], hint=C_DEVICE_HINT)
    assert_passed(code, log)
    assert "FAIL" not in log  # nowhere in the output, as before the helper


@pytest.mark.realtime
@pytest.mark.long  # CI's real-time step only (beside stress-ng), not the README suite too
def test_firmware_c_node_program_passes_a_signed_price_run_on_udp_multicast(
        tmp_path: Path) -> None:
    """Expected (any load): with --signed-price (the device's key file holds the router's
    public key, the tester signs every price with the router's and plays a key holder's
    refused ones) firmware_c's node program passes every requirement, AUTH-31..33 among
    them."""
    code, log = run_conformance(tmp_path, [str(node_program())], ["--signed-price"],
                                hint=C_DEVICE_HINT)
    assert_passed(code, log)
    assert all(re.search(rf"^  PASS  {m} ", log, re.M) for m in ("AUTH-31", "AUTH-32",
                                                                  "AUTH-33")), log


@pytest.mark.realtime
@pytest.mark.long  # CI's real-time step only (beside stress-ng), not the README suite too
def test_firmware_py_agent_passes_an_event_triggered_run_on_udp_multicast(
        tmp_path: Path) -> None:
    """Expected (any load): with --event-transmit (the device sends its MC frame on a
    State change, λ beyond the threshold or the heartbeat; the checker tells its ticks
    from the frames it sends together) firmware_py's agent passes every requirement,
    TX-7 and CFG-9 among them."""
    code, log = run_conformance(tmp_path, FIRMWARE_PY, ["--event-transmit"])
    assert_passed(code, log)
    assert all(re.search(rf"^  PASS  {m} ", log, re.M) for m in ("TX-7", "CFG-9")), log


@pytest.mark.realtime
def test_an_agent_whose_band_re_arms_at_the_reset_sample_fails_band_2(tmp_path: Path) -> None:
    """Expected (any load): exit 1, BAND-2 the one failed requirement, named with what
    the device does."""
    code, log = run_conformance(tmp_path, DEVIANT)
    assert code == 1, log
    fails = re.findall(r"^  FAIL  (\S+)", log, re.M)
    assert fails == ["BAND-2"], log
    assert "re-arms at the reset sample" in log


def test_a_quick_run_plays_the_first_steps_and_lists_the_rest_not_run(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`bess-ded conformance --quick` in process: the steps of ``QUICK`` only (start to
    commands, 7.1 of 16.2 s at Ts = 10 ms); firmware_py passes every requirement they
    exercise; those only the later steps exercise are NOT RUN (never passed, JUnit
    skipped), the verdict says it was a quick run, and the exit code is 0."""
    from sim.conformance.bus import report

    sc = load_case(1)
    _, cfg = conf.written_config(agent_configs_from_scenario(sc)[2])
    _, ring, _ = _setup(1, 3)
    planned = conf.plan(cfg, KEYS, sc.prices[0].rho, boot=2, quick=True)
    played = conf.played_steps(planned)
    assert [s.name for s in played] == list(conf.QUICK)
    assert played[-1].end * cfg.controller.ts == pytest.approx(7.1)
    frames = conf.simulate(cfg, ring(), planned, jitter=0.3)
    outcome = conf.check(cfg, ring(), KEYS["agent_3"], frames)
    results = conf.verdict(outcome, played=played)
    assert not outcome.mismatches and outcome.steps_seen == set(conf.QUICK)
    run = [r for r in results if not r.not_run]
    skipped = [r for r in results if r.not_run]
    assert run and all(r.passed for r in run), [r for r in run if not r.passed]
    assert not any(r.passed for r in skipped)
    # (of the requirements some runs exercise only, the PI family's: a reset device on a
    # keyed classic-bus run)
    assert outcome.exercised_on == {"reset", "pi family"}
    judged = {m for m in conf.spec_requirements()
              if conf.ONLY_ON.get(m, "pi family") == "pi family"}
    later = {m for s in conf.STEPS if s.name not in conf.QUICK for m in s.musts
             if m in judged}
    early = {m for s in played for m in s.musts if m in judged}
    assert {r.must for r in skipped} == later - early  # e.g. the timeouts' and CFG-6
    assert {"TMO-1", "CFG-6", "AUTH-18"} <= {r.must for r in skipped}
    assert {r.must for r in results} == later | early
    assert "not run: a quick run (--quick)" in skipped[0].detail
    code = report(outcome, results, tmp_path, tmp_path / "j.xml", "quick")
    out = capsys.readouterr().out
    assert code == 0
    assert f"bess-ded conformance: PASS (a quick run): {len(run)} of {len(run)}" in out
    assert f"{len(skipped)} not run (--quick)" in out and "  NOT RUN  TMO-1" in out
    # what only another run judges (ONLY_ON), with what that run is: never "passed" here
    assert "  not judged on this run: PRICE-5 (with --price-persist 1)" in out
    assert "  not judged on this run: CTRL-2, DWELL-1, DWELL-2 (on a dwell device)" in out
    other = json.loads((tmp_path / "conformance.json").read_text())["judged_on_other_runs"]
    assert other == conf.other_runs(outcome) and other["with --insecure"] == [
        "AUTH-1", "AUTH-20"]
    assert not {m for musts in other.values() for m in musts} & {r.must for r in results}
    suite = ET.parse(tmp_path / "j.xml").getroot().find("testsuite")
    assert suite is not None and suite.get("failures") == "0"
    assert suite.get("skipped") == str(len(skipped))
    # a failure in a quick run is a failure: the not-run ones do not hide it
    failing = conf.Outcome(ticks=outcome.ticks, steps_seen=outcome.steps_seen, mismatches=[
        _mm("MC", "Lambda", 1000, 5000, tick=603, step="commands",
            moment=("SET_GAINS in bounds",))])
    assert report(failing, conf.verdict(failing, played=played), tmp_path, None, "q") == 1
