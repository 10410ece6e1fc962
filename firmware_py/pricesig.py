"""The router's signed price (``signed_price``; issue 25, item 1, step d-min;
docs/security.md, firmware-spec AUTH-31..33).

With ``signed_price`` the per-tick ``ER_Price`` frames keep their MAC under the router's
node key (which every agent holds to verify them), but an agent takes a price only if
it equals the **signed segment**: the router signs, with an Ed25519 key only it holds,

    message = SIG_LABEL ‖ fleet ID (8 bytes) ‖ Boot (2, BE) ‖ segment number (2, BE)
              ‖ PriceValid (1) ‖ Rho (4, BE, two's complement)

(the segment number counts the price schedule's steps mod 2048 and only grows within a
boot; ``ER_Price.Segment`` is its low 3 bits), and sends it as ``ER_PriceSig``, a
multi-frame transfer of 11 classic frames (DBC, no MAC of its own): page 0 the signed
segment, pages 1..10 the 64-byte signature, 7 bytes a page. It goes out before the first
``ER_Price`` of each new segment and every second (late joiners, restarts). Every agent
holds only the router's *public* key: its key file cannot sign a price other agents take.

The receiver (``PriceSigReceiver``) reassembles the pages, verifies the signature once
per transfer (a repeat of the signature it already verified costs no verify), refuses a
signature older than the one it holds (replay), and then takes an ``ER_Price`` only if
(PriceValid, Rho, Segment) equal the signed segment's. Causes counted:
``unsigned_price`` (an ER_Price that is not the signed one, or before any signature),
``bad_signature`` (a transfer whose signature does not verify, or an older segment than
the one held), ``sig_malformed`` (a page out of order: no header, a page repeated with
other bytes, a last page with bytes beyond the signature). Nothing here raises on bus
input.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from . import contract

MESSAGE = "ER_PriceSig"
SIG_LABEL = b"bess-ded/price-signature/v1"
SIGN_KEY_LABEL = b"bess-ded/price-sign-key/v1"
SEED_BYTES = 32           # an Ed25519 private key (RFC 8032 seed)
PUBLIC_BYTES = 32
SIG_BYTES = 64
PAGE_BYTES = 7            # signature bytes per page (bits 8..63)
SIG_PAGES = -(-SIG_BYTES // PAGE_BYTES)   # 10: pages 1..10
PAGES = SIG_PAGES + 1     # with the header, page 0
# the segment number: ER_Price.Segment (its low bits) ‖ ER_PriceSig.SegmentHigh, as wide
# as the DBC makes them (3 + 8 bits: mod 2048)
SEGMENT_LOW_BITS = contract.raw_range("ER_Price", "Segment")[1].bit_length()
SEGMENT_LOW_MOD = 1 << SEGMENT_LOW_BITS
SEGMENT_MOD = SEGMENT_LOW_MOD << contract.raw_range(MESSAGE, "SegmentHigh")[1].bit_length()
CAUSES = contract.SIGNED_PRICE_COUNTERS
# a monitor's key table (label -> bytes): the router's public price key and the fleet ID
MONITOR_PUBLIC = "@price_verify"
MONITOR_FLEET = "@fleet_id"
# a tester's key table (one that plays the router: bess-ded conformance): its signing seed
TESTER_SIGN = "@price_sign"


def monitor_entries(public: bytes | None, fleet: str) -> dict[str, bytes]:
    """The entries a monitor's key table gets for a signed_price fleet (none otherwise)."""
    return {} if public is None else {MONITOR_PUBLIC: public,
                                      MONITOR_FLEET: bytes.fromhex(fleet)}


@dataclass(frozen=True)
class SignedSegment:
    """One price segment as the router signs it (raw wire values)."""

    boot: int
    number: int      # mod SEGMENT_MOD
    valid: int       # ER_Price.PriceValid
    rho: int         # ER_Price.Rho, Q24

    def message(self, fleet: str) -> bytes:
        """The bytes the signature covers (``fleet``: the key set's 16-hex-digit ID)."""
        return (SIG_LABEL + bytes.fromhex(fleet) + self.boot.to_bytes(2, "big")
                + (self.number % SEGMENT_MOD).to_bytes(2, "big") + bytes([self.valid & 1])
                + self.rho.to_bytes(4, "big", signed=True))

    def matches(self, raw: dict[str, int]) -> bool:
        """Whether an ER_Price (its raw signals) is this segment's."""
        return (raw["PriceValid"] == self.valid and raw["Rho"] == self.rho
                and raw["Segment"] == self.number % SEGMENT_LOW_MOD)

    def after(self, other: SignedSegment) -> bool:
        """Newer than ``other`` or the same: a later boot, or a segment number at or after
        it (mod 2048, within half the range) in the same boot."""
        if self.boot != other.boot:
            return self.boot > other.boot
        return (self.number - other.number) % SEGMENT_MOD < SEGMENT_MOD // 2

    def describe(self) -> str:
        """The segment in words, for a log line."""
        return (f"boot {self.boot}, segment {self.number}, PriceValid {self.valid}, "
                f"ρ {self.rho / (1 << 24):.6g}")


def public_key(seed: bytes) -> bytes:
    """The 32-byte public key of an Ed25519 private key (its 32-byte seed)."""
    return Ed25519PrivateKey.from_private_bytes(seed).public_key().public_bytes_raw()


def sign(seed: bytes, fleet: str, seg: SignedSegment) -> bytes:
    """The router's 64-byte signature of ``seg``."""
    return Ed25519PrivateKey.from_private_bytes(seed).sign(seg.message(fleet))


def verifies(public: bytes, fleet: str, seg: SignedSegment, signature: bytes) -> bool:
    """Whether ``signature`` is the holder of ``public``'s signature of ``seg``."""
    try:
        Ed25519PublicKey.from_public_bytes(public).verify(signature, seg.message(fleet))
    except (InvalidSignature, ValueError):
        return False
    return True


def pages(seg: SignedSegment, signature: bytes) -> list[dict[str, int]]:
    """The raw signals of every ER_PriceSig page, in order (0: the segment)."""
    out = [{"Page": 0, "PriceValid": seg.valid, "Segment": seg.number % SEGMENT_LOW_MOD,
            "SegmentHigh": (seg.number % SEGMENT_MOD) >> SEGMENT_LOW_BITS, "Rho": seg.rho,
            "Boot": seg.boot}]
    for k in range(SIG_PAGES):
        chunk = signature[k * PAGE_BYTES:(k + 1) * PAGE_BYTES]
        out.append({"Page": k + 1, "Signature": int.from_bytes(chunk, "little")})
    return out


class PriceSigReceiver:
    """Reassembles and verifies the router's price signatures; ``current`` is the newest
    verified signed segment (None before the first)."""

    def __init__(self, public: bytes, fleet: str) -> None:
        self.public = public
        self.fleet = fleet
        self.current: SignedSegment | None = None
        self._signature: bytes | None = None     # current's signature (a repeat: no verify)
        self._header: SignedSegment | None = None
        self._parts: dict[int, int] = {}
        self.verifications = 0

    def take(self, raw: dict[str, Any], min_boot: int = 0) -> tuple[str, str] | None:
        """One decoded ER_PriceSig page. None: taken (a page kept, or a signature verified
        or repeated); else (cause, reason) of a rejection (CAUSES). ``min_boot``: the
        router's boot as the receiver knows it from its freshness (an older signature is
        a replay of an earlier boot)."""
        page = raw["Page"]
        if page == 0:
            self._header = SignedSegment(raw["Boot"],
                                         raw["Segment"] | raw["SegmentHigh"] << SEGMENT_LOW_BITS,
                                         raw["PriceValid"], raw["Rho"])
            self._parts = {}
            return None
        if self._header is None:
            return ("sig_malformed", f"{MESSAGE} page {page} without its page 0")
        value = raw["Signature"]
        if page == SIG_PAGES and value >> (8 * (SIG_BYTES - (SIG_PAGES - 1) * PAGE_BYTES)):
            self._header = None
            return ("sig_malformed", f"{MESSAGE} page {page}: expected only "
                    f"{SIG_BYTES - (SIG_PAGES - 1) * PAGE_BYTES} signature byte(s), but got "
                    "more")
        if self._parts.get(page, value) != value:
            self._header = None
            return ("sig_malformed", f"{MESSAGE} page {page} repeated with other bytes")
        self._parts[page] = value
        if len(self._parts) < SIG_PAGES:
            return None
        seg, self._header = self._header, None
        signature = b"".join(self._parts[k].to_bytes(PAGE_BYTES, "little")
                             for k in range(1, PAGES))[:SIG_BYTES]
        self._parts = {}
        if seg == self.current and signature == self._signature:
            return None  # the once-a-second repeat of what is held: no verify
        self.verifications += 1
        if not verifies(self.public, self.fleet, seg, signature):
            return ("bad_signature", f"{MESSAGE} ({seg.describe()}): the signature does not "
                    "verify under the router's public key")
        if seg.boot < min_boot or (self.current is not None and not seg.after(self.current)):
            return ("bad_signature", f"{MESSAGE} ({seg.describe()}): a genuine but older "
                    "signature than the one held (a replay)")
        self.current, self._signature = seg, signature
        return None

    def check(self, raw: dict[str, int]) -> str | None:
        """None if an ER_Price (raw signals) is the signed segment's, else why not."""
        if self.current is None:
            return "ER_Price before any verified price signature (signed_price)"
        if self.current.matches(raw):
            return None
        return (f"ER_Price (PriceValid {raw['PriceValid']}, ρ {raw['Rho'] / (1 << 24):.6g}, "
                f"Segment {raw['Segment']}): expected the signed segment's "
                f"({self.current.describe()})")
