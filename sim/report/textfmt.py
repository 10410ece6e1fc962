"""Plain-text formatting of results, shared by the library and the ``bess-ded`` commands:
tables, times, settling, scenario descriptions, a progress line, JSON files."""

from __future__ import annotations

import json
import math
import re
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

from firmware_py.controllers import ControllerConfig
from sim.model.scenario import Scenario


def slug(label: str) -> str:
    """A label as a file-name part: 'k=1,h=2' → 'k=1_h=2', 'reset-PI' stays."""
    return re.sub(r"[^A-Za-z0-9.=+-]+", "_", label).strip("_") or "run"


def write_json(path: Path, obj: Any) -> None:
    """``obj`` as indented JSON (numpy scalars and arrays as numbers and lists)."""
    path.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")


def _json_default(x: Any) -> Any:
    if hasattr(x, "item"):  # numpy scalars
        return x.item()
    if hasattr(x, "tolist"):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def describe(sc: Scenario, fixed: bool) -> str:
    """'4 agents, Ts = 10 ms, 20 s, fixed point Q24+30, η_max(H) = ...': one line."""
    arith = f"fixed point Q{sc.controller.q}+30" if fixed else "float"
    return (f"{sc.n} agents, Ts = {sc.ts * 1e3:g} ms, {sc.duration:g} s, {arith}, "
            f"η_max(H) = {sc.analysis().eta_max:.4f}")


def controller_desc(c: ControllerConfig) -> str:
    """'reset: k = 1, h = 2, band = 0.0001' with only the parameters the kind uses."""
    parts = [f"k = {c.k:g}"]
    if c.kind in ("pi", "reset", "dwell"):
        parts.append(f"h = {c.h:g}")
    if c.kind in ("reset", "dwell"):
        parts.append(f"band = {c.band:g} cu/kWh")
    if c.kind == "dwell":
        parts.append(f"Δ = {c.dwell:g} s")
    if c.kind == "ft":
        parts.append(f"a = {c.ft_exponent:g}")
    return f"{c.kind}: " + ", ".join(parts)


class Progress:
    """A single updating line on stderr for runs that take a while.

    Pass as ``run_lockstep(..., progress=Progress(label))``. Silent unless stderr is
    a terminal, and until the run has taken ``delay`` seconds, so quick runs and
    logs stay clean. ``done()`` erases the line.
    """

    def __init__(self, label: str, stream: TextIO | None = None, delay: float = 0.4,
                 enabled: bool | None = None) -> None:
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() if enabled is None else enabled
        self.start = time.monotonic()
        self.delay = delay
        self.shown = False

    def __call__(self, step: int, steps: int) -> None:
        if not self.enabled or time.monotonic() - self.start < self.delay:
            return
        frac = step / max(steps, 1)
        bar = "#" * int(24 * frac)
        self.stream.write(f"\r  {self.label:<16} [{bar:<24}] {frac:4.0%}")
        self.stream.flush()
        self.shown = True

    def done(self) -> None:
        """Erase the progress line, if one is shown."""
        if self.shown:
            self.stream.write("\r" + " " * 60 + "\r")
            self.stream.flush()
            self.shown = False


# --------------------------------------------------------------------------- formatting


def table(headers: Sequence[str], rows: Sequence[Sequence[str]],
          align: str | None = None) -> str:
    """A plain text table. ``align`` holds one 'l' or 'r' per column (default: first
    column left, the rest right)."""
    align = align or "l" + "r" * (len(headers) - 1)
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) if rows else len(str(h))
              for i, h in enumerate(headers)]

    def line(cells: Sequence[str]) -> str:
        return "  ".join(str(c).ljust(w) if a == "l" else str(c).rjust(w)
                         for c, w, a in zip(cells, widths, align, strict=True)).rstrip()

    rule = "  ".join("-" * w for w in widths)
    return "\n".join([line(headers), rule, *(line(r) for r in rows)])


def fmt_time(x: float | None) -> str:
    """A time in s with two decimals, or 'never'."""
    return "never" if x is None else f"{x:.2f}"


def fmt_times(xs: Sequence[float | None]) -> str:
    """Times as ``fmt_time``, joined by '/'."""
    return "/".join(fmt_time(x) for x in xs)


def fmt_settling(sc: Scenario, times: Sequence[float | None]) -> str:
    """Every price segment's settling time with the price it settles to:
    '2.54 s to ρ = 0.8 (from t = 0 s), never to ρ = 1 (from t = 15 s)'."""
    parts = []
    for step, x in zip(sc.prices, times, strict=False):
        when = "never" if x is None else f"{x:.2f} s"
        parts.append(f"{when} to ρ = {step.rho:g} (from t = {step.t:g} s)")
    return ", ".join(parts)


def fmt_sci(x: float) -> str:
    """One significant decimal in scientific notation ('1.2e-04'); inf and nan as such."""
    return f"{x:.1e}" if math.isfinite(x) else str(x)


def fmt_resets(resets: Sequence[int]) -> str:
    """Per agent when few, else the total and range."""
    if len(resets) <= 6:
        return " ".join(str(r) for r in resets)
    if not any(resets):
        return "0"
    return f"Σ{sum(resets)} ({min(resets)}-{max(resets)})"


def fmt_pct(x: float) -> str:
    """A fraction as a percentage with one decimal: '12.5 %'."""
    return f"{100 * x:.1f} %"
