"""The command-line options every node shares (agent, plant, router, and the `bess-ded`
commands that open a bus), and what they set up: the bus flags, --key/--insecure, the
acceptance filter, --rt-priority. Kept free of numpy/matplotlib, as the agent entry point.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from .cliargs import RT_PRIORITY
from .errors import ParameterError
from .node import BusConfigError
from .secoc import KeyFileError, Keyring


def add_bus_arguments(p: argparse.ArgumentParser) -> None:
    """The bus flags every node shares; unset flags fall back to CAN_* variables."""
    p.add_argument("--interface", help="python-can interface (default: $CAN_INTERFACE or "
                   "udp_multicast)")
    p.add_argument("--channel", help="channel, e.g. vcan0 (default: $CAN_CHANNEL)")
    p.add_argument("--bus-config", help='extra python-can arguments as JSON, e.g. '
                   '\'{"port": 43200}\' (default: $CAN_CONFIG)')


def add_fd_argument(p: argparse.ArgumentParser) -> None:
    """--fd: the bus's frame format (LOOP-6), classic CAN unless given."""
    p.add_argument("--fd", action="store_true",
                   help="a CAN FD bus: send every frame as CAN FD with the bit-rate switch "
                   "(dbc/bess_ded_fd.dbc) and reject classic frames (default: classic CAN, "
                   "FD frames rejected)")
    p.add_argument("--no-lambda-tags", action="store_true",
                   help="with --fd: λ under its sender's node key in 8 bytes "
                   "(dbc/bess_ded_fd_untagged.dbc, a scenario's [security] lambda_tags = "
                   "false) instead of a 24-bit tag per receiver (AUTH-34, the default on FD)")


def lambda_tags_of(args: argparse.Namespace) -> bool:
    """Whether λ carries a tag per receiver on this node's bus (AUTH-34): on CAN FD unless
    --no-lambda-tags; ParameterError for --no-lambda-tags without --fd."""
    if args.no_lambda_tags and not args.fd:
        raise ParameterError("--no-lambda-tags", "it only with --fd (classic CAN has no room "
                             "for the tags)", "a classic bus")
    return not args.no_lambda_tags


def fd_argv(fd: bool, lambda_tags: bool) -> list[str]:
    """The node flags of a bus format: --fd, and --no-lambda-tags for FD without tags."""
    return (["--fd"] + ([] if lambda_tags else ["--no-lambda-tags"])) if fd else []


def add_key_arguments(p: argparse.ArgumentParser, repeat: bool = False) -> None:
    """--key FILE | --insecure, one of them required (docs/security.md); ``repeat``:
    --key may be given once per node of the process (a list)."""
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--key", metavar="FILE", action="append" if repeat else "store",
                   help="this node's key file from `bess-ded keys --fleet` (owner-only: "
                        "0600); its boot counter is advanced at every start")
    g.add_argument("--insecure", action="store_true",
                   help="demo mode: sign with the public all-zero key (anyone on the bus can "
                        "forge frames); prints a warning")


def keyring_from_args(args: argparse.Namespace, node: str, key: str | None = None) -> Keyring:
    """The keyring of ``node`` (e.g. "agent_3") from --key FILE (or ``key``, one of a
    repeated --key), or the public insecure one with a warning on stderr. A key file of
    another node is refused."""
    if args.insecure:
        print(f"bess-ded: warning: {node} runs --insecure: its frames are signed with the "
              "public demo key and anyone on the bus can forge them (docs/security.md)",
              file=sys.stderr, flush=True)
        return Keyring.insecure_for(node)
    key = key or args.key
    ring = Keyring.from_file(key)
    if ring.node != node:
        raise KeyFileError(f"--key {key}: expected the key file of {node}, but got "
                           f"the one of {ring.node}")
    return ring


def add_rt_argument(p: argparse.ArgumentParser) -> None:
    """--rt-priority for the nodes (agent, plant, router)."""
    p.add_argument("--rt-priority", type=RT_PRIORITY, default=0, metavar="N",
                   help="run under SCHED_FIFO priority N (1..99) so ticks keep their deadlines "
                   "on a loaded host; needs root or CAP_SYS_NICE (default: 0 = off)")


def add_filter_argument(p: argparse.ArgumentParser) -> None:
    """--[no-]acceptance-filter for the nodes (agent, plant, router)."""
    p.add_argument("--acceptance-filter", action=argparse.BooleanOptionalAction, default=None,
                   help="pass only the frames this node uses or sends, in the kernel "
                   "(default: on for socketcan, as an MCU's CAN controller would; off "
                   "elsewhere). --no-acceptance-filter lets every frame through, so the "
                   "node counts foreign IDs too, at more CPU on a busy bus")


def set_realtime(priority: int) -> None:
    """SCHED_FIFO for this process: the tick preempts ordinary work (logging, other
    programs). The loop sleeps in select between ticks, so it cannot starve the host."""
    if not 1 <= priority <= 99:
        raise BusConfigError(f"--rt-priority: expected 1..99, but got {priority}")
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, AttributeError, OSError) as e:
        logging.getLogger(__name__).warning("--rt-priority %d not applied (%s): running with "
                                            "normal priority", priority, e)
