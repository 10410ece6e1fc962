#!/usr/bin/env python3
"""How good is the conformance schedule: its score on single faults nobody wrote for it.

Plants each fault of tests/conformance_faults.py (one slip against one requirement of
docs/firmware-spec.md) in firmware_py's agent (``--device c``: each fault of
tests/conformance_faults_c.py built into a firmware_c library of its own, the C agent on
it as the device), plays the conformance schedule against it
in process (``sim.conformance.simulate``: no bus, a simulated clock, each tick and
tester frame up to ``--jitter``·Ts late, seeded), judges it as `bess-ded conformance`
does (``check``, ``explain``, ``verdict``) and prints, per fault: whether it was caught
(a requirement failed, or the run had a problem), the requirements failed in the
verdict's order (the report's FAIL lines), and whether the first one named is the
fault's own. Then the score: caught %, named first %, named at all %.

Usage::

    python tools/conformance_score.py                   # case 1, agent 3
    python tools/conformance_score.py --case 1:3 --case 7:5 --json score.json
    python tools/conformance_score.py --only wire_truncates lam_step_ge
    python tools/conformance_score.py --device c --jobs 2   # firmware_c's faults
    python tools/conformance_score.py --timing exact        # the device's clock trusted

Deterministic: the same code gives the same table on any machine (seed 0, jitter 0.3).
The faultless agent is scored first and must pass, or the score means nothing.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import asdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import conformance_faults as cf  # noqa: E402

DEVICES = ("py", "c")


def _set(device: str):  # type: ignore[no-untyped-def]
    """The fault set and its scorer: firmware_py's (``py``) or firmware_c's (``c``)."""
    if device == "c":
        import conformance_faults_c as cfc
        return cfc
    return cf


def _case(text: str) -> tuple[int, int]:
    case, _, dut = text.partition(":")
    try:
        return int(case), int(dut or 3)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected CASE:AGENT (e.g. 1:3), but got "
                                         f"{text!r}") from None


def _job(args: tuple[str, int, int, float, int, str, bool]) -> cf.Score:
    name, case, dut, jitter, seed, device, exact = args
    logging.disable(logging.CRITICAL)  # the faulty agents log what they do
    fs = _set(device)
    return fs.score(fs.BY_NAME[name], case, dut, jitter, seed, exact=exact)


def table(scores: list[cf.Score], case: tuple[int, int] | None = None) -> str:
    """One line per fault: caught, the own requirement first / at all / among those of
    the first difference, then the requirements failed (those failed only as "not
    exercised" counted, not listed); a fault played on another device than ``case``'s
    (another controller kind's) says where."""
    lines = [f"{'fault':26s} {'requirement':11s} {'class':11s} {'caught':6s} {'1st':3s} "
             f"{'any':3s} {'dif':3s} failed (verdict order: by evidence; +N not exercised)"]
    for s in scores:
        shown = [m for m in s.failed if m not in s.unexercised]
        failed = " ".join(shown[:7]) + (f" …{len(shown) - 7}" if len(shown) > 7 else "")
        if s.unexercised:
            failed += f" +{len(s.unexercised)}"
        if s.problems and not s.failed:
            failed = "problem: " + s.problems[0][:60]
        if case is not None and ((s.case, s.dut) != case or s.run):
            run = f", {cf.RUN_OPTIONS[s.run]}" if s.run else ""
            failed += f" (played on case {s.case}, agent {s.dut}{run})"
        lines.append(f"{s.fault:26s} {s.requirement:11s} {s.group:11s} "
                     f"{'yes' if s.caught else 'NO':6s} {'yes' if s.named_first else '-':3s} "
                     f"{'yes' if s.named else '-':3s} "
                     f"{'yes' if s.named_by_first_diff else '-':3s} {failed}")
    return "\n".join(lines)


def summary(scores: list[cf.Score]) -> dict[str, float | int]:
    n = len(scores)
    out: dict[str, float | int] = {"faults": n}
    for key, count in (("caught", sum(s.caught for s in scores)),
                       ("named_first", sum(s.named_first for s in scores)),
                       ("named", sum(s.named for s in scores)),
                       ("named_by_first_diff", sum(s.named_by_first_diff for s in scores))):
        out[key] = count
        out[f"{key}_pct"] = round(100 * count / n, 1) if n else 0.0
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", type=_case, action="append", metavar="CASE:AGENT",
                   help="a scenario and the agent the device replaces (default 1:3; "
                        "repeatable)")
    p.add_argument("--jitter", type=float, default=0.3,
                   help="ticks and tester frames up to this fraction of Ts late (0.3)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timing", choices=("bus", "exact"), default="bus",
                   help="bus: the oracle's timing tolerance of a bus run (default); "
                        "exact: the device's clock trusted (it ticks every Ts on the dot, "
                        "--jitter moves the tester's frames only): a frame exactly a "
                        "timeout old at a tick is a step")
    p.add_argument("--only", nargs="+", metavar="FAULT", help="these faults only")
    p.add_argument("--jobs", type=int, default=1, help="processes (default 1)")
    p.add_argument("--json", type=Path, metavar="OUT", help="write the scores here")
    p.add_argument("--device", choices=DEVICES, default="py",
                   help="py: firmware_py's agent and faults (default); c: the C agent, "
                        "each fault built into a library of its own (cached)")
    a = p.parse_args(argv)
    cases = a.case or [(1, 3)]
    fs = _set(a.device)
    names = a.only or [f.name for f in fs.FAULTS]
    unknown = sorted(set(names) - set(fs.BY_NAME))
    if unknown:
        p.error(f"--only: unknown faults {', '.join(unknown)}")
    logging.disable(logging.CRITICAL)
    start = time.perf_counter()
    exact = a.timing == "exact"
    doc: dict[str, object] = {"device": a.device, "jitter": a.jitter, "seed": a.seed,
                              "timing": a.timing, "cases": {}}
    for case, dut in cases:
        # the faultless agent on every device the faults are played on
        for on in dict.fromkeys([(case, dut, ""), *(cf.played_on(fs.BY_NAME[n], case, dut)
                                                   for n in names)]):
            base = fs.score(None, on[0], on[1], a.jitter, a.seed, exact=exact, run=on[2])
            if base.caught:
                print(f"case {on[0]} agent {on[1]} {on[2]}: the faultless agent fails "
                      f"({base.failed}, {base.problems}): no score", file=sys.stderr)
                return 1
        jobs = [(n, case, dut, a.jitter, a.seed, a.device, exact) for n in names]
        if a.jobs > 1:
            from multiprocessing import Pool
            with Pool(a.jobs) as pool:
                scores = pool.map(_job, jobs, chunksize=1)
        else:
            scores = [_job(j) for j in jobs]
        print(f"case {case}, agent {dut}, device {a.device} (jitter {a.jitter}, "
              f"seed {a.seed}, timing {a.timing}):")
        print(table(scores, (case, dut)))
        s = summary(scores)
        n = s["faults"]
        print(f"caught {s['caught']}/{n} ({s['caught_pct']} %); the own requirement named "
              f"first {s['named_first']}/{n} ({s['named_first_pct']} %), at all "
              f"{s['named']}/{n} ({s['named_pct']} %), by the first difference "
              f"{s['named_by_first_diff']}/{n} ({s['named_by_first_diff_pct']} %)\n")
        doc["cases"][f"{case}:{dut}"] = {  # type: ignore[index]
            "summary": s, "faults": [{**asdict(x), "caught": x.caught,
                                      "named_first": x.named_first, "named": x.named,
                                      "named_by_first_diff": x.named_by_first_diff}
                                     for x in scores]}
    print(f"{time.perf_counter() - start:.0f} s")
    if a.json:
        a.json.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
