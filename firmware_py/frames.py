"""The firmware's frame codec: DBC-driven encode/decode with the secured frame layout.

Why a codec of its own rather than ``cantools`` ``Message.encode``/``decode`` per
frame: a node decodes every frame on the bus (a few thousand per second with 64
agents) in pure Python, and cantools' generic path costs tens of microseconds per
frame. The DBC is still the only source of the layout: on load
every message is compiled into flat per-ID tables (shift, mask, sign, raw
range), and the tests check the result byte for byte against cantools.

Contract (see ``dbc/bess_ded.dbc`` and ``tools/gen_dbc.py``):

* classic CAN, 11-bit IDs, DLC 8, Intel signals, raw integers in the firmware; or, from
  the FD twin ``dbc/bess_ded_fd.dbc`` (``FrameCodec(FD_DBC_PATH)``), the same frames as CAN
  FD frames with the bit-rate switch: a codec sends its DBC's format and rejects the
  other (LOOP-6, ``malformed``);
* every frame but the syncs is **secured** (those that can change the dispatch, and
  the diagnostics and balance that report and account): ``Mac`` in bytes 0..2 and the
  truncated freshness value ``Counter`` in the low nibble of byte 3; the codec only
  places and reads them, the MAC itself is computed and checked by
  ``firmware_py.nodeio`` with the sender's key (docs/security.md). ``<name>_Sync``
  frames carry ``Mac``, ``Count`` and ``Boot``. A DBC message that is neither (no
  ``Mac``: an E2E-only frame with a CRC, which the project's DBC no longer has) is
  refused on load;
* a raw value outside the DBC's [min|max] is rejected (cantools does not check
  on decode).

Receive-side problems raise the ``FrameError`` subclasses of
``firmware_py.errors`` (each with the ``cause`` the runtime counts them under);
transmit-side misuse raises ``EncodeError`` (a ``ValueError``), because it is a
bug in the caller, not bus traffic.
"""

from __future__ import annotations

import hashlib
import logging
import math
import operator
import os
import pickle
import re
import sys
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import can
import cantools
import cantools.database.errors
from cantools.database.can import Database, Signal
from cantools.database.can import Message as DbcMessage

from dbc import DBC_PATH

from .errors import (
    ConfigError,
    EncodeError,
    FrameError,
    FrameLengthError,
    RangeError,
    UnknownFrameError,
)

log = logging.getLogger(__name__)

__all__ = [
    "DLC",
    "LAMBDA_Q",
    "N_AGENTS_MAX",
    "PIN_OFF",
    "PIN_ON",
    "format_fault",
    "COUNTER_MODULO",
    "TARGET_OFFSET",
    "DecodedFrame",
    "FrameCodec",
    "agent_of",
    "diag_name",
    "mc_name",
    "setpoint_name",
    "status_name",
    "target_agent",
    "target_raw",
]

LAMBDA_Q = 24
"""λ and ρ travel as int32 Q24: the DBC factor must be exactly 2**-LAMBDA_Q (checked on load)."""

DLC = 8

# The per-agent messages, in the order of the ID plan: name pattern -> its ID base is the
# DBC's ID of agent 1's frame minus 1 (checked for every agent on load).
_AGENT_MESSAGES = ("AGENT_{}_MC", "AGENT_{}_Setpoint", "PLANT_{}_Status", "AGENT_{}_Diag",
                   "AGENT_{}_MC_Sync", "AGENT_{}_Setpoint_Sync", "PLANT_{}_Status_Sync",
                   "AGENT_{}_Diag_Sync")
_AGENT_NAME = re.compile(r"^(?:AGENT|PLANT)_([1-9][0-9]*)_(?:MC|Setpoint|Status|Diag)(?:_Sync)?$")
_ER_MESSAGES = ("ER_Price", "ER_Command", "ER_Balance")
_PROTECTION = ("Mac", "Counter")  # filled in by the codec (Mac: by NodeIO)
# AUTH-34: on CAN FD, AGENT_i_MC and its sync carry a tag per receiver after the classic 8
# bytes: slot k = TagRx<k> (8 bits at TAG_SLOT_START + 32k) and Tag<k> (24 bits after it)
TAG_SLOT_START = 64
TAG_SLOT_BITS = 32
TAG_RX_EMPTY, TAG_RX_PLANT, TAG_RX_ROUTER = 0, 0xFE, 0xFF  # checked against the DBC's choices
_TAG_RX_CHOICES = {TAG_RX_EMPTY: "EMPTY", TAG_RX_PLANT: "PLANT", TAG_RX_ROUTER: "ROUTER"}
_TAG_SIGNAL = re.compile(r"Tag(?:Rx)?[0-9]+")


def _is_protection(name: str) -> bool:
    """Filled in by the sender's codec and NodeIO, not by the caller: Mac, Counter, tags."""
    return name in _PROTECTION or _TAG_SIGNAL.fullmatch(name) is not None


_LAYOUTS = {  # frame kind -> its protection signals' (start, length)
    "secured": {"Mac": (0, 24), "Counter": (24, 4)},
    "sync": {"Mac": (0, 24)},
    "transfer": {},  # ER_PriceSig: authenticated by the signature it carries, no MAC
}
TRANSFER_MESSAGES = frozenset({"ER_PriceSig"})  # the DBC's messages of kind "transfer"
_Q_SIGNALS = {"ER_Price": "Rho"}  # plus Lambda of every AGENT_i_MC


# ---------------------------------------------------------------------------- names


def _check_agent(i: int) -> int:
    if isinstance(i, bool) or not isinstance(i, int) or not 1 <= i <= N_AGENTS_MAX:
        raise EncodeError("agent", f"an agent index in 1..{N_AGENTS_MAX}", i)
    return i


def mc_name(i: int) -> str:
    """Name of agent ``i``'s marginal-cost frame (``AGENT_<i>_MC``, ID 0x100+i)."""
    return f"AGENT_{_check_agent(i)}_MC"


def setpoint_name(i: int) -> str:
    """Name of agent ``i``'s power-setpoint frame (``AGENT_<i>_Setpoint``, ID 0x200+i)."""
    return f"AGENT_{_check_agent(i)}_Setpoint"


def status_name(i: int) -> str:
    """Name of the plant's status frame for BESS ``i`` (``PLANT_<i>_Status``, ID 0x280+i)."""
    return f"PLANT_{_check_agent(i)}_Status"


def diag_name(i: int) -> str:
    """Name of agent ``i``'s multiplexed diagnostics frame (``AGENT_<i>_Diag``, ID 0x300+i)."""
    return f"AGENT_{_check_agent(i)}_Diag"


def agent_of(frame_id: int) -> int | None:
    """The agent index a per-agent frame ID belongs to, or None for ER frames and others.

    Pure arithmetic on the DBC's ID plan (MC/Setpoint/Status/Diag base + i, bases read
    from the DBC), so a receive loop can route a frame before decoding it.
    """
    for base in AGENT_BASES:
        if base < frame_id <= base + N_AGENTS_MAX:
            return frame_id - base
    return None


# ---------------------------------------------------------------------------- compiled layout

# One signal, flattened for the hot loops: (name, shift, mask, sign_bit, raw_min, raw_max).
# Intel byte order only: the DBC start bit is then the LSB position in the payload
# read as a little-endian 64-bit integer. sign_bit is 0 for unsigned signals.
_Sig = tuple[str, int, int, int, int, int]


@dataclass(frozen=True, slots=True)
class _Frame:
    name: str
    frame_id: int
    agent: int | None
    kind: str                           # "secured", "sync" or "transfer" (_LAYOUTS)
    fd: bool                            # a CAN FD frame (the DBC's VFrameFormat)
    counter_shift: int                  # start bit of Counter (0 for sync frames: none)
    length: int                         # payload bytes (DLC 8; 32 for a tagged FD frame)
    tag_slots: int                      # AUTH-34: receivers' tag slots (0: one Mac)
    base: tuple[_Sig, ...]              # decode: every non-multiplexed signal incl. Mac, Counter
    tx_base: tuple[_Sig, ...]           # encode: base minus Mac and Counter
    mux: str | None                     # multiplexer signal name, if any
    pages: Mapping[int, tuple[_Sig, ...]]
    scaling: Mapping[str, tuple[float, float]]  # name -> (scale, offset)
    choices: Mapping[str, Mapping[int, str]]
    ranges: Mapping[str, tuple[int, int]]


@dataclass(frozen=True, slots=True)
class _Compiled:
    db: Database
    by_id: Mapping[int, _Frame]
    by_name: Mapping[str, _Frame]
    n_agents: int                  # AGENT_1_MC..AGENT_<n>_MC
    bases: tuple[int, ...]         # ID base of each of _AGENT_MESSAGES (ID = base + i)
    counter_modulo: int            # 2**length of the Counter signal
    target_offset: int             # ER_Command.Target: agent = raw + this (the DBC's offset)
    fd: bool                       # every frame CAN FD (the FD twin) or none


def _raw_range(sig: Signal) -> tuple[int, int]:
    """Raw [lo, hi] from the DBC's physical [min|max], clamped to what the bits can hold.

    A small tolerance absorbs decimal round-off (-327.68 / 0.01 = -32768.000000000004).
    """
    n = sig.length
    lo = -(1 << (n - 1)) if sig.is_signed else 0
    hi = (1 << (n - 1)) - 1 if sig.is_signed else (1 << n) - 1
    if sig.minimum is not None:
        lo = max(lo, math.ceil((sig.minimum - sig.offset) / sig.scale - 1e-6))
    if sig.maximum is not None:
        hi = min(hi, math.floor((sig.maximum - sig.offset) / sig.scale + 1e-6))
    return lo, hi


def _compile_message(path: str, m: DbcMessage) -> _Frame:
    def bad(problem: str) -> ConfigError:
        return ConfigError(path, m.name, problem)

    names = {s.name: s for s in m.signals}
    tag_slots = sum(1 for n in names if n.startswith("TagRx"))
    n_bytes = DLC + TAG_SLOT_BITS // 8 * tag_slots
    if m.is_extended_frame or m.length != n_bytes or m.frame_id > 0x7FF \
            or (tag_slots and not m.is_fd):
        raise bad(f"expected an 11-bit frame of {n_bytes} bytes (8, and 4 per tag slot on CAN "
                  f"FD), but got ID 0x{m.frame_id:X} length {m.length} "
                  f"extended={m.is_extended_frame} fd={m.is_fd}")
    for k in range(tag_slots):
        start = TAG_SLOT_START + TAG_SLOT_BITS * k
        for sname, want in ((f"TagRx{k}", (start, 8)), (f"Tag{k}", (start + 8, 24))):
            s = names.get(sname)
            if s is None or (s.start, s.length) != want \
                    or (sname.startswith("TagRx") and dict(s.choices or {}) != _TAG_RX_CHOICES):
                raise bad(f"expected the tag slot signal {sname} {want[0]}|{want[1]} (TagRx "
                          f"with the choices {_TAG_RX_CHOICES}), but got "
                          f"{'nothing' if s is None else f'{s.start}|{s.length}'}")
    # the transfer messages are named: any other message without Mac fails the secured
    # layout's check below
    kind = ("sync" if m.name.endswith("_Sync") else
            "transfer" if m.name in TRANSFER_MESSAGES else "secured")
    for sname, (start, length) in _LAYOUTS[kind].items():
        s = names.get(sname)
        if s is None or (s.start, s.length) != (start, length):
            raise bad(f"expected the {kind} frame signal {sname} {start}|{length}, but got "
                      f"{'nothing' if s is None else f'{s.start}|{s.length}'}")
    base: list[_Sig] = []
    pages: dict[int, list[_Sig]] = {}
    scaling: dict[str, tuple[float, float]] = {}
    choices: dict[str, Mapping[int, str]] = {}
    ranges: dict[str, tuple[int, int]] = {}
    mux: str | None = None
    for s in m.signals:
        if s.byte_order != "little_endian" or s.is_float:
            raise bad(f"{s.name}: expected an Intel integer signal, but got "
                      f"{s.byte_order} float={s.is_float}")
        lo, hi = _raw_range(s)
        entry: _Sig = (s.name, s.start, (1 << s.length) - 1,
                       (1 << (s.length - 1)) if s.is_signed else 0, lo, hi)
        ranges[s.name] = (lo, hi)
        scaling[s.name] = (s.scale, s.offset)
        if s.choices:
            choices[s.name] = {int(k): str(v) for k, v in s.choices.items()}
        if s.is_multiplexer:
            if mux is not None:
                raise bad(f"expected at most one multiplexer, but got {mux} and {s.name}")
            mux = s.name
        if s.multiplexer_ids:
            if s.multiplexer_signal is None:
                raise bad(f"{s.name}: multiplexed signal without a multiplexer")
            for page in s.multiplexer_ids:
                pages.setdefault(page, []).append(entry)
        else:
            base.append(entry)
    # Mac and Counter first, then by start bit: the order raw dicts and errors list them in.
    base.sort(key=lambda e: (_PROTECTION.index(e[0]) if e[0] in _PROTECTION else 3, e[1]))
    # (the tag slots sort by their start bit, after the payload)
    named = _AGENT_NAME.match(m.name)
    agent = int(named.group(1)) if named else None
    return _Frame(
        name=m.name,
        frame_id=m.frame_id,
        agent=agent,
        kind=kind,
        fd=bool(m.is_fd),
        counter_shift=names["Counter"].start if "Counter" in names else 0,
        length=n_bytes,
        tag_slots=tag_slots,
        base=tuple(base),
        tx_base=tuple(e for e in base if not _is_protection(e[0])),
        mux=mux,
        pages={p: tuple(sigs) for p, sigs in pages.items()},
        scaling=scaling,
        choices=choices,
        ranges=ranges,
    )


def _check_plan(path: str, by_name: Mapping[str, _Frame]) -> tuple[int, tuple[int, ...]]:
    """Read the ID plan from the DBC and check it is the regular one the firmware relies on:
    AGENT_1..AGENT_<n> with every per-agent ID = its message's base + i, and the Q24 factor.
    Returns (n, the bases of _AGENT_MESSAGES)."""
    n = 0
    while _AGENT_MESSAGES[0].format(n + 1) in by_name:
        n += 1
    extra = sorted(name for name, f in by_name.items()
                   if f.agent is not None and not 1 <= f.agent <= n)
    if n == 0 or extra:
        raise ConfigError(path, "AGENT_<i>_MC", f"expected agents 1..n without gaps, but got "
                          f"{n} contiguous and also {', '.join(extra) or 'none'}")
    bases = tuple(by_name[p.format(1)].frame_id - 1 if p.format(1) in by_name else -1
                  for p in _AGENT_MESSAGES)
    for pattern, base in zip(_AGENT_MESSAGES, bases, strict=True):
        for i in range(1, n + 1):
            f = by_name.get(pattern.format(i))
            if f is None or f.frame_id != base + i:
                got = "nothing" if f is None else f"0x{f.frame_id:03X}"
                raise ConfigError(path, pattern.format(i), f"expected a frame with ID "
                                  f"0x{base + i:03X} (its base + {i}), but got {got}")
    for name in _ER_MESSAGES:
        if name not in by_name:
            raise ConfigError(path, name, "expected this message in the DBC, but got nothing")
    q_signals = dict(_Q_SIGNALS)
    q_signals.update({_AGENT_MESSAGES[0].format(i): "Lambda" for i in range(1, n + 1)})
    for name, sig in q_signals.items():
        scale, offset = by_name[name].scaling[sig]
        if scale != 2.0**-LAMBDA_Q or offset != 0:
            raise ConfigError(path, f"{name}.{sig}", f"expected factor 2**-{LAMBDA_Q} offset 0 "
                              f"(int32 Q{LAMBDA_Q}), but got factor {scale!r} offset {offset!r}")
    return n, bases


@lru_cache(maxsize=8)
def _compile(path: str, _mtime_ns: int) -> _Compiled:
    """Load and compile a DBC once per file version; codecs share the immutable result.

    The result is also pickled to the user's cache directory: parsing the DBC costs
    ~0.25 s per process on a host and ~3.4 s in the vcan tier's emulated guest, paid by
    every node at every start; unpickling costs ~5 % of that."""
    cache = _cache_file(path)
    try:
        with cache.open("rb") as f:
            cached = pickle.load(f)
        if isinstance(cached, _Compiled):
            return cached
    except Exception:  # noqa: BLE001 - absent, unreadable or stale: compile afresh
        pass
    compiled = _compile_dbc(path)
    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=cache.parent, delete=False) as tmp:
            pickle.dump(compiled, tmp)
        os.replace(tmp.name, cache)  # atomic: concurrent starts never read half a file
    except OSError as e:
        log.debug("DBC cache not written (%s): every start parses the DBC", e)
    return compiled


def _cache_file(path: str) -> Path:
    """Keyed by the DBC's bytes, this module's source and the cantools and Python
    versions: any change to them compiles afresh."""
    h = hashlib.sha256()
    for part in (Path(path).read_bytes(), Path(__file__).read_bytes(),
                 cantools.__version__.encode(), sys.version.encode()):
        h.update(part)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "bess-ded" / f"dbc-{h.hexdigest()[:32]}.pickle"


def _compile_dbc(path: str) -> _Compiled:
    db = cantools.database.load_file(path, strict=True)
    if not isinstance(db, Database):
        raise ConfigError(path, "format", f"expected a CAN database, but got {type(db).__name__}")
    frames = [_compile_message(path, m) for m in db.messages]
    by_name = {f.name: f for f in frames}
    n, bases = _check_plan(path, by_name)
    formats = {f.fd for f in frames}
    if len(formats) != 1:  # a node sends one format and rejects the other (LOOP-6)
        raise ConfigError(path, "VFrameFormat", "expected every message classic or every "
                          "message CAN FD, but got both")
    counter_bits = db.get_message_by_name("ER_Price").get_signal_by_name("Counter").length
    scale, offset = by_name["ER_Command"].scaling["Target"]
    if scale != 1 or offset != int(offset):
        raise ConfigError(path, "ER_Command.Target", f"expected factor 1 and an integer offset "
                          f"(agent = raw + offset), but got factor {scale!r} offset {offset!r}")
    return _Compiled(db=db, by_id={f.frame_id: f for f in frames}, by_name=by_name,
                     n_agents=n, bases=bases, counter_modulo=1 << counter_bits,
                     target_offset=int(offset), fd=formats.pop())


def _load(dbc_path: str | Path) -> _Compiled:
    path = Path(dbc_path).resolve()
    try:
        mtime = path.stat().st_mtime_ns
    except OSError as e:
        raise ConfigError(str(path), "file", f"expected a readable DBC file, but got {e}") \
            from None
    return _compile(str(path), mtime)


# The contract's numbers, read from the project's DBC once at import (firmware_py.contract
# publishes them with the rest; these names stay here for the codec and its importers).
_DEFAULT = _load(DBC_PATH)
N_AGENTS_MAX = _DEFAULT.n_agents
"""Agents the DBC defines frames for (AGENT_1..AGENT_<N_AGENTS_MAX>)."""
COUNTER_MODULO = _DEFAULT.counter_modulo
"""A secured frame's ``Counter`` (the low bits of its freshness value) counts modulo
2**(length of the Counter signal)."""
COUNTER_STEP_MAX = COUNTER_MODULO // 2
"""The largest forward step (1 + lost frames) of one sender's ``Counter`` between two
frames a recorder sees that it still reads as frames lost (``sim.run.buslog``'s sequence
statistics); more reads as a step backwards, i.e. out of sequence."""
AGENT_BASES = _DEFAULT.bases
MC_BASE, SETPOINT_BASE, STATUS_BASE, DIAG_BASE = AGENT_BASES[:4]
TARGET_OFFSET = _DEFAULT.target_offset
"""ER_Command.Target carries agent − TARGET_OFFSET (the DBC's offset, 1: six bits hold
agents 1..64 as raw 0..63, CMD-1). The codec works in raw values, so every sender and
receiver of a command converts with ``target_raw`` / ``target_agent``."""


def target_raw(agent: int) -> int:
    """ER_Command.Target's raw value addressing ``agent``."""
    return agent - TARGET_OFFSET


def target_agent(raw: int) -> int:
    """The agent an ER_Command's raw Target addresses."""
    return raw + TARGET_OFFSET


# ---------------------------------------------------------------------------- decoded frame


@dataclass(frozen=True, slots=True)
class DecodedFrame:
    """A received frame that passed every check of the codec: known ID, DLC, raw ranges
    (the MAC and freshness are NodeIO's).

    ``raw`` holds every signal present (including ``Mac`` and ``Counter``; for
    the multiplexed diag frame, ``Page`` and that page's signals only) as raw
    integers, which is what the fixed-point firmware uses. ``phys`` scales on
    demand for the simulator and logs.
    """

    name: str
    frame_id: int
    agent: int | None
    counter: int
    raw: dict[str, int]
    _frame: _Frame = field(repr=False, compare=False)

    def phys(self, signal: str) -> float:
        """Physical value raw·factor + offset (exact for Q24: the factor is a power of 2)."""
        try:
            v = self.raw[signal]
        except KeyError:
            raise KeyError(f"{self.name}.{signal}: expected one of "
                           f"{', '.join(self.raw)}, but got {signal!r}") from None
        scale, offset = self._frame.scaling[signal]
        if scale == 1 and offset == 0:
            return v
        return v * scale + offset

    @property
    def tag_slots(self) -> int:
        """Its receivers' tag slots (AUTH-34: a λ frame or its sync on CAN FD), else 0."""
        return self._frame.tag_slots

    def label(self, signal: str) -> str | None:
        """The DBC choice name of an enum signal's value (e.g. State → "RUNNING"), else None."""
        table = self._frame.choices.get(signal)
        return None if table is None else table.get(self.raw[signal])


# ---------------------------------------------------------------------------- codec


class _Verbatim(str):
    """A string that reprs as itself, for error texts quoted from cantools."""

    def __repr__(self) -> str:
        return str(self)


class _Missing:
    def __repr__(self) -> str:
        return "nothing (signal missing)"


_MISSING: Any = _Missing()


def _unpack(frame: str, sigs: Iterable[_Sig], x: int, raw: dict[str, int]) -> None:
    """Extract ``sigs`` from the payload ``x`` into ``raw``, range-checked (RangeError)."""
    for name, shift, mask, sign, lo, hi in sigs:
        v = (x >> shift) & mask
        if v & sign:
            v -= mask + 1
        if v < lo or v > hi:
            raise RangeError(f"{frame}.{name}: expected a raw value in {lo}..{hi}, "
                             f"but got {v}")
        raw[name] = v


PIN_ON, PIN_OFF = 1, 2
"""ER_Command PIN (CMD-7): its GainK raw says which way (the DBC's comment of GainK); any
other GainK, or GainH ≠ 0, is out of range like a raw value outside the DBC's."""


def _pin_rule(db: Database) -> tuple[int, int] | None:
    """(ER_Command's ID, the Command value of PIN), or None if the DBC has no PIN."""
    try:
        msg = db.get_message_by_name("ER_Command")
        choices: Mapping[Any, Any] = msg.get_signal_by_name("Command").choices or {}
    except KeyError:
        return None
    pin = [int(v) for v, n in choices.items() if str(n) == "PIN"]
    return (msg.frame_id, pin[0]) if pin else None


def format_fault(msg: can.Message, fd: bool) -> str:
    """Why ``msg`` is not a data frame of a bus of format ``fd`` (CAN FD or classic): the
    text of a ``malformed`` rejection (RX-2, LOOP-6)."""
    want = "a CAN FD data frame" if fd else "a classic CAN data frame"
    kind = ("an error frame" if msg.is_error_frame else
            "a remote frame" if msg.is_remote_frame else
            "a CAN FD frame" if msg.is_fd else "a classic CAN frame")
    return f"expected {want}, but got {kind}"


class FrameCodec:
    """Encode and decode every frame of the DBC, with the layout and raw range checks.

    The DBC is loaded (strict) and compiled once per file and shared by every
    codec in the process, so creating one codec per agent is cheap.
    """

    def __init__(self, dbc_path: str | Path = DBC_PATH) -> None:
        c = _load(dbc_path)
        self.path = Path(dbc_path).resolve()
        self._db = c.db
        self._by_id = c.by_id
        self._by_name = c.by_name
        self._ids = frozenset(c.by_id)
        self._pin_rule = _pin_rule(c.db)
        self.fd = c.fd
        """The bus's frame format: CAN FD (with the bit-rate switch) or classic."""

    # ------------------------------------------------------------ lookups

    @property
    def database(self) -> Database:
        """The cantools database (shared: do not modify it)."""
        return self._db

    def _frame(self, name: str) -> _Frame:
        f = self._by_name.get(name)
        if f is None:
            raise EncodeError("message", "a message name defined in the DBC (ER_Price, "
                              "ER_Command, ER_Balance, AGENT_<i>_MC, AGENT_<i>_Setpoint, "
                              "PLANT_<i>_Status, AGENT_<i>_Diag, <name>_Sync)", name)
        return f

    def frame_id(self, name: str) -> int:
        """The CAN ID of a message name; unknown names fail loudly (EncodeError)."""
        return self._frame(name).frame_id

    def frame_ids(self) -> frozenset[int]:
        """Every CAN ID the DBC defines (what a receiver accepts at all)."""
        return self._ids

    def kind(self, frame_id: int) -> str:
        """"secured" (MAC and truncated freshness), "sync" (full freshness under a MAC) or
        "transfer" (no MAC: ER_PriceSig, authenticated by its signature): how the frame is
        protected."""
        f = self._by_id.get(frame_id)
        if f is None:
            raise UnknownFrameError(f"0x{frame_id:03X}: expected an ID defined in the DBC, "
                                    "but got an unknown ID")
        return f.kind

    def tag_slots(self, name: str) -> int:
        """The receivers' tag slots of message ``name`` (AUTH-34: AGENT_i_MC and its sync
        on CAN FD); 0: it carries one Mac."""
        return self._frame(name).tag_slots

    def name_of(self, frame_id: int) -> str:
        """The DBC message name of ``frame_id``; UnknownFrameError if it has none."""
        f = self._by_id.get(frame_id)
        if f is None:
            raise UnknownFrameError(f"0x{frame_id:03X}: expected an ID defined in the DBC, "
                                    "but got an unknown ID")
        return f.name

    def pages(self, name: str) -> dict[int, tuple[str, ...]]:
        """A multiplexed message's pages: page -> its signals' names by start bit (the DBC's
        layout; AGENT_<i>_Diag's is what the agent fills in). Empty if not multiplexed."""
        f = self._frame(name)
        return {p: tuple(s[0] for s in sorted(sigs, key=lambda s: s[1]))
                for p, sigs in sorted(f.pages.items())}

    def scale(self, name: str, signal: str) -> float:
        """The DBC factor of a signal (phys = raw·factor + offset; ER_Command.Target alone
        has an offset: TARGET_OFFSET)."""
        f = self._frame(name)
        try:
            return f.scaling[signal][0]
        except KeyError:
            raise EncodeError(f"{name}.{signal}", f"a signal of {name} "
                              f"({', '.join(f.scaling)})", signal) from None

    def raw_range(self, name: str, signal: str) -> tuple[int, int]:
        """The raw [lo, hi] a signal must lie in (from the DBC's [min|max])."""
        f = self._frame(name)
        try:
            return f.ranges[signal]
        except KeyError:
            raise EncodeError(f"{name}.{signal}", f"a signal of {name} "
                              f"({', '.join(f.ranges)})", signal) from None

    # ------------------------------------------------------------ encode

    def _signals_for(self, f: _Frame, values: Mapping[str, Any]) -> tuple[_Sig, ...]:
        """The signals a frame must carry; for the multiplexed frame, the chosen page's."""
        if f.mux is None:
            return f.tx_base
        page = values.get(f.mux, _MISSING)
        if page is _MISSING:
            return f.tx_base  # the missing multiplexer is reported by the caller's check
        try:
            return f.tx_base + f.pages[operator.index(page)]
        except (KeyError, TypeError):
            lo, hi = f.ranges[f.mux]
            raise EncodeError(f"{f.name}.{f.mux}", f"a page in {sorted(f.pages)} "
                              f"(raw {lo}..{hi})", page) from None

    @staticmethod
    def _signal_set_error(f: _Frame, sigs: tuple[_Sig, ...], given: Mapping[str, Any]) -> None:
        names = [s[0] for s in sigs]
        missing = [n for n in names if n not in given]
        extra = [n for n in given if n not in names]
        if missing or extra:
            detail = "; ".join(p for p in (
                f"missing {', '.join(missing)}" if missing else "",
                f"not in this frame {', '.join(extra)}" if extra else "") if p)
            raise EncodeError(f.name, f"exactly the signals {', '.join(names)} (Mac and Counter "
                              f"are filled in by the sender) [{detail}]", sorted(given))

    @staticmethod
    def _check_counter(f: _Frame, counter: Any) -> int:
        try:
            c = operator.index(counter)
        except TypeError:
            raise EncodeError(f"{f.name}.Counter", f"an int in 0..{COUNTER_MODULO - 1}",
                              counter) from None
        if not 0 <= c < COUNTER_MODULO:
            raise EncodeError(f"{f.name}.Counter", f"an int in 0..{COUNTER_MODULO - 1}", counter)
        return c

    @staticmethod
    def _finish(f: _Frame, body: bytes) -> can.Message:
        """The frame with its Mac bytes 0 (NodeIO signs it: it holds the keys); an FD
        frame with the bit-rate switch (the FD DBC's CANFD_BRS)."""
        return can.Message(arbitration_id=f.frame_id, is_extended_id=False, data=body,
                           is_fd=f.fd, bitrate_switch=f.fd, check=True)

    def encode(self, name: str, raw: Mapping[str, int], counter: int) -> can.Message:
        """Build a frame from RAW integer signal values (what the fixed-point firmware holds).

        ``raw`` must name exactly the frame's signals except Mac and Counter (for
        a diag frame: ``Page`` and that page's signals). Each value must be an
        integer inside the DBC's raw range: nothing is clipped or wrapped, so a
        saturating counter must be saturated by the caller. Raises EncodeError.
        """
        f = self._by_name.get(name)
        if f is None:
            f = self._frame(name)
        counter = self._check_counter(f, counter)
        sigs = f.tx_base if f.mux is None else self._signals_for(f, raw)
        if len(raw) != len(sigs):
            self._signal_set_error(f, sigs, raw)
        x = counter << f.counter_shift if f.kind != "sync" else 0
        for sname, shift, mask, _sign, lo, hi in sigs:
            v = raw.get(sname, _MISSING)
            if type(v) is not int:
                if v is _MISSING:
                    self._signal_set_error(f, sigs, raw)
                try:
                    v = operator.index(v)
                except TypeError:
                    raise EncodeError(f"{name}.{sname}", f"a raw integer in {lo}..{hi}",
                                      v) from None
            if v < lo or v > hi:
                raise EncodeError(f"{name}.{sname}", f"a raw integer in {lo}..{hi}", v)
            x |= (v & mask) << shift
        return self._finish(f, x.to_bytes(f.length, "little"))

    def encode_phys(self, name: str, values: Mapping[str, Any], counter: int) -> can.Message:
        """Build a frame from PHYSICAL values (simulator side), scaled by cantools.

        cantools rounds with Python's round() (ties to even) and range-checks
        against the DBC (strict). Enum signals also accept their choice names.
        The firmware itself uses ``encode`` with raw integers for bit-exact λ.
        """
        f = self._frame(name)
        counter = self._check_counter(f, counter)
        sigs = self._signals_for(f, values)
        self._signal_set_error(f, sigs, values)
        msg = self._db.get_message_by_name(name)
        try:
            prot = {s[0]: 0 for s in f.base if _is_protection(s[0])}
            if "Counter" in prot:
                prot["Counter"] = counter
            body = msg.encode({**values, **prot}, scaling=True,
                              strict=True, padding=False)
        except (cantools.database.errors.EncodeError, KeyError, TypeError, ValueError) as e:
            raise EncodeError(name, "physical values inside the DBC ranges",
                              _Verbatim(str(e))) from None
        return self._finish(f, bytes(body))

    # ------------------------------------------------------------ decode

    def decode(self, msg: can.Message) -> DecodedFrame:
        """Check and decode a received frame. Raises a FrameError subclass on rejection.

        Order of checks: frame kind, known ID, DLC, raw ranges. Whatever
        fails first decides the ``cause`` the runtime counts.
        """
        fid = msg.arbitration_id
        if msg.is_extended_id:
            raise UnknownFrameError(f"0x{fid:08X}: expected an 11-bit standard ID, but got an "
                                    "extended (29-bit) frame")
        if msg.is_error_frame or msg.is_remote_frame or msg.is_fd != self.fd:
            raise FrameError(f"0x{fid:03X}: {format_fault(msg, self.fd)}")
        f = self._by_id.get(fid)
        if f is None:
            raise UnknownFrameError(f"0x{fid:03X}: expected an ID defined in the DBC, but got "
                                    "an unknown ID")
        data = msg.data
        if msg.dlc != f.length or len(data) != f.length:
            got = msg.dlc if msg.dlc == len(data) else f"{msg.dlc} with {len(data)} data bytes"
            raise FrameLengthError(f"{f.name} (0x{fid:03X}): expected DLC {f.length}, but got "
                                   f"{got}")
        x = int.from_bytes(data, "little")
        raw: dict[str, int] = {}
        _unpack(f.name, f.base, x, raw)
        if f.mux is not None:  # the page's signals, once the multiplexer is known
            _unpack(f.name, f.pages.get(raw[f.mux], ()), x, raw)
        if self._pin_rule is not None and fid == self._pin_rule[0] \
                and raw["Command"] == self._pin_rule[1] \
                and (raw["GainK"] not in (PIN_ON, PIN_OFF) or raw["GainH"] != 0):
            raise RangeError(f"{f.name}.GainK: expected {PIN_ON} (pin) or {PIN_OFF} (unpin) "
                             f"with GainH = 0 in a PIN command, but got GainK = {raw['GainK']}, "
                             f"GainH = {raw['GainH']}")
        return DecodedFrame(f.name, fid, f.agent, raw.get("Counter", 0), raw, f)
