"""`bess-ded conformance` on the runs that exercise more requirements (``ONLY_ON``):
with --insecure (AUTH-1, AUTH-20), with the resilient update on (--resilient F:
WMSR-1, and WMSR-2 on a device of more than F neighbours), on a pc or an ft device
(case 2's variants: STEP-10; STEP-11, CTRL-3, NUM-5), with --price-persist 1 (PRICE-5),
with --signed-price (AUTH-31..33), with --event-transmit (TX-7, CFG-9).
In process, on a simulated clock with late ticks and frames, as
tests/test_conformance.py."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import can
import pytest
from conformance_faults import (
    BY_NAME,
    no_trimming,
    schedule_setup,
    schedule_text,
    score,
    ties_light_first,
)

from firmware_py import controllers, pricesig
from firmware_py.config import Transmit
from firmware_py.frames import FrameCodec
from firmware_py.runtime import AgentRuntime
from sim import conformance as conf
from sim.cli import main


def test_an_insecure_run_judges_the_public_keys_and_their_replay_rule() -> None:
    """Expected: with --insecure (the tester and the device on the public demo keys, every
    sender at boot 1) firmware_py passes every requirement, AUTH-1 (the keys derived from
    the master) and AUTH-20 among them; a device that keeps a keyed node's replay rule in
    insecure mode (a replayed sync refused, not taken as a restarted sender's) fails."""
    cfg, ring, planned = schedule_setup(1, 3, run="insecure")

    def judged(deviation: Callable[[AgentRuntime], None] | None
               ) -> tuple[conf.Outcome, list[conf.Result]]:
        frames = conf.simulate(cfg, ring(), planned, deviation, jitter=0.3, seed=1)
        outcome = conf.check(cfg, ring(), ring().key, frames)
        return outcome, conf.verdict(outcome)

    outcome, results = judged(None)
    # the conditions this run meets
    assert outcome.exercised_on == {"insecure", "reset", "pi family"}
    assert not outcome.mismatches and not outcome.auth_errors
    assert all(r.passed for r in results), [r for r in results if not r.passed]
    assert {"AUTH-1", "AUTH-20"} <= {r.must for r in results}

    def keyed_rules(rt: AgentRuntime) -> None:
        rt.io.keys.insecure = False  # the keys stay the public ones

    outcome, results = judged(keyed_rules)
    failed = [r.must for r in results if r.failed]
    assert outcome.mismatches and "AUTH-16" in failed, failed


@pytest.mark.parametrize("case,dut,deviation,failed", [
    (7, 5, None, None),               # two neighbours, F = 1: WMSR-1 and WMSR-2
    (7, 5, ties_light_first, "WMSR-2"),
    (1, 3, no_trimming, "WMSR-1"),   # one neighbour: WMSR-1 only
])
def test_a_resilient_device_is_judged_on_its_trimming(
        case: int, dut: int, deviation: Callable[[AgentRuntime], None] | None,
        failed: str | None) -> None:
    """Expected: with resilient_f = 1 in the configuration the tester writes (the
    neighbours' weights each its own, so that WMSR-2's order shows), firmware_py passes
    every requirement, WMSR-1 and WMSR-2 among them where more than F neighbours meet at
    lambda_min; a device that trims equal λ the smaller weight first fails, named WMSR-2
    first (the oracle's edge: a trim through a tie), and one that does not trim fails,
    named WMSR-1 first (a known misreading: resilient_f's default taken)."""
    cfg, ring, planned = schedule_setup(case, dut, run="resilient")  # resilient_f = 1
    text = schedule_text(case, dut, run="resilient")
    weights = [n.weight for n in cfg.neighbours]
    assert len(set(weights)) == len(weights)
    original = controllers.resilient_trim
    frames = conf.simulate(cfg, ring(), planned, deviation, jitter=0.3, seed=dut)
    assert controllers.resilient_trim is original
    key = ring().key
    outcome = conf.check(cfg, ring(), key, frames)
    conf.explain(cfg, ring(), key, frames, outcome, config_text=text)
    results = conf.verdict(outcome)
    judged = {r.must for r in results}
    own = {"WMSR-1", "WMSR-2"} if len(weights) > 1 else {"WMSR-1"}
    assert judged & {"WMSR-1", "WMSR-2"} == own
    if failed is None:
        assert not outcome.mismatches and not outcome.auth_errors
        assert all(r.passed for r in results), [r for r in results if not r.passed]
        return
    bad = [r.must for r in results if r.failed]
    assert bad and bad[0] == failed and outcome.mismatches[0].signal == "Lambda", bad
    if failed == "WMSR-1":  # the whole ξ differs from the first tick: explained
        assert "does not trim" in results[0].detail, results[0]
    else:  # the oracle met a trim through equal λ_j of unequal weights there
        assert conf.WMSR_TIE in outcome.mismatches[0].transition, outcome.mismatches[0]


def test_the_resilient_option_writes_f_and_checks_its_range(
        tmp_path: Path, udp_port: int, capsys: pytest.CaptureFixture[str]) -> None:
    """`--resilient F` is written into the device's configuration; out of 1..31 it is bad
    input (exit 2, expected and given named)."""
    assert main(["conformance", "--case", "1", "--dut", "3", "--resilient", "0"]) == 2
    assert "expected an integer in 1..31, but got 0" in capsys.readouterr().err
    assert main(["conformance", "--case", "7", "--dut", "5", "--resilient", "2", "--wait",
                 "0.2", "--out", str(tmp_path), "--bus-config",
                 f'{{"port": {udp_port}}}']) == 1
    assert "resilient_f = 2" in (tmp_path / "agents" / "agent_5.toml").read_text()


def test_a_difference_named_only_by_another_runs_requirements_still_fails() -> None:
    """Expected: on a run that does not exercise WMSR-2 (no --resilient), a λ difference at
    the oracle's W-MSR tie edge, whose only name is WMSR-2, still fails the device (named
    WMSR-2 rather than nothing); on a resilient-ties run the same difference fails WMSR-2
    and a requirement of another run (AUTH-20) is never listed."""
    mm = conf.Mismatch(1.0, 100, "running", "MC", "Lambda", 7549742, 7549740,
                       transition=(conf.WMSR_TIE,), raw=(7549742, 7549740))
    assert conf.attribute(mm) == ("WMSR-2",)
    for on in (frozenset(), frozenset({"resilient", "resilient ties"})):
        results = conf.verdict(conf.Outcome(mismatches=[mm], exercised_on=on,
                                            steps_seen={s.name for s in conf.STEPS}))
        failed = [r.must for r in results if r.failed]
        assert failed == ["WMSR-2"], (on, failed)
        assert "AUTH-20" not in {r.must for r in results}


def test_a_moment_of_every_run_names_no_requirement_of_another_run_first() -> None:
    """Expected: the moments of the schedule that every run plays name requirements that
    every run exercises first (e.g. the extremes step's saturation: NUM-3, XI-3, not
    WMSR-2, which a run without --resilient does not exercise: a ξ that wraps would be
    named by it alone)."""
    mm = conf.Mismatch(14.8, 1480, "extremes", "MC", "Lambda", -66990676, -1574933,
                       moment=("every neighbour at lambda_min in ξ (ξ saturates)",),
                       raw=(-66990676, -1574933))
    assert conf.attribute(mm)[:2] == ("NUM-3", "XI-3")
    # and no moment every run plays is named by another run's requirements alone (the
    # band step's dwell moments are played on a dwell device only)
    moments = [*conf.MOMENTS.items(), *((n, m) for s in conf.STEPS if s.name != "band"
                                        for n, m in s.moments)]
    # (and the timeouts step's key holder's prices, played with --signed-price only)
    signed_only = {m for m, on in conf.ONLY_ON.items() if on == "signed price"}
    assert all(set(musts) - set(conf.ONLY_ON) for _, musts in moments
               if not set(musts) <= signed_only)


PI_FAMILY = {f"STEP-{n}" for n in range(2, 10)} | {"BAND-1", "BAND-2", "BAND-3"}


@pytest.mark.parametrize("run,fault,own", [
    ("pc", None, {"STEP-10"}),
    ("pc", "pc_step_on_wire_grid", {"STEP-10"}),
    ("ft", None, {"STEP-11", "CTRL-3", "NUM-5"}),
    ("ft", "ft_step_on_wire_grid", {"STEP-11", "CTRL-3", "NUM-5"}),
])
def test_a_pc_or_ft_device_is_judged_on_its_own_step(run: str, fault: str | None,
                                                      own: set[str]) -> None:
    """Expected: on case 2's variants PC and finite-time (`bess-ded conformance --case 2
    --variant PC`), firmware_py passes every requirement, its kind's step among them
    (STEP-10; STEP-11 with fpow's CTRL-3 and NUM-5, a = 3/4 in the file the tester
    writes: two roots and two products), and none of the PI family's step and band is
    judged; a device whose Δλ loses its guard bits fails, named by its kind's step."""
    cfg, ring, planned = schedule_setup(2, 3, run=run)
    assert cfg.controller.kind == run
    assert ("ft_exponent = 0.75" in schedule_text(2, 3, run)) == (run == "ft")
    apply = BY_NAME[fault].apply if fault else None
    frames = conf.simulate(cfg, ring(), planned, apply, jitter=0.3, seed=2)
    outcome = conf.check(cfg, ring(), ring().key, frames)
    results = conf.verdict(outcome)
    judged = {r.must for r in results}
    assert judged & (PI_FAMILY | {"STEP-10", "STEP-11", "CTRL-3", "NUM-5"}) == own
    if fault is None:
        assert not outcome.mismatches and not outcome.auth_errors
        assert all(r.passed for r in results), [r for r in results if not r.passed]
        return
    bad = [r.must for r in results if r.failed]
    assert bad[0] == BY_NAME[fault].requirement, bad


@pytest.mark.parametrize("fault", [None, "persist_one_candidate_first"])
def test_price_persist_one_is_judged_on_a_step_taken_at_once(fault: str | None) -> None:
    """Expected: with --price-persist 1 in the file the tester writes, firmware_py passes
    every requirement, PRICE-5 among them (the content step's persistent price step and
    the limits step's step one LSB beyond the bound taken at their first frame); a
    device that makes a step a candidate first fails, named PRICE-5 first."""
    cfg, ring, planned = schedule_setup(1, 3, run="persist 1")
    assert cfg.price_persist == 1 and "price_persist = 1" in schedule_text(1, 3, "persist 1")
    frames = conf.simulate(cfg, ring(), planned, BY_NAME[fault].apply if fault else None,
                           jitter=0.3, seed=4)
    outcome = conf.check(cfg, ring(), ring().key, frames)
    results = conf.verdict(outcome)
    assert "persist 1" in outcome.exercised_on and "PRICE-5" in {r.must for r in results}
    if fault is None:
        assert not outcome.mismatches and not outcome.auth_errors
        assert all(r.passed for r in results), [r for r in results if not r.passed]
        return
    assert [r.must for r in results if r.failed][0] == "PRICE-5"


@pytest.mark.parametrize("given", ["0", "6", "x"])
def test_price_persist_out_of_range_is_bad_input(given: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Expected: `--price-persist` takes 1..5 (the schedule's price steps fit 5 frames);
    anything else is exit 2 with one line naming the option, what it expects and what
    it got."""
    assert main(["conformance", "--case", "1", "--dut", "3", "--price-persist", given]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("bess-ded: error: --price-persist") and given in err, err
    assert "1..5" in err, err


def test_price_persist_one_is_written_into_the_devices_file(tmp_path: Path,
                                                             udp_port: int) -> None:
    """Expected: `--price-persist 1` writes price_persist = 1 into the device's file (the
    default run 5); with no device on the bus the run fails honestly (exit 1)."""
    assert main(["conformance", "--case", "1", "--dut", "3", "--price-persist", "1",
                 "--wait", "0.2", "--out", str(tmp_path), "--bus-config",
                 f'{{"port": {udp_port}}}']) == 1
    assert "price_persist = 1" in (tmp_path / "agents" / "agent_3.toml").read_text()


SIGNED = ("AUTH-31", "AUTH-32", "AUTH-33")


@pytest.mark.parametrize("fault", [None, "signed_checked_after_freshness",
                                   "signature_page_overwritten"])
def test_a_signed_price_run_judges_the_signatures(fault: str | None) -> None:
    """Expected: with --signed-price (signed_price in the device's file, the router's
    public key in its key file) the tester signs every price it plays and, while the
    price is stale, plays a key holder's prices under the router's node key that no
    conformant device takes (unsigned: another Segment, ρ one LSB off; under a bad, an
    older and two malformed signatures; 8 counts ahead of the router's): firmware_py
    refuses each, stays SAFE, and passes every requirement, AUTH-31..33 among them; a
    device that checks the signed price after the MAC and freshness (the router's own
    next price is then stale), or that lets a repeated page overwrite the first, fails,
    named by the broken requirement first."""
    cfg, ring, planned = schedule_setup(1, 3, run="signed price")
    assert cfg.signed_price and "signed_price = true" in schedule_text(1, 3, "signed price")
    notes = {p.note for p in planned}
    assert {"an unsigned price: the signed ρ under another Segment",
            "a price under a bad signature (another key's)"} <= notes
    frames = conf.simulate(cfg, ring(), planned, BY_NAME[fault].apply if fault else None,
                           jitter=0.3, seed=5)
    outcome = conf.check(cfg, ring(), ring().key, frames)
    results = conf.verdict(outcome)
    assert "signed price" in outcome.exercised_on
    assert set(SIGNED) <= {r.must for r in results}
    if fault is None:
        assert not outcome.mismatches and not outcome.auth_errors
        assert all(r.passed for r in results), [r for r in results if not r.passed]
        return
    assert [r.must for r in results if r.failed][0] == BY_NAME[fault].requirement


def test_an_unsigned_run_does_not_judge_the_signed_price() -> None:
    """Expected: the default run plays no signature and names AUTH-31..33 as judged on
    another run (`--signed-price`), never passed."""
    cfg, _, planned = schedule_setup(1, 3)
    assert not cfg.signed_price
    assert FrameCodec().frame_id(pricesig.MESSAGE) not in {p.msg.arbitration_id
                                                           for p in planned}
    outcome = conf.Outcome(exercised_on=conf.exercised_on(cfg, False, False),
                           steps_seen={s.name for s in conf.STEPS})
    assert not set(SIGNED) & {r.must for r in conf.verdict(outcome)}
    assert tuple(conf.other_runs(outcome)["with --signed-price"]) == SIGNED


def test_the_signed_price_option_writes_the_keys_and_refuses_insecure(
        tmp_path: Path, udp_port: int, capsys: pytest.CaptureFixture[str]) -> None:
    """Expected: `--signed-price` writes signed_price into the device's file and the
    router's public key (only) into its key file; with no device on the bus the run fails
    honestly (exit 1). With --insecure (no router key to sign with) it is bad input."""
    assert main(["conformance", "--case", "1", "--dut", "3", "--signed-price",
                 "--wait", "0.2", "--out", str(tmp_path), "--bus-config",
                 f'{{"port": {udp_port}}}']) == 1
    assert "signed_price = true" in (tmp_path / "agents" / "agent_3.toml").read_text()
    key_file = (tmp_path / "keys" / "agent_3.key").read_text()
    assert "verify_key" in key_file and "sign_key" not in key_file
    capsys.readouterr()
    assert main(["conformance", "--case", "1", "--dut", "3", "--signed-price",
                 "--insecure"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("bess-ded: error: --insecure: expected a key set with the "
                          "router's price key"), err


@pytest.mark.parametrize("fault", [None, "event_state_change_unsent", "cfg_threshold_default"])
def test_an_event_triggered_device_is_judged_on_when_it_sends(fault: str | None) -> None:
    """Expected: with --event-transmit (`[transmit] mode = "event"`, the threshold and the
    heartbeat off their defaults) the DUT's ticks are told from the frames it sends
    together and the silent ticks between by the period; firmware_py, which sends only
    on a State change, λ beyond the threshold or the heartbeat, passes every
    requirement, TX-7 and CFG-9 among them; a device that keeps a State change back
    until the heartbeat fails, named TX-7 first, and one that takes the threshold's
    default (3e-4) fails, named CFG-9 (a known misreading explains it)."""
    if fault is not None:
        s = score(BY_NAME[fault])
        assert s.run == "event" and s.named_first, (s.failed, s.first_mismatch)
        return
    cfg, ring, planned = schedule_setup(1, 3, run="event")
    text = schedule_text(1, 3, "event")
    assert cfg.transmit.event and cfg.transmit.heartbeat == conf.schedule.EVENT_HEARTBEAT
    assert cfg.transmit.threshold != Transmit().threshold and 'mode = "event"' in text
    frames = conf.simulate(cfg, ring(), planned, jitter=0.3, seed=6)
    mc = FrameCodec().frame_id("AGENT_3_MC")
    ticks = round((frames[-1].t - frames[0].t) / cfg.controller.ts)
    assert sum(not x.sent and x.msg.arbitration_id == mc for x in frames) < 0.9 * ticks
    outcome = conf.check(cfg, ring(), ring().key, frames)
    results = conf.verdict(outcome)
    assert "event" in outcome.exercised_on and {"TX-7", "CFG-9"} <= {r.must for r in results}
    assert not outcome.mismatches and not outcome.auth_errors
    assert all(r.passed for r in results), [r for r in results if not r.passed]


def test_the_event_option_writes_the_transmit_table(tmp_path: Path, udp_port: int) -> None:
    """Expected: `--event-transmit` writes `[transmit]` (mode event, the heartbeat below
    the neighbour timeout) into the device's file; with no device the run fails (exit 1)."""
    assert main(["conformance", "--case", "1", "--dut", "3", "--event-transmit",
                 "--wait", "0.2", "--out", str(tmp_path), "--bus-config",
                 f'{{"port": {udp_port}}}']) == 1
    text = (tmp_path / "agents" / "agent_3.toml").read_text()
    assert 'mode = "event"' in text and "heartbeat = 3" in text


def test_a_malformed_frame_of_an_event_triggered_device_is_reported_not_raised() -> None:
    """Expected: MC frames of an event-triggered device cut to 7 bytes (those before the
    schedule, whose last the oracle adopts as the device's memory, and one more at a
    tick where it sent none) are differences of the device, never an exception of the
    checker."""
    cfg, ring, planned = schedule_setup(1, 3, run="event")
    frames = conf.simulate(cfg, ring(), planned, jitter=0.3, seed=7)
    mc, ts = FrameCodec().frame_id("AGENT_3_MC"), cfg.controller.ts
    first_sent = next(f.t for f in frames if f.sent)

    def cut(f: conf.Frame, t: float) -> conf.Frame:
        return replace(f, t=t, msg=can.Message(arbitration_id=mc, is_extended_id=False,
                                               data=bytes(f.msg.data[:7])))
    dut = [n for n, f in enumerate(frames) if not f.sent and f.msg.arbitration_id == mc]
    for n in dut:
        if frames[n].t < first_sent:
            frames[n] = cut(frames[n], frames[n].t)
    # a silent tick in the control step: an MC frame there that the oracle did not send
    gap = next(n for a, n in zip(dut, dut[1:], strict=False)
               if frames[n].t - frames[a].t > 1.5 * ts and frames[a].t > first_sent + 2)
    a = dut[dut.index(gap) - 1]
    frames.insert(a + 1, cut(frames[a], frames[a].t + ts))
    frames.sort(key=lambda f: f.t)
    outcome = conf.check(cfg, ring(), ring().key, frames)
    assert outcome.mismatches and any(r.failed for r in conf.verdict(outcome))
