#!/usr/bin/env python3
"""Generate ``tests/vectors/node/*.json``, golden vectors of one agent node.

Each vector pins ``firmware_py.runtime.AgentRuntime`` (with its ``NodeIO`` receive and
transmit path: decode, SecOC MAC and freshness, the safety rules, the state machine, the
controller, the frame encoders) byte for byte: an agent configuration (TOML text), its
key material (derived from a fixed, public test master key), a timed trace of received
CAN frames and ticks, and every frame the agent sent, in order, at the tick that sent it.

The seam is the agent's own ``Node`` interface (firmware_py/node.py): ``on_frame(msg, t)``
for each received frame and ``tick(t)`` for each period, with simulated times, exactly as
``run_node`` calls them on a bus; python-can's bus and the run loop are not involved
(so no deadline miss, error frame or send failure occurs: LOOP-* are not pinned here).
The runtime reads no clock and no randomness of its own; the inputs below are fixed
(integer arithmetic and splitmix64 only), so a run regenerates identical files.

Usage: ``python tools/gen_vectors.py`` (controller and node vectors), or this module's
``main`` with ``-o DIR`` / ``--check`` (tests/vectors/README.md, "Node-level vectors").
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tomllib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import can

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))  # this worktree's firmware_py, not an installed copy
sys.path.insert(0, str(Path(__file__).parent))  # tools/gen_vectors.py

from gen_vectors import q24, splitmix64, write_or_check  # noqa: E402  (shared with the controller's)

from firmware_py import contract, frames, pricesig  # noqa: E402
from firmware_py.config import parse_agent_config  # noqa: E402
from firmware_py.frames import (  # noqa: E402
    FrameCodec,
    diag_name,
    mc_name,
    setpoint_name,
    status_name,
    target_agent,
    target_raw,
)
from firmware_py.runtime import AgentRuntime  # noqa: E402
from firmware_py.secoc import (  # noqa: E402
    INSECURE_MASTER,
    KDF_NAME,
    MAC_NAME,
    Keyring,
    derive_command_key,
    derive_frame_key,
    derive_node_key,
    derive_price_sign_key,
    fleet_id,
    sign_frame,
)

DEFAULT_OUTPUT = ROOT / "tests" / "vectors" / "node"
FORMAT = "bess-ded node vector 1"

# The public test master key of every secure vector (never a real fleet's key), and the
# boot counters: the agent's key file holds BOOT_COUNTER, so it runs at BOOT_COUNTER + 1
# (AUTH-3); the other nodes' frames are built at their own boot counters.
TEST_MASTER = bytes.fromhex("000102030405060708090a0b0c0d0e0f")
BOOT_COUNTER = 6
SENDER_BOOTS = {"router": 3, "plant": 5, "agent_1": 2, "agent_3": 4, "agent_4": 9}

AGENT = 2
RX_OFFSET = 0.004  # received frames arrive 4 ms after a tick: never at a timeout boundary

CODEC = FrameCodec()

BASE_TOML = """\
[agent]
id = 2
lambda0 = 0.8
pinned = true
fleet_size = 4

[controller]
kind = "reset"
k = 1.0
h = 2.0
ts = 0.01
band = 0.0001

[battery]
alpha = 0.005
beta = 0.18
m = 0.08
p_min = -100.0
p_max = 100.0
{extra}
[[neighbour]]
id = 1
weight = 1.0

[[neighbour]]
id = 3
weight = 0.5
"""


def noise(seed: int, n: int, amplitude: int) -> list[int]:
    """n integers r mod (2·amplitude + 1) − amplitude of splitmix64(seed)."""
    rng = splitmix64(seed)
    return [next(rng) % (2 * amplitude + 1) - amplitude for _ in range(n)]


def set_bits(data: bytearray, start: int, length: int, value: int) -> None:
    """Write ``value`` into bits start..start+length−1 (Intel / little-endian numbering)."""
    x = int.from_bytes(data, "little")
    mask = ((1 << length) - 1) << start
    x = (x & ~mask) | ((value << start) & mask)
    data[:] = x.to_bytes(len(data), "little")


class Sender:
    """One other node of the fleet (router, plant, a neighbour): its key, boot counter and
    the message count of each secured ID it sends, as its NodeIO would keep them."""

    def __init__(self, label: str, key: bytes, boot: int, master: bytes | None = None) -> None:
        self.label, self.key, self.boot, self.master = label, key, boot, master
        self.count: dict[int, int] = {}

    def key_for(self, name: str, target: int | None = None) -> bytes:
        """AUTH-28, AUTH-29: a link frame's or report's own key (from the fleet master);
        AUTH-30: a command's its target's; else the node's."""
        if name == contract.COMMAND and target is not None:
            if self.master is None:
                raise ValueError(f"{self.label}: {name} needs the fleet master key")
            return derive_command_key(self.master, f"agent_{target}")
        base = name.removesuffix("_Sync")
        if base not in contract.KEYED_FRAMES:
            return self.key
        if self.master is None:
            raise ValueError(f"{self.label}: {base} needs the fleet master key")
        return derive_frame_key(self.master, base)

    def frame(self, name: str, raw: Mapping[str, int], skip: int = 0,
              patch: tuple[int, int, int] | None = None,
              key: bytes | None = None) -> can.Message:
        """The next ``name`` frame (``skip`` counts left out first, as lost frames);
        ``patch`` = (start bit, length, raw value) written before signing (out of range);
        ``key``: sign with it instead (a forgery)."""
        fid = CODEC.frame_id(name)
        c = self.count.get(fid, 0) + skip
        msg = CODEC.encode(name, raw, c % (1 << contract.FV_TX_BITS))
        if patch is not None:
            set_bits(msg.data, *patch)
        target = (target_agent(raw["Target"]) if name == contract.COMMAND and "Target" in raw
                  else None)
        sign_frame(key or self.key_for(name, target), fid, msg.data,
                   contract.FRESHNESS.join(self.boot, c))
        self.count[fid] = c + 1
        return msg

    def sync(self, name: str, count: int | None = None, boot: int | None = None) -> can.Message:
        """``<name>_Sync`` announcing the next count (or ``count``) under ``boot``."""
        fid = CODEC.frame_id(name)
        count = self.count.get(fid, 0) if count is None else count
        boot = self.boot if boot is None else boot
        sync_id = contract.SYNC_OF[fid]
        msg = CODEC.encode(CODEC.name_of(sync_id), {"Count": count, "Boot": boot}, 0)
        sign_frame(self.key_for(name), sync_id, msg.data, contract.FRESHNESS.join(boot, count))
        return msg

    def restart(self) -> None:
        self.boot += 1
        self.count.clear()


def _hex(msg: can.Message) -> str:
    return bytes(msg.data).hex()


class Scenario:
    """Runs the agent live while the script feeds it, recording inputs and outputs."""

    def __init__(self, name: str, description: str, covers: list[str], extra_toml: str = "",
                 insecure: bool = False, tx_count: int | None = None,
                 toml: str | None = None, floors: dict[str, int] | None = None,
                 signed: bool = False) -> None:
        self.name, self.description, self.covers = name, description, covers
        self.toml = toml if toml is not None else BASE_TOML.format(extra=extra_toml)
        self.cfg = parse_agent_config(tomllib.loads(self.toml), f"{name}.json")
        self.ts = self.cfg.controller.ts
        self.insecure = insecure
        master = INSECURE_MASTER if insecure else TEST_MASTER
        node = f"agent_{self.cfg.id}"
        peer_labels = ["router", *(f"agent_{n.id}" for n in self.cfg.neighbours)]
        # AUTH-28: its own setpoint's and status' keys; the plant's node key it needs not
        frame_names = [setpoint_name(self.cfg.id), status_name(self.cfg.id),
                       diag_name(self.cfg.id)]   # AUTH-29: its Diag under its own key
        self.keys_doc: dict[str, Any]
        if insecure:
            keys = None
            self.keys_doc = {"insecure": True, "master_key": master.hex(), "kdf": KDF_NAME,
                             "mac": MAC_NAME, "node": node}
            boots = dict.fromkeys(SENDER_BOOTS, 1)
        else:
            peers = {p: derive_node_key(master, p) for p in peer_labels}
            frames = {f: derive_frame_key(master, f) for f in frame_names}
            commands = {node: derive_command_key(master, node)}   # AUTH-30
            # signed_price (AUTH-31): the router's public price key, as `bess-ded keys`
            # derives the router's signing key from the fleet master
            price = pricesig.public_key(derive_price_sign_key(master)) if signed else None
            keys = Keyring(node, derive_node_key(master, node), BOOT_COUNTER, lambda _b: None,
                           peers=peers, fleet=fleet_id(master), floors=floors, frames=frames,
                           commands=commands, price_verify=price)
            self.keys_doc = {"insecure": False, "master_key": master.hex(), "kdf": KDF_NAME,
                             "mac": MAC_NAME, "fleet_id": fleet_id(master), "node": node,
                             "key": derive_node_key(master, node).hex(),
                             "boot_counter": BOOT_COUNTER,
                             "peers": {p: k.hex() for p, k in peers.items()},
                             "frame_keys": {f: k.hex() for f, k in frames.items()},
                             "command_keys": {t: k.hex() for t, k in commands.items()}}
            if floors:  # AUTH-21: the key file's [floors]
                self.keys_doc["floors"] = dict(floors)
            if price is not None:  # AUTH-31: the key file's [price_signature] verify_key
                self.keys_doc["price_verify_key"] = price.hex()
            boots = dict(SENDER_BOOTS)
        self.agent = AgentRuntime(self.cfg, CODEC, keys=keys)
        self.setup: dict[str, Any] = {}
        if tx_count is not None:
            # a test hook: start the agent's own message counts high (AUTH-5 in seconds)
            self.agent.io.start_tx_counts(tx_count)
            self.setup["tx_count"] = tx_count
        self.senders = {lbl: Sender(lbl, derive_node_key(master, lbl), boots[lbl], master)
                        for lbl in SENDER_BOOTS}
        self.keys_doc["sender_boots"] = {lbl: s.boot for lbl, s in self.senders.items()}
        self.router, self.plant = self.senders["router"], self.senders["plant"]
        self.signed = signed
        self.price_seed = derive_price_sign_key(master)   # the router's (signed_price)
        self.inputs: list[list[Any]] = []
        self.outputs: list[list[Any]] = []
        self.last_t = -1.0
        self.n = 0  # the next tick number
        self.sent: list[can.Message] = []

    # ---- time
    def t_tick(self, n: int) -> float:
        return n * self.ts

    def t_rx(self, n: int) -> float:
        """Receive time after tick n (and before tick n + 1)."""
        return n * self.ts + RX_OFFSET

    def _at(self, t: float) -> None:
        if t < self.last_t:
            raise ValueError(f"{self.name}: events out of order ({t} after {self.last_t})")
        self.last_t = t

    # ---- events
    def tick(self) -> list[can.Message]:
        t = self.t_tick(self.n)
        self._at(t)
        self.inputs.append(["tick", t])
        frames = self.agent.tick(t)
        for f in frames:
            if f.is_extended_id or f.is_remote_frame or f.is_fd or f.dlc != 8:
                raise AssertionError(f"{self.name}: the agent sent a non-classic frame {f}")
            self.outputs.append([t, f.arbitration_id, _hex(f)])
        self.sent.extend(frames)
        self.n += 1
        return frames

    def rx(self, msg: can.Message, note: str = "", flags: str = "") -> None:
        """Deliver ``msg`` after the last tick (at t_rx of the tick before self.n)."""
        t = self.t_rx(self.n - 1)
        self._at(t)
        if flags:
            msg = can.Message(arbitration_id=msg.arbitration_id, data=msg.data,
                              is_extended_id="ext" in flags, is_remote_frame="rtr" in flags,
                              is_fd="fd" in flags, dlc=len(msg.data), check=False)
        row: list[Any] = ["rx", t, msg.arbitration_id, _hex(msg)]
        extra = {k: v for k, v in (("flags", flags), ("note", note)) if v}
        if extra:
            row.append(extra)
        self.inputs.append(row)
        self.agent.on_frame(msg, t)

    def raw(self, fid: int, data: bytes | str, note: str = "", flags: str = "") -> None:
        if isinstance(data, str):
            data = bytes.fromhex(data)
        self.rx(can.Message(arbitration_id=fid, data=data, is_extended_id=False,
                            dlc=len(data), check=False), note, flags)

    # ---- the usual traffic
    def price(self, rho: int, valid: int = 1, segment: int = 0, skip: int = 0,
              note: str = "") -> can.Message:
        m = self.router.frame("ER_Price", {"PriceValid": valid, "Segment": segment,
                                           "Rho": rho}, skip)
        self.rx(m, note)
        return m

    def status(self, oc: int = 0, volt: int = 0, soc_fault: int = 0, limited: int = 0,
               skip: int = 0, note: str = "") -> can.Message:
        m = self.plant.frame(status_name(AGENT), {
            "FaultOverCurrent": oc, "FaultVoltage": volt, "FaultSoc": soc_fault,
            "PowerLimited": limited, "Power": 1000, "Soc": 100}, skip)
        self.rx(m, note)
        return m

    def mc(self, j: int, lam: int, state: int = 1, skip: int = 0, note: str = "",
           resets: int = 0) -> can.Message:
        m = self.senders[f"agent_{j}"].frame(mc_name(j), {"State": state, "Lambda": lam,
                                                          "Resets": resets}, skip)
        self.rx(m, note)
        return m

    def command(self, cmd: str, target: int = AGENT, k: int = 0, h: int = 0,
                patch: tuple[int, int, int] | None = None, note: str = "",
                key: bytes | None = None) -> can.Message:
        m = self.router.frame("ER_Command", {"Command": int(contract.Command[cmd]),
                                             "Target": target_raw(target), "GainK": k,
                                             "GainH": h},
                              patch=patch, key=key)
        self.rx(m, note)
        return m

    def price_sig(self, number: int, rho: int, valid: int = 1, boot: int | None = None,
                  seed: bytes | None = None, note: str = "",
                  pages: Callable[[list[can.Message]], list[can.Message]] | None = None
                  ) -> pricesig.SignedSegment:
        """The router's ER_PriceSig transfer of segment ``number`` (AUTH-32): signed with
        its price key (``seed``: another key, a forgery), at its boot (or ``boot``);
        ``pages``: what happens to the 11 pages on the way."""
        seg = pricesig.SignedSegment(self.router.boot if boot is None else boot, number,
                                     valid, rho)
        sig = pricesig.sign(seed or self.price_seed, self.keys_doc["fleet_id"], seg)
        msgs = [CODEC.encode(pricesig.MESSAGE, raw, 0) for raw in pricesig.pages(seg, sig)]
        for k, m in enumerate(pages(msgs) if pages is not None else msgs):
            self.rx(m, note if k == 0 else "")
        return seg

    def sync(self, label: str, name: str, note: str = "", **kw: int) -> can.Message:
        m = self.senders[label].sync(name, **kw)
        self.rx(m, note)
        return m

    def sync_all(self, note: str = "the senders' syncs") -> None:
        self.sync("router", "ER_Price", note)
        self.sync("router", "ER_Command")
        self.sync("plant", status_name(AGENT))
        for nb in self.cfg.neighbours:
            self.sync(f"agent_{nb.id}", mc_name(nb.id))

    def join(self) -> None:
        """Tick through the agent's join window (AUTH-26) with nothing received: it takes
        each sender's newest sync at the first frame after it (secure keys only)."""
        if self.insecure:
            return
        while self.t_rx(self.n - 1) < self.agent.io.join_s:  # its hello is tick 0, t = 0
            self.tick()

    def run(self, ticks: int, *, price: int | None | Callable[[int], int | None] = None,
            status: bool | Callable[[int], bool] = True,
            nbrs: Mapping[int, Callable[[int], tuple[int, int] | None]] | None = None,
            hook: Callable[[int], object] | None = None) -> None:
        """``ticks`` ticks, each followed by the periodic inputs: every neighbour's MC
        (``nbrs[j](n)`` = (state, λ) or None: silent), the price at ticks n ≡ 0 (mod 5)
        (``price``: ρ, or a function of n, None: silent), the plant status at n ≡ 2
        (mod 5); then ``hook(n)`` for extra frames."""
        for _ in range(ticks):
            self.tick()
            n = self.n - 1
            for j, f in (nbrs or {}).items():
                v = f(n)
                if v is not None:
                    self.mc(j, v[1], v[0])
            p = price(n) if callable(price) else price
            if p is not None and n % 5 == 0:
                self.price(p)
            s = status(n) if callable(status) else status
            if s and n % 5 == 2:
                self.status()
            if hook is not None:
                hook(n)

    # ---- output
    def vector(self) -> dict[str, Any]:
        vec: dict[str, Any] = {
            "format": FORMAT, "name": self.name, "description": self.description,
            "covers": sorted(set(self.covers), key=_req_key), "config": self.toml,
            "keys": self.keys_doc}
        if self.setup:
            vec["setup"] = self.setup
        if self.signed:  # AUTH-32, AUTH-33: no Diag slot, so the vector states them at the end
            vec["counters"] = {k: self.agent.counters[k] for k in contract.SIGNED_PRICE_COUNTERS}
        vec["input"] = self.inputs
        vec["output"] = self.outputs
        return vec


def _req_key(req: str) -> tuple[str, int]:
    prefix, _, num = req.rpartition("-")
    return prefix, int(num)


def to_json(vec: dict[str, Any]) -> str:
    """Compact JSON, one header key and one event / frame per line (diffable, ASCII)."""
    parts = []
    for key, value in vec.items():
        if key in ("input", "output"):
            body = ",\n".join(json.dumps(r, separators=(",", ":")) for r in value)
            parts.append(f'"{key}":[\n{body}\n]')
        else:
            parts.append(f"{json.dumps(key)}:{json.dumps(value, separators=(',', ':'))}")
    return "{\n" + ",\n".join(parts) + "\n}\n"


# --------------------------------------------------------------------------- scenarios

RHO = q24(0.8)
LAM1, LAM3 = q24(0.81), q24(0.79)
NOISE_LSB = 3000  # neighbour λ ripple: ξ straddles the default band (1678 LSB)


def neighbours(seed: int = 1, n: int = 4000) -> dict[int, Callable[[int], tuple[int, int]]]:
    """Agents 1 and 3 RUNNING at λ ≈ 0.81 and 0.79 with a seeded ripple of ±3000 LSB."""
    r1, r3 = noise(seed, n, NOISE_LSB), noise(seed + 100, n, NOISE_LSB)
    return {1: lambda k: (1, LAM1 + r1[k]), 3: lambda k: (1, LAM3 + r3[k])}


def start(s: Scenario, ticks: int = 10,
          nbrs: dict[int, Callable[[int], tuple[int, int]]] | None = None
          ) -> dict[int, Callable[[int], tuple[int, int]]]:
    """Tick 0, the senders' syncs, the join window (AUTH-26), then ``ticks`` − 1 ticks of
    traffic (``nbrs``: the neighbours' λ, else ``neighbours()``): RUNNING after."""
    nb = neighbours() if nbrs is None else nbrs
    s.tick()
    s.sync_all()
    s.join()
    for j, f in nb.items():
        s.mc(j, f(0)[1], 1)
    s.price(RHO)
    s.status()
    s.run(ticks - 1, price=RHO, nbrs=nb)
    return nb


def sc_start_steady() -> Scenario:
    s = Scenario(
        "start_steady",
        "Normal start and steady stepping, secure keys: frames before the senders' syncs are "
        "unsynced; the join window (0.2 s from its first syncs: each sender's newest sync "
        "kept, so an earlier sync of the router's current boot, replayed first, is replaced "
        "by the genuine one, and replayed again after it is auth; frames in the window "
        "unsynced; the syncs taken at the first frame after it, every input lost: a wider "
        "window); the syncs (resync, a hello: the agent re-sends its own syncs 0.1 s after "
        "its first); INIT until both price and status are fresh (agent 3 INIT for 0.2 s: "
        "alive but not in xi); RUNNING with a pinned price and two neighbours rippling "
        "around the price (zero crossings, resets, the band); MC every tick, Setpoint every "
        "5, Diag every 10 (pages 0..12 twice, then 0..3; signed with its own key, AUTH-29), "
        "syncs every 1 s.",
        ["GEN-1", "GEN-2", "GEN-4", "STATE-1", "STATE-2", "STATE-4", "STATE-10", "TICK-1",
         "TX-1", "TX-2", "TX-3", "TX-4", "TX-5", "SP-1", "SP-3", "DIAG-1",
         "XI-1", "XI-2", "CTRL-1", "CTRL-4", "CTRL-5", "STEP-1", "STEP-2", "STEP-3", "STEP-4",
         "STEP-5", "STEP-6", "STEP-7", "STEP-8", "BAND-1", "BAND-2", "BAND-3", "LIVE-1",
         "LIVE-2", "TMO-1", "TMO-3", "PRICE-6", "RX-8", "RX-10", "RX-11", "AUTH-1", "AUTH-2",
         "AUTH-3", "AUTH-4", "AUTH-6", "AUTH-7", "AUTH-8", "AUTH-9", "AUTH-10", "AUTH-11",
         "AUTH-12", "AUTH-15", "AUTH-16", "AUTH-26", "AUTH-29", "NUM-1"])
    nb = neighbours()
    s.tick()                                   # tick 0: INIT, own syncs, Diag page 0
    s.price(RHO, note="before the router's sync: unsynced")
    s.mc(1, nb[1](0)[1], note="before agent 1's sync: unsynced")
    s.router.count[CODEC.frame_id("ER_Price")] = 40  # the router has run for a while
    early = s.router.sync("ER_Price", count=3)
    s.rx(early, note="an earlier sync of the router's current boot (a replay): kept")
    s.sync_all()  # the genuine ones: newer, they replace it
    s.rx(early, note="the earlier sync again, after a newer one: auth")
    s.price(RHO, note="in the join window: unsynced")
    s.join()
    s.price(RHO, note="first price after the window: accepted (its newest sync)")
    s.run(1, price=None, nbrs={1: nb[1], 3: lambda k: (0, LAM3)})
    s.run(20, price=RHO, nbrs={1: nb[1], 3: lambda k: (0, LAM3)})  # status from tick 2
    s.run(280, price=RHO, nbrs=nb)
    return s


def sc_init_wait() -> Scenario:
    s = Scenario(
        "init_wait_status",
        "INIT until the plant is heard: a fresh price alone keeps INIT (no timeout counted "
        "for a status never received); a status with an over-current fault keeps INIT "
        "(counted), INIT never goes to SAFE even when the price then stops; the fault "
        "clears with the price back: RUNNING at that tick, stepping at once.",
        ["STATE-1", "STATE-2", "STATE-4", "STATE-5", "STATE-10", "TMO-3", "TMO-2", "RX-11",
         "SP-3", "DIAG-1"])
    nb = neighbours()
    s.tick()
    s.sync_all()
    s.join()
    s.run(40, price=RHO, status=False, nbrs=nb)
    for _ in range(3):
        s.run(4, price=RHO, status=False, nbrs=nb)
        s.status(oc=1, note="over-current fault")
        s.run(1, price=RHO, status=False, nbrs=nb)
    s.run(40, price=None, status=False, nbrs=nb,
          hook=lambda n: s.status(oc=1) if n % 5 == 2 else None)  # price lost in INIT
    s.price(RHO)
    s.status(note="fault cleared")
    s.run(60, price=RHO, nbrs=nb)
    return s


def sc_neighbour_timeout() -> Scenario:
    s = Scenario(
        "neighbour_timeout",
        "Neighbour liveness: agent 1 silent for 10 ticks drops out after 3 periods (counted, "
        "its ID marked lost) and comes back 11 counts later (found within 8 freshness "
        "windows: lost frames counted); agent 3 silent for 1.5 s comes back 150 counts "
        "later (beyond 8 windows: unsynced until its sync, then resynced); a RUNNING "
        "neighbour's lambda step beyond lambda_step_max is rejected (last good kept), the "
        "same step after the slot timed out is accepted (not checked), a step while the "
        "neighbour reports SAFE is not checked either.",
        ["LIVE-1", "LIVE-2", "LIVE-3", "XI-1", "LAM-1", "LAM-2", "TMO-4", "AUTH-13",
         "AUTH-14", "AUTH-15", "AUTH-16", "DIAG-1", "DIAG-4", "RX-9", "RX-12"])
    nb = start(s)
    s.run(40, price=RHO, nbrs=nb)
    jump = q24(0.25)
    s.run(1, price=RHO, nbrs={3: nb[3]})
    s.mc(1, nb[1](s.n - 1)[1] + jump, note="agent 1: lambda step 0.25 > 0.1: implausible")
    s.run(1, price=RHO, nbrs={3: nb[3]})
    s.mc(1, nb[1](s.n - 1)[1] + jump, note="again: implausible (2 samples: 0.25 > 0.2)")
    s.run(3, price=RHO, nbrs=nb)
    s.run(10, price=RHO, nbrs={3: nb[3]})          # agent 1 silent: times out
    s.mc(1, nb[1](s.n - 1)[1] + jump, skip=10,
         note="agent 1 back 11 counts on (lost: wider window), lambda +0.25: not checked")
    s.run(30, price=RHO, nbrs={1: lambda k: (1, nb[1](k)[1] + jump), 3: nb[3]})
    s.run(150, price=RHO, nbrs={1: lambda k: (1, nb[1](k)[1] + jump)})  # agent 3 silent
    s.mc(3, nb[3](s.n - 1)[1], skip=150, note="agent 3 back 151 counts on: unsynced")
    s.run(1, price=RHO, nbrs={1: lambda k: (1, nb[1](k)[1] + jump)})
    s.mc(3, nb[3](s.n - 1)[1], note="unsynced")
    s.sync("agent_3", mc_name(3), note="agent 3's periodic sync: resynced")
    s.run(20, price=RHO, nbrs={1: lambda k: (1, nb[1](k)[1] + jump), 3: nb[3]})
    s.run(1, price=RHO, nbrs={1: lambda k: (1, nb[1](k)[1] + jump)})
    s.mc(3, nb[3](s.n - 1)[1] - jump, state=3, note="agent 3 SAFE, lambda -0.25: not checked")
    s.run(5, price=RHO, nbrs={1: lambda k: (1, nb[1](k)[1] + jump),
                              3: lambda k: (3, nb[3](k)[1] - jump)})
    s.run(40, price=RHO, nbrs={1: lambda k: (1, nb[1](k)[1] + jump),
                               3: lambda k: (1, nb[3](k)[1] - jump)})
    return s


def sc_price_timeout() -> Scenario:
    s = Scenario(
        "price_timeout_safe",
        "Price lost: RUNNING -> SAFE when the last valid price is older than price_s "
        "(counted once, ER_Price marked lost; nu and xi_prev zeroed, lambda held, setpoint "
        "disabled); PriceValid = 0 frames meanwhile refresh nothing; the router comes back "
        "with a level 0.7 above the last price (beyond price_step_max: needs 3 frames even "
        "though the old price went stale), its counts 50 on (lost: found in the wider "
        "window); SAFE -> RUNNING at the tick after the third frame.",
        ["STATE-2", "STATE-3", "STATE-4", "STATE-6", "STATE-10", "TMO-1", "TMO-2", "TMO-4",
         "PRICE-1", "PRICE-3", "PRICE-4", "PRICE-6", "SP-3", "AUTH-13", "AUTH-15",
         "DIAG-1"])
    nb = start(s)
    s.run(40, price=RHO, nbrs=nb)
    s.run(5, price=None, nbrs=nb)
    s.run(15, price=None, nbrs=nb,
          hook=lambda n: s.price(RHO, valid=0) if n % 5 == 0 else None)
    s.run(40, price=None, nbrs=nb)
    new = q24(1.5)
    s.price(new, skip=50, note="back, 0.7 above the last price: 1 of 3")
    s.run(5, price=new, nbrs=nb)
    s.run(60, price=new, nbrs=nb)
    return s


def sc_status() -> Scenario:
    s = Scenario(
        "status_fault_timeout",
        "Plant status: an over-current fault -> SAFE (counted on its rising edge only), "
        "cleared -> RUNNING; FaultSoc and PowerLimited change nothing; a voltage fault -> "
        "SAFE; the status stops -> SAFE at status_s (counted once, PLANT_2_Status lost), "
        "back -> RUNNING.",
        ["STATE-2", "STATE-3", "STATE-4", "STATE-6", "RX-11", "TMO-1", "TMO-2", "TMO-4",
         "DIAG-1", "SP-3"])
    nb = start(s)
    s.run(20, price=RHO, nbrs=nb)

    def faults(oc: int = 0, volt: int = 0, soc: int = 0, lim: int = 0, k: int = 30) -> None:
        s.run(k, price=RHO, status=False, nbrs=nb,
              hook=lambda n: s.status(oc, volt, soc, lim) if n % 5 == 2 else None)

    faults(oc=1, k=30)
    faults(k=20)
    faults(soc=1, lim=1, k=20)
    faults(volt=1, k=20)
    faults(k=20)
    s.run(40, price=RHO, status=False, nbrs=nb)
    s.run(40, price=RHO, nbrs=nb)
    return s


def sc_commands() -> Scenario:
    s = Scenario(
        "commands",
        "Every command: ISOLATE (ISOLATED at once, idle MC, counters of the controller "
        "zeroed), ISOLATE again (counted, no effect), a price outage while ISOLATED (counted, "
        "stays ISOLATED), SET_GAINS while ISOLATED, RECONNECT (INIT at once, RUNNING at the "
        "next tick with a stepped lambda), RECONNECT while RUNNING (counted, no effect), "
        "commands for agent 3 (under agent 3's key, AUTH-30: ignored, not verified), a "
        "RECONNECT for this agent under agent 3's command key while ISOLATED (auth: what "
        "agent 3's key file can sign), SET_GAINS inside the bounds (nu := 0, new k*Ts, "
        "h*Ts), outside (implausible_gains), inside the bounds with h = 0 (h_min = 0 here) "
        "that the controller refuses (range).",
        ["CMD-1", "CMD-2", "CMD-3", "CMD-4", "CMD-5", "STATE-7", "STATE-8", "STATE-9",
         "STATE-10", "TMO-2", "DIAG-1", "DIAG-3", "DIAG-4", "RX-10", "XI-1", "AUTH-30"],
        extra_toml="\n[limits]\nh_min = 0.0\n")
    nb = start(s)
    s.run(60, price=RHO, nbrs=nb)
    s.command("ISOLATE", target=3, note="ISOLATE for agent 3: ignored")
    s.run(5, price=RHO, nbrs=nb)
    s.command("RECONNECT", target=3, note="RECONNECT for agent 3: ignored")
    s.run(5, price=RHO, nbrs=nb)
    s.command("ISOLATE", note="ISOLATE: ISOLATED at once")
    s.run(10, price=RHO, nbrs=nb)
    s.command("ISOLATE", note="ISOLATE again: counted, nothing changes")
    s.run(10, price=RHO, nbrs=nb)
    s.command("RECONNECT", key=derive_command_key(TEST_MASTER, "agent_3"),
              note="RECONNECT under agent 3's command key (AUTH-30): auth, stays ISOLATED")
    s.run(5, price=RHO, nbrs=nb)
    s.run(40, price=None, nbrs=nb)      # price lost while ISOLATED
    s.command("SET_GAINS", k=1500, h=3000, note="SET_GAINS k = 1.5, h = 3 while ISOLATED")
    s.run(10, price=RHO, nbrs=nb)
    s.command("RECONNECT", note="RECONNECT: INIT now, RUNNING at the next tick")
    s.run(30, price=RHO, nbrs=nb)
    s.command("RECONNECT", note="RECONNECT while RUNNING: counted, no effect")
    s.run(10, price=RHO, nbrs=nb)
    s.command("SET_GAINS", target=3, k=1000, h=2000, note="SET_GAINS for agent 3: ignored")
    s.run(10, price=RHO, nbrs=nb)
    s.command("SET_GAINS", k=2000, h=4000, note="SET_GAINS k = 2, h = 4: at the bounds")
    s.run(30, price=RHO, nbrs=nb)
    s.command("SET_GAINS", k=2001, h=2000, note="k = 2.001 > k_max: implausible_gains")
    s.run(10, price=RHO, nbrs=nb)
    s.command("SET_GAINS", k=1000, h=0, note="h = 0: in the bounds, refused (range)")
    s.run(10, price=RHO, nbrs=nb)
    s.command("SET_GAINS", k=499, h=2000, note="k = 0.499 < k_min: implausible_gains")
    s.run(60, price=RHO, nbrs=nb)
    return s


def sc_auth() -> Scenario:
    s = Scenario(
        "auth_forgery_replay",
        "Authentication: a price with a forged MAC (auth, last_safety = auth), five in a "
        "row (untrusted verdict; the genuine price keeps being used), a replayed MC of "
        "agent 1 (auth), agent 1's MC held back and delivered 3 ticks late (valid MAC, "
        "old freshness, never accepted: stale, not auth), again (now a replay: auth), "
        "a genuine status 20 counts on while not lost (beyond the window: "
        "auth), a sync in step (nothing), a replayed older sync (auth), a forged sync "
        "(auth on the sync ID), a sync with Boot = 0 (range on the sync ID), a status "
        "sync that moves the plant on (resync).",
        ["AUTH-7", "AUTH-10", "AUTH-12", "AUTH-14", "AUTH-15", "AUTH-16", "AUTH-17", "AUTH-25",
         "RX-8", "RX-10", "RX-12", "RX-13", "DIAG-1", "DIAG-4"])
    nb = start(s)
    s.run(20, price=RHO, nbrs=nb)
    forged = s.router.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": q24(2.0)})
    forged.data[0] ^= 0x5A
    s.router.count[CODEC.frame_id("ER_Price")] -= 1  # the router itself never sent it
    s.rx(forged, note="forged MAC (price 2.0): auth")
    s.run(10, price=RHO, nbrs=nb)
    for i in range(5):
        f = s.router.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": q24(3.0)})
        f.data[1] ^= 1 + i
        s.router.count[CODEC.frame_id("ER_Price")] -= 1
        s.rx(f, note=f"forged MAC {i + 1} of 5" + (": untrusted" if i == 4 else ""))
    s.run(20, price=RHO, nbrs=nb)
    old = s.mc(1, nb[1](s.n - 1)[1] + 1, note="genuine")
    s.run(5, price=RHO, nbrs=nb)
    s.rx(old, note="replay of agent 1's MC 5 ticks ago: auth")
    s.run(5, price=RHO, nbrs=nb)
    a1 = s.senders["agent_1"]
    held = a1.frame(mc_name(1), {"State": 1, "Lambda": nb[1](s.n - 1)[1], "Resets": 0})
    s.run(3, price=RHO, nbrs=nb)
    s.rx(held, note="agent 1's MC held back 3 ticks (lost, then late): stale")
    s.rx(held, note="the same frame again: accepted as stale once, now a replay: auth")
    s.run(10, price=RHO, nbrs=nb)
    s.status(skip=20, note="genuine status 21 counts on, ID not lost: auth")
    s.plant.count[CODEC.frame_id(status_name(AGENT))] -= 21
    s.run(10, price=RHO, nbrs=nb)
    s.sync("router", "ER_Price", note="sync in step: nothing")
    old_sync = s.router.sync("ER_Price", count=3)
    s.rx(old_sync, note="an older sync of the router: replay, auth")
    bad = s.router.sync("ER_Command")
    bad.data[2] ^= 0x80
    s.rx(bad, note="forged sync: auth on ER_Command_Sync")
    zero = s.router.sync("ER_Price")
    set_bits(zero.data, 48, 16, 0)
    s.rx(zero, note="sync with Boot = 0: range")
    s.run(10, price=RHO, nbrs=nb)
    s.plant.count[CODEC.frame_id(status_name(AGENT))] += 16
    s.sync("plant", status_name(AGENT), note="plant sync 16 counts on (as far as a frame "
           "could reach, AUTH-27): resync")
    s.run(40, price=RHO, nbrs=nb)
    return s


def sc_peer_restart() -> Scenario:
    s = Scenario(
        "peer_restart",
        "Restarted senders: agent 1 restarts (boot + 1, count 0): its frames before its "
        "sync fail (auth), its sync with the new boot resyncs it and makes a hello pending: "
        "the agent re-sends its syncs 0.1 s after its last; the router restarts likewise; "
        "other agents' link frames (AUTH-28: PLANT_1_Status_Sync, agent 1's Setpoint_Sync, "
        "a forged PLANT_3_Status_Sync) are under keys the agent does not hold: ignored, "
        "no hello, no auth; AGENT_4_MC_Sync (no key held) is ignored; the agent's own frames "
        "echoed back are ignored, the same IDs with other data are impersonation.",
        ["AUTH-9", "AUTH-11", "AUTH-14", "AUTH-16", "AUTH-18", "AUTH-19", "AUTH-28", "RX-3",
         "RX-4", "RX-5", "RX-6", "LIVE-2", "DIAG-1"])
    nb = start(s)
    s.run(40, price=RHO, nbrs=nb)
    a1 = s.senders["agent_1"]
    a1.restart()
    s.run(1, price=RHO, nbrs={3: nb[3]})
    s.mc(1, nb[1](s.n - 1)[1], note="agent 1 restarted, before its sync: auth")
    s.run(1, price=RHO, nbrs={3: nb[3]})
    s.sync("agent_1", mc_name(1), note="agent 1's sync, new boot: resync, hello pending")
    s.run(20, price=RHO, nbrs=nb)
    s.sync("plant", status_name(1), note="PLANT_1_Status_Sync, agent 1's link: ignored")
    s.run(13, price=RHO, nbrs=nb)
    s.sync("agent_1", setpoint_name(1), note="AGENT_1_Setpoint_Sync, agent 1's link: ignored")
    s.run(15, price=RHO, nbrs=nb)
    s.sync("agent_1", setpoint_name(1), note="again: ignored")
    bad = s.senders["plant"].sync(status_name(3), boot=7)
    bad.data[0] ^= 1
    s.rx(bad, note="forged PLANT_3_Status_Sync: not its link, ignored")
    s.sync("agent_4", mc_name(4), note="AGENT_4_MC_Sync, no key held: ignored")
    s.run(15, price=RHO, nbrs=nb)
    s.router.restart()
    s.run(4, price=None, nbrs=nb)
    s.sync("router", "ER_Price", note="router restarted: its price sync")
    s.sync("router", "ER_Command")
    s.run(20, price=RHO, nbrs=nb)
    own = [m for m in s.sent if m.arbitration_id == CODEC.frame_id(mc_name(AGENT))][-1]
    s.rx(own, note="own MC echoed back: ignored")
    own_sync = [m for m in s.sent if m.arbitration_id == contract.SYNC_OF[own.arbitration_id]]
    s.rx(own_sync[-1], note="own MC_Sync echoed back: ignored")
    spoof = bytearray(own.data)
    spoof[5] ^= 0x10
    s.raw(own.arbitration_id, bytes(spoof), note="own MC ID, other data: impersonation")
    s.run(40, price=RHO, nbrs=nb)
    return s


def sc_malformed() -> Scenario:
    s = Scenario(
        "malformed_foreign",
        "Frames the agent must drop and count by cause: extended ID, remote and FD frames, "
        "an ID not in the DBC, AGENT_9_MC of an agent outside the fleet (foreign), "
        "AGENT_4_MC (not a neighbour: ignored), DLC 7 (five in a row: untrusted verdict), "
        "Soc > 200, Command 0 and a PIN with GainK 3 (range), a command for agent 64 "
        "(raw Target 63: ignored), a price above lambda_max and a "
        "neighbour lambda below lambda_min (range, after the MAC), a price below rho_min "
        "(implausible_price).",
        ["RX-1", "RX-2", "RX-6", "RX-7", "RX-9", "RX-12", "RX-13", "PRICE-2", "DIAG-1",
         "DIAG-4", "GEN-3", "LIVE-1"])
    nb = start(s)
    s.run(20, price=RHO, nbrs=nb)
    good = s.router.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": RHO})
    s.router.count[CODEC.frame_id("ER_Price")] -= 1
    s.raw(0x010, bytes(good.data), flags="ext", note="extended ID 0x00000010: unknown_id")
    s.raw(0x010, bytes(good.data), flags="rtr", note="remote frame: malformed")
    s.raw(0x010, bytes(good.data), flags="fd", note="CAN FD frame: malformed")
    s.raw(0x7F0, "0011223344556677", note="ID not in the DBC: unknown_id")
    s.raw(mc_name_id(9), "0011223344556677", note="AGENT_9_MC, fleet of 4: foreign_id")
    s.raw(status_id(3), "0011223344556677", note="PLANT_3_Status: not for this agent")
    s.rx(s.senders["agent_4"].frame(mc_name(4), {"State": 1, "Lambda": RHO, "Resets": 0}),
         note="AGENT_4_MC, not a neighbour: ignored")
    s.run(5, price=RHO, nbrs=nb)
    for i in range(5):
        m = s.plant.frame(status_name(AGENT), {
            "FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
            "Power": 0, "Soc": 100})
        s.plant.count[CODEC.frame_id(status_name(AGENT))] -= 1
        s.raw(m.arbitration_id, bytes(m.data[:7]),
              note="DLC 7: dlc" + (" (5th: untrusted)" if i == 4 else ""))
    s.run(10, price=RHO, nbrs=nb)
    s.rx(s.plant.frame(status_name(AGENT), {
        "FaultOverCurrent": 0, "FaultVoltage": 0, "FaultSoc": 0, "PowerLimited": 0,
        "Power": 0, "Soc": 200}, patch=(48, 8, 201)), note="Soc raw 201 > 200: range")
    s.command("ISOLATE", patch=(28, 2, 0), note="Command 0: range")
    s.command("PIN", k=1, patch=(36, 14, 3), note="PIN with GainK 3: range")
    s.command("ISOLATE", patch=(30, 6, 63), note="Target raw 63 = agent 64: not this agent")
    s.run(10, price=RHO, nbrs=nb)
    s.price(q24(10.5), note="price 10.5 > lambda_max: range")
    s.mc(1, q24(-10.5), note="lambda -10.5 < lambda_min: range")
    s.run(5, price=RHO, nbrs=nb)
    s.price(q24(-5.5), note="price -5.5 < rho_min: implausible_price")
    s.run(40, price=RHO, nbrs=nb)
    return s


def mc_name_id(j: int) -> int:
    return CODEC.frame_id(mc_name(j))


def status_id(j: int) -> int:
    return CODEC.frame_id(status_name(j))


def sc_price_steps() -> Scenario:
    s = Scenario(
        "price_steps",
        "Price plausibility: a step within price_step_max is accepted at once; a step "
        "beyond it needs price_persist = 3 equal frames (a different level restarts the "
        "count; forged frames and PriceValid = 0 between them do not break the run); a "
        "price outside [rho_min, rho_max] is rejected and forgets the candidate.",
        ["PRICE-1", "PRICE-2", "PRICE-3", "PRICE-4", "PRICE-6", "RX-9", "RX-10", "DIAG-1",
         "DIAG-4"])
    nb = start(s)
    s.run(20, price=RHO, nbrs=nb)
    steps = [(1.2, "step 0.4: accepted"), (1.6, "step 0.4: accepted"),
             (2.2, "step 0.6: 1 of 3"), (2.2, "2 of 3"), (2.4, "another level: 1 of 3"),
             (2.4, "2 of 3"), (2.4, "3 of 3: accepted"), (2.0, "step 0.4: accepted")]
    for p, note in steps:
        s.run(2, price=None, nbrs=nb)
        s.price(q24(p), note=note)
    s.run(5, price=None, nbrs=nb)
    lvl = q24(2.6)
    for k in range(3):
        s.price(lvl, note=f"{k + 1} of 3 with other frames between")
        f = s.router.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": lvl})
        s.router.count[CODEC.frame_id("ER_Price")] -= 1
        f.data[0] ^= 0xFF
        s.rx(f, note="forged: does not break the run")
        s.price(q24(0.5), valid=0, note="PriceValid = 0: does not break the run")
        s.run(3, price=None, nbrs=nb)
    s.price(q24(0.5), note="a step down of 2.0: 1 of 3")
    s.price(q24(5.5), note="above rho_max: implausible_price, candidate forgotten")
    s.price(q24(0.5), note="1 of 3 again")
    s.run(5, price=q24(0.5), nbrs=nb)
    s.run(30, price=q24(0.5), nbrs=nb)
    return s


def sc_tx_wrap() -> Scenario:
    s = Scenario(
        "tx_count_wrap",
        "The agent's message counts start at 2**24 - 12 (setup.tx_count, a test hook): "
        "the MC count reaches 2**24 after 12 frames: a new boot (persisted), every count "
        "back to 0, the frame sent under the new boot and the syncs at the next tick.",
        ["AUTH-3", "AUTH-4", "AUTH-5", "AUTH-9"],
        tx_count=contract.FRESHNESS.max_counter - 11)
    nb = start(s)
    s.run(40, price=RHO, nbrs=nb)
    return s


INSECURE_TOML = """\
# time scale 2 (sim.model.scenario.scaled): ts = 0.02, k = 1/2, h = 2/4
[agent]
id = 2
lambda0 = 0.8033
pinned = false
fleet_size = 4

[controller]
kind = "dwell"
k = 0.5
h = 0.5
ts = 0.02
dwell = 0.2
band = 0.0001

[battery]
alpha = 0.005
beta = 0.18
m = 0.08
p_min = -100.0
p_max = 100.0

[limits]
price_persist = 1

[[neighbour]]
id = 1
weight = 1.0

[[neighbour]]
id = 3
weight = 0.5
"""


def sc_insecure() -> Scenario:
    s = Scenario(
        "insecure_scaled",
        "--insecure (all-zero master key, every node at boot 1, no sync needed), a "
        "time-scaled agent (F = 2: ts = 0.02, k = 0.5, h = 0.5, dwell controller with "
        "dwell = 0.2 s = 10 samples, not pinned, lambda(0) at the neighbours' weighted mean: "
        "crossings blocked by the dwell): every cadence in ticks, timeouts in Ts; "
        "price_persist = 1 takes a far step at once; a status outage (SAFE and back: the "
        "dwell timer and the band run on); SET_GAINS carries the scaled gains (k = 0.6, "
        "h = 0.8); a restarted insecure router (boot 1, count 0 again) fails until its sync, "
        "which goes back and is accepted.",
        ["AUTH-20", "AUTH-16", "AUTH-17", "PRICE-5", "CMD-5", "CMD-6", "SCALE-2", "STATE-3",
         "STATE-4", "STATE-6", "DWELL-1", "DWELL-2", "CTRL-2", "TMO-1", "TMO-2", "DIAG-1"],
        insecure=True, toml=INSECURE_TOML)
    nb = neighbours(7)
    s.tick()
    s.run(60, price=RHO, nbrs=nb)
    s.run(1, price=None, nbrs=nb)
    s.price(q24(1.6), note="a step of 0.8 > 0.5, price_persist = 1: accepted")
    s.run(20, price=q24(1.6), nbrs=nb)
    s.run(32, price=q24(1.6), status=False, nbrs=nb)  # status_s = 25 Ts: SAFE, then back
    s.run(20, price=q24(1.6), nbrs=nb)
    s.command("SET_GAINS", k=600, h=800, note="SET_GAINS k = 0.6, h = 0.8 (scaled)")
    s.run(10, price=q24(1.6), nbrs=nb)
    s.router.restart()
    s.router.boot = 1
    s.run(1, price=None, nbrs=nb)
    s.price(q24(1.6), note="restarted router, boot 1 count 0 again: auth")
    s.sync("router", "ER_Price", note="its sync goes back: accepted (insecure)")
    s.run(20, price=q24(1.6), nbrs=nb)
    return s


def sc_boot_floors() -> Scenario:
    floors = {"router": 3, "plant": 5, "agent_1": 2, "agent_3": 4}  # the senders' boots
    s = Scenario(
        "boot_floors",
        "Boot floors (the key file's [floors]: each sender's boot at this start): before the "
        "genuine syncs, an earlier run's router price sync (boot 2 < floor 3) is auth and "
        "sets nothing, so its price is unsynced, and agent 1's MC sync of boot 1 is auth; "
        "the genuine syncs and frames then start the agent as usual; later the plant's sync "
        "of PLANT_2_Status at boot 4 (< the plant's floor 5, kept for its link frame, "
        "AUTH-28) is auth and sets nothing, an agent 3 sync of a new "
        "boot (above its floor) resyncs.",
        ["AUTH-16", "AUTH-21", "AUTH-28", "CFG-8"], floors=floors)
    nb = neighbours()
    s.tick()
    earlier = Sender("router", s.router.key, 2)
    earlier.count[CODEC.frame_id("ER_Price")] = 500
    s.rx(earlier.sync("ER_Price"), note="an earlier run's price sync, boot 2 < 3: auth")
    s.rx(earlier.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": q24(1.5)}),
         note="its price: unsynced")
    old_a1 = Sender("agent_1", s.senders["agent_1"].key, 1)
    s.rx(old_a1.sync(mc_name(1), count=77), note="agent 1's MC sync of boot 1 < 2: auth")
    s.sync_all()
    s.join()
    for j, f in nb.items():
        s.mc(j, f(0)[1], 1)
    s.price(RHO)
    s.status()
    s.run(40, price=RHO, nbrs=nb)
    s.rx(s.plant.sync(status_name(AGENT), boot=4), note="the plant's sync, boot 4 < 5: auth")
    s.run(15, price=RHO, nbrs=nb)
    s.senders["agent_3"].restart()
    s.sync("agent_3", mc_name(3), note="agent 3 restarted, boot 5 > floor 4: resync")
    s.run(30, price=RHO, nbrs=nb)
    return s


def sc_boot_jump() -> Scenario:
    s = Scenario(
        "sync_boot_jump",
        "Bounded and pending boot advance (AUTH-27, AUTH-35), syncs signed with the router's "
        "key as a key holder forges them: a price sync 9 boots ahead of the router's is "
        "refused (sync_jump and auth on the sync ID, nothing set); one 8 boots ahead is "
        "held, not taken: the genuine prices go on, and the router's next sync, of the boot "
        "it is in, drops it (sync_jump): a price forged on its track is then auth. Held "
        "again and completed by a price forged on its track, it is taken (resync, hello) "
        "and the genuine prices fail (auth) until the router's next sync undoes it "
        "(sync_jump, resync, hello). The router then restarts (boot + 1): its sync is held "
        "and taken at its first price.",
        ["AUTH-16", "AUTH-27", "AUTH-35", "DIAG-1"])
    nb = start(s)
    s.run(40, price=RHO, nbrs=nb)
    boot = s.router.boot
    s.rx(s.router.sync("ER_Price", count=0, boot=boot + 9),
         note="a price sync 9 boots ahead: sync_jump and auth, nothing set")
    s.run(20, price=RHO, nbrs=nb)
    s.rx(s.router.sync("ER_Price", count=0, boot=boot + 8),
         note="8 boots ahead: held (AUTH-35), nothing set")
    s.run(12, price=RHO, nbrs=nb)
    s.sync("router", "ER_Price", note="the router's own sync, of the boot it is in: drops "
           "the held advance (sync_jump)")
    forger = Sender("router", s.router.key, boot + 8)
    s.rx(forger.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": RHO}),
         note="a price forged on the dropped track: auth")
    s.run(20, price=RHO, nbrs=nb)
    s.rx(s.router.sync("ER_Price", count=1, boot=boot + 8),
         note="8 boots ahead again: held")
    s.rx(forger.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": RHO}),
         note="a price forged on the held track: the advance taken (resync, hello)")
    s.run(12, price=RHO, nbrs=nb)
    s.sync("router", "ER_Price", note="the router's own sync, of the boot it is in: undoes "
           "the advance (sync_jump, resync, hello)")
    s.run(30, price=RHO, nbrs=nb)
    s.router.restart()
    s.run(4, price=None, nbrs=nb)
    s.sync("router", "ER_Price", note="the router restarted (boot + 1): its price sync, held")
    s.sync("router", "ER_Command")
    s.run(30, price=RHO, nbrs=nb)
    return s


def sc_count_jump() -> Scenario:
    s = Scenario(
        "sync_count_jump",
        "Bounded count advance (AUTH-27), syncs signed with the router's key as a key holder "
        "forges them: a price sync of the router's boot 17 counts ahead of an input in step "
        "(16 more than a frame could reach) is refused (sync_jump and auth, nothing set), "
        "one 16 ahead taken; a command sync 129 ahead (its wide search reaches 128) "
        "refused; after a price timeout (ER_Command lost with it) a command sync 200 ahead "
        "is taken, and a command at that count too.",
        ["AUTH-16", "AUTH-27", "AUTH-13", "DIAG-1"])
    nb = start(s)
    s.run(30, price=RHO, nbrs=nb)
    price, command = CODEC.frame_id("ER_Price"), CODEC.frame_id("ER_Command")
    count = s.router.count[price]
    s.rx(s.router.sync("ER_Price", count=count + 17),
         note="a price sync of the router's boot 17 counts ahead (16 more than a frame could "
         "reach): sync_jump and auth, nothing set")
    s.run(10, price=RHO, nbrs=nb)
    s.router.count[price] += 16   # 16 prices this agent missed
    s.sync("router", "ER_Price", note="16 ahead (a frame could have been): taken")
    s.run(10, price=RHO, nbrs=nb)
    count = s.router.count.get(command, 0)
    s.sync("router", "ER_Command", note="the command sync in step: ER_Command no longer lost "
           "(since the join)")
    s.rx(s.router.sync("ER_Command", count=count + 129),
         note="a command sync 129 counts ahead (its wide search reaches 128): sync_jump, auth")
    s.run(10, price=RHO, nbrs=nb)
    s.run(30, price=None, nbrs=nb)   # the price times out: ER_Command is lost too
    s.router.count[command] = count + 200   # commands to others this agent missed
    s.sync("router", "ER_Command", note="after the price timed out, a command sync 200 "
           "ahead: taken (the router's input is lost)")
    s.command("RECONNECT", note="a command at that count: taken (counted, no effect)")
    s.sync("router", "ER_Price")
    s.run(30, price=RHO, nbrs=nb)
    return s


def sc_resilient() -> Scenario:
    toml = BASE_TOML.format(extra="").replace(
        "fleet_size = 4\n", "fleet_size = 4\nresilient_f = 1\n") + (
        "\n[[neighbour]]\nid = 4\nweight = 2.0\n")
    s = Scenario(
        "resilient_trim",
        "The resilient update (W-MSR, resilient_f = 1) with three neighbours: agent 4 lies "
        "0.05 above agent 1 (the largest lambda above the own: dropped, and agent 3's, the "
        "smallest below, too); then tells exactly agent 1's lambda (a tie: of the two, "
        "weight 2.0, agent 4's, is dropped); then 0.03 below agent 3 (the smallest below: "
        "dropped, with agent 1, the largest above); the price term never dropped.",
        ["CFG-2", "XI-1", "XI-2", "WMSR-1", "WMSR-2"], toml=toml)
    nb = neighbours()
    lie = noise(7, 4000, NOISE_LSB)
    high = {**nb, 4: lambda k: (1, LAM1 + q24(0.05) + lie[k])}
    start(s, 151, high)
    s.run(100, price=RHO, nbrs={**nb, 4: lambda k: (1, nb[1](k)[1])})
    s.run(100, price=RHO, nbrs={**nb, 4: lambda k: (1, LAM3 - q24(0.03) + lie[k])})
    return s


def sc_event_transmit() -> Scenario:
    s = Scenario(
        "event_transmit",
        "Event-triggered MC ([transmit] mode = event, threshold 3e-4, heartbeat 5: the "
        "neighbour timeout defaults to 7 periods): the first tick sends; then an MC frame "
        "only when the wire lambda moved more than the threshold from the one last sent, the "
        "State changed (INIT -> RUNNING, ISOLATE, RECONNECT), or 5 ticks passed; its message "
        "count C advances per frame sent, not per tick (AUTH-4), and MC_Sync announces the "
        "next one. Agent 1 sends every 4th tick only and agent 3 falls silent for 6 ticks: "
        "held and alive (in xi); agent 3 silent for 9 ticks times out (7 periods) and comes "
        "back. A price step moves lambda: a frame every tick while it moves fast.",
        ["CFG-6", "CFG-9", "TX-1", "TX-7", "TICK-1", "LIVE-2", "LIVE-3", "AUTH-4", "AUTH-8",
         "XI-1", "DIAG-1"],
        extra_toml='\n[transmit]\nmode = "event"\nthreshold = 3e-4\nheartbeat = 5\n')
    nb = start(s)
    s.run(60, price=RHO, nbrs=nb)
    sparse = {1: lambda k: nb[1](k) if k % 4 == 0 else None, 3: nb[3]}
    s.run(40, price=RHO, nbrs=sparse)
    s.run(6, price=RHO, nbrs={1: sparse[1]})        # agent 3 silent 6 ticks: still alive
    s.run(20, price=RHO, nbrs=sparse)
    s.run(9, price=RHO, nbrs={1: sparse[1]})        # 9 ticks: timed out after 7 periods
    s.run(30, price=RHO, nbrs=sparse)
    s.command("ISOLATE", note="ISOLATE: the State change is sent at once")
    s.run(12, price=RHO, nbrs=sparse)
    s.command("RECONNECT", note="RECONNECT: INIT, then RUNNING: both sent")
    s.run(20, price=RHO, nbrs=sparse)
    rho2 = q24(0.9)
    s.run(5, price=rho2, nbrs=sparse)               # a price step: lambda moves
    s.run(200, price=rho2, nbrs=sparse)
    return s


def sc_pin() -> Scenario:
    s = Scenario(
        "pin",
        "PIN (ER_Command Command 0, CMD-7) on a pinned agent: an UNPIN (GainK 2) for agent 3 "
        "(ignored); UNPIN: the price term leaves xi at once, lambda follows the neighbours "
        "only; PINs out of range (GainK 0, GainK 3, GainH 1: rejected before authentication, "
        "counted under range); ISOLATE, PIN while ISOLATED (counted, no other effect), "
        "RECONNECT: back to RUNNING with the price term, lambda back to the price.",
        ["CMD-1", "CMD-2", "CMD-7", "XI-1", "XI-2", "STATE-7", "STATE-8"])
    nb = start(s)
    off, on = frames.PIN_OFF, frames.PIN_ON
    s.run(60, price=RHO, nbrs=nb)
    s.command("PIN", target=3, k=off, note="UNPIN for agent 3: ignored")
    s.run(10, price=RHO, nbrs=nb)
    s.command("PIN", k=off, note="UNPIN: the price term leaves xi")
    s.run(100, price=RHO, nbrs=nb)
    s.command("PIN", k=0, note="PIN with GainK 0: range")
    s.command("PIN", k=3, note="PIN with GainK 3: range")
    s.command("PIN", k=on, h=1, note="PIN with GainH 1: range")
    s.run(20, price=RHO, nbrs=nb)
    s.command("ISOLATE", note="ISOLATE")
    s.run(10, price=RHO, nbrs=nb)
    s.command("PIN", k=on, note="PIN while ISOLATED: counted, pinned again")
    s.run(10, price=RHO, nbrs=nb)
    s.command("RECONNECT", note="RECONNECT: RUNNING with the price term")
    s.run(150, price=RHO, nbrs=nb)
    return s


def sc_signed_price() -> Scenario:
    s = Scenario(
        "signed_price",
        "The signed price ([security] signed_price, the router's public price key in the key "
        "file): an ER_Price before any signature is unsigned_price; the router's ER_PriceSig "
        "transfer (11 pages, no MAC) verified once, its prices taken (RUNNING); the "
        "once-a-second repeat (no verify); a price other than the signed one under the "
        "router's valid MAC and its next count (unsigned_price, refused before its "
        "freshness: the genuine price of that count is still taken); transfers signed with "
        "another key and with a bit flipped (bad_signature, the price held); pages without "
        "their page 0, repeated with other bytes, a last page too long, out of range, of "
        "5 bytes (sig_malformed); a new segment (its Segment bits) and its price; the old "
        "segment's price (unsigned_price) and its transfer replayed (bad_signature: older), "
        "a genuine signature of the router's previous boot (bad_signature: replay); the "
        "segment number stepping 1 → 1000 → 2000 → 0 (each newer: mod 2048); a key "
        "holder's price sync 8 boots ahead, held, and the signed price replayed on its "
        "track: no signature of that boot vouches for it (unsynced, AUTH-33), the router's "
        "next sync drops it; the router restarted: its price held (unsynced) until its "
        "signature of the new boot, then taken.",
        ["AUTH-31", "AUTH-32", "AUTH-33", "AUTH-35", "PRICE-6"], extra_toml="\n[security]\n"
        "signed_price = true\n", signed=True)
    price_id = CODEC.frame_id("ER_Price")
    nb = neighbours()
    s.tick()
    s.sync_all()
    s.join()
    s.price(RHO, note="before any signature: unsigned_price")
    seg0 = s.price_sig(0, RHO, note="the router's signed segment 0: verified")
    for j, f in nb.items():
        s.mc(j, f(0)[1], 1)
    s.price(RHO, note="the signed segment's price: taken")
    s.status()
    s.run(30, price=RHO, nbrs=nb)
    s.price_sig(0, RHO, note="the once-a-second repeat: no verify")
    forged = s.router.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": q24(3.0)})
    s.router.count[price_id] -= 1   # its count is the router's next genuine one
    s.rx(forged, note="ρ = 3 under the router's MAC and next count: unsigned_price")
    s.price(RHO, note="the genuine price of that count: taken (its freshness untouched)")
    s.run(10, price=RHO, nbrs=nb)
    s.price_sig(1, q24(3.0), seed=bytes(32), note="segment 1 (ρ = 3) under another key: "
                "bad_signature")
    s.price_sig(1, RHO, pages=lambda m: [m[0], *m[1:3],
                                         can.Message(arbitration_id=m[3].arbitration_id,
                                                     data=bytes([m[3].data[0]])
                                                     + bytes([m[3].data[1] ^ 4])
                                                     + bytes(m[3].data[2:]),
                                                     is_extended_id=False), *m[4:]],
                note="a bit flipped in page 3: bad_signature")
    s.run(5, price=RHO, nbrs=nb)

    def malformed(m: list[can.Message]) -> list[can.Message]:
        page2 = bytearray(m[2].data)
        page2[3] ^= 0x40
        last = bytearray(m[10].data)
        last[2] = 1
        high = bytearray(m[5].data)
        high[0] = (high[0] & 0xF0) | 12
        short = can.Message(arbitration_id=m[4].arbitration_id, data=bytes(m[4].data[:5]),
                            dlc=5, is_extended_id=False, check=False)
        return [m[1], m[0], m[1], m[2],
                can.Message(arbitration_id=m[2].arbitration_id, data=bytes(page2),
                            is_extended_id=False),
                m[3], can.Message(arbitration_id=m[5].arbitration_id, data=bytes(high),
                                  is_extended_id=False), short,
                m[0], *m[1:10], can.Message(arbitration_id=m[10].arbitration_id,
                                            data=bytes(last), is_extended_id=False)]
    s.price_sig(1, RHO, pages=malformed, note="pages 1 without page 0, page 2 repeated with "
                "other bytes, page 12, 5 bytes, a last page too long: sig_malformed")
    s.run(5, price=RHO, nbrs=nb)
    rho1 = RHO + 1000
    s.price_sig(1, rho1, note="segment 1: verified")
    s.run(10, price=None, nbrs=nb,
          hook=lambda n: s.price(rho1, segment=1) if n % 5 == 0 else None)
    s.price(RHO, note="segment 0's price: unsigned_price")
    s.price_sig(seg0.number, seg0.rho, note="segment 0's transfer replayed: bad_signature")
    s.price_sig(7, rho1, boot=s.router.boot - 1, note="a genuine signature of the router's "
                "previous boot: bad_signature")
    s.run(10, price=None, nbrs=nb,
          hook=lambda n: s.price(rho1, segment=1) if n % 5 == 0 else None)
    for number in (1000, 2000):   # steps below half the range: newer
        s.price_sig(number, rho1, note=f"segment {number}: verified")
        s.run(10, price=None, nbrs=nb,
              hook=lambda n, k=number: s.price(rho1, segment=k % 8) if n % 5 == 0 else None)
    s.price_sig(0, RHO, note="segment 2048 = 0 (mod 2048): newer, verified")
    s.run(20, price=RHO, nbrs=nb)
    boot = s.router.boot   # AUTH-33 and AUTH-35: a held price advance needs its signature
    s.rx(s.router.sync("ER_Price", count=0, boot=boot + 8),
         note="a key holder's price sync 8 boots ahead: held (AUTH-35)")
    forger = Sender("router", s.router.key, boot + 8)
    s.rx(forger.frame("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": RHO}),
         note="the signed price replayed on the held track: no signature of that boot "
         "(unsynced, not taken)")
    s.run(10, price=RHO, nbrs=nb)
    s.sync("router", "ER_Price", note="the router's sync of its boot: drops the held "
           "advance (sync_jump)")
    s.run(10, price=RHO, nbrs=nb)
    s.router.restart()
    s.sync("router", "ER_Price", note="the router restarted (boot + 1): its sync, held")
    s.sync("router", "ER_Command")
    s.price(RHO, note="its price before its signature of the new boot: unsynced, held")
    s.price_sig(0, RHO, note="its signature of the new boot: verified")
    s.run(20, price=RHO, nbrs=nb)
    return s


SCENARIOS: tuple[Callable[[], Scenario], ...] = (
    sc_start_steady, sc_init_wait, sc_neighbour_timeout, sc_price_timeout, sc_status,
    sc_commands, sc_auth, sc_peer_restart, sc_malformed, sc_price_steps, sc_tx_wrap,
    sc_insecure, sc_boot_floors, sc_boot_jump, sc_count_jump,
    sc_resilient, sc_event_transmit, sc_pin, sc_signed_price)


def render_all() -> dict[str, str]:
    """File name → text of every node vector, exactly as committed."""
    out: dict[str, str] = {}
    fw_log = logging.getLogger("firmware_py")
    level = fw_log.level
    fw_log.setLevel(logging.ERROR)  # the scenarios provoke every warning on purpose
    try:
        for make in SCENARIOS:
            s = make()
            name = f"{s.name}.json"
            if name in out:
                raise ValueError(f"two vectors named {s.name}")
            out[name] = to_json(s.vector())
    finally:
        fw_log.setLevel(level)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("-o", "--output", type=Path, default=DEFAULT_OUTPUT)
    p.add_argument("--check", action="store_true")
    args = p.parse_args(argv)
    rc = write_or_check(render_all(), args.output, args.check)
    if rc:
        sys.stderr.write("run python tools/gen_vectors.py\n")
    return rc


if __name__ == "__main__":
    raise SystemExit(main())
