"""The bus contract in one place: every number the code needs from ``dbc/bess_ded.dbc``.

Nothing here is typed in by hand: frame IDs and the per-agent ID bases, the agent
limit, cycle times, the Counter signal's modulus, the State and Command values and the
signals' raw ranges are read from the DBC (compiled once by ``firmware_py.frames``
and shared with every codec). A DBC that lacks something this module names fails
at import, with a ConfigError naming the DBC and the missing item, not later on the
bus.

Cadences. The DBC's GenMsgCycleTime values are written for the agents' sample time
Ts = ``MC_CYCLE_S`` (10 ms, the AGENT_<i>_MC cycle). Every node counts cadences in
ticks of that cycle: a message is sent every ``every_ticks(name)`` = round(cycle /
MC cycle) ticks. A node running at another Ts (a time-scaled run: Ts = 10 ms·F)
therefore stretches every cycle by the same F: ``cycle_s(name, ts)``. Receivers
time a cyclic sender out after ``TIMEOUT_CYCLES`` of its cycles (``timeout_s``), the
AUTOSAR E2E convention of "a few missed periods".

"Active". An agent takes part in the dispatch (its λ enters its neighbours' consensus
error, its BESS follows its setpoint) iff its State is RUNNING: ``is_active``. Every
module that needs the notion uses this function.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import IntEnum

from cantools.database.can import Message as DbcMessage

from dbc import DBC_PATH

from .errors import ConfigError
from .frames import (
    AGENT_BASES,
    COUNTER_MODULO,
    DIAG_BASE,
    MC_BASE,
    N_AGENTS_MAX,
    SETPOINT_BASE,
    STATUS_BASE,
    FrameCodec,
    agent_of,
    diag_name,
    mc_name,
    setpoint_name,
    status_name,
)
from .secoc import FreshnessLayout

__all__ = [
    "AGENT_BASES",
    "COUNTER_MODULO",
    "DIAG_BASE",
    "ER_BALANCE_ID",
    "ER_COMMAND_ID",
    "ER_PRICE_ID",
    "MC_BASE",
    "MC_CYCLE_S",
    "N_AGENTS_MAX",
    "FV_BOOT_BITS",
    "FV_COUNT_BITS",
    "FRESHNESS",
    "FV_TX_BITS",
    "COMMAND",
    "TOTALS",
    "KEYED_FRAMES",
    "LINK_FRAMES",
    "MAC_BITS",
    "PEER_SYNCED_BY",
    "REPORT_IDS",
    "SECURED_IDS",
    "SIGNED_PRICE_COUNTERS",
    "SETPOINT_BASE",
    "SYNCED_BY",
    "SYNC_OF",
    "STATUS_BASE",
    "TIMEOUT_CYCLES",
    "Command",
    "State",
    "agent_ids",
    "command_key_name",
    "cycle_ms",
    "cycle_s",
    "diag_name",
    "every_ticks",
    "frame_key",
    "is_active",
    "is_cyclic",
    "keyed_frames",
    "lambda_receivers",
    "link_frames",
    "mc_name",
    "parties_of",
    "raw_range",
    "receivers_of",
    "scale",
    "sender_of",
    "setpoint_name",
    "status_name",
    "timeout_s",
]

_CODEC = FrameCodec()  # the compiled DBC, shared with every other codec of the process
_DB = _CODEC.database
_SRC = str(DBC_PATH)

TIMEOUT_CYCLES = 5
"""A receiver times a cyclic sender out after this many of its cycles without a frame."""

ER_PRICE_ID = _CODEC.frame_id("ER_Price")
ER_COMMAND_ID = _CODEC.frame_id("ER_Command")
ER_BALANCE_ID = _CODEC.frame_id("ER_Balance")


def _message(name: str) -> DbcMessage:
    try:
        return _DB.get_message_by_name(name)
    except KeyError:
        raise ConfigError(_SRC, name, "expected this message in the DBC, but got "
                          "nothing") from None


def cycle_ms(name: str) -> int:
    """GenMsgCycleTime of a cyclic message, ms (for Ts = MC_CYCLE_S). An event message
    (no cycle time, e.g. ER_Command) raises ConfigError: it has no cadence."""
    ms = _message(name).cycle_time
    if not ms:
        raise ConfigError(_SRC, name, "expected a cyclic message (GenMsgCycleTime), but got "
                          "an event message")
    return int(ms)


def is_cyclic(name: str) -> bool:
    """True if the DBC gives ``name`` a cycle time (every message but ER_Command)."""
    return bool(_message(name).cycle_time)


_MC_CYCLE_MS = cycle_ms(mc_name(1))
MC_CYCLE_S = _MC_CYCLE_MS / 1000.0
"""The agents' sample time Ts the DBC's cycle times are written for (AGENT_<i>_MC), s."""


def every_ticks(name: str) -> int:
    """A cyclic message is sent every this many ticks of the MC cycle (≥ 1)."""
    ms = cycle_ms(name)
    ticks = round(ms / _MC_CYCLE_MS)
    if ticks < 1 or ticks * _MC_CYCLE_MS != ms:
        raise ConfigError(_SRC, name, f"expected a cycle time that is a multiple of the "
                          f"{_MC_CYCLE_MS} ms MC cycle, but got {ms} ms")
    return ticks


def cycle_s(name: str, ts: float = MC_CYCLE_S) -> float:
    """The cycle of ``name`` in s for nodes ticking at ``ts``: every_ticks(name)·ts, the
    DBC's cycle at Ts = 10 ms, stretched by F in a time-scaled run (Ts = 10 ms·F)."""
    return every_ticks(name) * ts


def timeout_s(name: str, ts: float = MC_CYCLE_S) -> float:
    """How long a receiver waits for ``name`` before timing its sender out:
    TIMEOUT_CYCLES cycles (250 ms for a 50 ms frame at Ts = 10 ms)."""
    return TIMEOUT_CYCLES * cycle_s(name, ts)


def raw_range(name: str, signal: str) -> tuple[int, int]:
    """The raw [lo, hi] of a signal, from the DBC's [min|max]."""
    return _CODEC.raw_range(name, signal)


def scale(name: str, signal: str) -> float:
    """The DBC factor of a signal (phys = raw·factor; offset 0 is checked here)."""
    sig = _message(name).get_signal_by_name(signal)
    if sig.offset != 0:
        raise ConfigError(_SRC, f"{name}.{signal}", f"expected offset 0, but got {sig.offset}")
    return _CODEC.scale(name, signal)


def agent_ids(n: int | None = None) -> range:
    """Agent indices 1..n (default: every agent the DBC defines)."""
    return range(1, (N_AGENTS_MAX if n is None else n) + 1)


def _choice(message: str, signal: str, label: str) -> int:
    """The value the DBC's VAL_ table of ``message.signal`` gives ``label``."""
    try:
        sig = _message(message).get_signal_by_name(signal)
    except KeyError:
        raise ConfigError(_SRC, f"{message}.{signal}", "expected this signal in the DBC, but "
                          "got nothing") from None
    for value, name in (sig.choices or {}).items():
        if str(name) == label:
            return int(value)
    have = ", ".join(str(v) for v in (sig.choices or {}).values()) or "no choices"
    raise ConfigError(_SRC, f"{message}.{signal}", f"expected a choice named {label}, but got "
                      f"{have}")


class State(IntEnum):
    """AGENT_<i>_MC.State (and AGENT_<i>_Diag.State): the agent state machine."""

    INIT = _choice(mc_name(1), "State", "INIT")
    RUNNING = _choice(mc_name(1), "State", "RUNNING")
    ISOLATED = _choice(mc_name(1), "State", "ISOLATED")
    SAFE = _choice(mc_name(1), "State", "SAFE")


class Command(IntEnum):
    """ER_Command.Command."""

    ISOLATE = _choice("ER_Command", "Command", "ISOLATE")
    RECONNECT = _choice("ER_Command", "Command", "RECONNECT")
    SET_GAINS = _choice("ER_Command", "Command", "SET_GAINS")
    PIN = _choice("ER_Command", "Command", "PIN")  # GainK: frames.PIN_ON / PIN_OFF (CMD-7)


def is_active(state: int) -> bool:
    """An agent takes part in the dispatch iff its State is RUNNING (the one definition)."""
    return state == State.RUNNING



# ---------------------------------------------------------------------------- SecOC

SECURED_IDS = frozenset(fid for fid in _CODEC.frame_ids() if _CODEC.kind(fid) == "secured")
"""The frames that can change the dispatch: they carry a MAC (docs/security.md)."""
SYNC_OF = {fid: _CODEC.frame_id(_CODEC.name_of(fid) + "_Sync") for fid in SECURED_IDS}
"""Secured frame ID -> the ID of its ``<name>_Sync`` frame (read from the DBC)."""
SYNCED_BY = {sync: fid for fid, sync in SYNC_OF.items()}
"""``<name>_Sync`` ID -> the secured frame ID whose freshness it carries."""
REPORT_IDS = frozenset(fid for fid in SECURED_IDS
                       if {r for s in _DB.get_message_by_frame_id(fid).signals
                           for r in s.receivers} <= {"ER"})
"""Secured frames that report or account (AGENT_<i>_Diag, PLANT_Totals, ER_Balance): no
agent or plant receives them (DBC receivers: the router at most), only the router and the
recorder."""
PEER_SYNCED_BY = {sync: fid for sync, fid in SYNCED_BY.items() if fid not in REPORT_IDS}
"""The syncs a node may take as a peer's (NodeIO._peer_sync): those of the frames that
drive the dispatch. A peer's restart shows on them; a report frame's sync adds nothing
(and the C agent keeps per-sync state for these only)."""


def receivers_of(fid: int) -> frozenset[str]:
    """The key labels of a message's DBC receivers (ER -> router, PLANT -> plant)."""
    nodes = {r for s in _DB.get_message_by_frame_id(fid).signals for r in s.receivers}
    return frozenset({"ER": "router", "PLANT": "plant"}.get(n, n.lower()) for n in nodes)


LINK_FRAMES = frozenset(
    _CODEC.name_of(fid) for fid in SECURED_IDS
    if fid not in REPORT_IDS and sum(r.startswith("agent_") for r in receivers_of(fid))
    + ("plant" in receivers_of(fid)) == 1)
"""AUTH-28: the secured messages with a single receiving peer, an agent or the plant
(AGENT_<i>_Setpoint: the plant; PLANT_<i>_Status: agent i; the router's ledger takes the
report PLANT_Totals): each is signed with a key of its own, held by its sender and its DBC
receivers only (``secoc.derive_frame_key``), so no third node can forge it. The other
secured messages are broadcasts (ER_Price, ER_Command, AGENT_<i>_MC) or reports, signed
with their sender's node key."""
REPORT_FRAMES = frozenset(_CODEC.name_of(fid) for fid in REPORT_IDS)
KEYED_FRAMES = LINK_FRAMES | REPORT_FRAMES
"""The secured messages signed with a key of their own (``secoc.derive_frame_key``), held
by their sender and their DBC receivers only: the link frames (AUTH-28) and the reports
(AUTH-29: AGENT_<i>_Diag and PLANT_Totals, read by the router; ER_Balance, read by no
node). The recorder derives every key from the master key. The broadcasts (ER_Price,
AGENT_<i>_MC) keep their sender's node key; ER_Command its target's command key
(AUTH-30)."""
_PARTIES = {_CODEC.name_of(fid): receivers_of(fid)
            for fid in SECURED_IDS if _CODEC.name_of(fid) in KEYED_FRAMES}


def parties_of(name: str) -> frozenset[str]:
    """The nodes holding frame ``name``'s own key (AUTH-28, AUTH-29): its sender and its
    DBC receivers."""
    return _PARTIES[name] | {sender_of(name)}


def link_frames(n: int | None = None) -> list[str]:
    """The link frames (AUTH-28) of a fleet of ``n`` agents (None: every agent the DBC
    defines), by frame ID."""
    return _by_id(LINK_FRAMES, n)


def keyed_frames(n: int | None = None) -> list[str]:
    """The messages with a key of their own (link frames and reports, KEYED_FRAMES) of a
    fleet of ``n`` agents (None: every agent the DBC defines), by frame ID."""
    return _by_id(KEYED_FRAMES, n)


def _by_id(names: frozenset[str], n: int | None) -> list[str]:
    fids = sorted(_CODEC.frame_id(name) for name in names)
    return [_CODEC.name_of(fid) for fid in fids
            if n is None or (agent_of(fid) or 0) <= n]


COMMAND = "ER_Command"
"""AUTH-30: the message addressed to one agent (its Target) and signed with that agent's
command key (``secoc.derive_command_key``), held by the router and the target only; its
sync (no Target) keeps the router's node key."""
TOTALS = "PLANT_Totals"
"""AUTH-29: the plant's input to the router's ledger (ΣP_i and the batteries' cost rate,
with each status cycle), a report under a key only the plant and the router hold."""


def lambda_receivers(neighbours: list[int]) -> list[str]:
    """The receivers of an agent's λ tags in slot order (AUTH-34, CAN FD): its neighbours
    by index, then the plant, then the router."""
    return [*(f"agent_{j}" for j in sorted(neighbours)), "plant", "router"]


def command_key_name(target: int) -> str:
    """The name of the command key of agent ``target`` in a monitor's key table."""
    return f"{COMMAND}@agent_{target}"


def frame_key(keys: Mapping[str, bytes], name: str, target: int | None = None) -> bytes | None:
    """The key of message ``name`` (or its ``_Sync``) from a monitor's key table
    (``label -> node key``, ``message -> frame key``, ``command_key_name(i) -> command
    key``): a link frame's or report's own key, an ER_Command's its ``target``'s
    command key (AUTH-30), a broadcast's sender's key; None if the table has none."""
    if name == COMMAND:
        return None if target is None else keys.get(command_key_name(target))
    base = name.removesuffix("_Sync")
    if base in KEYED_FRAMES:
        return keys.get(base)
    return keys.get(sender_of(base))


MAC_BITS = _CODEC.raw_range("ER_Price", "Mac")[1].bit_length()
"""Bits of the truncated CMAC on the wire (the DBC's Mac signal)."""
FV_TX_BITS = _CODEC.raw_range("ER_Price", "Counter")[1].bit_length()
"""Bits of the truncated freshness value on the wire (a secured frame's Counter)."""
FV_COUNT_BITS = _CODEC.raw_range("ER_Price_Sync", "Count")[1].bit_length()
FV_BOOT_BITS = _CODEC.raw_range("ER_Price_Sync", "Boot")[1].bit_length()
"""The full freshness value is Boot (FV_BOOT_BITS) ‖ Count (FV_COUNT_BITS)."""
FRESHNESS = FreshnessLayout(FV_BOOT_BITS, FV_COUNT_BITS)
"""The one join and split of a freshness value (Boot ‖ Count), sized by the DBC."""

# An agent's counters (docs/firmware-spec.md section 13) by the names firmware_py counts
# them under, in the order firmware_c indexes them (BD_C_*, generated from this tuple by
# firmware_c/gen_contract.py): the one list of both agents and of the node vectors.
# (No crc, repeated_counter, counter_jump, counter_clash or untrusted: those counted the
# E2E-only frames' checks, and the DBC has no such frame; their Diag slots are reserved,
# DIAG_RESERVED.)
AGENT_COUNTERS: tuple[str, ...] = (
    "dlc", "range", "unknown_id", "malformed", "impersonation",
    "lost_frames", "saturations", "neighbour_timeouts", "price_timeouts", "status_timeouts",
    "plant_faults", "foreign", "foreign_id",
    "untrusted_sources", "implausible_price", "implausible_lambda",
    "implausible_gains", "auth", "unsynced", "resyncs", "deadline_miss", "send_failure",
    "error_frame", "commands", "commands_isolate", "commands_reconnect",
    "price_steps_accepted", "setpoint_limited",
    "not_a_frame", "invalid_frame", "rx_error",  # the bus's inputs (LOOP-6)
    "stale",
    "joining",  # AUTH-26: frames of the join window
    "sync_jump",  # AUTH-27: syncs refused for a boot jump (also counted under auth)
)

SIGNED_PRICE_COUNTERS: tuple[str, ...] = ("unsigned_price", "bad_signature", "sig_malformed")
"""An agent's counters of the opt-in signed price (AUTH-32, AUTH-33;
firmware_py.pricesig, firmware_c/src/agent_sig.c): not in AGENT_COUNTERS (no Diag slot);
firmware_c's BD_C_* list them after AGENT_COUNTERS' (firmware_c/gen_contract.py).
Reported in the exit summary and in the verdict (in-process from the agents; in `up`
from ``--counters-dir``'s files)."""

DIAG_RESERVED: frozenset[str] = frozenset(
    s.name for s in _message(diag_name(1)).signals if (s.comment or "").startswith("Reserved"))
"""The AGENT_<i>_Diag signals the DBC marks reserved (its comment, from tools/gen_dbc.py's
slot table): always sent as 0, kept so the layout does not move (DIAG-1). They counted the
checks of E2E-only frames (CRC, rolling counter), which the DBC no longer has."""


def sender_of(name: str) -> str:
    """The key label of a message's transmitter in the DBC: ``router`` (ER), ``plant``
    (PLANT) or ``agent_<i>`` (AGENT_<i>)."""
    node = _message(name).senders[0]
    return {"ER": "router", "PLANT": "plant"}.get(node, node.lower())
