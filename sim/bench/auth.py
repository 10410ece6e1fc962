"""What every authentication scheme of issue 25 costs: bus load, sign/verify time,
latency, and what an insider still forges (``bess-ded bench --auth``, docs/performance.md,
docs/security.md "Authentication schemes compared").

The fleets are real scenarios: case 1 (4 agents, star), case 7 (12, ring) and a
32-agent ring (``ring_scenario``). Their frames are the DBC's (``fleet_messages``): every
secured message of the fleet and its ``<name>_Sync``, at the DBC's cycle times scaled to
the scenario's Ts (``contract.cycle_s``), ER_Balance with every page each cycle, a Diag
frame one page a cycle, ER_Command an event (no periodic load). The receivers that need
a tag are the nodes that verify the frame today: the holders of its key (the sender's
node key: ``sim.run.keyset.peers_of``; a link frame's or a report's:
``contract.parties_of``), less the sender; a report (Diag, ER_Balance) has one, its DBC
receiver or the recorder.

How each scheme puts a message on the wire (``Scheme.mode``, ``occurrence``):

- ``shared``: today's frame, a 24-bit CMAC-AES-128 under the sender's node key (a link
  frame's own key, AUTH-28): one classic frame of the DBC's length.
- ``tags``: a tag per receiver under a key only sender and receiver hold. Classic CAN:
  the frame carries the first tag, extra frames of the same length carry
  ``len // tag`` tags each. CAN FD: one FD frame of payload + R tags (padded to an FD
  size; over 64 bytes, more frames). One receiver: today's frame.
- ``sign``: the router's messages. A cyclic frame (the price, the syncs) keeps its
  MAC and is *bound* to a signature (Ed25519 or ECDSA-P256, 64 bytes) over its content
  (segment, ρ, validity, the router's boot), sent at each price segment change and
  once per sync period (late joiners): 8 classic frames, or one 64-byte FD frame. A
  receiver takes a price only if it equals the signed one. An event message (ER_Command)
  carries its own signature (its cost per command is latency, no periodic load).
- ``tesla``: the frame's tag under the sender's current key of a one-way key chain
  (TESLA, delayed disclosure); the sender discloses each interval's key one interval
  later, a 16-byte key in 2 classic frames per interval (its fastest cycle).

Scheme ``d-min`` is the step that fits classic CAN: the router signed, the links and
reports pairwise, λ left under its sender's node key.

Timings are measured on this machine with the libraries the firmware uses (medians of
batches, ``time.perf_counter``): printed and written, never asserted.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from dbc import FD_DBC_PATH
from firmware_py import contract, secoc
from firmware_py.frames import FrameCodec, agent_of
from sim.bench.canframe import (
    FD_MAX,
    classic_frame_time,
    fd_frame_time,
)


def _fd_data_rate() -> int:
    """The FD data phase's bit rate: the FD twin DBC's BaudrateCANFD attribute, bit/s."""
    dbc = FrameCodec(FD_DBC_PATH).database.dbc
    if dbc is None or "BaudrateCANFD" not in dbc.attributes:
        raise ValueError(f"{FD_DBC_PATH} has no BaudrateCANFD attribute")
    return int(dbc.attributes["BaudrateCANFD"].value)


FD_DATA_RATE = _fd_data_rate()
"""Data-phase bit rate of the CAN FD schemes, bit/s (nominal: the DBC's Baudrate)."""
SIG_BYTES = 64                       # Ed25519; ECDSA-P256 as raw r ‖ s
TAG_BYTES = contract.MAC_BITS // 8   # 3: the DBC's Mac signal
DISCLOSED_KEY_BYTES = secoc.KEY_BYTES
INSIDER = "agent_3"
# Cortex-M4 at 168 MHz, SEGGER emLib figures (DESIGN.md section 7): cited, not measured
M4_VERIFY_MS = {"ed25519": 175.0, "p256": 83.0}


@cache
def dbc_bitrate() -> int:
    """The bus's nominal bit rate: the DBC's Baudrate attribute, bit/s."""
    dbc = FrameCodec().database.dbc
    if dbc is None or "Baudrate" not in dbc.attributes:
        raise ValueError("the DBC has no Baudrate attribute")
    return int(dbc.attributes["Baudrate"].value)


# --------------------------------------------------------------------------- fleets


@dataclass(frozen=True)
class Message:
    """One secured message (or sync) of a fleet, as the bus carries it."""

    name: str
    sender: str
    receivers: tuple[str, ...]     # the nodes that need a tag (verify it)
    holders: tuple[str, ...]       # who holds its key today (the sender included)
    per_s: float                   # occurrences per second (0: an event message)
    length: int                    # DLC, bytes
    role: str                      # "agent" | "router" (broadcasts) | "link" | "report"


def ring_scenario(n: int = 32, duration: float = 30.0) -> Any:
    """``n`` agents on a ring 1–2–…–n–1 (batteries as ``random_fleet``'s), ``duration``
    seconds at Ts = 10 ms, one price."""
    from sim.model.generate import random_fleet
    from sim.model.scenario import parse_scenario

    data = random_fleet(n, 2, seed=0, duration=duration)
    data["name"] = data["title"] = f"ring-{n}"
    data["graph"]["edges"] = [[i, i % n + 1] for i in range(1, n + 1)]
    return parse_scenario(data, f"<ring-{n}>")


def fleets() -> dict[str, Any]:
    """The fleets of issue 25's acceptance: case 1, case 7 and a 32-agent ring."""
    from sim.model.scenario import load_case

    return {"case 1": load_case(1), "case 7": load_case(7), "ring-32": ring_scenario()}


def fleet_messages(sc: Any, ts: float | None = None) -> list[Message]:
    """Every secured message and sync of ``sc``'s fleet, from the DBC (module doc)."""
    from sim.run.keyset import peers_of

    codec = FrameCodec()
    peers = peers_of(sc)
    ts = sc.ts if ts is None else ts
    out = []
    for m in codec.database.messages:
        fid = m.frame_id
        if codec.kind(fid) not in ("secured", "sync") or (agent_of(fid) or 0) > sc.n:
            continue
        base = m.name.removesuffix("_Sync")
        sender = contract.sender_of(base)
        base_id = codec.frame_id(base)
        if base in contract.KEYED_FRAMES:  # AUTH-28, AUTH-29: a key of its own
            holders = contract.parties_of(base)
            role = "report" if base_id in contract.REPORT_IDS else "link"
        else:
            holders = frozenset({sender, *(n for n, ps in peers.items() if sender in ps)})
            role = "router" if sender == "router" else "agent"
        if role == "report":
            dbc_rx = contract.receivers_of(base_id)
            receivers: tuple[str, ...] = tuple(sorted(dbc_rx)) or ("recorder",)
        else:
            receivers = tuple(sorted(holders - {sender}))
        if m.name == contract.COMMAND:  # AUTH-30: each command under its target's key,
            holders = frozenset({sender})  # which only the router shares with the target
            receivers = tuple(f"agent_{i}" for i in contract.agent_ids(sc.n))
        per_s = 0.0
        if contract.is_cyclic(m.name):
            pages = len(codec.pages(m.name)) if m.name == "ER_Balance" else 1
            per_s = pages / contract.cycle_s(m.name, ts)
        out.append(Message(m.name, sender, receivers, tuple(sorted(holders)), per_s,
                           m.length, role))
    return out


# --------------------------------------------------------------------------- schemes


@dataclass(frozen=True)
class Scheme:
    """How each kind of message is authenticated (module doc)."""

    key: str
    label: str
    agent: str                 # mode of the agents' broadcasts (MC)
    router: str                # mode of the router's broadcasts (price, command)
    fd: bool = False           # CAN FD with the bit-rate switch for the multi-tag frames
    sig: str | None = None     # "ed25519" | "p256" for router = "sign"
    links: str | None = None   # links and reports; None: "shared" with λ shared, else tags

    def mode(self, msg: Message) -> str:
        """How ``msg`` is authenticated: "shared", "tags", "sign" or "tesla"."""
        if msg.role in ("agent", "router"):
            return self.agent if msg.role == "agent" else self.router
        return self.links or ("shared" if self.agent == "shared" else "tags")


SCHEMES = (
    Scheme("a", "shared key (today)", "shared", "shared"),
    Scheme("a-fd", "shared key, CAN FD (lambda_tags = false)", "shared", "shared", fd=True),
    Scheme("b", "pairwise tags, classic", "tags", "tags"),
    Scheme("c", "pairwise tags, CAN FD", "tags", "tags", fd=True),
    Scheme("d", "Ed25519 router + pairwise λ, classic", "tags", "sign", sig="ed25519"),
    Scheme("d-fd", "Ed25519 router + pairwise λ, CAN FD", "tags", "sign", fd=True,
           sig="ed25519"),
    Scheme("d-p256", "ECDSA-P256 router + pairwise λ, classic", "tags", "sign",
           sig="p256"),
    Scheme("d-min", "Ed25519 router + pairwise links, λ shared, classic", "shared", "sign",
           sig="ed25519", links="tags"),
    Scheme("e", "TESLA (delayed disclosure), classic", "tesla", "tesla"),
)


@dataclass(frozen=True)
class Bus:
    """The bit rates: nominal (the DBC's), and the FD data phase."""

    nominal: float
    data: float = FD_DATA_RATE

    def classic(self, length: int) -> float:
        """Seconds of a worst-case classic frame of ``length`` bytes."""
        return classic_frame_time(length, self.nominal)

    def fd(self, length: int) -> float:
        """Seconds of a worst-case FD frame (bit-rate switch) of ``length`` bytes."""
        return fd_frame_time(length, self.nominal, self.data)


def single(scheme: Scheme, msg: Message, bus: Bus) -> float:
    """Bus seconds of ``msg`` as one frame of its DLC: classic, or FD on an FD scheme."""
    return bus.fd(msg.length) if scheme.fd else bus.classic(msg.length)


def occurrence(scheme: Scheme, msg: Message, bus: Bus) -> tuple[float, int]:
    """(bus seconds, frames) of one occurrence of ``msg`` under ``scheme`` (its
    signature or key disclosure aside: ``extras``). On an FD scheme every frame is an
    FD frame with the bit-rate switch."""
    one = single(scheme, msg, bus)
    r = len(msg.receivers)
    if scheme.mode(msg) != "tags" or r <= 1:
        return one, 1
    if not scheme.fd:
        frames = 1 + math.ceil((r - 1) / (msg.length // TAG_BYTES))
        return frames * one, frames
    total = msg.length - TAG_BYTES + r * TAG_BYTES
    full, rest = divmod(total, FD_MAX)
    return full * bus.fd(FD_MAX) + (bus.fd(rest) if rest else 0.0), full + (rest > 0)


def signature_time(scheme: Scheme, bus: Bus) -> float:
    """Bus seconds of one signature: 8 classic frames, or one 64-byte FD frame."""
    return bus.fd(SIG_BYTES) if scheme.fd else \
        math.ceil(SIG_BYTES / 8) * bus.classic(8)


def extras(scheme: Scheme, sc: Any, msgs: list[Message], bus: Bus
           ) -> tuple[float, float]:
    """(bus seconds per second, frames per second) a scheme adds besides the messages:
    the price signatures (``sign``), the key disclosures (``tesla``)."""
    busy = frames = 0.0
    if scheme.router == "sign":
        sync = contract.cycle_s("ER_Price_Sync", sc.ts)
        per_s = 1.0 / sync + (len(sc.prices) - 1) / sc.duration
        busy += per_s * signature_time(scheme, bus)
        frames += per_s * (1 if scheme.fd else math.ceil(SIG_BYTES / 8))
    fastest: dict[str, float] = {}
    for m in msgs:
        if scheme.mode(m) == "tesla" and m.per_s:
            fastest[m.sender] = max(fastest.get(m.sender, 0.0), m.per_s)
    n_disc = math.ceil(DISCLOSED_KEY_BYTES / 8)
    for per_s in fastest.values():
        busy += per_s * n_disc * bus.classic(8)
        frames += per_s * n_disc
    return busy, frames


def bus_load(scheme: Scheme, sc: Any, bus: Bus | None = None,
             msgs: list[Message] | None = None) -> dict[str, float]:
    """Bus load (fraction of the bus's time) and frames/s of ``sc``'s fleet: its
    ``fleet_messages``, or ``msgs`` (sim.bench.fleetload: more agents than the DBC's,
    fewer MC frames)."""
    bus = bus or Bus(dbc_bitrate())
    msgs = fleet_messages(sc) if msgs is None else msgs
    busy, frames = extras(scheme, sc, msgs, bus)
    for m in msgs:
        t, k = occurrence(scheme, m, bus)
        busy += m.per_s * t
        frames += m.per_s * k
    return {"load": busy, "frames_per_s": frames}


def added_latency(scheme: Scheme, sc: Any, role: str, bus: Bus | None = None) -> float:
    """Worst added delay (s) before a receiver may use an ``agent`` (λ) or ``router``
    (price) message of ``sc`` under ``scheme``, against today's frame: the last tag
    frame, the longer FD frame, the signature on the bus (its verify time aside), or
    the disclosure interval and frames."""
    bus = bus or Bus(dbc_bitrate())
    msgs = [m for m in fleet_messages(sc) if m.role == role and m.per_s
            and not m.name.endswith("_Sync")]
    worst = 0.0
    for m in msgs:
        mode, base = scheme.mode(m), single(scheme, m, bus)
        if mode == "tags":
            t, k = occurrence(scheme, m, bus)
            extra = (t - base) if scheme.fd else (k - 1) * base
        elif mode == "sign":
            extra = signature_time(scheme, bus)
        elif mode == "tesla":
            extra = 1.0 / m.per_s + math.ceil(DISCLOSED_KEY_BYTES / 8) * base
        else:
            extra = 0.0
        worst = max(worst, extra)
    return worst


def insider_forges(scheme: Scheme, sc: Any, insider: str = INSIDER) -> dict[str, str]:
    """The messages (and syncs) of others an insider holding ``insider``'s key file can
    still make some other node accept under ``scheme``: name -> "forge" (any content),
    or "bound" (a cyclic frame bound to a signature: only the signed content). A
    router's sync under ``sign`` keeps its MAC: "forge" (alone it is held, AUTH-35, but a
    frame bound to the signature, replayed on its track, completes it; AUTH-27 bounds
    its boot and undoes it)."""
    out = {}
    for m in fleet_messages(sc):
        if m.sender == insider or insider not in m.holders:
            continue
        fooled = set(m.receivers) - {insider}
        mode = scheme.mode(m)
        if not fooled or mode in ("tags", "tesla"):
            continue
        if mode == "shared":
            out[m.name] = "forge"
        elif mode == "sign" and contract.is_cyclic(m.name):
            out[m.name] = "forge" if m.name.endswith("_Sync") else "bound"
    return out


def forged_summary(forged: dict[str, str]) -> str:
    """'ER_Price, AGENT_1_MC (+ syncs)' from ``insider_forges``."""
    frames = sorted((n for n in forged if not n.endswith("_Sync")),
                    key=lambda n: (contract.sender_of(n), n))
    syncs = sorted(n.removesuffix("_Sync") for n in forged if n.endswith("_Sync"))
    text = ", ".join(n + (" (signed ρ only)" if forged[n] == "bound" else "")
                     for n in frames)
    if syncs and syncs != sorted(n for n in frames):
        text += (", " if text else "") + "syncs of " + ", ".join(syncs)
    elif syncs:
        text += " (+ their syncs)"
    return text or "nothing (own frames only)"


# --------------------------------------------------------------------------- timing


def crypto_costs(quick: bool, r_tags: int) -> dict[str, dict[str, float]]:
    """µs to sign and verify one message, per primitive, measured here: the 24-bit
    CMAC-AES-128 tag of a secured frame as firmware_py writes and checks it
    (``secoc.sign_frame``, ``secoc.frame_verifies``), ``r_tags`` of them (a λ with r
    receivers), Ed25519 and ECDSA-P256 (``cryptography``) over the price's authenticated
    data, and a TESLA key-chain step (SHA-256). Batches run round-robin over the
    primitives, so a burst of load from another process hits them alike; the median of
    the batches is kept."""
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec, ed25519

    n, n_sig, reps = (300, 20, 5) if quick else (3000, 200, 9)
    key, fid, fv = bytes(range(16)), contract.ER_PRICE_ID, (5 << 24) | 1234
    frame = bytearray(bytes(3) + bytes([0x10, 0x66, 0x66, 0x66, 0x06]))
    secoc.sign_frame(key, fid, frame, fv)
    data = secoc.auth_data(fid, secoc.frame_payload(frame), fv)
    edk = ed25519.Ed25519PrivateKey.from_private_bytes(bytes(range(32)))
    ed_pub, ed_sig = edk.public_key(), edk.sign(data)
    pk = ec.derive_private_key(12345, ec.SECP256R1())
    ecdsa = ec.ECDSA(hashes.SHA256())
    p_pub, p_sig = pk.public_key(), pk.sign(data, ecdsa)

    def tags() -> None:
        for _ in range(r_tags):
            secoc.sign_frame(key, fid, frame, fv)

    def chain_step() -> None:
        h = hashes.Hash(hashes.SHA256())
        h.update(key)
        h.finalize()

    ops: dict[tuple[str, str], tuple[Callable[[], object], int]] = {
        ("cmac_tag", "sign_us"): (lambda: secoc.sign_frame(key, fid, frame, fv), n),
        ("cmac_tag", "verify_us"): (lambda: secoc.frame_verifies(key, fid, frame, fv), n),
        ("cmac_tags", "sign_us"): (tags, max(n // r_tags, 10)),
        ("tesla_chain", "verify_us"): (chain_step, n),
        ("ed25519", "sign_us"): (lambda: edk.sign(data), n_sig),
        ("ed25519", "verify_us"): (lambda: ed_pub.verify(ed_sig, data), n_sig),
        ("p256", "sign_us"): (lambda: pk.sign(data, ecdsa), n_sig),
        ("p256", "verify_us"): (lambda: p_pub.verify(p_sig, data, ecdsa), n_sig),
    }
    times: dict[tuple[str, str], list[float]] = {k: [] for k in ops}
    for _ in range(reps):
        for k, (fn, count) in ops.items():
            t0 = time.perf_counter()
            for _ in range(count):
                fn()
            times[k].append((time.perf_counter() - t0) / count * 1e6)
    out: dict[str, dict[str, float]] = {"cmac_tags": {"tags": r_tags}}
    for (prim, what), us in times.items():
        out.setdefault(prim, {})[what] = statistics.median(us)
    return out


def scheme_us(scheme: Scheme, costs: dict[str, dict[str, float]]) -> tuple[float, float]:
    """(sign, verify) µs of the scheme's costliest per-message operation: the router's
    signature for ``sign``, a λ's r tags (one verified) for ``tags``, one tag (plus a
    chain step at the receiver, once per interval) for ``shared`` and ``tesla``."""
    tag = costs["cmac_tag"]
    if scheme.router == "sign" and scheme.sig:
        return costs[scheme.sig]["sign_us"], costs[scheme.sig]["verify_us"]
    if scheme.agent == "tags":
        return costs["cmac_tags"]["sign_us"], tag["verify_us"]
    if scheme.agent == "tesla":
        return tag["sign_us"], tag["verify_us"] + costs["tesla_chain"]["verify_us"]
    return tag["sign_us"], tag["verify_us"]


# --------------------------------------------------------------------------- the table


HEADERS = ["scheme", "sign [µs]", "verify [µs]", "load case 1", "load case 7",
           "load ring-32", "+λ latency [ms]", "+price latency [ms]",
           f"{INSIDER} (case 1) still forges"]


def run(quick: bool) -> tuple[list[list[str]], dict[str, Any]]:
    """The rows of HEADERS and the data for --json: every scheme on every fleet."""
    fl = fleets()
    bus = Bus(dbc_bitrate())
    r_max = max(len(m.receivers) for sc in fl.values() for m in fleet_messages(sc)
                if m.role == "agent")
    costs = crypto_costs(quick, r_max)
    rows, data = [], {}
    for s in SCHEMES:
        sign, verify = scheme_us(s, costs)
        loads = {f: bus_load(s, sc, bus) for f, sc in fl.items()}
        lat_l = max(added_latency(s, sc, "agent", bus) for sc in fl.values()) * 1e3
        lat_p = max(added_latency(s, sc, "router", bus) for sc in fl.values()) * 1e3
        forged = {f: insider_forges(s, sc) for f, sc in fl.items()}
        verify_note = (f" + verify (M4: {M4_VERIFY_MS[s.sig]:.0f})"
                       if s.router == "sign" and s.sig else "")
        rows.append([f"{s.key}: {s.label}", f"{sign:.1f}", f"{verify:.1f}",
                     *(f"{100 * v['load']:.1f} %" for v in loads.values()),
                     f"{lat_l:.2f}", f"{lat_p:.2f}{verify_note}",
                     forged_summary(forged["case 1"])])
        data[s.key] = {"label": s.label, "sign_us": sign, "verify_us": verify,
                       "fd": s.fd, "loads": loads, "latency_lambda_ms": lat_l,
                       "latency_price_ms": lat_p, "insider": INSIDER,
                       "insider_forges": forged}
    meta = {"nominal_bps": bus.nominal, "fd_data_bps": bus.data, "ts_s": {
        f: sc.ts for f, sc in fl.items()}, "lambda_tags_measured": r_max,
        "primitives_us": costs, "m4_verify_ms_cited": M4_VERIFY_MS}
    return rows, {"schemes": data, **meta}


def plot(data: dict[str, Any], path: Path) -> None:
    """A bar chart of the bus load of every scheme on every fleet, 100 % marked."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    schemes = data["schemes"]
    fleet_names = list(next(iter(schemes.values()))["loads"])
    fig = Figure(figsize=(10, 4.2), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    width = 0.8 / len(fleet_names)
    for i, fleet in enumerate(fleet_names):
        xs = [k + (i - (len(fleet_names) - 1) / 2) * width for k in range(len(schemes))]
        ax.bar(xs, [100 * v["loads"][fleet]["load"] for v in schemes.values()], width,
               label=fleet)
    ax.axhline(100, color="red", lw=1, ls="--", label="bus full")
    ax.set_xticks(range(len(schemes)), list(schemes), rotation=0)
    ax.set_ylabel("bus load [%]")
    ax.set_title(f"Bus load per authentication scheme, Ts = 10 ms, "
                 f"{data['nominal_bps'] / 1e3:.0f} kbit/s "
                 f"(FD data {data['fd_data_bps'] / 1e6:g} Mbit/s)")
    ax.legend()
    fig.savefig(path, dpi=110)

