#!/usr/bin/env python3
"""Refresh the generated parts of docs/firmware-spec.md section 16 (Coverage).

* the ``; conformance: STEP, ...`` tail of each row's test(s) cell, from
  ``sim.conformance.STEPS`` (each step lists the MUSTs it checks on a node);
* the ``Totals:`` line, counted from the rows.

Statuses and test names are written by hand; tests/test_spec_coverage.py checks that
the table has one row per requirement and that this script's output is current.

Usage: ``python tools/spec_coverage.py`` (rewrites the file; ``--check``: exit 1 if it
would change it)."""

from __future__ import annotations

import re
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from sim.conformance import STEPS  # noqa: E402

SPEC = ROOT / "docs" / "firmware-spec.md"
ROW = re.compile(r"^\| ([A-Z]+-\d+) \| ([a-z ]+) \| (.*) \|$")


def steps_by_must() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for step in STEPS:
        for must in step.musts:
            names = out.setdefault(must, [])
            if step.name not in names:
                names.append(step.name)
    return out


def refreshed(text: str) -> str:
    start, end = text.index("## 16. Coverage"), text.index("## 17. ")
    steps = steps_by_must()
    status: Counter[str] = Counter()
    lines = []
    for line in text[start:end].split("\n"):
        m = ROW.match(line)
        if m:
            rid, st, cell = m.groups()
            cell = re.sub(r"; conformance: [^|]*$", "", cell)
            if rid in steps:
                cell += "; conformance: " + ", ".join(steps[rid])
            status[st] += 1
            line = f"| {rid} | {st} | {cell} |"
        lines.append(line)
    sec = "\n".join(lines)
    total = (f"Totals: {status['covered']} covered, {status['partial']} partial, "
             f"{status['not yet']} not yet (of {sum(status.values())}).")
    sec, n = re.subn(r"^Totals: .*$", total, sec, flags=re.M)
    if n != 1:
        raise SystemExit(f"{SPEC}: expected one Totals line in section 16, found {n}")
    return text[:start] + sec + text[end:]


def main(argv: list[str]) -> int:
    text = SPEC.read_text(encoding="utf-8")
    new = refreshed(text)
    if "--check" in argv:
        if new != text:
            print(f"{SPEC}: section 16 is stale: run tools/spec_coverage.py", file=sys.stderr)
            return 1
        return 0
    SPEC.write_text(new, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
