"""The bus a run uses: its python-can options (``BusOptions``), a private udp_multicast
port per run (``private_port``), and what the recorder and the Tester need of a bus's
receive socket (``RECORDER_RCVBUF``, ``udp_drops``; ``bus_socket`` and
``enlarge_receive_buffer`` are firmware_py.node's, beside ``open_bus``).

Part of `bess-ded up` (``sim.run.busrun``), apart from the node processes
(``sim.run.nodeprocs``) and the recorder (``sim.run.recorder``).
"""

from __future__ import annotations

import json
import os
import random
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from firmware_py.errors import BessDedError
from firmware_py.node import bus_kwargs
from firmware_py.node import bus_socket as bus_socket  # re-exported: the run's helpers
from firmware_py.node import enlarge_receive_buffer as enlarge_receive_buffer


class BusRunError(BessDedError):
    """A bus run could not start or went wrong (no price frame, a node that
    cannot start, ...)."""


@dataclass
class BusOptions:
    """The bus a run uses: python-can interface, channel and extra config (JSON)."""

    interface: str | None = None
    channel: str | None = None
    config: str | None = None   # JSON of extra python-can arguments

    def resolved(self) -> dict[str, Any]:
        """The python-can arguments of this bus (flags, then CAN_* environment)."""
        return bus_kwargs(self.interface, self.channel, self.config)

    def argv(self) -> list[str]:
        """The same bus, as flags for a child node (resolved here so all nodes agree).
        Settings every node takes by itself (``bus_kwargs``'s defaults, e.g. socketcan's
        fd) are left out: firmware_c's node program takes no --bus-config."""
        kw = self.resolved()
        own = bus_kwargs(kw["interface"], kw.get("channel"), None)
        out = ["--interface", kw.pop("interface")]
        if "channel" in kw:
            out += ["--channel", str(kw.pop("channel"))]
        kw = {k: v for k, v in kw.items() if k not in own or own[k] != v}
        if kw:
            out += ["--bus-config", json.dumps(kw)]
        return out



# firmware_c's node program (bessded-agent) speaks these; python-can's udp_multicast
# defaults (can/interfaces/udp_multicast/bus.py) are its own too
C_INTERFACES = ("socketcan", "udp_multicast")
C_BUS_EXPECTED = ("--interface socketcan with a --channel (vcan0, can0, ...) or "
                  "--interface udp_multicast (a multicast group --channel, a port in "
                  "--bus-config, no other setting): the buses firmware_c's node program "
                  "runs on")
UDP_DEFAULT_PORT = 43113
UDP_SETTINGS_C = frozenset({"interface", "channel", "port", "fd", "hop_limit"})


def c_node_bus_argv(bus: BusOptions) -> list[str] | None:
    """The bus as flags for firmware_c's node program: ``--channel IFACE`` on socketcan,
    ``--interface udp_multicast --channel GROUP --port N`` on udp_multicast (python-can's
    default group and port where none is named); None for a bus it cannot speak (another
    interface, a socketcan one without a channel, udp_multicast settings it does not
    take: anything but a port, and a hop limit other than python-can's 1)."""
    kw = bus.resolved()
    if kw["interface"] == "socketcan":
        return ["--channel", str(kw["channel"])] if kw.get("channel") else None
    if kw["interface"] != "udp_multicast" or set(kw) - UDP_SETTINGS_C \
            or kw.get("hop_limit", 1) != 1:
        return None
    from can.interfaces.udp_multicast import UdpMulticastBus

    port = kw.get("port", UDP_DEFAULT_PORT)
    channel = kw.get("channel") or UdpMulticastBus.DEFAULT_GROUP_IPv6
    if type(port) is not int or not isinstance(channel, str):
        return None
    return ["--interface", "udp_multicast", "--channel", channel, "--port", str(port)]


PRIVATE_PORTS = (30000, 43000)  # below the test sessions' blocks (tests/conftest.py: 43200+)


def private_port(bus: BusOptions) -> tuple[BusOptions, int | None]:
    """On udp_multicast without a port named (flag or CAN_CONFIG), the same bus on a port
    of its own: every run on python-can's default port hears every other one (seen: ~900
    resets per agent and identical diagnostics in two concurrent runs). A different
    multicast group is not enough: Linux delivers a port's datagrams for every group
    joined on the host to every socket bound to that port. Returns (bus, chosen port)."""
    kw = bus.resolved()
    if kw["interface"] != "udp_multicast" or "port" in kw:
        return bus, None
    free = sorted(set(range(*PRIVATE_PORTS)) - bound_udp_ports())
    if not free:
        raise BusRunError(f"no free UDP port in {PRIVATE_PORTS[0]}..{PRIVATE_PORTS[1] - 1} for "
                          "a private udp_multicast bus: name one with --bus-config "
                          "'{\"port\": N}'")
    port = random.SystemRandom().choice(free)
    extra = {k: v for k, v in kw.items() if k not in ("interface", "channel")}
    return BusOptions(kw["interface"], kw.get("channel"),
                      json.dumps({**extra, "port": port})), port


def _udp_sockets() -> Iterator[list[str]]:
    """The columns of each UDP socket on this host (/proc/net/udp{,6}; none elsewhere):
    [1] the local address:port (hex), [9] the inode, the last the kernel's drops."""
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        yield from (line.split() for line in lines)


def bound_udp_ports() -> set[int]:
    """Local UDP ports with a socket bound on this host (empty where /proc has none)."""
    return {int(cols[1].rsplit(":", 1)[1], 16) for cols in _udp_sockets()}


def udp_drops(sock: socket.socket) -> int:
    """Datagrams the kernel dropped for this UDP socket (its ``drops`` column in
    /proc/net/udp{,6}); 0 for other sockets."""
    try:
        inode = str(os.fstat(sock.fileno()).st_ino)
    except OSError:
        return 0
    return next((int(cols[-1]) for cols in _udp_sockets()
                 if len(cols) > 12 and cols[9] == inode), 0)



# the recorder's kernel receive queue: ~20k CAN frames (an skb per frame) of slack while
# the real-time nodes starve it (firmware_py.node.enlarge_receive_buffer)
RECORDER_RCVBUF = 16 << 20  # bytes
