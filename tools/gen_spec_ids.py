#!/usr/bin/env python3
"""Write ``sim/conformance/spec_requirements.txt``: every requirement ID of docs/firmware-spec.md,
in the spec's order, one a line.

`bess-ded conformance` orders and checks its verdict by these IDs; docs/ is not part of
the installed package, so the list ships as package data of sim. A test
(tests/test_conformance.py) fails when the committed file differs from the spec.

Usage::

    python tools/gen_spec_ids.py            # (re)write sim/conformance/spec_requirements.txt
    python tools/gen_spec_ids.py --check    # exit 1 if it is stale
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SPEC = ROOT / "docs" / "firmware-spec.md"
OUT = ROOT / "sim" / "conformance" / "spec_requirements.txt"


def ids(text: str) -> list[str]:
    """The IDs the spec defines (``- **GEN-1** ...`` list items), first occurrence order."""
    return list(dict.fromkeys(re.findall(r"^- \*\*([A-Z]+-\d+)\*\*", text, re.M)))


def render() -> str:
    return ("# every requirement ID of docs/firmware-spec.md, in order "
            "(tools/gen_spec_ids.py writes this file)\n"
            + "".join(f"{i}\n" for i in ids(SPEC.read_text(encoding="utf-8"))))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if the file is stale")
    args = ap.parse_args()
    text = render()
    if args.check:
        stale = not OUT.exists() or OUT.read_text(encoding="utf-8") != text
        if stale:
            print(f"{OUT} is stale: run python tools/gen_spec_ids.py", file=sys.stderr)
        return 1 if stale else 0
    OUT.write_text(text, encoding="utf-8")
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
