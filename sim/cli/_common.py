"""Helpers shared by the simulation subcommands (not a subcommand itself)."""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn, TextIO

from firmware_py.controllers import ControllerConfig
from firmware_py.errors import ConfigError, ParameterError

from ..scenario import SCENARIO_DIR, Scenario, load_case, load_scenario


def one_line_errors(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Make ``p``'s usage errors the CLI's one-line shape: ``bess-ded: error: --duration:
    expected a finite number > 0, but got 0`` on stderr, exit code 2 (sim.cli.main
    returns it), instead of argparse's usage block and ``bess-ded CMD: error: argument``."""
    command = p.prog.split()[-1]

    def error(message: str) -> NoReturn:
        message = re.sub(r"^argument (\S+?)(/\S+)?: ", r"\1: ", message)
        message = with_suggestion(message, [])
        p.exit(2, f"bess-ded: error: {' '.join(message.split())} (usage: bess-ded {command} "
                  "-h)\n")

    p.error = error  # type: ignore[method-assign]
    return p


CASE_HELP = "a case number (1-7, the paper's cases) or a path to a scenario .toml"


def add_case_option(p: argparse.ArgumentParser, required: bool = True) -> None:
    """``--case CASE``: how every command names its scenario (``--scenario FILE``, an older
    spelling, is the same option)."""
    p.add_argument("--case", "--scenario", dest="case", metavar="CASE", required=required,
                   help=CASE_HELP + " (--scenario is the same option)")


def with_suggestion(message: str, options: Sequence[str]) -> str:
    """argparse's message plus "did you mean ...?" for a mistyped choice (from the choices
    it lists) or an unrecognized option (from ``options``, the command's flags)."""
    import difflib

    m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)$", message)
    if m:
        given, choices = m.group(1), re.findall(r"'([^']*)'", m.group(2))
        near = difflib.get_close_matches(given, choices, n=1, cutoff=0.6)
        near = near or [c for c in choices if c.casefold() == given.casefold()]
        return message + (f" (did you mean {near[0]!r}?)" if near else "")
    m = re.match(r"unrecognized arguments: (.*)$", message)
    if m:
        hints = []
        for word in m.group(1).split():
            flag = word.split("=", 1)[0]
            near = difflib.get_close_matches(flag, options, n=1, cutoff=0.6) \
                if flag.startswith("-") else []
            if near:
                hints.append(f"{flag!r}: did you mean {near[0]!r}?")
        return message + (f" ({'; '.join(hints)})" if hints else "")
    return message


def add_scenario_argument(p: argparse.ArgumentParser) -> None:
    """``CASE`` or ``--case CASE`` (`case`, `compare`); read it with ``scenario_spec``."""
    p.add_argument("case", metavar="CASE", nargs="?", help=CASE_HELP)
    p.add_argument("--case", "--scenario", dest="case_option", metavar="CASE",
                   help="the same, as every other command names it")


def scenario_spec(args: argparse.Namespace) -> str:
    """The scenario of ``add_scenario_argument``: given once, as CASE or --case."""
    given = [x for x in (args.case, args.case_option) if x is not None]
    if len(given) != 1:
        raise ParameterError("CASE", "one scenario, as CASE or --case CASE (e.g. `bess-ded "
                             f"{args.command} 1`)", " and ".join(given) or "none")
    return given[0]


def add_no_plot_argument(p: argparse.ArgumentParser, what: str) -> None:
    """``--no-plot`` (``--no-plots`` is the same flag) in every command that draws."""
    p.add_argument("--no-plot", "--no-plots", dest="no_plot", action="store_true",
                   help=f"skip {what}")


def add_arithmetic_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--fixed", dest="fixed", action="store_true", default=True,
                   help="fixed point (Q24 words, Q54 state), what the firmware runs (default)")
    g.add_argument("--float", dest="fixed", action="store_false",
                   help="the float twin of the same controller")


def resolve_scenario(spec: str) -> Scenario:
    """A case number → the bundled sim/scenarios/caseN.toml; anything else → a path."""
    path = Path(spec)
    if spec.isdigit() and (SCENARIO_DIR / f"case{int(spec)}.toml").exists():
        return load_case(int(spec))
    if not spec.isdigit() and (path.suffix == ".toml" or path.exists() or "/" in spec):
        return load_scenario(path)
    known = sorted((p.stem.removeprefix("case") for p in SCENARIO_DIR.glob("case*.toml")),
                   key=lambda k: (len(k), k))
    raise ConfigError(spec, "case", f"expected a case number ({', '.join(known)}) or a path to "
                      f"a scenario .toml, but got {spec!r}")


def slug(label: str) -> str:
    """A label as a file-name part: 'k=1,h=2' → 'k=1_h=2', 'reset-PI' stays."""
    return re.sub(r"[^A-Za-z0-9.=+-]+", "_", label).strip("_") or "run"


def write_json(path: Path, obj: Any) -> None:
    path.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")


def _json_default(x: Any) -> Any:
    if hasattr(x, "item"):  # numpy scalars
        return x.item()
    if hasattr(x, "tolist"):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def describe(sc: Scenario, fixed: bool) -> str:
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
    return "never" if x is None else f"{x:.2f}"


def fmt_times(xs: Sequence[float | None]) -> str:
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
    return f"{x:.1e}" if math.isfinite(x) else str(x)


def fmt_resets(resets: Sequence[int]) -> str:
    """Per agent when few, else the total and range."""
    if len(resets) <= 6:
        return " ".join(str(r) for r in resets)
    if not any(resets):
        return "0"
    return f"Σ{sum(resets)} ({min(resets)}-{max(resets)})"


def fmt_pct(x: float) -> str:
    return f"{100 * x:.1f} %"
