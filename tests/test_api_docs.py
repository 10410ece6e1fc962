"""docs/api.md: every ```python example runs as it is written (in a fresh namespace, in a
temporary working directory). An example preceded by ``<!-- marks: NAME ... -->`` gets
those pytest marks (slow: an in-process bus run; long: processes on the wall clock)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

API_MD = Path(__file__).parents[1] / "docs" / "api.md"
EXAMPLE = re.compile(r"(?:<!-- marks: ([\w ]+) -->\n)?```python\n(.*?)```", re.S)


def _examples() -> list[object]:
    text = API_MD.read_text()
    params = []
    for m in EXAMPLE.finditer(text):
        line = text.count("\n", 0, m.start(2)) + 1
        heading = re.findall(r"^## (.+)$", text[:m.start()], re.M)
        name = f"{heading[-1] if heading else 'intro'} (line {line})"
        marks = [getattr(pytest.mark, mark) for mark in (m.group(1) or "").split()]
        params.append(pytest.param(m.group(2), line, id=name, marks=marks))
    return params


def test_the_page_has_an_example_per_task() -> None:
    assert len(_examples()) >= 7


@pytest.mark.parametrize("code,line", _examples())
def test_example_runs(code: str, line: int, tmp_path: Path,
                      monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # anything written to a default runs/ stays in tmp_path
    exec(compile(code, f"{API_MD}:{line}", "exec"), {"__name__": "api_example"})
