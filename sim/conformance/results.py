"""From an outcome to results per requirement (``verdict``), their explanation and
JUnit XML."""

from __future__ import annotations

import functools
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable, Sequence
from copy import copy
from dataclasses import dataclass, replace
from pathlib import Path

import can

from firmware_py.config import AgentConfig
from firmware_py.frames import FrameCodec
from firmware_py.runtime import AgentRuntime
from firmware_py.secoc import Keyring
from sim.conformance.mutants import MUTANTS, ignoring, misreads
from sim.conformance.oracle import (
    LAMBDA_HELD,
    MOMENT_TICKS,
    SIGNAL_MUSTS,
    WMSR_TIE,
    Frame,
    Mismatch,
    Outcome,
    check,
)
from sim.conformance.schedule import ON_WHAT, ONLY_ON, STEPS, Step

# docs/firmware-spec.md's requirement IDs in order, shipped as package data (docs/ is not
# installed); tools/gen_spec_ids.py writes it, a test checks it against the spec
REQUIREMENTS_FILE = Path(__file__).resolve().parent / "spec_requirements.txt"


@dataclass(frozen=True)
class Result:
    """The verdict on one requirement (``must``): passed or not, and why."""

    must: str
    passed: bool
    detail: str
    # not run: a --quick run does not play the steps that exercise it (never passed)
    not_run: bool = False

    @property
    def failed(self) -> bool:
        """Failed (not passed, and run)."""
        return not self.passed and not self.not_run


@functools.cache
def spec_requirements() -> tuple[str, ...]:
    """Every requirement ID of docs/firmware-spec.md, in order (the packaged list)."""
    lines = REQUIREMENTS_FILE.read_text(encoding="utf-8").splitlines()
    return tuple(line for line in lines if line and not line.startswith("#"))


# What the schedule's noted frames (``Frame.note``, tester side) exercise: a difference
# within MOMENT_TICKS after one names these first (narrowed by its signal's, where they
# meet). A step may declare more (``Step.moments``); a note ending in "…" is a prefix.
MOMENTS: dict[str, tuple[str, ...]] = {
    "an earlier run's price sync (AUTH-21)": ("AUTH-21",),
    "sync of …": ("AUTH-9", "AUTH-21", "AUTH-16"),  # at the DUT's boot floors
    # (AUTH-20 first on an --insecure run: taken there; on another, not exercised)
    "a command before its sync …": ("AUTH-20", "AUTH-11", "AUTH-14"),
    "a price frame 16 freshness …": ("AUTH-12", "AUTH-13", "AUTH-15"),
    "forged MAC": ("RX-8", "AUTH-14", "AUTH-10"),
    "a forged frame after an in-step sync …": ("AUTH-16", "AUTH-14"),
    "replay of a genuine frame": ("AUTH-12", "AUTH-14", "RX-8"),
    "replay of the first price sync": ("AUTH-20", "AUTH-16", "AUTH-17"),
    "frame from another boot": ("AUTH-11", "AUTH-14", "RX-8"),
    "a genuine frame delivered …": ("AUTH-25",),
    "extended ID": ("RX-1",), "unknown ID": ("RX-6",),
    "a flood of unknown IDs …": ("DIAG-2", "RX-6"),
    "the DUT's own MC ID": ("RX-3",),
    "DLC 7": ("RX-7",),
    "an FD frame on a classic bus": ("RX-2",),
    "DLC 7, untrusted_after in a row": ("RX-13", "RX-7"),
    "one more forged status after valid ones …": ("RX-10", "RX-13"),
    "SET_GAINS in bounds": ("CMD-5", "CMD-2"),
    "SET_GAINS out of bounds": ("CMD-5", "DIAG-4"),
    "SET_GAINS one LSB …": ("CMD-5", "DIAG-4"),
    "SET_GAINS at …": ("CMD-5", "CMD-2"),
    "SET_GAINS outside RUNNING …": ("CMD-5",),
    "SET_GAINS whose KTS rounds …": ("CMD-5",),
    "ISOLATE for another agent": ("CMD-1",),
    "ISOLATE": ("STATE-7", "CMD-3", "CMD-2"),
    "ISOLATE while ISOLATED": ("STATE-7", "STATE-9", "CMD-3"),
    "RECONNECT": ("STATE-8", "CMD-4", "STATE-4"),
    "RECONNECT in …": ("STATE-8", "CMD-4"),
    "RECONNECT, …": ("STATE-8", "CMD-4", "STATE-4"),
    "ISOLATE in …": ("STATE-7", "CMD-3"),
    "a neighbour λ step …": ("LAM-1",),
    "a neighbour frame exactly 2.5 periods …": ("LAM-1",),  # the tie of rne (samples)
    "a neighbour λ jump …": ("LIVE-1", "LAM-1"),
    "a neighbour λ square step": ("LIVE-1", "LAM-1"),
    "a neighbour's first frame after …": ("AUTH-13", "AUTH-15", "LIVE-2"),
    "a neighbour alive but INIT …": ("XI-1",),
    "the price's last frame, exactly …": ("STATE-2", "TMO-1"),
    "a price step of exactly …": ("PRICE-3",),
    # PRICE-5 first: judged with --price-persist 1 only, where such a step is taken at once
    "a price step one LSB beyond …": ("PRICE-5", "PRICE-3", "PRICE-4"),
    "a price step back …": ("PRICE-3",),
    "a price step above …": ("PRICE-5", "PRICE-4", "PRICE-3"),
    "a PriceValid = 0 frame …": ("PRICE-1", "PRICE-4"),
    "a status with FaultSoc …": ("RX-11",),
    "PIN with GainK …": ("RX-7", "CMD-7"),
    "PIN for another agent": ("CMD-1", "CMD-7"),
    "PIN …": ("CMD-7", "XI-2"),
}

# The oracle's state changes (``Mismatch.transition``) and what they exercise
TRANSITIONS: dict[str, tuple[str, ...]] = {
    "INIT → RUNNING": ("STATE-4", "STATE-6"),
    "SAFE → RUNNING": ("STATE-4", "STATE-6"),
    "RUNNING → SAFE": ("STATE-3", "STATE-6", "SP-3"),
    "RUNNING → ISOLATED": ("STATE-7",),
    "ISOLATED → INIT": ("STATE-8",),
}

# The oracle's state changes that health decides (STATE-2): a device whose State differs
# there judged the inputs otherwise, which the definition of health names first
HEALTH_DECIDED = {"INIT → RUNNING", "SAFE → RUNNING", "RUNNING → SAFE"}

# A state the DUT reports instead of the oracle's: the rule that decides between them
STATE_RULES: dict[tuple[str, str], tuple[str, ...]] = {
    ("INIT", "SAFE"): ("STATE-5",), ("INIT", "RUNNING"): ("STATE-4", "STATE-2"),
    ("RUNNING", "INIT"): ("STATE-4", "STATE-2"),
    ("SAFE", "RUNNING"): ("STATE-3", "TMO-2", "STATE-2"),
    ("RUNNING", "SAFE"): ("STATE-3", "TMO-2", "STATE-2"), ("SAFE", "INIT"): ("STATE-4",),
    ("ISOLATED", "SAFE"): ("STATE-9",), ("ISOLATED", "INIT"): ("STATE-9", "STATE-8"),
    ("ISOLATED", "RUNNING"): ("STATE-9", "STATE-8"),
}

# the signal that shows a tick's cause first, when several differ in it
_PRIMARY = ("Sync.frames", "frames of the tick.", "MC.State", "MC.Resets", "MC.Lambda",
            "Setpoint.Enable", "Setpoint.PowerSetpoint")


def _primary(mm: Mismatch) -> int:
    key = f"{mm.message}.{mm.signal}"
    return _PRIMARY.index(key) if key in _PRIMARY else len(_PRIMARY)


def _moment_musts(note: str, steps: Sequence[Step]) -> tuple[str, ...]:
    table = dict(MOMENTS)
    for s in steps:
        table.update(dict(s.moments))
    if note in table:
        return table[note]
    return next((v for k, v in table.items() if k.endswith("…") and note.startswith(k[:-1])),
                ())


def _ordered(first: Sequence[str], second: Sequence[str]) -> tuple[str, ...]:
    return tuple(dict.fromkeys((*first, *second)))


def attribute(mm: Mismatch, steps: Sequence[Step] = STEPS,
              alongside: Sequence[Mismatch] = ()) -> tuple[str, ...]:
    """The requirements one difference names, the likeliest first: what the schedule was
    exercising at that moment (a noted frame of the tester: a command, a forged MAC, ...;
    else a state change of the oracle), narrowed by the signal where they meet; else the
    signal's own (``SIGNAL_MUSTS``; for a λ or setpoint one LSB off, the rounding rule;
    for a State, the transition rule between the two states), narrowed by the step's."""
    key = f"{mm.message}.{mm.signal}"
    sig = SIGNAL_MUSTS.get(key, ())
    exp, got = mm.raw
    one_lsb = isinstance(exp, int) and isinstance(got, int) and abs(exp - got) == 1
    # one LSB off is a rounding: of λ(0) from the file (NUM-4) before any control step;
    # of the gains a SET_GAINS just gave (CMD-5), or the limits step's (whose ramp to a
    # large |ξ| is there to show a KTS' one Q30 LSB off); else of the wire λ (Q54 → Q24)
    if key == "MC.Lambda" and one_lsb:
        if mm.step in ("start", "price-only"):
            return ("NUM-4", "NUM-8")
        if mm.step == "limits" or any("CMD-5" in _moment_musts(n, steps)
                                      for n in mm.moment):
            return ("CMD-5", "NUM-8")
        return ("STEP-10", "STEP-11", "NUM-8")  # the first two on pc, ft devices only
    if key == "Setpoint.PowerSetpoint" and one_lsb:
        return ("SP-1",)
    # a Diag counter expected at its maximum and below it: it wrapped (DIAG-2)
    if mm.message == "Diag" and exp == DIAG_MAX and isinstance(got, int) and got < exp:
        return _ordered(("DIAG-2",), sig)
    if key == "MC.State":
        sig = _ordered(STATE_RULES.get((str(mm.expected), str(mm.got)), ()), sig)
        # ISOLATED expected, and the idle λ the ISOLATE gives it (STATE-7) is on the
        # wire: the command was taken, the state not kept (STATE-9)
        if str(mm.expected) == "ISOLATED" and not any(
                (o.message, o.signal) == ("MC", "Lambda") for o in alongside):
            return _ordered(("STATE-9",), sig)
    step = next((s for s in steps if s.name == mm.step), None)
    step_musts = step.musts if step else ()
    # what the tester just did first: an edge the controller met can be its consequence
    contexts = [c for c in ([_moment_musts(n, steps) for n in mm.moment]
                            + [EDGES.get(e, ()) for e in mm.transition]
                            + [_transition_musts(w, key) for w in mm.transition]) if c]
    # those the signal can show, of every context, the latest (the most specific) first
    meet = _ordered([m for context in contexts for m in context if m in sig], ())
    if meet:
        return meet
    meet = tuple(m for m in sig if m in step_musts)
    if contexts:
        if mm.message == "Diag" and sig and mm.signal not in _DERIVED:
            return meet or sig  # a counter names its own cause
        return contexts[0]
    if meet:
        return meet
    return sig or step_musts or ("TICK-1",)


def _transition_musts(went: str, key: str) -> tuple[str, ...]:
    """What the oracle's state change ``went`` exercises, for a difference in ``key``."""
    musts = TRANSITIONS.get(went, ())
    return ("STATE-2", *musts) if key == "MC.State" and went in HEALTH_DECIDED else musts


DIAG_MAX = 0xFFFF  # a 16-bit Diag counter's saturation value (DIAG-2)

# Diag values that show the consequence of a classification, not a cause of their own
_DERIVED = {"SafetySender", "SafetyCause", "NeighboursAlive", "State"}

# What the oracle's controller met exactly at the divergent tick (``Mismatch.transition``)
EDGES: dict[str, tuple[str, ...]] = {
    "ξ = 0 after ξprev ≠ 0": ("STEP-2",),
    "|ξ| = BAND": ("BAND-3",),
    "λ beyond the λ limits": ("STEP-12",),
    LAMBDA_HELD: ("STATE-10",),  # the oracle gives it to a λ difference only
    WMSR_TIE: ("WMSR-2",),
}


def verdict(outcome: Outcome, steps: Sequence[Step] = STEPS,
            played: Sequence[Step] | None = None) -> list[Result]:
    """Pass or fail for each requirement the schedule exercises: the failed ones first,
    in the order of the evidence (the first difference's requirements first), then the
    rest in the spec's order. A difference fails the requirements ``attribute`` names;
    the differences right after it (an episode: the oracle re-synchronised to the DUT
    after each) are the same cause and fail nothing more. ``played``: the steps a
    --quick run played (None: all); the requirements only the others exercise come
    last, "not run" (``Result.not_run``), neither passed nor failed."""
    if played is not None and len(played) < len(steps):
        results = verdict(outcome, played)
        run = {r.must for r in results}
        skipped = [s.name for s in steps if s not in played]
        for must in sorted({m for s in steps for m in s.musts if _judged(m, outcome)} - run,
                           key=_must_order):
            where = ", ".join(s.name for s in steps if must in s.musts)
            results.append(Result(must, False, f"not run: a quick run (--quick) does not "
                                  f"play step {where} (skipped: {', '.join(skipped)})",
                                  not_run=True))
        return results
    exercised: dict[str, list[str]] = {}
    for s in steps:
        for m in s.musts:
            if _judged(m, outcome):
                exercised.setdefault(m, []).append(s.name)
    # (time, order, requirements, why)
    evidence: list[tuple[float, int, tuple[str, ...], str]] = []
    by_tick: dict[int, list[Mismatch]] = {}
    for mm in outcome.mismatches:
        by_tick.setdefault(mm.tick, []).append(mm)
    episodes: dict[int, tuple[Mismatch, int, int]] = {}  # first tick → (cause, n, last)
    for tick, mms in by_tick.items():
        if mms[0].follows is not None and mms[0].follows in episodes:
            cause, n, _ = episodes[mms[0].follows]
            episodes[mms[0].follows] = (cause, n + len(mms), tick)
            continue
        episodes[tick] = (min(mms, key=_primary), len(mms), tick)
    for n_ep, (cause, n, last) in enumerate(episodes.values()):
        musts = attribute(cause, steps, by_tick[cause.tick])
        why = _first_divergence(cause, musts, n, last)
        evidence.append((cause.t, n_ep, musts, why))
    for err, t in zip(outcome.auth_errors,
                      [*outcome.auth_times, *[math.inf] * len(outcome.auth_errors)],
                      strict=False):
        evidence.append((t, len(evidence), ("AUTH-4", "AUTH-6", "AUTH-7", "AUTH-8"), err))
    if outcome.format_errors:  # GEN-1: one report for every frame in the wrong format
        t, first = outcome.format_errors[0]
        n = len(outcome.format_errors)
        evidence.append((t, len(evidence), ("GEN-1",),
                         f"{first}" + (f" ({n - 1} more frames in the wrong format)"
                                       if n > 1 else "")))
    evidence.sort(key=lambda e: (e[0], e[1]))
    failed: dict[str, list[str]] = {}
    for _, _, musts, why in evidence:
        # a requirement this run does not exercise fails on another's difference only if
        # nothing else is named for it (a difference always fails something)
        for must in [m for m in musts if _judged(m, outcome)] or musts:
            failed.setdefault(must, []).append(why)
    if outcome.explained_by:  # a known deviation explains the DUT: name that one
        first = str(outcome.mismatches[0])
        failed = {must: [f"the DUT behaves as if {what} (first difference: {first})"]
                  for must, what in outcome.explained_by.items()} | {
                 must: why for must, why in failed.items()
                 if must.startswith("AUTH-") or must == "GEN-1"}
    results = [Result(must, False, why[0]) for must, why in failed.items()]
    for must in sorted(exercised, key=_must_order):
        if must in failed:
            continue
        if not set(exercised[must]) & outcome.steps_seen:
            if outcome.stopped:
                results.append(Result(must, False, f"not checked: {outcome.stopped} "
                                      f"(before step {exercised[must][0]})"))
            else:
                results.append(Result(must, False, "not exercised: the device's frames "
                                      "ended before step " + exercised[must][0]))
        else:
            results.append(Result(must, True, "steps " + ", ".join(exercised[must])))
    return results


def other_runs(outcome: Outcome) -> dict[str, list[str]]:
    """The requirements of ``ONLY_ON`` that ``outcome``'s run does not exercise, by what a
    run must be to judge them (``ON_WHAT``): what else a device has to be run on."""
    other: dict[str, list[str]] = {}
    for must in sorted(ONLY_ON, key=_must_order):
        if not _judged(must, outcome):
            other.setdefault(ON_WHAT[ONLY_ON[must]], []).append(must)
    return other


def _judged(must: str, outcome: Outcome) -> bool:
    """Whether ``outcome``'s run exercises ``must``: always, or under a condition of
    ``ONLY_ON`` the run meets (a dwell device, λ tags, --insecure, --resilient F)."""
    return must not in ONLY_ON or ONLY_ON[must] in outcome.exercised_on


def _first_divergence(mm: Mismatch, musts: Sequence[str], n: int, last: int) -> str:
    """The report of one divergence: where, what, the requirement under test there."""
    at = f"step {mm.step}, the device's tick {mm.tick} (t = {mm.t:.3f} s)"
    if mm.moment:
        at += f", after the tester's {mm.moment[0]!r}"
    elif mm.transition:  # the oracle's state change ("A → B") or the edge it met
        went = mm.transition[0]
        at += f", the oracle going {went}" if "→" in went else f", the oracle at {went}"
    what = (f"{mm.message}.{mm.signal} = {mm.got!r}, expected {mm.expected!r}"
            if mm.signal else f"{mm.message}: {mm.got!r}, expected {mm.expected!r}")
    more = (f"; {n - 1} more difference{'s' if n > 2 else ''} to tick {last} (the oracle "
            f"re-synchronised to the device after each)" if n > 1 else "")
    return f"first divergence at {at}: {what}; under test there: {', '.join(musts)}{more}"


def _must_order(must: str) -> tuple[int, int]:
    order = spec_requirements()
    prefix, n = must.rsplit("-", 1)
    return (order.index(must) if must in order else len(order), int(n))


def explain(cfg: AgentConfig, keyring: Keyring, dut_key: bytes, frames: Sequence[Frame],
            outcome: Outcome, codec: FrameCodec | None = None,
            config_text: str | None = None) -> None:
    """Name the requirement when a known deviation (``MUTANTS``) or a known misreading
    of the configuration (``misreads``: ``cfg`` is the reference parser's reading of
    the DUT's file, ``config_text``) explains the DUT better than the spec: with it
    modelled, the oracle must match the DUT at every tick (a deviation that only
    matches the first ticks for the fault explains nothing, nor one that meets every
    divergence but differs from the DUT where the DUT kept to the spec)."""
    if not outcome.mismatches:
        return
    first = outcome.mismatches[0].tick
    inputs = [f for f in frames if f.sent]  # the tester's frames
    candidates: list[tuple[str, str, AgentConfig, Callable[[AgentRuntime], None] | None]]
    candidates = [(must, what, cfg, deviation) for must, (what, deviation)
                  in MUTANTS.items()]
    alts = misreads(cfg, config_text)
    if alts:  # only those whose own frames first differ where the DUT's did (a replay)
        at = _first_differences(cfg, [a for _, _, a in alts], keyring, frames, inputs, codec)
        t_first, ts = outcome.mismatches[0].t, cfg.controller.ts
        candidates += [(must, what, alt_cfg, None) for (must, what, alt_cfg), t in
                       zip(alts, at, strict=True)
                       if abs(t - t_first) <= MISREAD_TICKS * ts]
    candidates += [(must, what, cfg, ignoring(msg))
                   for must, what, msg in _commands_before(cfg, inputs, outcome, codec)]
    for must, what, model, deviation in candidates:
        alt = check(model, keyring, dut_key, frames, codec, deviation, max_mismatches=1,
                    filtered_first=outcome.filtered, exact=outcome.exact)
        if alt.mismatches and alt.mismatches[0].tick <= first:
            continue
        # check the rest of the schedule with that deviation modelled
        rest = check(model, keyring, dut_key, frames, codec, deviation,
                     filtered_first=alt.filtered, exact=outcome.exact)
        # the deviation explains every tick where the spec's oracle diverged, and
        # differs from the device nowhere else (a model that meets the device's first
        # difference but misses a tick where the device kept to the spec is another
        # device: e.g. a default timeout one period short against one exactly at it)
        if rest.mismatches or rest.differing_ticks:
            continue
        outcome.explained_by[must] = what
        outcome.steps_seen, outcome.ticks = rest.steps_seen, rest.ticks
        outcome.mismatches[1:] = [replace(m, follows=None) for m in rest.mismatches]
        outcome.stopped = rest.stopped
        return


def _commands_before(cfg: AgentConfig, inputs: Sequence[Frame], outcome: Outcome,
                     codec: FrameCodec | None) -> list[tuple[str, str, can.Message]]:
    """The tester's (``inputs``) noted commands of the MOMENT_TICKS before the first
    divergence, the latest first: (the requirement its note exercises first, "it does
    not act on …", the frame). A device that ignored one of them is explained by
    ``ignoring`` it."""
    codec = codec or FrameCodec()
    command_id = codec.frame_id("ER_Command")
    if not inputs:
        return []
    first = outcome.mismatches[0]
    since = first.t - MOMENT_TICKS * cfg.controller.ts
    out = []
    for f in reversed(inputs):
        musts = _moment_musts(f.note, STEPS) if f.note else ()
        if (f.msg.arbitration_id == command_id and musts
                and since <= f.t - inputs[0].t < first.t):
            out.append((musts[0], f"it does not act on the tester's command {f.note!r} "
                        f"({f.t - inputs[0].t:.3f} s)", f.msg))
    return out


MISREAD_TICKS = 12
"""A misreading is tried only when its first difference from the file's reading (on a
plain replay of the record) lies this close (ticks) to the DUT's first divergence."""


def _first_differences(cfg: AgentConfig, alts: Sequence[AgentConfig], keyring: Keyring,
                       frames: Sequence[Frame], inputs: Sequence[Frame],
                       codec: FrameCodec | None) -> list[float]:
    """For each configuration of ``alts``: the time (from the tester's first frame, as
    ``Mismatch.t``; inf if never) of the first tick where firmware_py's agent configured
    so sends other frames than configured as ``cfg``, both fed the tester's frames of the
    record (``inputs``) when sent and ticked at the DUT's ticks (one order, no hypotheses:
    a screen for ``explain``; each on a copy of ``keyring``: its start takes a boot)."""
    from firmware_py.frames import diag_name
    from sim.conformance.oracle import dut_ticks, quiet_firmware

    codec = codec or FrameCodec()
    diag_id = codec.frame_id(diag_name(cfg.id))
    first_sent = inputs[0].t if inputs else math.inf
    ticks = dut_ticks(cfg, codec, frames)
    # the Diag pages aligned with the DUT's, as ``check`` does
    align = next((f for f in frames if not f.sent and f.msg.arbitration_id == diag_id
                  and f.t < first_sent), None)
    page = 0
    if align is not None:
        page = int(codec.decode(align.msg).raw["Page"])
        ticks = [t for t in ticks if t >= max((u for u in ticks if u <= align.t),
                                               default=-math.inf)]

    def replay(model: AgentConfig) -> list[tuple[object, ...]]:
        rt = AgentRuntime(model, codec, keys=copy(keyring))
        rt.ticks = 10 * page
        out, nxt = [], 0
        with quiet_firmware():
            for t in ticks:
                while nxt < len(inputs) and inputs[nxt].t < t:
                    rt.on_frame(inputs[nxt].msg, inputs[nxt].t)
                    nxt += 1
                out.append(tuple(_plain(codec, m) for m in rt.tick(t)))
        return out

    ref = replay(cfg)
    at = []
    for alt in alts:
        mine = replay(alt)
        at.append(next((t - first_sent for t, a, b in zip(ticks, ref, mine, strict=True)
                        if a != b), math.inf))
    return at


def _plain(codec: FrameCodec, msg: can.Message) -> object:
    """A frame's signals but its MAC and boot (each replay starts a boot of its own)."""
    try:
        raw = codec.decode(msg).raw
    except Exception:  # noqa: BLE001 - an undecodable frame compares as its bytes
        return msg.arbitration_id, bytes(msg.data)
    return msg.arbitration_id, tuple(sorted((k, v) for k, v in raw.items()
                                            if k not in ("Mac", "Boot")
                                            and not re.fullmatch(r"Tag[0-9]+", k)))


def junit(results: Sequence[Result], path: Path, name: str) -> None:
    """JUnit XML: one test case per requirement."""
    suite = ET.Element("testsuite", name=name, tests=str(len(results)),
                       failures=str(sum(r.failed for r in results)),
                       skipped=str(sum(r.not_run for r in results)))
    for r in results:
        case = ET.SubElement(suite, "testcase", classname=f"conformance.{r.must.split('-')[0]}",
                             name=r.must)
        if r.not_run:
            ET.SubElement(case, "skipped", message=r.detail[:200])
        elif not r.passed:
            ET.SubElement(case, "failure", message=r.detail[:200]).text = r.detail
    root = ET.Element("testsuites", name=name)
    root.append(suite)
    tree = ET.ElementTree(root)
    ET.indent(tree)
    path.parent.mkdir(parents=True, exist_ok=True)
    tree.write(path, encoding="utf-8", xml_declaration=True)
