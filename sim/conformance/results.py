"""From an outcome to results per requirement (``verdict``), their explanation and
JUnit XML."""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from firmware_py.config import AgentConfig
from firmware_py.frames import FrameCodec
from firmware_py.secoc import Keyring
from sim.conformance.mutants import MUTANTS
from sim.conformance.oracle import SIGNAL_MUSTS, Frame, Outcome, check
from sim.conformance.schedule import STEPS, Step

# docs/firmware-spec.md's requirement IDs in order, shipped as package data (docs/ is not
# installed); tools/gen_spec_ids.py writes it, a test checks it against the spec
REQUIREMENTS_FILE = Path(__file__).resolve().parent / "spec_requirements.txt"


@dataclass(frozen=True)
class Result:
    """The verdict on one requirement (``must``): passed or not, and why."""

    must: str
    passed: bool
    detail: str


@functools.cache
def spec_requirements() -> tuple[str, ...]:
    """Every requirement ID of docs/firmware-spec.md, in order (the packaged list)."""
    lines = REQUIREMENTS_FILE.read_text(encoding="utf-8").splitlines()
    return tuple(line for line in lines if line and not line.startswith("#"))


def verdict(outcome: Outcome, steps: Sequence[Step] = STEPS) -> list[Result]:
    """Pass or fail for each requirement the schedule exercises."""
    exercised: dict[str, list[str]] = {}
    for s in steps:
        for m in s.musts:
            exercised.setdefault(m, []).append(s.name)
    failed: dict[str, list[str]] = {}
    for mm in outcome.mismatches:
        musts = set(SIGNAL_MUSTS.get(f"{mm.message}.{mm.signal}", ()))
        step = next((s for s in steps if s.name == mm.step), None)
        if step is not None and musts & set(step.musts):
            musts &= set(step.musts)
        if not musts:
            musts = set(step.musts) if step else {"TICK-1"}
        for must in musts:
            failed.setdefault(must, []).append(str(mm))
    for err in outcome.auth_errors:
        for must in ("AUTH-4", "AUTH-6", "AUTH-7", "AUTH-8"):
            failed.setdefault(must, []).append(err)
    if outcome.explained_by:  # a known deviation explains the DUT: name that one
        first = str(outcome.mismatches[0])
        failed = {must: [f"the DUT behaves as if {what} (first difference: {first})"]
                  for must, what in outcome.explained_by.items()} | {
                 must: why for must, why in failed.items() if must.startswith("AUTH-")}
    results = []
    for must in sorted(exercised, key=_must_order):
        if must in failed:
            results.append(Result(must, False, failed[must][0]))
        elif not set(exercised[must]) & outcome.steps_seen:
            results.append(Result(must, False, "not exercised: the run ended before step "
                                  + exercised[must][0]))
        else:
            results.append(Result(must, True, "steps " + ", ".join(exercised[must])))
    for must in sorted(set(failed) - set(exercised), key=_must_order):
        results.append(Result(must, False, failed[must][0]))
    return results


def _must_order(must: str) -> tuple[int, int]:
    order = spec_requirements()
    prefix, n = must.rsplit("-", 1)
    return (order.index(must) if must in order else len(order), int(n))


def explain(cfg: AgentConfig, keyring: Keyring, dut_key: bytes, frames: Sequence[Frame],
            outcome: Outcome, codec: FrameCodec | None = None) -> None:
    """Name the requirement when a known deviation explains the DUT better than the spec."""
    if not outcome.mismatches:
        return
    first = outcome.mismatches[0].tick
    for must, (what, deviation) in MUTANTS.items():
        alt = check(cfg, keyring, dut_key, frames, codec, deviation, max_mismatches=1,
                    filtered_first=outcome.filtered)
        if not alt.mismatches or alt.mismatches[0].tick > first + 50:
            # check the rest of the schedule with that deviation modelled
            rest = check(cfg, keyring, dut_key, frames, codec, deviation,
                         filtered_first=alt.filtered)
            outcome.explained_by[must] = what
            outcome.steps_seen, outcome.ticks = rest.steps_seen, rest.ticks
            outcome.mismatches[1:] = rest.mismatches
            return


def junit(results: Sequence[Result], path: Path, name: str) -> None:
    """JUnit XML: one test case per requirement."""
    suite = ET.Element("testsuite", name=name, tests=str(len(results)),
                       failures=str(sum(not r.passed for r in results)))
    for r in results:
        case = ET.SubElement(suite, "testcase", classname=f"conformance.{r.must.split('-')[0]}",
                             name=r.must)
        if not r.passed:
            ET.SubElement(case, "failure", message=r.detail[:200]).text = r.detail
    root = ET.Element("testsuites", name=name)
    root.append(suite)
    tree = ET.ElementTree(root)
    ET.indent(tree)
    path.parent.mkdir(parents=True, exist_ok=True)
    tree.write(path, encoding="utf-8", xml_declaration=True)
