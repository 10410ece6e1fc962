"""A key holder's forgeries: what one node's key file lets an insider send as the other
nodes (`bess-ded inject insider --key-file FILE`, issue 25; docs/security.md).

For every secured message of the fleet that the file's node does not send itself, the
insider builds the most harmful frame it can (the price at three times the scenario's, an
ISOLATE of each other agent, an over-current status, a setpoint at p_max, a λ far from
the price, a Diag page full of timeouts) and signs it with the best key the file holds:

* the key that really signs that message, where the file holds it (what the scheme
  leaves forgeable: the residual risk). It then follows the genuine sender's freshness,
  verifying its frames with that key, so that every forged frame carries the value the
  sender's next frame takes: what a receiver that checks only the MAC accepts;
* else the nearest key it holds: its own frame key of the same kind (a link frame, a
  report), its own command key, its own node key; and a sync one boot ahead every sync
  period (within AUTH-27's bound), as a right key would need.

Besides, with the router's node key (every agent's file holds it to verify the price),
the router's own syncs: every sync period an `ER_Price_Sync` and an `ER_Command_Sync` of
the router's next boot, count 0, exactly what the router sends when it restarts.
Receivers in step hold such a sync and drop it at the router's next one (AUTH-35:
``sync_jump``); it is not residual unless a frame verifies on it.

The plan says which is which. A node that rejects a frame forged under a stand-in key
counts ``auth``; a signed-price agent refuses any price but the signed one
(``unsigned_price``); the genuine sender of each forged frame sees its own ID
(``impersonation``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import can

from firmware_py import contract
from firmware_py import fixedpoint as fx
from firmware_py.contract import Command, State
from firmware_py.frames import (
    FrameCodec,
    diag_name,
    mc_name,
    setpoint_name,
    status_name,
    target_raw,
)
from firmware_py.nodeio import FleetSender, NodeIO
from firmware_py.secoc import Keyring, NodeKey, pair_label
from sim.model.scenario import Scenario

SYNC_EVERY_S = 1.0      # a stand-in sync per forged message and second (the DBC's sync rate)
COMMAND_CYCLE_MS = 50   # ER_Command has no cycle: the insider repeats it at the status rate
FORGED_PRICE_FACTOR = 3.0


@dataclass
class Forgery:
    """One message the insider forges: the frame's signal values, the key that signs it
    (``key_name``: which one, as a person would say it), and whether it is the key that
    really signs the message (``genuine``: then the frame follows its sender's
    freshness)."""

    name: str
    raw: Mapping[str, int]
    key_name: str
    genuine: bool
    cycle_ms: int
    tx: FleetSender
    signed: bool = False  # ER_Price on a signed-price fleet: refused unless the signed one
    target: int | None = None  # ER_Command: the agent it commands
    held: bool = False  # a router's sync of its next boot: held and dropped (AUTH-35)

    @property
    def title(self) -> str:
        """The message, and an ER_Command's target."""
        return self.name if self.target is None else f"{self.name} to agent {self.target}"

    @property
    def residual(self) -> bool:
        """Forgeable: the genuine key, and nothing else the receivers check."""
        return self.genuine and not self.signed and not self.held
    sent: int = 0
    held_back: int = 0   # genuine-key frames not sent yet: the sender not heard yet


@dataclass
class InsiderPlan:
    """The insider's forgeries and its listener (the genuine sender's frames it verifies
    to follow their freshness)."""

    node: str
    forgeries: list[Forgery]
    listener: NodeIO | None
    codec: FrameCodec
    ts: float


def _no_persist(_boot: int) -> None:
    """The insider never writes the stolen file back."""


def stolen_keyring(key: NodeKey) -> Keyring:
    """The keyring of a stolen key file, its boots never persisted (a copy, not the
    node)."""
    return Keyring(key.node, key.key, key.boot_counter, _no_persist, peers=key.peers,
                   fleet=key.fleet_id, floors=key.floors, frames=key.frames,
                   commands=key.commands, price_verify=key.price_verify, tags=key.tags)


def _payloads(sc: Scenario, codec: FrameCodec, node: str) -> list[tuple[str, dict[str, int],
                                                                      int | None]]:
    """(message, raw values, command target) of every harmful frame of another node."""
    forged_rho = fx.to_fixed(min(FORGED_PRICE_FACTOR * sc.prices[0].rho, sc.rho_max))
    out: list[tuple[str, dict[str, int], int | None]] = []
    if node != "router":
        out.append(("ER_Price", {"PriceValid": 1, "Segment": 0, "Rho": forged_rho}, None))
    for j in range(1, sc.n + 1):
        agent = f"agent_{j}"
        if node != "router" and agent != node:
            out.append((contract.COMMAND, {"Command": int(Command.ISOLATE),
                                           "Target": target_raw(j), "GainK": 0, "GainH": 0}, j))
        if agent != node:
            out += [(mc_name(j), {"State": int(State.RUNNING), "Resets": 0,
                                  "Lambda": forged_rho}, None),
                    (setpoint_name(j), {"Enable": 1, "PowerSetpoint":
                                        codec.raw_range(setpoint_name(j), "PowerSetpoint")[1]},
                     None),
                    (diag_name(j), {"Page": 6, "PriceTimeouts": 200, "StatusTimeouts": 0},
                     None)]
        if node != "plant":
            out.append((status_name(j), {"Soc": 100, "Power": 0, "PowerLimited": 0,
                                         "FaultSoc": 0, "FaultVoltage": 0,
                                         "FaultOverCurrent": 1}, None))
    if node not in ("plant", "router"):  # the ledger's input: no battery power, no cost
        out.append((contract.TOTALS, {"BatteryPower": 0, "BatteryCostRate": 0}, None))
    return out


def _stand_in(ring: Keyring, name: str, target: int | None) -> tuple[bytes, str]:
    """The nearest key the file holds for ``name``, and what it is."""
    node = ring.node
    if name == contract.COMMAND:
        own = ring.command_key(node, derive=False) if node.startswith("agent_") else None
        if own is not None:
            return own, f"its own command key ({node})"
    base = name.removesuffix("_Sync")
    if base in contract.KEYED_FRAMES and node.startswith("agent_"):
        i = int(node.removeprefix("agent_"))
        same_kind = {"Setpoint": setpoint_name, "Status": status_name,
                     "Diag": diag_name}.get(base.rsplit("_", 1)[-1])
        own_name = same_kind(i) if same_kind is not None else None
        own = ring.key_for(own_name, derive=False) if own_name is not None else None
        if own is not None:
            return own, f"{own_name}'s key"
    return ring.key, f"its own node key ({node})"


def plan(sc: Scenario, key: NodeKey, codec: FrameCodec,
         tag_receivers: Mapping[int, list[str]]) -> InsiderPlan:
    """What ``key``'s file forges in scenario ``sc`` on ``codec``'s bus (``tag_receivers``:
    on a tagged CAN FD bus, each agent's λ receivers in slot order)."""
    ring = stolen_keyring(key)
    forgeries: list[Forgery] = []
    followed: list[int] = []
    for name, raw, target in _payloads(sc, codec, ring.node):
        fid = codec.frame_id(name)
        if not contract.receivers_of(fid) - {ring.node} and fid not in contract.REPORT_IDS:
            continue  # its one receiver is the insider's node (the plant's setpoints)
        tagged = bool(codec.tag_slots(name))
        genuine_key = None if tagged else ring.key_for(name, derive=False, target=target)
        # FleetSender's name for the key (AUTH-28..30): a command's target, a link frame
        # or report, a broadcast's sender
        label = (contract.command_key_name(target) if target is not None
                 else name if name in contract.KEYED_FRAMES else contract.sender_of(name))
        if genuine_key is not None:
            keys = {label: genuine_key}
            what = ("the genuine " + (f"{name} key" if name in contract.KEYED_FRAMES else
                                      f"command key of agent {target}" if target is not None
                                      else f"node key of {contract.sender_of(name)}"))
            followed.append(fid)
        elif tagged:
            sender = contract.sender_of(name)
            j = int(sender.removeprefix("agent_"))
            # the pair key (sender, itself) it holds tags only its own slot: lying to
            # itself is not an attack, so every tag is under its own node key
            keys = {pair_label(sender, r): ring.key for r in tag_receivers[j]}
            what = "its own node key for every receiver's tag"
        else:
            stand_in, what = _stand_in(ring, name, target)
            keys = {label: stand_in}
            if target is not None:  # ER_Command_Sync: the router's node key, if held
                keys["router"] = ring.key_of("router", derive=False) or ring.key
        cycle = contract.cycle_ms(name) if contract.is_cyclic(name) else COMMAND_CYCLE_MS
        tx = FleetSender(codec, keys=keys, boot=key.boot_counter + 2,
                         tag_receivers=tag_receivers)
        forgeries.append(Forgery(name, raw, what, genuine_key is not None, cycle, tx,
                                 signed=name == "ER_Price" and sc.signed_price,
                                 target=target))
    router_key = ring.key_of("router", derive=False) if ring.node != "router" else None
    if router_key is not None:  # the router's syncs of its next boot (AUTH-35: held)
        followed.append(codec.frame_id("ER_Price"))  # whose boot the listener follows
        for base in ("ER_Price", contract.COMMAND):
            forgeries.append(Forgery(
                f"{base}_Sync", {}, "the genuine node key of router", True,
                round(1000 * SYNC_EVERY_S), FleetSender(codec, keys={"router": router_key}),
                held=True))
    listener = None
    if followed:
        listener = NodeIO(codec, ring.node, [_any_own(ring.node)],
                          sorted(set(followed)), fleet_size=sc.n, keys=ring,
                          untrusted_after=10**9, join_s=0)
    return InsiderPlan(ring.node, forgeries, listener, codec, sc.ts)


def _any_own(node: str) -> str:
    """One untagged message ``node`` sends (a NodeIO needs its sender)."""
    if node == "router":
        return "ER_Price"
    if node == "plant":
        return status_name(1)
    return diag_name(int(node.removeprefix("agent_")))


def _ticks(ms: float) -> int:
    """A DBC cycle in ticks: the cycles stretch with Ts in a time-scaled run."""
    return max(1, round(ms / 1000.0 / contract.MC_CYCLE_S))


def describe(p: InsiderPlan) -> list[str]:
    """The plan, one line per message."""
    lines = [f"insider with {p.node}'s key file: {len(p.forgeries)} forgeries"]
    for f in p.forgeries:
        fate = ("FORGEABLE (the residual risk: receivers take it)" if f.residual else
                "held, dropped at the router's next sync (sync_jump)" if f.held else
                "refused unless it is the signed price (unsigned_price)" if f.genuine
                else "refused (auth)")
        lines.append(f"  {f.title:<24} every {f.cycle_ms:>3} ms under {f.key_name}: {fate}")
    return lines


def without_residual(p: InsiderPlan) -> InsiderPlan:
    """The plan without the forgeries receivers take (``residual``): what a test of
    "everything else is refused" sends (`inject insider --skip-residual`)."""
    p.forgeries = [f for f in p.forgeries if not f.residual]
    return p


def step(p: InsiderPlan, k: int) -> list[can.Message]:
    """The insider's frames at tick ``k``."""
    out: list[can.Message] = []
    for f in p.forgeries:
        every = _ticks(f.cycle_ms)
        if f.held:
            if k % every == 0 and (sync := _next_boot_sync(p, f)) is not None:
                out.append(sync)
                f.sent += 1
            continue
        if f.genuine:
            fid = p.codec.frame_id(f.name)
            fv = p.listener.last_freshness(fid) if p.listener is not None else None
            if fv is None:
                f.held_back += k % every == 0
                continue
            boot, count = contract.FRESHNESS.split(fv)
            f.tx.follow(f.name, boot, count)
        elif k % _ticks(1000 * SYNC_EVERY_S) == 0:
            out.append(f.tx.sync(f.name))
        if k % every == 0:
            out.append(f.tx.frame(f.name, f.raw))  # the codec's format (FD on an FD bus)
            f.sent += 1
    return out


def _next_boot_sync(p: InsiderPlan, f: Forgery) -> can.Message | None:
    """The router's sync ``f`` of its next boot, count 0 (what it sends at a restart);
    None (counted ``held_back``) until the listener has heard its price."""
    fv = (p.listener.last_freshness(p.codec.frame_id("ER_Price"))
          if p.listener is not None else None)
    if fv is None:
        f.held_back += 1
        return None
    base = f.name.removesuffix("_Sync")
    f.tx.follow(base, contract.FRESHNESS.split(fv + 1)[0] + 1, -1)
    return f.tx.sync(base)


def hear(p: InsiderPlan, msg: can.Message, t: float) -> None:
    """A frame off the bus: the genuine senders' freshness, for the listener."""
    if p.listener is not None:
        p.listener.receive(msg, t)


def run(bus: can.BusABC, p: InsiderPlan, duration: float, start_s: float = 0.0,
        clock: Callable[[], float] = time.monotonic) -> dict[str, Any]:
    """Forge for ``duration`` s after ``start_s`` s of listening, one tick every Ts:
    the frames of each tick, after hearing everything the bus brought. Returns the
    counts."""
    t0 = clock()
    k = 0
    while (now := clock() - t0) < start_s + duration:
        deadline = t0 + (k + 1) * p.ts
        while (left := deadline - clock()) > 0:
            msg = bus.recv(timeout=left)
            if msg is not None:
                hear(p, msg, clock() - t0)
        if now >= start_s:
            for m in step(p, k):
                bus.send(m, timeout=0.1)
        k += 1
    return {f.title: {"sent": f.sent, "key": f.key_name, "genuine": f.genuine,
                      "residual": f.residual, "held_back": f.held_back}
            for f in p.forgeries}
