"""Several agents in one process: one loop (``node.run_nodes``) and one bus socket.

Why one socket and not one per agent: on udp_multicast every socket on the host
receives every frame of the bus, and python-can's ``recv`` (a syscall, a msgpack
decode, a Message) is most of what a Python node spends on a frame it does not use.
K sockets in one process would read each frame K times; one socket reads it once and
hands it to each agent, which then sees what its own socket would have delivered:
every frame of the bus, its own echo included, counted and dropped by its own NodeIO.
Each agent keeps its own NodeIO (echo memory, E2E trackers, counters), its own keys
and its own control core; only the scheduling is shared.

On interfaces that do not loop a socket's sends back to itself (socketcan, virtual)
the shared socket asks for its own messages, or the agents of one host would not hear
each other. Acceptance filters: the kernel passes the union of the agents' IDs and
each agent gets only its own (``AcceptedOnly``), dropped uncounted as its own filter
would have dropped them.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import can

from .node import Node, with_acceptance_filter

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
