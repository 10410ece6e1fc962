"""Argument parsing shared by the subcommands (not a subcommand itself); the formatting
of results is the library's: sim/report/textfmt.py."""

from __future__ import annotations

import argparse
import re
from collections.abc import Sequence
from typing import NoReturn

from firmware_py.errors import ParameterError


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
    """--fixed (the default) | --float: the arithmetic of the lockstep runs."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--fixed", dest="fixed", action="store_true", default=True,
                   help="fixed point (Q24 words, Q54 state), what the firmware runs (default)")
    g.add_argument("--float", dest="fixed", action="store_false",
                   help="the float twin of the same controller")


def add_transmit_argument(p: argparse.ArgumentParser) -> None:
    """--transmit periodic|event: how the agents send their λ (firmware-spec TX-7)."""
    from firmware_py.config import TRANSMIT_MODES

    p.add_argument("--transmit", choices=TRANSMIT_MODES, default=None,
                   help="the agents send their λ (MC frame) every tick (periodic) or when it "
                   "moved more than a threshold and at least every heartbeat (event; the "
                   "scenario's event_threshold, event_heartbeat); default: the scenario's "
                   "transmit, else periodic")
