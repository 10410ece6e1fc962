"""Crafted bad traffic for fault-injection tests: `bess-ded inject KIND ...`.

Each kind sends frames that a correct agent must reject and count under one
cause (see AgentRuntime.counters). Frames are built with the codec from the public
DBC, as an attacker without keys would, and broken in exactly one way, so each test
checks one path. Without the sender's key no forged frame can carry a valid MAC, so
every well-formed forgery ends as ``auth``.
"""

from __future__ import annotations

import random
import time
from collections.abc import Iterator

import can

from firmware_py import fixedpoint as fx
from firmware_py.contract import COUNTER_MODULO, State
from firmware_py.frames import FrameCodec, mc_name

KINDS = {
    "forge": "ER_Price frames at ρ = 5, a guessed MAC         → every agent: auth",
    "corrupt": "ER_Price frames with ρ's top byte flipped        → every agent: auth",
    "dlc": "ER_Price frames with DLC 5                        → every agent: dlc",
    "range": "ER_Command frames with Target 40 (no such agent) → every agent: range",
    "unknown": "frames on IDs the DBC does not define            → every agent: unknown_id",
    "impersonate": "AGENT_<target>_MC frames not sent by it        → the target: impersonation",
    "flood": "random IDs, DLCs and payloads                     → no crash, all counted",
}


def frames(kind: str, count: int, target: int = 1, seed: int = 0,
           codec: FrameCodec | None = None) -> Iterator[can.Message]:
    codec = codec or FrameCodec()
    rng = random.Random(seed)
    rho = fx.to_fixed(0.8)
    for n in range(count):
        ctr = (n + 7) % COUNTER_MODULO
        if kind == "forge":
            m = codec.encode("ER_Price", {"PriceValid": 1, "Rho": fx.to_fixed(5.0),
                                          "Segment": 0}, ctr)
            m.data[0:3] = rng.randbytes(3)
        elif kind == "corrupt":
            m = codec.encode("ER_Price", {"PriceValid": 1, "Rho": rho, "Segment": 0}, ctr)
            m.data[0:3] = rng.randbytes(3)
            m.data[7] ^= 0x5A
        elif kind == "dlc":
            m = codec.encode("ER_Price", {"PriceValid": 1, "Rho": rho, "Segment": 0}, ctr)
            m = can.Message(arbitration_id=m.arbitration_id, is_extended_id=False,
                            data=m.data[:5])
        elif kind == "range":
            m = codec.encode("ER_Command", {"Command": 1, "Target": 1, "GainK": 0,
                                            "GainH": 0}, ctr)
            x = int.from_bytes(m.data, "little") & ~(0x3F << 30) | 40 << 30
            m.data[:] = x.to_bytes(8, "little")  # Target 40: past the DBC's 1..32
        elif kind == "unknown":
            m = can.Message(arbitration_id=rng.choice([0x7FF, 0x555, 0x7A0, 0x001]),
                            is_extended_id=False, data=bytes(8))
        elif kind == "impersonate":
            m = codec.encode(mc_name(target), {"State": int(State.RUNNING), "Lambda": rho,
                                               "Resets": 0}, ctr)
        elif kind == "flood":
            dlc = rng.randint(0, 8)
            m = can.Message(arbitration_id=rng.randint(0, 0x7FF), is_extended_id=False,
                            data=bytes(rng.getrandbits(8) for _ in range(dlc)))
        else:
            raise ValueError(f"kind: expected one of {', '.join(KINDS)}, but got {kind!r}")
        yield m


def send(bus: can.BusABC, kind: str, count: int, target: int = 1, rate: float = 1000.0,
         seed: int = 0) -> int:
    """Send ``count`` frames of ``kind`` at about ``rate`` frames/s; returns frames sent."""
    sent = 0
    period = 1.0 / rate if rate > 0 else 0.0
    next_t = time.monotonic()
    for m in frames(kind, count, target, seed):
        bus.send(m, timeout=0.1)
        sent += 1
        next_t += period
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    return sent
