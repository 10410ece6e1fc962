"""Shared fixtures. An autouse guard fails any test that leaks a virtual bus or a child
process: a node that outlives its test is exactly the bug users would hit."""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable
from pathlib import Path

import can.interfaces.virtual as virtual
import pytest

# udp_multicast runs of one test session take ports from a block of 100 of its own (by
# pid), so two sessions running at once (a developer's and CI's) never hear each other.
_ports = itertools.count(43200 + (os.getpid() % 200) * 100)


def next_udp_port() -> int:
    return next(_ports)


def _children() -> set[int]:
    me = str(os.getpid())
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[1] == me and fields[0] != "Z":
            out.add(int(stat.parent.name))
    return out


@pytest.fixture(autouse=True)
def no_leaks():
    before = _children()
    yield
    with virtual.channels_lock:
        open_channels = {name: len(buses) for name, buses in virtual.channels.items() if buses}
    leaked = _children() - before
    assert not open_channels, f"test left virtual buses open: {open_channels}"
    assert not leaked, f"test left child processes running: {sorted(leaked)}"


@pytest.fixture
def udp_port() -> int:
    """A multicast port of its own, so concurrent runs never hear each other."""
    return next_udp_port()


@pytest.fixture(scope="session")
def udp_ports() -> Callable[[], int]:
    """The port allocator itself, for fixtures wider than one test."""
    return next_udp_port
