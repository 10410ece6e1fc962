"""Run one node (agent, plant or router) on a python-can bus: the periodic super-loop.

A node is pure logic behind a narrow seam: ``on_frame(msg, t)`` for every received
frame and ``tick(t) -> frames to send`` once per period. The clock is injected
(``time.monotonic`` by default), so tests drive nodes with fixed timestamps, and
the bus is passed in, never created by the node.

The loop is single-threaded, like an MCU super-loop: it receives until the next
release time, then ticks; when it is late, it first reads what is already queued
(up to DRAIN_MAX frames), so an overrunning node still sees its inputs. A tick
released more than half a period late is a deadline miss; whole periods that were
skipped count as misses too, and the loop re-aligns instead of bunching ticks (a
burst of late control steps is worse for the consensus than one skipped sample).
"""

from __future__ import annotations

import gc
import json
import logging
import os
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol

import can

from .errors import BessDedError

log = logging.getLogger(__name__)

DEFAULT_INTERFACE = "udp_multicast"  # works everywhere python-can runs, no kernel CAN needed


class Node(Protocol):
    """What run_node drives: a node with a tick ``period`` that takes frames and
    sends frames on each tick."""

    period: float

    def on_frame(self, msg: can.Message, t: float) -> None:
        """Take one received frame at time ``t``."""

    def tick(self, t: float) -> Iterable[can.Message]:
        """Run one tick at time ``t``; the frames to send."""

    def note(self, event: str, count: int = 1) -> None:
        """Count a runtime event: "deadline_miss", "send_failure", "error_frame" or a
        bus input that is not a frame (RX_CAUSES)."""


class RxTxBus(Protocol):
    """What the loop uses of a bus: a python-can bus, or a wrapper such as FaultyBus."""

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame within ``timeout`` s (None: wait), or None."""

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Put ``msg`` on the bus."""


class BusConfigError(BessDedError, ValueError):
    """The bus flags or CAN_* environment name no usable bus (a usage error)."""


def bus_kwargs(interface: str | None = None, channel: str | None = None,
               config: str | dict[str, Any] | None = None) -> dict[str, Any]:
    """Resolve flags, then CAN_INTERFACE / CAN_CHANNEL / CAN_CONFIG, then the default.

    ``config`` (or CAN_CONFIG) is a JSON object of extra python-can arguments,
    e.g. ``{"port": 43200}`` for udp_multicast. Its keys are checked against what the
    interface's bus class takes (``accepted_bus_keys``): python-can passes unknown
    keys on to BusABC, which ignores them, so a typo would silently change nothing.
    """
    interface = interface or os.environ.get("CAN_INTERFACE") or DEFAULT_INTERFACE
    channel = channel or os.environ.get("CAN_CHANNEL")
    raw = config if config is not None else os.environ.get("CAN_CONFIG")
    if isinstance(raw, str):
        try:
            extra = json.loads(raw) if raw.strip() else {}
        except json.JSONDecodeError as e:
            raise BusConfigError(f"CAN config: expected a JSON object, but got {raw!r} ({e})")\
                from None
    else:
        extra = dict(raw or {})
    if not isinstance(extra, dict):
        raise BusConfigError(f"CAN config: expected a JSON object, but got {extra!r}")
    check_bus_keys(interface, extra)
    kw: dict[str, Any] = {"interface": interface, **extra}
    if channel is not None:
        kw["channel"] = channel
    elif interface == "socketcan":
        kw["channel"] = "vcan0"
    elif interface == "virtual":
        kw.setdefault("channel", "bess-ded")
    if interface == "virtual":
        kw.setdefault("receive_own_messages", False)
    if interface in ("udp_multicast", "socketcan"):
        # CAN FD frames are read, not dropped unseen by python-can or the kernel: every node
        # rejects and counts them (malformed, RX-2) and sends classic frames only
        kw.setdefault("fd", True)
    return kw


# Taken by can.Bus itself, not passed to the bus class.
FACTORY_KEYS = ("config_context", "ignore_config")
# Interfaces whose bus class (python-can 4.6, read in its source) hands **kwargs straight
# to BusABC, which ignores all but can_filters: their signatures are the whole truth.
# Others (pcan, kvaser, ...) read more settings out of **kwargs, so they are not checked.
CHECKED_INTERFACES = frozenset({"udp_multicast", "socketcan", "virtual"})


def accepted_bus_keys(interface: str) -> tuple[str, ...] | None:
    """The keyword arguments python-can's bus class for ``interface`` uses: its
    ``__init__`` parameters, BusABC's when it passes ``**kwargs`` on (can_filters),
    and can.Bus's own. None when the interface is not in CHECKED_INTERFACES or its
    module does not import: can.Bus then reports that itself, better than a guess."""
    import importlib
    import inspect

    from can.interfaces import BACKENDS

    if interface not in CHECKED_INTERFACES:
        return None
    try:
        module_name, class_name = BACKENDS[interface]
        cls = getattr(importlib.import_module(module_name), class_name)
    except Exception:  # any import failure: leave it to can.Bus, which says why
        return None
    names: list[str] = []
    for klass in (cls, can.BusABC):
        params = inspect.signature(klass.__init__).parameters.values()
        names += [p.name for p in params if p.name != "self" and p.name not in names
                  and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
        if not any(p.kind is p.VAR_KEYWORD for p in params):
            break  # extra keys never reach BusABC
    return (*names, *FACTORY_KEYS)


def check_bus_keys(interface: str, extra: dict[str, Any]) -> None:
    """Reject keys the interface would silently ignore (a typo, or a setting such as
    socketcan's bitrate that lives elsewhere)."""
    accepted = accepted_bus_keys(interface)
    if accepted is None:
        return
    for key in extra:
        if key in accepted:
            continue
        if key == "interface":
            hint = " (give the interface with --interface or CAN_INTERFACE)"
        elif key in ("bitrate", "data_bitrate") and interface == "socketcan":
            hint = (" (socketcan's bitrate is the kernel's: ip link set CHANNEL type can "
                    "bitrate N)")
        else:
            import difflib

            close = difflib.get_close_matches(str(key), accepted, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise BusConfigError(f"CAN config: {interface} accepts {', '.join(accepted)}; but got "
                             f"unknown key {key!r}{hint}")


def open_bus(receive_buffer: int | None = None, **kw: Any) -> can.BusABC:
    """Open a python-can bus from ``bus_kwargs`` output, with a clear error if it fails;
    ``receive_buffer``: its socket's kernel receive queue in bytes, where it has one (a
    recorder's; a node keeps the default: under overload a control loop is better served
    by the kernel dropping old frames than by a deep queue of stale ones)."""
    try:
        bus = can.Bus(**kw)
    except (OSError, can.CanError, ValueError, ImportError) as e:
        raise BusConfigError(f"cannot open CAN bus {kw}: {e}") from None
    if receive_buffer is not None:
        enlarge_receive_buffer(bus, receive_buffer)
    return bus


def bus_socket(bus: can.BusABC) -> socket.socket | None:
    """The bus's own socket, None for interfaces without one. python-can exposes the
    socketcan socket as ``bus.socket``; udp_multicast keeps its own in
    ``bus._multicast._socket`` (no public accessor)."""
    sock = getattr(bus, "socket", None)
    if sock is None:
        sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    return sock if isinstance(sock, socket.socket) else None


def enlarge_receive_buffer(bus: can.BusABC, size: int) -> bool:
    """Let the kernel queue ``size`` bytes of frames for ``bus`` (a socketcan socket holds
    ~200 frames by default, a udp_multicast one ~300) instead of dropping them while
    the process is starved. SO_RCVBUFFORCE (root) passes net.core.rmem_max, SO_RCVBUF
    is capped by it. False where the bus has no socket or neither option is allowed."""
    sock = bus_socket(bus)
    if sock is None:
        return False
    for opt in (getattr(socket, "SO_RCVBUFFORCE", 33), socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, size)
            return True
        except OSError:
            continue
    return False


# Interfaces whose can_filters run below the process (kernel or CAN controller), like an
# MCU's acceptance filter. Elsewhere python-can filters in user space, after the read: no
# CPU saved, and the frames it drops would go uncounted, so no filter is installed there.
KERNEL_FILTERED = {"socketcan"}


def with_acceptance_filter(kw: dict[str, Any], ids: Iterable[int],
                           enabled: bool | None = None) -> dict[str, Any]:
    """``kw`` plus can_filters that pass only the 11-bit ``ids`` (the frames the node uses
    or sends), when ``enabled`` (None: on the kernel-filtered interfaces only). A filtered
    frame never reaches the node and is not counted by it; the recorder still logs it."""
    if enabled is None:
        enabled = kw.get("interface") in KERNEL_FILTERED
    if not enabled:
        return kw
    return {**kw, "can_filters": [{"can_id": i, "can_mask": 0x7FF, "extended": False}
                                  for i in sorted(set(ids))]}


class AcceptanceBus:
    """The bus as its acceptance filter leaves it (GEN-5). python-can binds a SocketCAN
    socket before it installs the kernel filter, so a frame sent in between still reaches
    the node; this drops every data frame the filter would not have passed, uncounted as
    the filter itself would. Error frames pass (LOOP-4)."""

    def __init__(self, bus: can.BusABC, filters: Iterable[dict[str, Any]],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.bus, self.clock = bus, clock
        self.ids = frozenset(f["can_id"] for f in filters)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Pass the frame on to the bus (the filter is on the receive side)."""
        self.bus.send(msg, timeout=timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame within ``timeout`` that the filter passes (error frames
        always do), or None."""
        end = None if timeout is None else self.clock() + timeout
        while True:
            msg = self.bus.recv(timeout=None if end is None else max(0.0, end - self.clock()))
            if (msg is None or msg.is_error_frame
                    or (not msg.is_extended_id and msg.arbitration_id in self.ids)):
                return msg


def behind_filter(bus: can.BusABC, kw: dict[str, Any]) -> RxTxBus:
    """What the node reads: ``bus``, behind its acceptance filter's gap when it has one."""
    return AcceptanceBus(bus, kw["can_filters"]) if kw.get("can_filters") else bus


class StopFlag:
    """Set by SIGINT/SIGTERM (or by a test) to end the loop cleanly."""

    def __init__(self) -> None:
        self._event = threading.Event()

    def set(self, *_: object) -> None:
        """Ask the loop to stop (also the SIGINT/SIGTERM handler: extra args ignored)."""
        self._event.set()

    def is_set(self) -> bool:
        """True once stop was asked for."""
        return self._event.is_set()

    def install_signal_handlers(self) -> None:
        """Make SIGINT and SIGTERM set this flag (a clean stop, not an exception)."""
        signal.signal(signal.SIGINT, self.set)
        signal.signal(signal.SIGTERM, self.set)


DRAIN_MAX = 256  # frames read per tick when late: bounded, so a flood cannot stop the ticks

# What a bus can hand up instead of a frame, counted by the node under these causes:
RX_CAUSES = (
    "not_a_frame",    # bytes python-can cannot read as a message (udp_multicast: any datagram)
    "invalid_frame",  # a message no CAN bus carries: ID beyond 11/29 bits, DLC > 8 on a
                      # classic frame, data longer than its DLC, fields of the wrong type
    "rx_error",       # the receive itself failed (socket error, interface down)
)
RX_LOG_FIRST = 5  # receive failures logged in full per cause, then every 1000th


def rx_cause(e: BaseException) -> str:
    """The RX_CAUSES entry of an exception raised by a python-can ``recv``.

    udp_multicast unpacks each datagram with msgpack into ``can.Message(check=True)``
    and raises CanOperationError from what failed: an error raised inside can.Message
    (its check, or a field of the wrong type) is an impossible frame; any other (msgpack's,
    or arguments that are not a message's) means the bytes are no message at all. A
    socket's error (python-can raises CanOperationError from the OSError) is ``rx_error``."""
    inner = e.__cause__
    if inner is None or not isinstance(e, can.CanOperationError) or isinstance(inner, OSError):
        return "rx_error"
    tb = inner.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_filename == _MESSAGE_PY:
            return "invalid_frame"
        tb = tb.tb_next
    return "not_a_frame"


_MESSAGE_PY = can.message.__file__


def frame_fault(msg: can.Message) -> str | None:
    """Why ``msg`` cannot be a CAN frame, or None. python-can checks ranges, not types:
    a float ID or a string flag in a udp_multicast datagram passes its check and would
    break whatever formats or indexes with it."""
    fid, data = msg.arbitration_id, msg.data
    if type(fid) is not int or type(msg.dlc) is not int or not isinstance(data, (bytes,
                                                                              bytearray)):
        return f"expected an int ID and DLC and bytes, but got {type(fid).__name__}, " \
               f"{type(msg.dlc).__name__} and {type(data).__name__}"
    flags = (msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame, msg.is_fd)
    if not all(type(f) is bool for f in flags):
        return f"expected boolean frame flags, but got {[type(f).__name__ for f in flags]}"
    limit = 0x1FFFFFFF if msg.is_extended_id else 0x7FF
    if not msg.is_error_frame and not 0 <= fid <= limit:  # an error frame's ID: its class
        return f"expected an ID in 0..0x{limit:X}, but got {fid:#x}"
    if len(data) > (64 if msg.is_fd else 8):
        return f"expected at most {64 if msg.is_fd else 8} data bytes, but got {len(data)}"
    return None


class GuardedBus:
    """The bus as a node reads it: nothing it delivers ends the node. What python-can
    raises from ``recv`` instead of a message, and messages whose fields no CAN frame
    has (``frame_fault``), are counted through ``note(cause)`` under RX_CAUSES and
    reading goes on within the same timeout, so the node keeps its schedule. A failing
    receive (``rx_error``) waits out the rest of the timeout (at most ERROR_PAUSE_S)
    instead of spinning on an interface that keeps failing."""

    ERROR_PAUSE_S = 0.01
    BURST_MAX = DRAIN_MAX  # bad datagrams read per call: recv(timeout=0) stays bounded

    def __init__(self, bus: RxTxBus, note: Callable[[str], None],
                 clock: Callable[[], float] = time.monotonic, who: str = "node",
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.bus, self.note, self.clock, self.who, self.sleep = bus, note, clock, who, sleep
        self.counters: dict[str, int] = dict.fromkeys(RX_CAUSES, 0)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Pass the frame on to the bus (send failures are the loop's to count)."""
        self.bus.send(msg, timeout=timeout)

    def _count(self, cause: str, reason: str) -> None:
        self.counters[cause] += 1
        self.note(cause)
        n = self.counters[cause]
        if n <= RX_LOG_FIRST or n % 1000 == 0:
            log.warning("%s dropped a bus input (%s #%d): %s", self.who, cause, n, reason)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next valid frame within ``timeout``, or None; what the bus raises or
        delivers instead of a frame is counted by cause and skipped."""
        end = None if timeout is None else self.clock() + timeout
        for _ in range(self.BURST_MAX):
            left = None if end is None else max(0.0, end - self.clock())
            try:
                msg = self.bus.recv(timeout=left)
            except (can.CanError, OSError) as e:
                cause = rx_cause(e)
                self._count(cause, f"{e}" + (f": {e.__cause__}" if e.__cause__ else ""))
                if cause == "rx_error":
                    self.sleep(min(self.ERROR_PAUSE_S, left if left is not None else
                                   self.ERROR_PAUSE_S))
                    return None
            else:
                if msg is None:
                    return None
                fault = frame_fault(msg)
                if fault is None:
                    return msg
                self._count("invalid_frame", fault)
            if end is not None and self.clock() >= end and timeout != 0:
                return None
        return None


def _deliver(nodes: Sequence[Node], msg: can.Message, clock: Callable[[], float]) -> None:
    """Hand ``msg`` to each node in turn, each at the clock of its own delivery, as each
    node's own socket would have delivered it."""
    for node in nodes:
        if msg.is_error_frame:  # a bus event (socketcan error class), not data
            node.note("error_frame")
        else:
            node.on_frame(msg, clock())


def spread_phases(k: int, span: float) -> list[float]:
    """The starts of ``k`` nodes of one host spread evenly over ``span`` seconds (a sync
    period, AUTH-9): each ticks at its own instant within Ts, and each sends its syncs
    at its own tick, as k separate nodes started one after the other would, instead of
    k ticks in a row at every release (the k-th up to k ticks late) and k nodes' syncs
    in one burst each second that every receiver on the bus must take at once."""
    return [i * span / k for i in range(k)]


def _started(nodes: Sequence[Node], waiting: set[int]) -> Sequence[Node]:
    """``nodes`` but those whose first release is still to come (they are not on yet)."""
    return nodes if not waiting else [n for n in nodes if id(n) not in waiting]


def freeze_startup_objects() -> None:
    """In a node's process, before its loop: move everything allocated so far (the DBC,
    keys, configs: long-lived) out of the collector's reach. A full collection over it
    takes ~0.1 s, which the loop would take as a burst of deadline misses (measured: 125
    ms, 16 agents of a host late at once); what the loop allocates is collected as
    usual."""
    gc.collect()
    gc.freeze()


def _send(node: Node, frames: Iterable[can.Message], bus: RxTxBus, period: float) -> None:
    for frame in frames:
        try:
            bus.send(frame, timeout=period)
        except can.CanError as e:
            node.note("send_failure")
            log.warning("send failed for 0x%03X: %s", frame.arbitration_id, e)


def run_node(node: Node, bus: RxTxBus, *, duration: float | None = None,
             stop: StopFlag | None = None, clock: Callable[[], float] = time.monotonic,
             on_tick: Callable[[float], None] | None = None, phase: float = 0.0) -> None:
    """Drive ``node`` on ``bus`` until ``duration`` elapses or ``stop`` is set, its first
    release ``phase`` seconds after the start.

    Send failures (bus buffer full, interface down) are counted by the node
    (``note("send_failure")``) and logged; they never end the loop.
    """
    run_nodes([node], bus, duration=duration, stop=stop, clock=clock, on_tick=on_tick,
              phases=[phase])


class NodesOnOneBus(BessDedError, ValueError):
    """Nodes that cannot share one loop (none, or periods that differ)."""


def run_nodes(nodes: Sequence[Node], bus: RxTxBus, *, duration: float | None = None,
              stop: StopFlag | None = None, clock: Callable[[], float] = time.monotonic,
              on_tick: Callable[[float], None] | None = None,
              route: Callable[[can.Message], Sequence[Node]] | None = None,
              phases: Sequence[float] | None = None) -> None:
    """Drive several nodes of one period on one loop and one ``bus`` (a multi-agent host:
    one process, one socket, instead of one of each per node). Every frame read goes to
    every node; every release ticks them one after the other, each at the clock of its
    own turn, and sends its frames at once (its echo comes back like any frame).

    Each node keeps its own release and deadline accounting, exactly ``run_node``'s: a
    node whose turn comes more than Ts/2 after its release (delayed by its own overrun
    or by the nodes before it) counts 1 + floor(late/Ts) misses and skips the periods
    it missed; it rejoins the others at a later release (each release is its own running
    binary64 sum, as LOOP-1 says: one an ulp behind the others ticks at the next pass).
    A bus input that is not a frame is counted by every node (each socket read it).
    ``route(msg)``: the nodes a frame is handed to (default: all; firmware_py.host.Routes
    leaves out those it cannot affect). ``phases[i]``: node i's first release after the
    start (default: all at the start; ``spread_phases``: spread over a sync period, so
    that no node waits behind the others' ticks and syncs); a node hears nothing before
    it. ``run_node`` is this loop with one node."""
    nodes = list(nodes)
    if not nodes or any(n.period != nodes[0].period for n in nodes):
        raise NodesOnOneBus(f"one loop drives nodes of one period, but got periods "
                            f"{[n.period for n in nodes]}")
    stop = stop or StopFlag()
    if not isinstance(bus, GuardedBus):
        def note_all(cause: str) -> None:  # each node's socket would have read it
            for n in nodes:
                n.note(cause)
        bus = GuardedBus(bus, note_all, clock)
    period = nodes[0].period
    start = clock()
    phases = [0.0] * len(nodes) if phases is None else list(phases)
    if len(phases) != len(nodes) or any(not 0.0 <= p for p in phases):
        raise NodesOnOneBus(f"expected a phase >= 0 per node, but got {phases}")
    releases = [start + p for p in phases]
    # a node hears the bus from its own start (its first release) on
    waiting = {id(n) for n, r in zip(nodes, releases, strict=True) if r > start}
    while not stop.is_set():
        now = clock()
        if duration is not None and now - start >= duration:
            break
        release = min(releases)
        if now < release:
            msg = bus.recv(timeout=min(release - now, 0.05))
            if msg is not None:
                _deliver(_started(nodes if route is None else route(msg), waiting),
                         msg, clock)
            continue
        # Take what is already queued before ticking: a node whose ticks overrun Ts
        # would otherwise never get back to the branch above and never read its inputs.
        # In a host, what is queued only for nodes not due now is theirs after the due
        # ones have ticked (it is not the ticking nodes' input, and a burst of the
        # others' frames, such as a plant's syncs, would hold every tick behind it).
        due = {id(n) for n, r in zip(nodes, releases, strict=True) if r <= now}
        later: list[tuple[list[Node], can.Message]] = []
        for _ in range(DRAIN_MAX):
            msg = bus.recv(timeout=0)
            if msg is None:
                break
            targets = _started(nodes if route is None else route(msg), waiting)
            if len(due) == len(nodes):
                _deliver(targets, msg, clock)
                continue
            _deliver([n for n in targets if id(n) in due], msg, clock)
            rest = [n for n in targets if id(n) not in due]
            if rest:
                later.append((rest, msg))
        for i, node in enumerate(nodes):  # those starting now hear from here on
            if releases[i] <= now:
                waiting.discard(id(node))
        first = True
        for i, node in enumerate(nodes):
            if releases[i] > now:
                continue  # not yet released (a later phase, or it skipped ahead)
            t = now if first else clock()
            first = False
            late = t - releases[i]
            if late > period / 2:
                skipped = int(late // period)
                node.note("deadline_miss", 1 + skipped)
                releases[i] += skipped * period
            _send(node, node.tick(t), bus, period)
            releases[i] += period
        for rest, msg in later:
            _deliver(rest, msg, clock)
        if on_tick is not None:
            on_tick(now - start)
