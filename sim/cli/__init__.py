"""The ``bess-ded`` command line. Each subcommand lives in its own module here.

Adding a subcommand ``NAME``:

1. create ``sim/cli/NAME.py`` with::

       def register(sub: argparse._SubParsersAction) -> None:
           p = sub.add_parser("NAME", help="one line for `bess-ded -h`", description=__doc__)
           p.add_argument(...)
           p.set_defaults(func=run)

       def run(args: argparse.Namespace) -> int:   # the exit code
           ...

2. add ``"NAME"`` to ``COMMANDS`` below (the order is the order of ``bess-ded -h``).

Keep a subcommand thin: parsing and printing over a function of the library in
``sim/`` that does the work and returns a result (docs/api.md); nothing outside
``sim/cli`` imports from it. Keep ``register`` cheap (import heavy modules inside
``run``): every invocation registers every subcommand. Raise a ``BessDedError`` for
anything the user can fix; ``main`` prints it as ``bess-ded: error: <message>`` and
exits with 2, no traceback.
A listed command whose module is missing or fails to import is never skipped: `bess-ded
-h` lists it as unavailable, with the import error, and using it exits 2 naming that
error; the other commands work on.
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import sys
from collections.abc import Sequence
from typing import NoReturn

from firmware_py.errors import BessDedError

PROG = "bess-ded"
EXIT_ERROR = 2

COMMANDS: tuple[str, ...] = (
    "case",      # one scenario in the lockstep simulator: metrics, trajectory, figures
    "compare",   # every controller on one scenario
    "bench",     # micro-benchmarks of the control core and the simulator
    "sweep",     # many lockstep runs over graphs, gains and seeds: one table
    "tune",      # reset-PI gains from the graph's spectrum and a peak-|u| bound
    "up",        # a whole case as processes on a CAN bus
    "deploy",    # a scenario's node configurations and key files, nothing run
    "restbus",   # the fleet but one node, for a device under test on the bus
    "conformance",  # prove an agent node conformant over the bus
    "analyze",   # metrics, anomalies and plots from any recorded log
    "record",    # capture a bus to a candump log
    "agent",     # one agent firmware node
    "plant",     # the plant simulator node
    "router",    # the energy-router (price) node
    "inject",    # crafted bad frames for fault-injection tests
    "keys",      # provision SecOC keys for a fleet (docs/security.md)
)


def build_parser() -> argparse.ArgumentParser:
    """The `bess-ded` parser with every command's subparser (a command whose
    module fails to import is registered as broken and reports why when run)."""
    parser = argparse.ArgumentParser(
        prog=PROG, description="Distributed economic dispatch for batteries: reset-PI "
        "marginal-cost consensus, simulated or as CAN nodes.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except Exception as e:  # a broken module must not take the other commands down
            _register_broken(sub, name, e)
            continue
        module.register(sub)
    return parser


def _register_broken(sub: argparse._SubParsersAction, name: str, exc: Exception) -> None:
    """A command whose module fails to import: listed, and fails loudly when used."""
    reason = f"{type(exc).__name__}: {exc}"

    def run(args: argparse.Namespace) -> int:
        raise BessDedError(f"command {name!r} is unavailable: its module failed to import "
                           f"({reason})")

    p = sub.add_parser(name, help=f"(unavailable: {reason})", add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=run)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the exit code (also when called
    in-process, e.g. from tests: argparse's own exits are turned into return codes)."""
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    _suggest_on_error(parser, argv)
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2), already printed
        return e.code if isinstance(e.code, int) else EXIT_ERROR
    try:
        return int(args.func(args) or 0)
    except BessDedError as e:
        _error(str(e))
    except BrokenPipeError:  # `bess-ded ... | head`: the reader left, nothing to report
        _silence_stdout()
        return 1
    except OSError as e:  # an unwritable --out, a missing file: the user's to fix
        _error(f"{e.strerror or e}: {e.filename}" if e.filename else str(e))
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    return EXIT_ERROR


def _suggest_on_error(parser: argparse.ArgumentParser, argv: list[str]) -> None:
    """The top-level parser's errors (a mistyped command, an option the command does not
    have) in one line, with a "did you mean" from difflib (argparse has none before 3.12)."""
    from ._common import with_suggestion

    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))

    def error(message: str) -> NoReturn:
        command = next((a for a in argv if a in sub.choices), None)
        options = [] if command is None else [
            o for a in sub.choices[command]._actions for o in a.option_strings]
        message = re.sub(r"^argument (\S+): ", r"\1: ", message)
        message = with_suggestion(message, options)
        usage = f"bess-ded {command} -h" if command else "bess-ded -h"
        parser.exit(EXIT_ERROR, f"{PROG}: error: {' '.join(message.split())} (usage: "
                    f"{usage})\n")

    parser.error = error  # type: ignore[method-assign,assignment]


def _error(message: str) -> None:
    one_line = " ".join(message.split())
    print(f"{PROG}: error: {one_line}", file=sys.stderr)


def _silence_stdout() -> None:
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
