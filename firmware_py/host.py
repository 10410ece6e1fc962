"""Several agents in one process: one loop (``node.run_nodes``) and one bus socket.

Why one socket and not one per agent: on udp_multicast every socket on the host
receives every frame of the bus, and python-can's ``recv`` (a syscall, a msgpack
decode, a Message) is most of what a Python node spends on a frame it does not use.
K sockets in one process would read each frame K times; one socket reads it once and
hands it to each agent, which then sees what its own socket would have delivered:
every frame of the bus, its own echo included, counted and dropped by its own NodeIO.
Each agent keeps its own NodeIO (echo memory, freshness state, counters), its own keys
and its own control core; only the scheduling is shared.

On interfaces that do not loop a socket's sends back to itself (socketcan, virtual)
the shared socket asks for its own messages, or the agents of one host would not hear
each other. Acceptance filters: the kernel passes the union of the agents' IDs and
each agent gets only its own (``AcceptedOnly``), dropped uncounted as its own filter
would have dropped them.

What an agent would drop uncounted and without effect (``NodeIO.ignores``: most of a
large fleet's traffic) is not handed to it at all (``Routes``), once it has joined: its
NodeIO then does exactly what it did, for fewer calls.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import can

from .node import Node, with_acceptance_filter
from .nodeio import NodeIO

# interfaces whose socket does not receive its own sends unless asked to
NO_LOOPBACK = frozenset({"socketcan", "virtual"})


class AcceptedOnly:
    """A node behind its own acceptance filter on a socket it shares: data frames of
    other IDs never reach it (error frames do: LOOP-4, counted by the loop)."""

    def __init__(self, node: Node, ids: Iterable[int]) -> None:
        self.node = node
        self.ids = frozenset(ids)
        self.period = node.period

    def on_frame(self, msg: can.Message, t: float) -> None:
        """Pass the frame on if the node's filter passes it."""
        if not msg.is_extended_id and msg.arbitration_id in self.ids:
            self.node.on_frame(msg, t)

    def tick(self, t: float) -> Iterable[can.Message]:
        """The node's tick."""
        return self.node.tick(t)

    def note(self, event: str, count: int = 1) -> None:
        """The node's count."""
        self.node.note(event, count)


def host_bus(kw: dict[str, Any], accepted: Sequence[Iterable[int]],
             enabled: bool | None = None) -> tuple[dict[str, Any], bool]:
    """The bus arguments of a host of agents that accept ``accepted`` IDs each (from
    ``bus_kwargs``): the union filter where filters are on, and the host's own sends
    looped back where the interface does not do it. Also whether each agent needs its
    own filter in front of it (``AcceptedOnly``)."""
    union = frozenset().union(*map(frozenset, accepted))
    out = with_acceptance_filter(kw, union, enabled)
    if len(accepted) > 1 and out.get("interface") in NO_LOOPBACK:
        out = {**out, "receive_own_messages": True}
    return out, bool(out.get("can_filters")) and len(accepted) > 1


class Routes:
    """The nodes of a host a received frame can affect, in host order: for a data frame of
    the bus's format (the DBC's: classic or FD), those whose NodeIO does not ``ignore`` its
    ID (cached per ID) and those still joining; anything else (an extended, remote or
    error frame, a frame of the other format: counted) goes to all.
    ``ios[i]`` is ``nodes[i]``'s NodeIO."""

    def __init__(self, nodes: Sequence[Node], ios: Sequence[NodeIO]) -> None:
        self.nodes, self.ios = list(nodes), list(ios)
        self._fd = bool(ios) and ios[0].codec.fd
        self._by_id: dict[int, list[Node]] = {}
        self._joined = False

    def __call__(self, msg: can.Message) -> Sequence[Node]:
        """The nodes to hand ``msg`` to."""
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame \
                or msg.is_fd != self._fd:  # the other frame format: every node counts it
            return self.nodes
        fid = msg.arbitration_id
        if not self._joined:
            if any(io.joining for io in self.ios):
                return [n for n, io in zip(self.nodes, self.ios, strict=True)
                        if io.joining or not io.ignores(fid)]
            self._joined = True
        out = self._by_id.get(fid)
        if out is None:
            out = self._by_id[fid] = [n for n, io in zip(self.nodes, self.ios, strict=True)
                                      if not io.ignores(fid)]
        return out
