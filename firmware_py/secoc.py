"""Frame authentication in the style of AUTOSAR SecOC profile 1 for classic CAN.

The core: pure functions and small classes; ``firmware_py.nodeio`` puts them on the
wire (docs/security.md). All cryptography comes from the maintained ``cryptography``
package; nothing here is hand-written crypto.

Keys
    ``derive_node_key(master, node)``: NIST SP 800-108 key derivation in counter
    mode with CMAC-AES-128 as the PRF (``KBKDFCMAC``), one 128-bit key per node::

        K_node = PRF(K_master, [i]_32 ‖ LABEL ‖ 0x00 ‖ UTF-8(node) ‖ [128]_32),  i = 1

    with LABEL = ``b"bess-ded/secoc/node-key/v1"``, the counter ``i`` and the output
    length L = 128 as 32-bit big-endian integers, the counter before the fixed data.
    A node holds only its own K_node; knowing it says nothing about another node's
    key or about K_master (a PRF output).

    ``derive_frame_key(master, name)``: the key of a *link frame*, a secured message
    with a single receiving peer (``contract.LINK_FRAMES``: AGENT_<i>_Setpoint to the
    plant, PLANT_<i>_Status to agent i, which the router reads too), and of its sync
    (AUTH-28)::

        K_frame = PRF(K_master, [1]_32 ‖ FRAME_LABEL ‖ 0x00 ‖ UTF-8(message name) ‖ [128]_32)

    with FRAME_LABEL = ``b"bess-ded/secoc/frame-key/v1"``. Only the frame's sender and
    its DBC receivers hold it (a key file's ``[frame_keys]``), so a third node's key
    file cannot sign it: agent 3 can no longer forge agent 1's status or setpoint.

    ``derive_command_key(master, target)``: the key of the ER_Command frames addressed
    to agent ``target`` ('agent_3', the frame's Target), AUTH-30::

        K_cmd = PRF(K_master, [1]_32 ‖ COMMAND_LABEL ‖ 0x00 ‖ UTF-8(target) ‖ [128]_32)

    with COMMAND_LABEL = ``b"bess-ded/secoc/command-key/v1"``. Only the router and that
    agent hold it (a key file's ``[command_keys]``): agent 3 can no longer isolate
    agent 1. ER_Command_Sync keeps the router's node key (it has no Target).

    ``derive_lambda_tag_key(master, sender, receiver)``: on CAN FD, the key of the
    pair (agent i, one receiver of its λ) whose 24-bit tag the receiver verifies in
    ``AGENT_i_MC`` and its sync (AUTH-34)::

        K_tag = PRF(K_master, [1]_32 ‖ TAG_LABEL ‖ 0x00 ‖ UTF-8("agent_i>" ‖ receiver) ‖ [128]_32)

    with TAG_LABEL = ``b"bess-ded/secoc/lambda-tag-key/v1"`` (a key file's
    ``[lambda_tag_keys]``): only agent i and that receiver hold it.
    ``fleet_id(master)`` is a public 64-bit tag of the key set (same KDF, label
    ``b"bess-ded/secoc/fleet-id/v1"``, empty context, L = 64) so that nodes from
    different provisionings can tell.

Freshness
    Per sender and frame ID, a 40-bit full freshness value FV = boot counter (16 bits)
    ‖ message counter (24 bits) (``FreshnessLayout``). The boot counter is persisted
    in the node's key file and bumped *before* the first frame of every start, and
    whenever a message counter would wrap (``Keyring.new_boot``), so FV strictly
    increases across restarts; ``firmware_py.nodeio`` counts the messages. Only the
    low ``tx_bits`` (4: the DBC's Counter) of FV go on the wire; the receiver rebuilds
    the full value from the last one it accepted (``FreshnessVerifier``).

Authenticator
    ``authenticator(key, data_id, payload, freshness, bits)`` is the most significant
    ``bits`` bits of CMAC-AES-128(K_sender, M) with::

        M = data_id (2 bytes, big-endian) ‖ payload (as is) ‖ FV (8 bytes, big-endian)

    This is the layout of ``cantools.autosar.secoc.compute_authenticator`` for a
    message whose SecOC properties say ``freshness_bit_length = 64`` and
    ``payload_length = len(payload)`` (cantools packs ``u16 ‖ payload ‖ u64`` with
    bitstruct, most significant bit first); tests/test_secoc.py checks that they agree.
    The truncation keeps the leading bits of the CMAC, as SecOC and cantools'
    ``apply_authenticator`` do.
"""

from __future__ import annotations

import functools
import hmac
import os
import re
import stat
import tomllib
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from cryptography.hazmat.primitives import cmac
from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.kdf.kbkdf import KBKDFCMAC, CounterLocation, Mode

from .errors import BessDedError

KEY_BYTES = 16                      # AES-128
MAC_BITS = 24                       # profile 1: a 24-bit truncated CMAC on the wire
TX_FRESHNESS_BITS = 4               # the low 4 bits of FV on the wire (the DBC's Counter)
DATA_ID_BITS = 16                   # SecOCDataId is a uint16
SEEN_BITS = 32                      # accepted frames remembered below the last (AUTH-25)
# AUTH-27: a sync may move its sender's boot counter at most this far ahead of the boot a
# receiver expects. A genuine sender moves one boot per start (and per 2^24 frames on an
# ID), more only when starts fail before their first sync is heard (the boot is persisted
# first, AUTH-3): 8 leaves 7 failed starts in a row (systemd gives up after 5 by default).
# A key holder's forged sync can thus move a sender's freshness at most 8 of its 65,535
# boots, not to its end (which locked the sender out for good: issue 25).
SYNC_BOOT_JUMP_MAX = 8
FV_WIRE_BYTES = 8                   # FV in the MAC input: always 8 bytes, big-endian
NODE_KEY_LABEL = b"bess-ded/secoc/node-key/v1"
FLEET_ID_LABEL = b"bess-ded/secoc/fleet-id/v1"
FRAME_KEY_LABEL = b"bess-ded/secoc/frame-key/v1"
COMMAND_KEY_LABEL = b"bess-ded/secoc/command-key/v1"
LAMBDA_TAG_KEY_LABEL = b"bess-ded/secoc/lambda-tag-key/v1"  # AUTH-34 (CAN FD)
PRICE_SIGN_KEY_LABEL = b"bess-ded/price-sign-key/v1"  # signed_price: the router's Ed25519 seed
PRICE_SIGN_BYTES = 32
KEY_FILE_FORMAT = "bess-ded-secoc-node-key/1"
MASTER_FILE_FORMAT = "bess-ded-secoc-master-key/1"
KDF_NAME = "NIST SP 800-108 counter mode, CMAC-AES-128"
MAC_NAME = "CMAC-AES-128"
_NODE_RE = re.compile(r"[a-z][a-z0-9_]{0,31}")
_FRAME_RE = re.compile(r"[A-Z][A-Za-z0-9_]{0,31}")


def beyond_boot_bound(boot: int, expected: int) -> bool:
    """AUTH-27: whether a verified sync's ``boot`` lies too far ahead of the ``expected``
    one to be taken (the nodes and the recorder's monitor refuse it alike)."""
    return boot - expected > SYNC_BOOT_JUMP_MAX


class SecOCError(BessDedError, ValueError):
    """A SecOC parameter or key is invalid (wrong length, out-of-range value)."""


class KeyFileError(BessDedError):
    """A key file is missing, unreadable, malformed, or readable by others."""


# --------------------------------------------------------------------------- keys


def _check_key(key: bytes, what: str = "key") -> bytes:
    if not isinstance(key, bytes | bytearray) or len(key) != KEY_BYTES:
        got = f"{len(key)} bytes" if isinstance(key, bytes | bytearray) else type(key).__name__
        raise SecOCError(f"{what}: expected {KEY_BYTES} bytes (AES-128), but got {got}")
    return bytes(key)


def check_node_name(node: str) -> str:
    """A node label: lower-case letters, digits and '_', starting with a letter, at
    most 32 characters ('agent_3', 'plant', 'router')."""
    if not isinstance(node, str) or not _NODE_RE.fullmatch(node):
        raise SecOCError(f"node: expected a name like 'agent_3', 'plant' or 'router' "
                         f"([a-z][a-z0-9_]*, at most 32 characters), but got {node!r}")
    return node


def _kbkdf(master_key: bytes, label: bytes, context: bytes, length: int) -> bytes:
    return KBKDFCMAC(
        algorithm=algorithms.AES, mode=Mode.CounterMode, length=length,
        rlen=4, llen=4, location=CounterLocation.BeforeFixed,
        label=label, context=context, fixed=None,
    ).derive(_check_key(master_key, "master key"))


def derive_node_key(master_key: bytes, node: str) -> bytes:
    """The node's 16-byte CMAC key (see the module docstring for the exact encoding)."""
    return _kbkdf(master_key, NODE_KEY_LABEL, check_node_name(node).encode(), KEY_BYTES)


def check_frame_name(name: str) -> str:
    """A DBC message name as a frame key's label ('PLANT_1_Status')."""
    if not isinstance(name, str) or not _FRAME_RE.fullmatch(name):
        raise SecOCError(f"frame: expected a DBC message name like 'PLANT_1_Status' "
                         f"([A-Z][A-Za-z0-9_]*, at most 32 characters), but got {name!r}")
    return name


def derive_frame_key(master_key: bytes, name: str) -> bytes:
    """The 16-byte CMAC key of link frame ``name`` and of its sync (AUTH-28; the module
    docstring gives the encoding): held only by its sender and its receivers."""
    return _kbkdf(master_key, FRAME_KEY_LABEL, check_frame_name(name).encode(), KEY_BYTES)


def check_target(target: str) -> str:
    """A command's target as a key label: an agent ('agent_3')."""
    if not isinstance(target, str) or not re.fullmatch(r"agent_[1-9][0-9]?", target):
        raise SecOCError(f"command target: expected an agent like 'agent_3', but got "
                         f"{target!r}")
    return target


def derive_command_key(master_key: bytes, target: str) -> bytes:
    """The 16-byte CMAC key of the ER_Command frames addressed to agent ``target``
    (AUTH-30; the module docstring gives the encoding): held only by the router and that
    agent."""
    return _kbkdf(master_key, COMMAND_KEY_LABEL, check_target(target).encode(), KEY_BYTES)


_PAIR_RE = re.compile(r"(agent_[1-9][0-9]?)>(agent_[1-9][0-9]?|plant|router)")


def pair_label(sender: str, receiver: str) -> str:
    """A λ tag key's label (AUTH-34): ``"agent_1>agent_3"``, ``"agent_1>plant"``."""
    return check_pair(f"{sender}>{receiver}")


def check_pair(label: str) -> str:
    """A λ tag key's label, checked: an agent, '>', and an agent, the plant or the router."""
    m = _PAIR_RE.fullmatch(label) if isinstance(label, str) else None
    if m is None or m.group(1) == m.group(2):
        raise SecOCError(f"lambda tag key: expected 'agent_i>RECEIVER' (an agent other than "
                         f"agent_i, plant or router), but got {label!r}")
    return label


def derive_lambda_tag_key(master_key: bytes, sender: str, receiver: str) -> bytes:
    """The 16-byte CMAC key of the tags agent ``sender``'s λ frames (and their sync) carry
    for ``receiver`` on CAN FD (AUTH-34; the module docstring gives the encoding): held
    only by the two of them."""
    return _kbkdf(master_key, LAMBDA_TAG_KEY_LABEL, pair_label(sender, receiver).encode(),
                  KEY_BYTES)


def tag_code(node: str) -> int:
    """The receiver code of ``node`` in a tag slot (AUTH-34, the FD DBC's TagRx choices):
    agent j → j, the plant → 0xFE, the router → 0xFF."""
    from .frames import TAG_RX_PLANT, TAG_RX_ROUTER  # frames imports this module's users

    if node == "plant":
        return TAG_RX_PLANT
    if node == "router":
        return TAG_RX_ROUTER
    return int(check_node_name(node).removeprefix("agent_"))


def derive_price_sign_key(master_key: bytes) -> bytes:
    """signed_price (AUTH-31): the router's 32-byte Ed25519 private key (RFC 8032 seed),
    KBKDF of the master key with PRICE_SIGN_KEY_LABEL and context ``router``. Only the
    router's key file holds it; every other node holds its public key."""
    return _kbkdf(master_key, PRICE_SIGN_KEY_LABEL, b"router", PRICE_SIGN_BYTES)


def fleet_id(master_key: bytes) -> str:
    """A public 16-hex-digit tag of a key set: equal for every node of one provisioning."""
    return _kbkdf(master_key, FLEET_ID_LABEL, b"", 8).hex()


def fleet_nodes(n_agents: int) -> list[str]:
    """Every node of a fleet of ``n_agents`` agents, in provisioning order."""
    if n_agents < 1:
        raise SecOCError(f"n_agents: expected ≥ 1, but got {n_agents}")
    return [f"agent_{i}" for i in range(1, n_agents + 1)] + ["plant", "router"]


# --------------------------------------------------------------------------- authenticator


@functools.lru_cache(maxsize=1024)
def _cmac_of(key: bytes) -> cmac.CMAC:
    """A CMAC context keyed with ``key``, never finalised: each tag starts from a copy
    (the AES key schedule is done once per key, not per frame: ~13x faster a tag)."""
    return cmac.CMAC(algorithms.AES(_check_key(key)))


def cmac_aes128(key: bytes, message: bytes) -> bytes:
    """The full 16-byte CMAC-AES-128 tag (NIST SP 800-38B) of ``message``."""
    c = _cmac_of(bytes(key)).copy()
    c.update(message)
    return c.finalize()


def auth_data(data_id: int, payload: bytes, freshness: int) -> bytes:
    """The MAC input: data_id (2 bytes BE) ‖ payload ‖ freshness (8 bytes BE)."""
    if not 0 <= data_id < 1 << DATA_ID_BITS:
        raise SecOCError(f"data_id: expected 0..{(1 << DATA_ID_BITS) - 1}, but got {data_id}")
    if not 0 <= freshness < 1 << (8 * FV_WIRE_BYTES):
        raise SecOCError(f"freshness: expected 0..2^64-1, but got {freshness}")
    return (data_id.to_bytes(2, "big") + bytes(payload)
            + freshness.to_bytes(FV_WIRE_BYTES, "big"))


def _check_bits(bits: int) -> int:
    if not isinstance(bits, int) or not 1 <= bits <= 128:
        raise SecOCError(f"bits: expected 1..128 (24 in profile 1), but got {bits!r}")
    return bits


def authenticator(key: bytes, data_id: int, payload: bytes, freshness: int,
                  bits: int = MAC_BITS) -> int:
    """The leading ``bits`` bits of CMAC-AES-128(key, auth_data(...)), as an integer."""
    tag = cmac_aes128(key, auth_data(data_id, payload, freshness))
    return int.from_bytes(tag, "big") >> (128 - _check_bits(bits))


def verify(key: bytes, data_id: int, payload: bytes, freshness: int, mac: int,
           bits: int = MAC_BITS) -> bool:
    """Whether ``mac`` is the authenticator of (data_id, payload, freshness); the
    comparison takes the same time wherever the values differ."""
    expected = authenticator(key, data_id, payload, freshness, bits)
    if not isinstance(mac, int) or not 0 <= mac < 1 << bits:
        return False
    n = (bits + 7) // 8
    return hmac.compare_digest(expected.to_bytes(n, "big"), mac.to_bytes(n, "big"))


# --------------------------------------------------------------------------- freshness


@dataclass(frozen=True)
class FreshnessLayout:
    """FV = boot counter (``boot_bits``) ‖ message counter (``counter_bits``)."""

    boot_bits: int = 16
    counter_bits: int = 24

    def __post_init__(self) -> None:
        if self.boot_bits < 1 or self.counter_bits < 1 or self.bits > 8 * FV_WIRE_BYTES:
            raise SecOCError(f"freshness layout: expected boot_bits, counter_bits ≥ 1 and "
                             f"a total ≤ 64 bits, but got {self.boot_bits} + "
                             f"{self.counter_bits}")

    @property
    def bits(self) -> int:
        """Bits of a whole freshness value (boot + counter)."""
        return self.boot_bits + self.counter_bits

    @property
    def max_boot(self) -> int:
        """The largest boot counter the layout holds."""
        return (1 << self.boot_bits) - 1

    @property
    def max_counter(self) -> int:
        """The largest message counter the layout holds."""
        return (1 << self.counter_bits) - 1

    @property
    def max_value(self) -> int:
        """The largest freshness value the layout holds."""
        return (1 << self.bits) - 1

    def join(self, boot: int, counter: int) -> int:
        """The freshness value of (``boot``, ``counter``); SecOCError if either is
        out of range."""
        if not 0 <= boot <= self.max_boot or not 0 <= counter <= self.max_counter:
            raise SecOCError(f"freshness: boot {boot} or counter {counter} out of range")
        return boot << self.counter_bits | counter

    def split(self, freshness: int) -> tuple[int, int]:
        """(boot, counter) of a freshness value."""
        return freshness >> self.counter_bits, freshness & self.max_counter

    def undoes_advance(self, fv: int, last: int, back: int | None) -> bool:
        """AUTH-27: whether a verified sync of value ``fv`` undoes the boot advance whose
        undo point is ``back`` (None: none pending), ``last`` the value taken since: its
        boot is at or after the one the advance left and before the current one, and it
        is newer than anything taken of that boot. The nodes and the recorder's monitor
        decide with this one rule."""
        if back is None or fv - 1 <= back:
            return False
        boot = self.split(fv)[0]
        return self.split(back + 1)[0] <= boot < self.split(last + 1)[0]


DEFAULT_LAYOUT = FreshnessLayout()


def truncate(freshness: int, tx_bits: int = TX_FRESHNESS_BITS) -> int:
    """The low ``tx_bits`` of FV: what a frame carries."""
    return freshness & ((1 << tx_bits) - 1)


class FreshnessVerifier:
    """Receiver side: per sender, the last accepted FV; accepts only larger ones.

    ``candidate(sender, truncated)`` rebuilds the full FV from the ``tx_bits`` low
    bits a frame carries, as SecOC does: the high bits of the last accepted value,
    plus one step of 2^tx_bits when the received low bits are not above the last
    ones. The candidate is therefore always in (last, last + 2^tx_bits]: the
    acceptance window. Up to 2^tx_bits − 1 consecutive lost frames are tolerated;
    after a longer gap, or a sender restart (its boot counter moved on), the MAC
    check fails until a resynchronisation. The caller checks the MAC with the
    candidate and calls ``accept`` only if it holds (``NodeIO`` does both).

    ``accept(sender, full, frame=False)`` takes an authenticated frame that carries a
    sender's full FV (docs/security.md: the sender's ``<name>_Sync`` frame). Call it
    only after that frame's MAC was verified; it moves the state forward only (a
    replayed sync cannot rewind).
    A sender with no state yet (``last(sender) is None``) needs a resync first.
    """

    def __init__(self, tx_bits: int = TX_FRESHNESS_BITS,
                 layout: FreshnessLayout = DEFAULT_LAYOUT,
                 initial: Mapping[Hashable, int] | None = None) -> None:
        if not 1 <= tx_bits <= layout.bits:
            raise SecOCError(f"tx_bits: expected 1..{layout.bits}, but got {tx_bits}")
        self.tx_bits = tx_bits
        self.layout = layout
        self._last: dict[Hashable, int] = dict(initial or {})
        # per sender: bit k set = the frame with FV last − k was accepted (k < SEEN_BITS)
        self._seen: dict[Hashable, int] = {}

    def last(self, sender: Hashable) -> int | None:
        """The last freshness value accepted from ``sender``, None before the first."""
        return self._last.get(sender)

    def state(self) -> dict[Hashable, int]:
        """Every sender's last accepted FV (e.g. to persist a receiver's state)."""
        return dict(self._last)

    def candidate(self, sender: Hashable, truncated: int) -> int | None:
        """The full FV to verify a frame with, or None (no state for this sender, or
        the candidate would exceed the layout: resync or re-key needed)."""
        last = self._last.get(sender)
        mask = (1 << self.tx_bits) - 1
        if last is None or not 0 <= truncated <= mask:
            return None
        high = last >> self.tx_bits
        if truncated <= last & mask:
            high += 1
        value = high << self.tx_bits | truncated
        return value if value <= self.layout.max_value else None

    def past(self, sender: Hashable, truncated: int, windows: int = 1) -> list[int]:
        """The values at or below the last accepted one that carry ``truncated`` as
        their low bits and were not accepted themselves, newest first, one per window
        of 2^tx_bits, ``windows`` windows back: what a genuine frame that arrived late
        or out of order verifies with (``NodeIO`` counts such a frame ``stale``, not
        forged). A value already accepted is left out: that frame again is a replay
        (or a duplicate), not a late one. Empty without state for this sender."""
        last = self._last.get(sender)
        mask = (1 << self.tx_bits) - 1
        if last is None or not 0 <= truncated <= mask:
            return []
        newest = last - ((last - truncated) & mask)
        return [v for v in range(newest, newest - (windows << self.tx_bits), -(mask + 1))
                if v >= 0 and not self.seen(sender, v)]

    def search(self, sender: Hashable, truncated: int, windows: int,
               verifies: Callable[[int], bool]) -> int | None:
        """AUTH-13: the first FV from the candidate on, one per window of 2^tx_bits,
        ``windows`` windows forward, for which ``verifies`` (the frame's MAC check)
        holds; None if none does (or the sender has no state). The one search every
        receiver uses: the nodes' ``NodeIO`` and the recorder alike."""
        fv = self.candidate(sender, truncated)
        for _ in range(windows):
            if fv is None:
                return None
            if verifies(fv):
                return fv
            fv += 1 << self.tx_bits
        return None

    def search_late(self, sender: Hashable, truncated: int, windows: int,
                    verifies: Callable[[int], bool]) -> bool:
        """AUTH-25: whether a frame that failed ``search`` verifies with one of
        ``past(sender, truncated, windows)`` (its sender's genuine frame, late); that
        value is then spent (``mark``), so the same frame again is a replay."""
        for fv in self.past(sender, truncated, windows):
            if verifies(fv):
                self.mark(sender, fv)
                return True
        return False

    def late_sync(self, behind: int) -> bool:
        """AUTH-16, AUTH-25: a verified sync ``behind`` values below the newest one
        known of its sender is that sender's genuine sync delivered late (its tick's
        frame overtook it) when less than one window behind, else a replayed sync."""
        return behind < 1 << self.tx_bits

    def seen(self, sender: Hashable, freshness: int) -> bool:
        """Whether a frame with this FV was accepted (known for the SEEN_BITS values up
        to the last accepted one; older ones count as seen)."""
        last = self._last.get(sender)
        if last is None or freshness > last:
            return False
        back = last - freshness
        return back >= SEEN_BITS or bool(self._seen.get(sender, 0) >> back & 1)

    def mark(self, sender: Hashable, freshness: int) -> None:
        """A late frame with this FV (≤ the last accepted) verified: that value is
        spent too, so the same frame again is a replay."""
        last = self._last.get(sender)
        if last is not None and 0 <= last - freshness < SEEN_BITS:
            self._seen[sender] = self._seen.get(sender, 0) | 1 << (last - freshness)

    def accept(self, sender: Hashable, freshness: int, frame: bool = True) -> bool:
        """Record an authenticated FV; False (and no change) unless it is strictly
        greater than the last accepted one. ``frame``: a frame with this FV was
        accepted (False: a sync's FV − 1, which no frame of this receiver carried)."""
        last = self._last.get(sender)
        if not 0 <= freshness <= self.layout.max_value or (last is not None
                                                           and freshness <= last):
            return False
        shift = freshness - last if last is not None else SEEN_BITS
        seen = self._seen.get(sender, 0) << shift if shift < SEEN_BITS else 0
        self._seen[sender] = (seen | int(frame)) & ((1 << SEEN_BITS) - 1)
        self._last[sender] = freshness
        return True

    def forget(self, sender: Hashable) -> None:
        """Drop a sender's state (``--insecure`` only: a restarted sender there has no
        persisted boot counter, so its values may go back)."""
        self._last.pop(sender, None)
        self._seen.pop(sender, None)


# --------------------------------------------------------------------------- key files


@dataclass(frozen=True)
class NodeKey:
    """One node's key file, loaded."""

    node: str
    key: bytes
    fleet_id: str
    boot_counter: int
    path: Path
    peers: Mapping[str, bytes] = field(default_factory=dict)  # label -> verification key
    floors: Mapping[str, int] = field(default_factory=dict)   # label -> lowest boot accepted
    frames: Mapping[str, bytes] = field(default_factory=dict)  # link frame -> its key
    commands: Mapping[str, bytes] = field(default_factory=dict)  # target -> command key
    tags: Mapping[str, bytes] = field(default_factory=dict)  # 'agent_i>r' -> λ tag key
    price_sign: bytes | None = None    # signed_price: the router's Ed25519 seed (router only)
    price_verify: bytes | None = None  # signed_price: the router's Ed25519 public key

    def __repr__(self) -> str:  # never print the key
        return (f"NodeKey(node={self.node!r}, fleet_id={self.fleet_id!r}, "
                f"boot_counter={self.boot_counter}, path={str(self.path)!r})")

    def persist(self) -> Callable[[int], None]:
        """A ``Keyring`` persist callback writing the boot counter to this key file."""
        return lambda boot: save_boot_counter(self.path, boot)


def node_key_document(node: str, key: bytes, fleet: str, boot_counter: int = 0,
                      peers: Mapping[str, bytes] | None = None,
                      floors: Mapping[str, int] | None = None,
                      frames: Mapping[str, bytes] | None = None,
                      commands: Mapping[str, bytes] | None = None,
                      price_sign: bytes | None = None,
                      price_verify: bytes | None = None,
                      tags: Mapping[str, bytes] | None = None) -> dict:
    """The TOML document of a node key file. ``peers``: the verification keys of the
    senders of the broadcast frames this node receives (need to know: docs/security.md);
    ``floors``: the lowest boot counter it accepts from each sender (AUTH-21);
    ``frames``: the keys of the link frames and reports it sends or receives (AUTH-28,
    AUTH-29); ``commands``: the ER_Command keys per target agent (AUTH-30); ``tags``: the
    λ tag keys of the pairs it is one of (AUTH-34, CAN FD)."""
    doc = {
        "format": KEY_FILE_FORMAT,
        "node": check_node_name(node),
        "fleet_id": fleet,
        "kdf": KDF_NAME,
        "mac": MAC_NAME,
        "key": _check_key(key).hex(),
        "freshness": {"boot_counter": boot_counter},
        "peers": {check_node_name(p): _check_key(k).hex() for p, k in (peers or {}).items()},
    }
    if frames:
        doc["frame_keys"] = {check_frame_name(f): _check_key(k).hex()
                             for f, k in sorted(frames.items())}
    if commands:
        doc["command_keys"] = {check_target(t): _check_key(k).hex()
                               for t, k in sorted(commands.items())}
    if tags:
        doc["lambda_tag_keys"] = {check_pair(t): _check_key(k).hex()
                                  for t, k in sorted(tags.items())}
    if floors:
        doc["floors"] = {check_node_name(p): int(b) for p, b in sorted(floors.items())}
    if price_sign is not None or price_verify is not None:  # signed_price (AUTH-31)
        doc["price_signature"] = ({"sign_key": price_sign.hex()} if price_sign is not None
                                  else {"verify_key": price_verify.hex()})  # type: ignore[union-attr]
    return doc


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` with mode 0600 from the first byte on: a temporary
    file created 0600 (O_EXCL, no symlink following), fsynced, then renamed over."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0),
                 0o600)
    try:
        os.fchmod(fd, 0o600)  # the umask can only have removed bits; make it exact
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    try:  # make the rename durable too
        dfd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)


def _check_private(path: Path, what: str) -> None:
    try:
        st = os.lstat(path)
    except OSError as e:
        raise KeyFileError(f"{path}: cannot read the {what}: {e.strerror or e}") from e
    if stat.S_ISLNK(st.st_mode):
        # refused, not followed: the link's directory and the target's could differ in who
        # may access them, and a boot counter saved through it would replace the link by
        # a copy (write_private renames over it), leaving the target's counter behind
        raise KeyFileError(f"{path}: expected the {what} itself, but got a symbolic link "
                           f"(to {os.readlink(path)}): give the file's own path")
    if not stat.S_ISREG(st.st_mode):
        raise KeyFileError(f"{path}: expected a regular file for the {what}")
    if st.st_mode & 0o077:
        raise KeyFileError(
            f"{path}: permissions {stat.S_IMODE(st.st_mode):04o} are too open: the {what} "
            f"must not be accessible by group or others (chmod 600 {path})")
    if hasattr(os, "getuid") and st.st_uid != os.getuid():
        raise KeyFileError(f"{path}: the {what} is owned by uid {st.st_uid}, not by this "
                           f"user ({os.getuid()})")


def _read_private(path: Path, what: str) -> dict:
    _check_private(path, what)
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise KeyFileError(f"{path}: not a readable TOML {what}: {e}") from e


def _key_table(doc: dict, table_name: str, what: str,
               check: Callable[[str], object], path: Path) -> dict[str, bytes]:
    """A key file's ``[table_name]`` of WHAT = key (hex), each name checked."""
    table = doc.get(table_name, {})
    if not isinstance(table, dict):
        raise KeyFileError(f"{path}: [{table_name}] expected a table of {what} = key (hex)")
    keys = {}
    for name in table:
        try:
            check(name)
        except SecOCError as e:
            raise KeyFileError(f"{path}: [{table_name}] {e}") from e
        keys[name] = _hex_key(table, name, path)
    return keys


def _hex_key(doc: dict, name: str, path: Path) -> bytes:
    value = doc.get(name)
    try:
        key = bytes.fromhex(value) if isinstance(value, str) else b""
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise KeyFileError(f"{path}: [{name}] expected {2 * KEY_BYTES} hex digits")
    return key


def load_node_key(path: Path | str) -> NodeKey:
    """Load a node key file written by ``bess-ded keys``. Refuses, like ssh, a file
    that group or others may access, one owned by another user, and malformed ones."""
    path = Path(path)
    doc = _read_private(path, "node key file")
    if doc.get("format") != KEY_FILE_FORMAT:
        raise KeyFileError(f"{path}: [format] expected {KEY_FILE_FORMAT!r}, but got "
                           f"{doc.get('format')!r}")
    node = doc.get("node")
    try:
        check_node_name(node)  # type: ignore[arg-type]
    except SecOCError as e:
        raise KeyFileError(f"{path}: [node] {e}") from e
    fleet = doc.get("fleet_id")
    if not isinstance(fleet, str) or not re.fullmatch(r"[0-9a-f]{16}", fleet):
        raise KeyFileError(f"{path}: [fleet_id] expected 16 hex digits")
    fresh = doc.get("freshness")
    boot = fresh.get("boot_counter") if isinstance(fresh, dict) else None
    if (not isinstance(boot, int) or isinstance(boot, bool)
            or not 0 <= boot <= DEFAULT_LAYOUT.max_boot):
        raise KeyFileError(f"{path}: [freshness.boot_counter] expected an integer "
                           f"0..{DEFAULT_LAYOUT.max_boot}, but got {boot!r}")
    peers = _key_table(doc, "peers", "node", check_node_name, path)
    frames = _key_table(doc, "frame_keys", "message", check_frame_name, path)
    commands = _key_table(doc, "command_keys", "target", check_target, path)
    tags = _key_table(doc, "lambda_tag_keys", "pair", check_pair, path)
    _check_own_keys(node, frames, commands, path)  # type: ignore[arg-type]
    not_ours = sorted(t for t in tags if node not in t.split(">"))
    if not_ours:
        raise KeyFileError(f"{path}: [lambda_tag_keys] expected the pairs {node} is one of "
                           f"only, but got {', '.join(not_ours)} (re-provision with "
                           "bess-ded keys)")
    senders = set(peers) | _frame_senders(frames) | _tag_senders(node, tags)  # type: ignore[arg-type]
    floors = doc.get("floors", {})
    if not isinstance(floors, dict) or any(
            p not in senders or not isinstance(b, int) or isinstance(b, bool)
            or not 0 <= b <= DEFAULT_LAYOUT.max_boot for p, b in floors.items()):
        raise KeyFileError(f"{path}: [floors] expected a table of peer = lowest boot counter "
                           f"(0..{DEFAULT_LAYOUT.max_boot}), for peers listed in [peers] or "
                           f"senders of [frame_keys] or [lambda_tag_keys]")
    sign, verify = _price_keys(doc, path)
    return NodeKey(node=node, key=_hex_key(doc, "key", path),  # type: ignore[arg-type]
                   fleet_id=fleet, boot_counter=boot, path=path, peers=peers,
                   floors=dict(floors), frames=frames, commands=commands, tags=tags,
                   price_sign=sign, price_verify=verify)


def _price_keys(doc: dict, path: Path) -> tuple[bytes | None, bytes | None]:
    """[price_signature] (signed_price, AUTH-31): sign_key (the router's Ed25519 seed) or
    verify_key (its public key), 32 bytes hex each; (None, None) without the table."""
    t = doc.get("price_signature")
    if t is None:
        return None, None
    if not isinstance(t, dict) or len(t) != 1 or not set(t) <= {"sign_key", "verify_key"}:
        raise KeyFileError(f"{path}: [price_signature] expected exactly one of sign_key, "
                           "verify_key")
    (name, value), = t.items()
    try:
        raw = bytes.fromhex(value) if isinstance(value, str) else b""
    except ValueError:
        raw = b""
    if len(raw) != PRICE_SIGN_BYTES:
        raise KeyFileError(f"{path}: [price_signature.{name}] expected {PRICE_SIGN_BYTES} "
                           "bytes as hex")
    if name == "sign_key":
        return raw, None
    return None, raw


def _check_own_keys(node: str, frames: Mapping[str, bytes], commands: Mapping[str, bytes],
                    path: Path) -> None:
    """A node's file holds only the frame keys of the frames it sends or receives
    (AUTH-28, AUTH-29) and the command keys of the commands to itself (the router: to
    every agent; AUTH-30), as firmware_c's loader checks: a key beyond them would let the
    node speak for another, so a file with one is refused, not trimmed silently."""
    from . import contract  # contract imports this module

    foreign = sorted(f for f in frames if f not in contract.KEYED_FRAMES
                     or node not in contract.parties_of(f))
    if foreign:
        raise KeyFileError(f"{path}: [frame_keys] expected the keys of the frames {node} "
                           f"sends or receives only, but got {', '.join(foreign)} "
                           "(re-provision with bess-ded keys)")
    others = sorted(t for t in commands if node not in (t, "router"))
    if others:
        raise KeyFileError(f"{path}: [command_keys] expected "
                           f"{'the key of ' + node if node.startswith('agent_') else 'none'} "
                           f"only, but got {', '.join(others)} (re-provision with "
                           "bess-ded keys)")


def _tag_senders(node: str, tags: Mapping[str, bytes]) -> set[str]:
    """AUTH-34: the agents whose tagged λ this node receives (their floors may be kept)."""
    return {s for s, r in (t.split(">") for t in tags) if r == node}


def _frame_senders(frames: Mapping[str, bytes]) -> set[str]:
    """The senders of link frames (their floors may be kept, AUTH-21)."""
    from . import contract  # contract imports this module

    return {contract.sender_of(f) for f in frames if f in contract.KEYED_FRAMES}


def save_boot_counter(path: Path | str, boot: int) -> None:
    """Persist a new boot counter into a node key file (atomically, staying 0600)."""
    import tomli_w

    current = load_node_key(path)
    if boot < current.boot_counter:
        raise SecOCError(f"{path}: boot counter must not go back ({current.boot_counter} "
                         f"→ {boot})")
    doc = node_key_document(current.node, current.key, current.fleet_id, boot, current.peers,
                            current.floors, current.frames, current.commands,
                            current.price_sign, current.price_verify, current.tags)
    write_private(Path(path), KEY_FILE_HEADER + tomli_w.dumps(doc))


def save_floors(path: Path | str, floors: Mapping[str, int]) -> None:
    """Raise a node key file's boot floors (AUTH-21) to ``floors`` (peer -> the lowest
    boot counter it may use from now on); a floor never goes down."""
    import tomli_w

    current = load_node_key(path)
    merged = dict(current.floors)
    senders = (set(current.peers) | _frame_senders(current.frames)
               | _tag_senders(current.node, current.tags))
    for peer, boot in floors.items():
        if peer in senders:
            merged[peer] = max(merged.get(peer, 0), boot)
    doc = node_key_document(current.node, current.key, current.fleet_id,
                            current.boot_counter, current.peers, merged, current.frames,
                            current.commands, current.price_sign, current.price_verify,
                            current.tags)
    write_private(Path(path), KEY_FILE_HEADER + tomli_w.dumps(doc))


def master_key_document(master_key: bytes) -> dict:
    """The TOML document of a master key file: format, fleet id and the key in hex."""
    return {"format": MASTER_FILE_FORMAT, "fleet_id": fleet_id(master_key),
            "master_key": _check_key(master_key, "master key").hex()}


def load_master_key(path: Path | str) -> bytes:
    """A master key file: the TOML ``bess-ded keys`` writes, or one line of 32 hex
    digits; same permission rules as a node key file."""
    path = Path(path)
    _check_private(path, "master key file")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise KeyFileError(f"{path}: cannot read the master key file: {e}") from e
    line = raw.strip()
    if re.fullmatch(rb"[0-9a-fA-F]{%d}" % (2 * KEY_BYTES), line):
        return bytes.fromhex(line.decode())
    try:
        doc = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError):
        raise KeyFileError(f"{path}: expected a master key file written by bess-ded keys, "
                           f"or {2 * KEY_BYTES} hex digits") from None
    if doc.get("format") != MASTER_FILE_FORMAT:
        raise KeyFileError(f"{path}: [format] expected {MASTER_FILE_FORMAT!r}, but got "
                           f"{doc.get('format')!r}")
    return _hex_key(doc, "master_key", path)


KEY_FILE_HEADER = ("# bess-ded SecOC node key (docs/security.md). Secret: keep it "
                    "owner-only (0600).\n# freshness.boot_counter is rewritten at every "
                    "start; losing it means re-provisioning.\n")
MASTER_FILE_HEADER = ("# bess-ded SecOC fleet master key (docs/security.md). Every node key "
                      "derives from it:\n# keep it offline, not on the nodes.\n")


# --------------------------------------------------------------------------- keyrings

INSECURE_BOOT = 1
"""The boot counter of every ``--insecure`` sender (nothing is persisted in that mode)."""
INSECURE_MASTER = bytes(KEY_BYTES)
"""The public master key of ``--insecure`` mode (all zero): frames still carry a MAC and
freshness, so corruption and stale frames are caught, but anyone can forge them."""


class Keyring:
    """What one node needs on the bus: its own key and boot counter, and the
    verification key of every sender it receives secured frames from.

    Built from a key file (``from_file``: the peers it lists), from a fleet master
    key held in memory (``fleet``: simulated and in-process runs; every key derived on
    demand), or for ``--insecure`` demos (``insecure``: the public all-zero master
    key, and a receiver accepts a sync that goes back, since a restarted insecure
    sender has no persisted boot counter).
    """

    def __init__(self, node: str, key: bytes, boot: int, persist: Callable[[int], None],
                 peers: Mapping[str, bytes] | None = None, master: bytes | None = None,
                 insecure: bool = False, fleet: str = "",
                 floors: Mapping[str, int] | None = None,
                 frames: Mapping[str, bytes] | None = None,
                 commands: Mapping[str, bytes] | None = None,
                 price_sign: bytes | None = None,
                 price_verify: bytes | None = None,
                 tags: Mapping[str, bytes] | None = None) -> None:
        self.node = check_node_name(node)
        self.key = _check_key(key)
        self.boot = boot
        self._persist = persist
        self._peers = dict(peers or {})
        self._master = master
        self.insecure = insecure
        self.fleet_id = fleet
        # AUTH-21: per peer, the lowest boot counter this node accepts (a sync of an
        # earlier boot is a replay of an earlier run, or the peer's key file rolled back)
        self.floors = dict(floors or {})
        self._frames = dict(frames or {})  # AUTH-28: link frame -> its key
        self._commands = dict(commands or {})  # AUTH-30: target agent -> command key
        self._tags = dict(tags or {})  # AUTH-34: 'agent_i>receiver' -> λ tag key
        # signed_price (AUTH-31): the router's Ed25519 private key (the router only) and
        # its public key (every node of a signed fleet); None: not a signed fleet
        self.price_sign = price_sign
        if price_sign is not None and price_verify is None:
            from .pricesig import public_key
            price_verify = public_key(price_sign)
        self.price_verify = price_verify

    def floor_of(self, node: str) -> int:
        """The lowest boot counter accepted from ``node`` (0: no floor; never insecure)."""
        return 0 if self.insecure else self.floors.get(node, 0)

    def __repr__(self) -> str:  # never print a key
        return (f"Keyring(node={self.node!r}, boot={self.boot}, insecure={self.insecure}, "
                f"peers={sorted(self._peers) if self._master is None else 'derived'})")

    def key_of(self, node: str, derive: bool = True) -> bytes | None:
        """The verification key of ``node``'s frames, None if this node does not hold it
        (``derive=False``: only the keys listed or derived so far, not a fleet master's)."""
        if node == self.node:
            return self.key
        k = self._peers.get(node)
        if k is None and self._master is not None and derive:
            k = self._peers[node] = derive_node_key(self._master, node)
        return k

    def command_key(self, target: str, derive: bool = True) -> bytes | None:
        """The key of the ER_Command frames to agent ``target`` (AUTH-30): held by the
        router and that agent only; None for any other node, or if not listed."""
        if self.node not in (target, "router"):
            return None
        k = self._commands.get(target)
        if k is None and self._master is not None and derive:
            k = self._commands[target] = derive_command_key(self._master, target)
        return k

    def tag_key(self, sender: str, receiver: str, derive: bool = True) -> bytes | None:
        """The key of the tags ``sender``'s λ frames carry for ``receiver`` on CAN FD
        (AUTH-34): held by the two of them only; None for any other node, or if not
        listed."""
        if self.node not in (sender, receiver):
            return None
        label = pair_label(sender, receiver)
        k = self._tags.get(label)
        if k is None and self._master is not None and derive:
            k = self._tags[label] = derive_lambda_tag_key(self._master, sender, receiver)
        return k

    def listed_tag_keys(self) -> dict[str, bytes]:
        """The λ tag keys listed or derived so far (pair label → key), a copy."""
        return dict(self._tags)

    def key_for(self, name: str, derive: bool = True,
                target: int | None = None) -> bytes | None:
        """The key that signs and verifies message ``name`` (or its ``_Sync``): a link
        frame's or a report's own key (AUTH-28, AUTH-29) if this node is its sender or a
        receiver, else None; an ER_Command's, its ``target``'s command key (AUTH-30; by
        default this agent's own); a broadcast frame's (and ER_Command_Sync's) sender's
        key (``key_of``). None: this node does not hold it."""
        from . import contract  # contract imports this module

        if name == contract.COMMAND:
            label = self.node if target is None else f"agent_{target}"
            return self.command_key(label, derive) if label.startswith("agent_") else None
        base = name.removesuffix("_Sync")
        if base not in contract.KEYED_FRAMES:
            return self.key_of(contract.sender_of(base), derive)
        if self.node not in contract.parties_of(base):
            return None
        k = self._frames.get(base)
        if k is None and self._master is not None and derive:
            k = self._frames[base] = derive_frame_key(self._master, base)
        return k

    def listed_frame_keys(self) -> dict[str, bytes]:
        """The link frame keys listed or derived so far (name → key), a copy."""
        return dict(self._frames)

    def listed_command_keys(self) -> dict[str, bytes]:
        """The command keys listed or derived so far (target → key), a copy."""
        return dict(self._commands)

    def listed_keys(self) -> dict[str, bytes]:
        """The peer keys listed or derived so far (label → key), a copy: what a key file
        lists, without the ones a fleet master key would derive later."""
        return dict(self._peers)

    @property
    def master(self) -> bytes | None:
        """The fleet master key every peer key is derived from on demand (``fleet``,
        ``insecure_for``); None for a key file's keyring (its peers are listed)."""
        return self._master

    def adopt_boot(self, boot: int) -> None:
        """Persist ``boot`` (write-ahead), then take it as this node's boot counter: for a
        runtime that counts its boots itself (the C agent's persist_boot). Raises what the
        persistence raises, the boot counter then unchanged."""
        self._persist(boot)
        self.boot = boot

    def new_boot(self) -> int:
        """Start a boot: the next boot counter, persisted before it is returned."""
        if self.boot >= DEFAULT_LAYOUT.max_boot:
            raise SecOCError("boot counter exhausted: re-provision the fleet's keys "
                             "(bess-ded keys --fleet ... --force)")
        self._persist(self.boot + 1)  # write-ahead: durable before it is used
        self.boot += 1
        return self.boot

    @classmethod
    def from_file(cls, path: Path | str) -> Keyring:
        """The keyring of a node key file (its boots persisted back to the file)."""
        k = load_node_key(path)
        return cls(k.node, k.key, k.boot_counter, k.persist(), peers=k.peers,
                   fleet=k.fleet_id, floors=k.floors, frames=k.frames, commands=k.commands,
                   price_sign=k.price_sign, price_verify=k.price_verify, tags=k.tags)

    @classmethod
    def insecure_for(cls, node: str) -> Keyring:
        """``node``'s keyring from the public demo master key (--insecure): anyone can
        forge its frames; boots are not persisted."""
        return cls(node, derive_node_key(INSECURE_MASTER, node), INSECURE_BOOT - 1,
                   lambda _b: None,
                   master=INSECURE_MASTER, insecure=True, fleet=fleet_id(INSECURE_MASTER))

    @classmethod
    def fleet(cls, master: bytes, nodes: list[str],
              signed_price: bool = False) -> dict[str, Keyring]:
        """In-memory keyrings for ``nodes`` (boot counters kept in memory: a node
        restarted with the same keyring object starts a new boot, as from its file);
        ``signed_price``: the router gets the price signing key, every other node its
        public key only (AUTH-31)."""
        sign = verify = None
        if signed_price:
            from .pricesig import public_key
            sign = derive_price_sign_key(master)
            verify = public_key(sign)
        return {n: cls(n, derive_node_key(master, n), 0, lambda _b: None, master=master,
                       fleet=fleet_id(master),
                       price_sign=sign if n == "router" else None, price_verify=verify)
                for n in nodes}


def frame_payload(data: bytes | bytearray) -> bytes:
    """The payload a secured or sync frame's MAC covers: bytes 3..7 with bits 24..27
    (the truncated freshness value, or the low bits of a sync's Count) zeroed."""
    return bytes((data[3] & 0xF0,)) + bytes(data[4:8])


def frame_mac(data: bytes | bytearray) -> int:
    """The truncated MAC a frame carries: bytes 0..2, most significant first."""
    return int.from_bytes(data[0:MAC_BITS // 8], "big")


def sign_frame(key: bytes, frame_id: int, data: bytearray, freshness: int) -> None:
    """Write the MAC of a secured or sync frame over its payload and ``freshness``."""
    mac = authenticator(key, frame_id, frame_payload(data), freshness, MAC_BITS)
    data[0:MAC_BITS // 8] = mac.to_bytes(MAC_BITS // 8, "big")


TAG_SLOT_BYTES = 4  # AUTH-34: a slot is its receiver's code (1 byte) and its tag (3)
_TAGS_AT = 8        # the first slot's byte: after the classic 8 bytes


def frame_tag(data: bytes | bytearray, code: int) -> int | None:
    """The tag of the first slot of a tagged frame whose receiver is ``code`` (AUTH-34),
    None if it has none."""
    for at in range(_TAGS_AT, len(data) - TAG_SLOT_BYTES + 1, TAG_SLOT_BYTES):
        if data[at] == code:
            return int.from_bytes(data[at + 1:at + TAG_SLOT_BYTES], "big")
    return None


def sign_tags(tags: list[tuple[int, bytes]], frame_id: int, data: bytearray,
              freshness: int) -> None:
    """Write the slots of a tagged frame (AUTH-34): for each (receiver code, pair key) in
    order its code and tag, over the same input as a Mac; the Mac bytes stay 0."""
    payload = frame_payload(data)
    for k, (code, key) in enumerate(tags):
        at = _TAGS_AT + TAG_SLOT_BYTES * k
        tag = authenticator(key, frame_id, payload, freshness, MAC_BITS)
        data[at] = code
        data[at + 1:at + TAG_SLOT_BYTES] = tag.to_bytes(MAC_BITS // 8, "big")


def tag_label(code: int) -> str | None:
    """The node a tag slot's receiver code names (AUTH-34), None for an empty slot or a
    code no node has."""
    from .frames import N_AGENTS_MAX, TAG_RX_PLANT, TAG_RX_ROUTER

    if code == TAG_RX_PLANT:
        return "plant"
    if code == TAG_RX_ROUTER:
        return "router"
    return f"agent_{code}" if 1 <= code <= N_AGENTS_MAX else None


def tags_verify(key_of: Callable[[str], bytes | None], sender: str, frame_id: int,
                data: bytes | bytearray, freshness: int) -> bool:
    """A monitor's check of a tagged frame (AUTH-34; it holds every pair key): at least
    one slot, and every non-empty slot's tag verifies under ``key_of(pair label)``."""
    payload, slots = frame_payload(data), 0
    for at in range(_TAGS_AT, len(data) - TAG_SLOT_BYTES + 1, TAG_SLOT_BYTES):
        if data[at] == 0:
            continue
        receiver = tag_label(data[at])
        key = None if receiver is None or receiver == sender else key_of(
            pair_label(sender, receiver))
        mac = int.from_bytes(data[at + 1:at + TAG_SLOT_BYTES], "big")
        if key is None or not verify(key, frame_id, payload, freshness, mac, MAC_BITS):
            return False
        slots += 1
    return slots > 0


def frame_verifies(key: bytes, frame_id: int, data: bytes | bytearray, freshness: int,
                   tag_code: int | None = None) -> bool:
    """True when the MAC in ``data`` verifies for ``frame_id`` with ``key`` at
    ``freshness``; ``tag_code``: a tagged frame's (AUTH-34), whose slot for that receiver
    must verify instead (False if it has none)."""
    mac = frame_mac(data) if tag_code is None else frame_tag(data, tag_code)
    return mac is not None and verify(key, frame_id, frame_payload(data), freshness, mac,
                                      MAC_BITS)
