"""``Tester``: send and expect frames by message and signal name, as any node of a fleet.

Transmit goes through ``firmware_py.nodeio.FleetSender`` (the codec's layout, the SecOC
freshness and MAC with the node's key, and the ``<name>_Sync`` frames a receiver needs
first); receive through ``FrameCodec.decode`` (DLC, ranges) and the recorder's SecOC
monitor (``sim.run.buslog``: MAC and freshness with the fleet's keys). A frame that
fails a check is never returned, but counted in ``Tester.rejected`` by cause (and by
ID), and named in the timeout error of ``expect``.

Bus time: ``Tester.now()``. On a real bus (any python-can interface) it is the wall
clock, in seconds since the tester was made; on a fleet run in-process on a simulated
clock (``SimFleet``) it is the simulated time, and waiting steps the fleet.

Over 500 lines: the Tester is one public class (send, expect, wait, bus time),
documented as a unit in docs/testing.md; its helpers are private to it.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

import can

from firmware_py import contract, secoc
from firmware_py.errors import BessDedError, FrameError
from firmware_py.frames import DecodedFrame, FrameCodec, agent_of, diag_name, format_fault
from firmware_py.node import RX_CAUSES, GuardedBus, frame_fault, rx_cause
from firmware_py.nodeio import SYNC_S, FleetSender
from sim.run.monitor import Forged, Monitor

__all__ = ["ExpectationError", "Periodic", "Received", "Tester", "TesterError",
           "WallClock", "fleet_keys"]

INBOX_DEPTH = 4096   # frames kept per message name for expect (40 s of one MC stream)
ECHO_DEPTH = 16      # own frames remembered per ID to recognise their echo
_PROTECTION = ("Mac", "Counter")  # filled in by the sender; in ``raw`` only
POLL_S = 0.02        # wall clock: how often a waiting expect looks at the clock


class TesterError(BessDedError, ValueError):
    """A misuse of the tester (an unknown message, signal or node): names what was
    expected and what was given."""

    __test__ = False  # not a test class for pytest, whatever the module importing it

    def __init__(self, what: str, expected: str, got: object) -> None:
        super().__init__(f"{what}: expected {expected}, but got {got!r}")


class ExpectationError(AssertionError):
    """An expectation on the bus did not hold (a timeout, an unwanted frame)."""


# ---------------------------------------------------------------------------- clocks


class Clock(Protocol):
    """The bus time a Tester runs on: a simulated fleet's, or the wall clock."""

    def now(self) -> float:
        """The bus time now (s)."""

    def wait(self, tester: Tester, dt: float) -> None:
        """Let up to ``dt`` of bus time pass (at least a little), delivering frames."""

    def every(self, period: float, fn: Callable[[float], None]) -> Callable[[], None]:
        """Call ``fn(t)`` every ``period`` of bus time from now; returns a stop function."""


class WallClock:
    """Bus time on a real bus: the wall clock (monotonic), from when it was made."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def now(self) -> float:
        """Seconds since this clock was made (monotonic)."""
        return time.monotonic() - self._t0

    def wait(self, tester: Tester, dt: float) -> None:
        """Wait up to ``dt`` (at most POLL_S) or until the tester hears a frame."""
        tester.wait_for_input(min(dt, POLL_S))

    def every(self, period: float, fn: Callable[[float], None]) -> Callable[[], None]:
        """Call ``fn(t)`` every ``period`` s from a thread; returns a stop function."""
        stop = threading.Event()

        def loop() -> None:
            due = self.now()
            while not stop.is_set():
                fn(self.now())
                due += period
                delay = due - self.now()
                if delay < -period:  # starved: skip the missed periods, do not burst
                    due = self.now()
                    delay = 0.0
                stop.wait(max(0.0, delay))

        th = threading.Thread(target=loop, name="bess-testkit-periodic", daemon=True)
        th.start()

        def halt() -> None:
            stop.set()
            th.join(timeout=5.0)

        return halt


# ---------------------------------------------------------------------------- frames


@dataclass(frozen=True)
class Received:
    """One received frame that passed every check.

    ``signals``: physical values (enum signals as numbers; ``label(name)`` gives the
    DBC's choice name), Mac and Counter left out; ``raw``: the raw integers, those
    included; ``t``:
    bus time of its reception; ``msg``: the python-can message as received."""

    name: str
    signals: dict[str, float]
    raw: dict[str, int]
    t: float
    msg: can.Message = field(repr=False)
    frame: DecodedFrame = field(repr=False)
    seq: int = field(repr=False, default=0)

    def __getitem__(self, signal: str) -> float:
        return self.frame.phys(signal)

    def label(self, signal: str) -> str | None:
        """The DBC choice name of an enum signal's value (State → "RUNNING"), else None."""
        self.frame.phys(signal)  # names the signals of the frame if unknown
        return self.frame.label(signal)


Where = Mapping[str, Any] | Callable[[Received], bool] | None
Since = Literal["call", "mark"] | float   # expect's window


def fleet_keys(master: bytes, n: int | None = None) -> dict[str, bytes]:
    """Every node key of a fleet master key (label → key) and every link frame key
    (message name → key, AUTH-28), for up to ``n`` agents."""
    from firmware_py.frames import N_AGENTS_MAX
    from sim.run.keyset import derived_keys

    return derived_keys(master, n or N_AGENTS_MAX)


def _resolve_keys(keys: Any) -> dict[str, bytes] | None:
    """A key set directory (``bess-ded keys``), a ``KeySet``, a label → key mapping, or
    None (the public --insecure keys)."""
    if keys is None:
        return None
    if hasattr(keys, "node_keys"):
        return dict(keys.node_keys())
    if isinstance(keys, str | Path):
        from sim.run.keyset import load_key_set

        path = Path(keys)
        if not path.is_dir():
            raise TesterError("keys", "a key set directory (bess-ded keys --fleet ... --out "
                              "DIR)", str(path))
        got = load_key_set(path)
        if not got:
            raise TesterError("keys", f"a key set directory with <node>.key files in {path}",
                              "no key file")
        return got
    if isinstance(keys, Mapping):
        return dict(keys)
    raise TesterError("keys", "a key set directory, a KeySet, a {node: key} mapping or "
                      "None (insecure)", type(keys).__name__)


def node_label(node: str | int) -> str:
    """``3`` or ``"agent_3"`` → ``"agent_3"``; ``"plant"``, ``"router"`` as they are."""
    if isinstance(node, int) and not isinstance(node, bool):
        return f"agent_{node}"
    if isinstance(node, str):
        if node.isdigit():
            return f"agent_{int(node)}"
        if node in ("plant", "router") or (node.startswith("agent_")
                                           and node[6:].isdigit()):
            return node
    raise TesterError("node", "an agent number, 'agent_<i>', 'plant' or 'router'", node)


# ---------------------------------------------------------------------------- the tester


class Periodic:
    """A message sent every ``period`` by ``Tester.send_periodic``: ``update`` its
    signals (values or callables of the bus time since it started), ``stop`` it."""

    def __init__(self, tester: Tester, name: str, signals: Mapping[str, Any],
                 period: float, as_node: str | int | None) -> None:
        self._tester, self.name, self.period, self.as_node = tester, name, period, as_node
        self._signals = dict(signals)
        self._lock = threading.Lock()
        self.sent = 0
        self.error: BaseException | None = None
        self.t_start = tester.now()
        tester._check_signals(name, self._values(0.0))  # fail now, not in a thread
        self._halt = tester._clock.every(period, self._fire)
        self._stopped = False

    def _values(self, t: float) -> dict[str, Any]:
        with self._lock:
            sig = dict(self._signals)
        return {k: (v(t) if callable(v) else v) for k, v in sig.items()}

    def _fire(self, t: float) -> None:
        if self.error is not None:
            return
        try:
            self._tester._send(self.name, self._values(t - self.t_start), self.as_node,
                               mark=False)
            self.sent += 1
        except BaseException as e:  # reported by stop() and the tester's close()
            self.error = e

    def update(self, signals: Mapping[str, Any] | None = None, **more: Any) -> None:
        """Change some of the signals sent from the next frame on (checked now)."""
        new = {**(signals or {}), **more}
        with self._lock:
            merged = {**self._signals, **new}
        self._tester._check_signals(self.name, {k: (v(0.0) if callable(v) else v)
                                                for k, v in merged.items()})
        with self._lock:
            self._signals = merged

    def stop(self) -> None:
        """Stop sending; raises TesterError if a send failed meanwhile."""
        if not self._stopped:
            self._stopped = True
            self._halt()
        if self.error is not None:
            raise TesterError(f"send_periodic({self.name})", "every frame sent",
                              str(self.error)) from self.error


class Tester:
    """Sends and expects frames on ``bus`` by message and signal name.

    ``keys``: the fleet's keys (a ``bess-ded keys`` directory, a ``KeySet``, a label →
    key mapping; None: the public ``--insecure`` keys). ``as_node``: the node the
    tester sends as by default ("router", "plant", "agent_<i>" or an agent number;
    None: each message's DBC sender). ``clock``: ``WallClock()`` (default, any real
    bus) or a ``SimFleet`` (its simulated clock). ``boot``: the SecOC boot counter the
    tester signs under (a receiver takes its syncs when above what it saw of that
    sender). The tester reads the bus from a thread of its own on the wall clock;
    ``close()`` stops it and every periodic message (not the bus)."""

    __test__ = False  # not a test class for pytest, whatever the module importing it

    def __init__(self, bus: can.BusABC, keys: Any = None, *, as_node: str | int | None = None,
                 clock: Clock | None = None, codec: FrameCodec | None = None,
                 boot: int = secoc.INSECURE_BOOT, sync_s: float = SYNC_S,
                 tag_receivers: Mapping[int, Sequence[str]] | None = None) -> None:
        self.bus = bus
        # on a tagged FD bus (AUTH-34), agent j → the receivers of its λ in slot order
        self.tag_receivers = dict(tag_receivers or {})
        self.codec = codec or FrameCodec()
        node_keys = _resolve_keys(keys)
        self.insecure = node_keys is None
        if node_keys is None:
            node_keys = fleet_keys(secoc.INSECURE_MASTER)
        self.keys = node_keys
        self.as_node = None if as_node is None else node_label(as_node)
        self._boot = boot
        self._senders: dict[str, FleetSender] = {}  # signing identity -> its sequences
        self._monitor = Monitor(node_keys)
        self._clock: Clock = clock or WallClock()
        self.sync_s = sync_s
        self._cond = threading.Condition()
        self._tx_lock = threading.Lock()
        self._seq = 0
        self._mark = 0                              # since="mark": after send/mark/sleep
        self._reply_from: int | None = None         # a send() no expect has followed yet
        self._consumed: dict[str, int] = {}         # per message: the last one expect returned
        self._inbox: dict[str, deque[Received]] = {}
        self._echo: dict[int, deque[bytes]] = {}
        self._synced: dict[tuple[str, int], float] = {}  # (identity, ID) -> its last sync
        self.rejected: Counter[str] = Counter()     # cause -> frames
        self.rejected_by_id: dict[int, Counter[str]] = {}
        self.last_rejection: dict[str, str] = {}    # cause -> its last reason
        self._rejections: dict[int, deque[tuple[int, str]]] = {}  # ID -> (seq, cause)
        self.received: Counter[str] = Counter()     # message -> frames that passed
        self.sent: Counter[str] = Counter()
        self._periodic: list[Periodic] = []
        self._closed = False
        self._notifier: can.Notifier | None = None
        attach = getattr(self._clock, "attach", None)
        if attach is not None:
            attach(self)  # a simulated clock delivers the frames itself
        else:
            from sim.run.busopts import RECORDER_RCVBUF, enlarge_receive_buffer

            # as the recorder's: a starved reader finds the frames queued, not dropped (a
            # gap of 8 freshness windows on one ID would read as a forgery until its sync)
            enlarge_receive_buffer(bus, RECORDER_RCVBUF)
            self._notifier = can.Notifier(bus, [self._listener()], timeout=0.05)

    # ------------------------------------------------------------ plumbing

    def now(self) -> float:
        """Bus time (s): wall time since the tester started, or the simulated time."""
        return self._clock.now()

    def _listener(self) -> can.Listener:
        tester = self

        class _L(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                tester.on_frame(msg)

            def on_error(self, exc: Exception) -> None:  # keep reading: count it by cause
                tester.on_error(exc)

        return _L()

    def on_error(self, exc: Exception) -> None:
        """Count a receive error of the bus (python-can's, a listener's ``on_error``) by
        its cause (node.RX_CAUSES), as a node counts it, and go on reading."""
        self._bus_input(rx_cause(exc), f"{exc}: {exc.__cause__}")

    def wait_for_input(self, timeout: float) -> None:
        """Block up to ``timeout`` s or until the tester hears a frame or another bus
        input (a real-time Clock's ``wait``)."""
        with self._cond:
            self._cond.wait(max(0.0, timeout))

    def _bus_input(self, cause: str, reason: str) -> None:
        """Something the bus delivered that is not a frame (node.RX_CAUSES): counted."""
        with self._cond:
            self.rejected[cause] += 1
            self.last_rejection[cause] = reason
            self._cond.notify_all()

    def pump(self) -> None:
        """Read what the bus holds now (the simulated clock calls it after each step)."""
        bus = GuardedBus(self.bus, lambda cause: self._bus_input(cause, "a bus input that "
                         "is not a frame (logged)"), who="tester")
        while (msg := bus.recv(timeout=0)) is not None:
            self.on_frame(msg)

    def on_frame(self, msg: can.Message) -> None:
        """Check one received frame: keep it for ``expect`` or count its rejection."""
        if (fault := frame_fault(msg)) is not None:  # e.g. a float ID: not even a frame
            self._bus_input("invalid_frame", fault)
            return
        fid = msg.arbitration_id
        data = bytes(msg.data)
        with self._cond:
            echo = self._echo.get(fid)
            if echo is not None and data in echo:
                echo.remove(data)
                return  # our own frame, echoed back (udp_multicast always echoes)
            if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame \
                    or msg.is_fd != self.codec.fd:
                self._reject(fid, "malformed", f"0x{fid:X}: expected an 11-bit data frame of "
                             f"the bus's format ({format_fault(msg, self.codec.fd)})")
                return
            try:
                f = self.codec.decode(msg)
            except FrameError as e:
                self._reject(fid, getattr(e, "cause", "malformed"), str(e))
                return
            kind = self.codec.kind(fid)
            try:
                if kind == "sync":
                    self._monitor.sync(f, msg.data)
                elif kind == "secured" and not self._monitor.check(f, msg.data):
                    self._reject(fid, "unsynced", f"{f.name}: no verified "
                                 f"{f.name}_Sync of {contract.sender_of(f.name)} heard yet")
                    return
            except Forged:
                self._reject(fid, "auth", f"{f.name}: expected a MAC that verifies with "
                             f"{contract.sender_of(f.name.removesuffix('_Sync'))}'s key "
                             "and a fresh freshness value, but it does not (forged, "
                             "replayed or corrupted)")
                return
            self._seq += 1
            scaled = {k: f.phys(k) for k in f.raw if k not in _PROTECTION}
            rec = Received(f.name, scaled, dict(f.raw), self._clock.now(), msg, f, self._seq)
            box = self._inbox.get(f.name)
            if box is None:
                box = self._inbox[f.name] = deque(maxlen=INBOX_DEPTH)
            box.append(rec)
            self.received[f.name] += 1
            self._cond.notify_all()

    def _reject(self, fid: int, cause: str, reason: str) -> None:
        self.rejected[cause] += 1
        self.rejected_by_id.setdefault(fid, Counter())[cause] += 1
        log = self._rejections.get(fid)
        if log is None:
            log = self._rejections[fid] = deque(maxlen=INBOX_DEPTH)
        log.append((self._seq, cause))  # after frame number _seq: for expect's report
        self.last_rejection[cause] = reason
        self._cond.notify_all()

    # ------------------------------------------------------------ transmit

    def _message(self, name: Any) -> str:
        if not isinstance(name, str):
            raise TesterError("message", "a message name of the DBC", name)
        try:
            self.codec.frame_id(name)
        except BessDedError as e:
            raise TesterError("message", str(e).split("expected ", 1)[-1].split(", but")[0],
                              name) from None
        return name

    def signal_names(self, name: str) -> list[str]:
        """The signals ``send`` takes for ``name`` (the DBC's, minus Mac and Counter)."""
        msg = self.codec.database.get_message_by_name(self._message(name))
        return [s.name for s in msg.signals if s.name not in _PROTECTION]

    def _check_signals(self, name: str, signals: Mapping[str, Any]) -> None:
        self._message(name)
        known = self.signal_names(name)
        unknown = [s for s in signals if s not in known]
        if unknown:
            protected = [s for s in unknown if s in _PROTECTION]
            hint = (f" ({', '.join(protected)}: filled in by the tester)" if protected else "")
            raise TesterError(f"{name} signals", f"signals among {', '.join(known)}{hint}",
                              sorted(unknown))
        self.codec.encode_phys(name, signals, 0)  # ranges, missing signals, choice names

    def _label_for(self, name: str, as_node: str | int | None) -> str:
        sender = contract.sender_of(name.removesuffix("_Sync"))
        node = self.as_node if as_node is None else node_label(as_node)
        return sender if node is None else node

    def _send(self, name: str, signals: Mapping[str, Any], as_node: str | int | None,
              mark: bool) -> can.Message:
        name = self._message(name)
        label = self._label_for(name, as_node)
        if label not in self.keys:
            raise TesterError("as_node", f"a node whose key the tester holds "
                              f"({', '.join(sorted(self.keys))})", label)
        fid = self.codec.frame_id(name)
        self._check_signals(name, signals)
        with self._tx_lock:
            sender = contract.sender_of(name.removesuffix("_Sync"))
            # one FleetSender per identity: as the DBC's sender, the genuine sequence;
            # as another node, that node's key and a freshness sequence of its own (a
            # forgery the receivers must reject, which leaves the genuine one intact)
            fs = self._senders.get(label)
            if fs is None:
                fs = self._senders[label] = FleetSender(self.codec, {}, boot=self._boot,
                                                        tag_receivers=self.tag_receivers)
            base = name.removesuffix("_Sync")
            if base in contract.KEYED_FRAMES:  # AUTH-28, AUTH-29: its own key, held by its parties
                own = self.keys.get(base) if label == sender else None
                fs.keys[base] = own if own is not None else self.keys[label]
            else:
                fs.keys[sender] = self.keys[label]
            for r in self.tag_receivers.get(agent_of(fid) or 0, ()):  # AUTH-34: as itself,
                pair = secoc.pair_label(sender, r)                    # its pair keys
                key = self.keys.get(pair) if label == sender else self.keys[label]
                if key is not None:
                    fs.keys[pair] = key
            if name == contract.COMMAND:  # AUTH-30: its target's command key, the router's
                cname = contract.command_key_name(int(signals["Target"]))
                own = self.keys.get(cname) if label == sender else None
                fs.keys[cname] = own if own is not None else self.keys[label]
            out: list[can.Message] = []
            t = self.now()
            if fid in contract.SECURED_IDS:
                last = self._synced.get((label, fid))
                if last is None or t - last >= self.sync_s:
                    out.append(fs.sync(name))
                    self._synced[(label, fid)] = t
            out.append(fs.frame(name, signals, phys=True))
            for m in out:
                m.timestamp = t
                with self._cond:
                    self._echo.setdefault(m.arbitration_id,
                                          deque(maxlen=ECHO_DEPTH)).append(bytes(m.data))
                self.bus.send(m)
            self.sent[name] += 1
        if mark:
            with self._cond:
                self._mark = self._seq
                if self._reply_from is None:
                    self._reply_from = self._seq
        return out[-1]

    def send(self, message: str, signals: Mapping[str, Any] | None = None, *,
             as_node: str | int | None = None, **more: Any) -> can.Message:
        """Send ``message`` once with physical signal values (enum signals also by their
        choice name: ``Command="ISOLATE"``); every signal but Mac and Counter, which the
        tester fills in (the frame's freshness and MAC with ``as_node``'s key, after its
        ``<message>_Sync`` when due).
        A frame received after it counts for the next ``expect`` (a reply to this frame
        is not lost to the time between the two calls). Returns the frame."""
        return self._send(message, {**(signals or {}), **more}, as_node, mark=True)

    def send_periodic(self, message: str, signals: Mapping[str, Any] | None = None,
                      period_s: float | None = None, *, as_node: str | int | None = None,
                      **more: Any) -> Periodic:
        """Send ``message`` every ``period_s`` of bus time (default: its DBC cycle) until
        ``.stop()``. A signal's value may be a callable of the bus time since the start
        (a ramp: ``Rho=lambda t: 0.8 + 0.01 * t``); ``.update(**signals)`` changes them."""
        self._message(message)
        if period_s is None:
            if not contract.is_cyclic(message):
                raise TesterError("period_s", f"a period for {message} (an event message: "
                                  "the DBC gives it no cycle time)", None)
            period_s = contract.cycle_ms(message) / 1000.0
        if not (isinstance(period_s, int | float) and math.isfinite(period_s)
                and period_s > 0):
            raise TesterError("period_s", "a period > 0 s", period_s)
        p = Periodic(self, message, {**(signals or {}), **more}, float(period_s), as_node)
        self._periodic.append(p)
        return p

    # ------------------------------------------------------------ receive

    def mark(self) -> None:
        """From now on, ``expect(..., since="mark")`` looks only at frames received after
        this call."""
        with self._cond:
            self._mark = self._seq

    def _matcher(self, name: str, where: Where) -> Callable[[Received], bool]:
        if where is None:
            return lambda r: True
        if callable(where):
            return where  # type: ignore[return-value]
        if not isinstance(where, Mapping):
            raise TesterError("where", "None, {signal: value or predicate} or a predicate "
                              "of the received frame", where)
        known = [s.name for s in self.codec.database.get_message_by_name(name).signals]
        unknown = [s for s in where if s not in known]
        if unknown:
            raise TesterError(f"{name} where", f"signals among {', '.join(known)}",
                              sorted(unknown))
        conds = dict(where)
        half_step = {sig: self.codec.scale(name, sig) / 2 for sig in conds}

        def match(r: Received) -> bool:
            for sig, want in conds.items():
                if sig not in r.raw:   # another page of a multiplexed frame
                    return False
                if callable(want):
                    if not want(r.frame.phys(sig)):
                        return False
                elif isinstance(want, str):
                    if r.frame.label(sig) != want:
                        return False
                elif abs(r.frame.phys(sig) - want) > half_step[sig]:
                    return False  # a number: the value as encoded (half a raw step)
            return True

        return match

    def _find(self, name: str, after: int, match: Callable[[Received], bool]
              ) -> Received | None:
        for r in self._inbox.get(name, ()):
            if r.seq > after and match(r):
                return r
        return None

    def expect(self, message: str, timeout_s: float = 1.0, where: Where = None, *,
               since: Since = "call") -> Received:
        """The first ``message`` frame that passed every check, was received in the
        window ``since`` says, and matches ``where`` ({signal: value}: a number matches
        the physical value as encoded, within half a raw step (``Rho=0.8``), a string the
        choice name, a callable is a predicate of the physical value; or a predicate of
        the ``Received`` frame), within ``timeout_s`` of bus time; else ExpectationError
        (with what was received and rejected).

        ``since``: ``"call"`` (default, as cantools' Tester): a frame received after this
        call, never one buffered before it; or after the tester's last ``send`` if no
        ``expect`` came between them (the reply to what it just sent).
        ``"mark"``: after the last ``send``, ``mark`` or ``sleep``, buffered frames
        included. Both also after the frame the previous ``expect`` of this message
        returned. A number: any frame received after that bus time."""
        self._message(message)
        if not (since in ("call", "mark") or (isinstance(since, int | float)
                                             and not isinstance(since, bool))):
            raise TesterError("since", "'call', 'mark' or a bus time in s", since)
        with self._cond:
            start = self._call_start(since)
        match = self._matcher(message, where)
        t_start = self.now()
        deadline = t_start + timeout_s
        fid = self.codec.frame_id(message)
        ids = [fid]  # its sync too: a sync that fails leaves the frames unsynced
        if fid in contract.SYNC_OF:
            ids.append(contract.SYNC_OF[fid])
        with self._cond:
            window = self._after(message, since, start)  # frames and rejections after it
        while True:
            with self._cond:
                after = self._after(message, since, start)
                r = self._find(message, after, match)
                if r is not None:
                    self._consumed[message] = r.seq
                    self._reply_from = None
                    return r
            if self.now() >= deadline:
                break
            self._clock.wait(self, deadline - self.now())
        with self._cond:
            rejs = {i: Counter(c for s, c in self._rejections.get(i, ()) if s >= window)
                    for i in ids}
            seen = sum(1 for r in self._inbox.get(message, ()) if r.seq > window)
            last = next((r for r in reversed(self._inbox.get(message, ()))
                         if r.seq > window), None)
        cond = "" if where is None else f" with {_describe(where)}"
        window_is = {"call": "after the call, or the send before it",
                     "mark": "after the last send, mark, sleep or match"}.get(
                         str(since), f"after t = {since}")
        detail = f"{seen} {message} frame(s) passed the checks in its window ({window_is})"
        if last is not None:
            detail += f", the last: {_signals_text(last)}"
        for i, bad in rejs.items():
            if bad:
                detail += (f"; {sum(bad.values())} frame(s) of 0x{i:03X} "
                           f"({self.codec.name_of(i)}) rejected ("
                           + ", ".join(f"{k}: {v}" for k, v in sorted(bad.items())) + ")")
        if any(rejs.values()) and "unsynced" in self.last_rejection and self.rejected["auth"]:
            detail += " (are the tester's keys the fleet's?)"
        for cause in RX_CAUSES:
            if cause in self.last_rejection:
                detail += (f"; {self.rejected[cause]} bus input(s) that are no frame "
                           f"({cause}), the last: {self.last_rejection[cause]}")
        raise ExpectationError(f"expected {message}{cond} within {timeout_s:g} s of bus time "
                               f"(t = {t_start:.3f} → {deadline:.3f} s), but got none: "
                               f"{detail}")

    def _call_start(self, since: Since) -> int:
        """The frame count an expect's window starts after, fixed when it is called."""
        if since == "call":
            return self._seq if self._reply_from is None else self._reply_from
        return self._mark

    def _after(self, message: str, since: Since, start: int) -> int:
        consumed = self._consumed.get(message, 0)
        if isinstance(since, str):
            return max(start, consumed)
        return max((r.seq for r in self._inbox.get(message, ()) if r.t <= since), default=0)

    def collect(self, message: str, duration_s: float, where: Where = None) -> list[Received]:
        """Every ``message`` frame (matching ``where``) received during the next
        ``duration_s`` of bus time."""
        self._message(message)
        match = self._matcher(message, where)
        with self._cond:
            start = self._seq
        self.sleep(duration_s)
        with self._cond:
            return [r for r in self._inbox.get(message, ()) if r.seq > start and match(r)]

    def expect_none(self, message: str, duration_s: float, where: Where = None) -> None:
        """No ``message`` frame (matching ``where``) passes the checks during the next
        ``duration_s`` of bus time (frames that fail them are counted, not taken)."""
        got = self.collect(message, duration_s, where)
        if got:
            cond = "" if where is None else f" with {_describe(where)}"
            raise ExpectationError(f"expected no {message}{cond} for {duration_s:g} s of bus "
                                   f"time, but got {len(got)}, the first at t = "
                                   f"{got[0].t:.3f} s: {_signals_text(got[0])}")

    def sleep(self, duration_s: float) -> None:
        """Let ``duration_s`` of bus time pass (on the simulated clock: step the fleet);
        ``expect`` then looks at frames received after it."""
        end = self.now() + duration_s
        while (left := end - self.now()) > 1e-12:
            self._clock.wait(self, left)
        self.mark()  # what came before is old news for expect

    # ------------------------------------------------------------ diagnostics

    def diagnostics(self, node: str | int, timeout_s: float = 10.0) -> dict[str, int]:
        """Every counter of an agent's ``AGENT_<i>_Diag`` pages, from pages received from
        now on (one full round of pages; each page's newest value)."""
        label = node_label(node)
        if not label.startswith("agent_"):
            raise TesterError("diagnostics node", "an agent (the plant and the router "
                              "broadcast no Diag frame)", node)
        name = diag_name(int(label[6:]))
        msg = self.codec.database.get_message_by_name(name)
        pages = sorted({i for s in msg.signals for i in (s.multiplexer_ids or ())})
        mux = next(s.name for s in msg.signals if s.is_multiplexer)
        with self._cond:
            start = self._seq
        got: dict[int, dict[str, int]] = {}
        t_start = self.now()
        deadline = t_start + timeout_s
        while True:
            with self._cond:
                for r in self._inbox.get(name, ()):
                    if r.seq > start:
                        got[r.raw[mux]] = {k: v for k, v in r.raw.items()
                                           if k not in _PROTECTION and k != mux}
            if set(pages) <= set(got):
                break
            if self.now() >= deadline:
                fid = self.codec.frame_id(name)
                rej = self.rejected_by_id.get(fid, Counter())
                raise ExpectationError(
                    f"expected every page {pages} of {name} within {timeout_s:g} s of bus "
                    f"time, but got pages {sorted(got)}"
                    + (f"; rejected frames of 0x{fid:03X}: {dict(rej)}" if rej else ""))
            self._clock.wait(self, deadline - self.now())
        out: dict[str, int] = {}
        for p in pages:
            out.update(got[p])
        return out

    def assert_diagnostics(self, node: str | int, timeout_s: float = 10.0,
                           **expected: Any) -> dict[str, int]:
        """``diagnostics(node)`` with each named counter equal to a value or satisfying a
        predicate (``RejectedAuth=lambda n: n >= 1``). Returns the diagnostics."""
        diag = self.diagnostics(node, timeout_s)
        unknown = sorted(k for k in expected if k not in diag)
        if unknown:
            raise TesterError(f"{node_label(node)} diagnostics", "counters among "
                              + ", ".join(sorted(diag)), unknown)
        bad = {k: diag[k] for k, want in expected.items()
               if not (want(diag[k]) if callable(want) else diag[k] == want)}
        if bad:
            raise ExpectationError(
                f"{node_label(node)} diagnostics: expected "
                + ", ".join(f"{k} {_want_text(expected[k])}" for k in bad)
                + f", but got {', '.join(f'{k} = {v}' for k, v in bad.items())}")
        return diag

    # ------------------------------------------------------------ end

    def close(self) -> None:
        """Stop every periodic message and the reader thread (the bus stays open).
        A periodic message that failed raises here."""
        if self._closed:
            return
        self._closed = True
        errors = []
        for p in self._periodic:
            try:
                p.stop()
            except TesterError as e:
                errors.append(e)
        if self._notifier is not None:
            self._notifier.stop()
        detach = getattr(self._clock, "detach", None)
        if detach is not None:
            detach(self)
        if errors:
            raise errors[0]

    def __enter__(self) -> Tester:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def summary(self) -> str:
        """One line: frames sent, received and rejected (by cause)."""
        rej = ", ".join(f"{k}: {v}" for k, v in sorted(self.rejected.items())) or "none"
        return (f"sent {sum(self.sent.values())}, received {sum(self.received.values())}, "
                f"rejected {sum(self.rejected.values())} ({rej})")


def _describe(where: Where) -> str:
    if callable(where):
        return getattr(where, "__name__", "a predicate")
    assert where is not None
    return ", ".join(f"{k} {_want_text(v)}" for k, v in where.items())


def _want_text(want: Any) -> str:
    if callable(want):
        return f"satisfying {getattr(want, '__name__', 'a predicate')}"
    return f"== {want!r}"


def _signals_text(r: Received) -> str:
    parts: Iterable[str] = (f"{k}={r.label(k) or _num(v)}" for k, v in r.signals.items()
                            if k not in _PROTECTION)
    return f"{{{', '.join(parts)}}} at t = {r.t:.3f} s"


def _num(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)
