"""The coverage table of docs/conformance.md (tools/gen_conformance_table.py): every
requirement of the spec has a step of the conformance schedule or a stated reason, and
the committed table is the one the tool writes."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tool():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location(
        "gen_conformance_table", ROOT / "tools" / "gen_conformance_table.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_spec_requirement_has_a_step_or_a_reason() -> None:
    """Expected: no requirement of spec_requirements.txt is in neither STEPS nor
    NOT_ON_BUS, none is in both, and neither names an ID the spec lacks."""
    assert _tool().problems() == []


def test_the_coverage_table_in_the_doc_is_current() -> None:
    """Expected: docs/conformance.md carries exactly the table the tool renders
    (regenerate: python tools/gen_conformance_table.py)."""
    tool = _tool()
    doc = tool.DOC.read_text(encoding="utf-8")
    assert tool.BEGIN in doc and tool.END in doc
    assert tool.updated(doc) == doc, "stale: run python tools/gen_conformance_table.py"


def test_a_requirement_without_step_or_reason_is_reported(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Expected: dropping a requirement's reason makes the check name it."""
    tool = _tool()
    monkeypatch.delitem(tool.NOT_ON_BUS, "AUTH-5")
    assert any(p.startswith("AUTH-5:") for p in tool.problems())
