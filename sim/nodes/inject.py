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
from dataclasses import dataclass
from typing import Any

import can
import msgpack

from firmware_py import fixedpoint as fx
from firmware_py.contract import COUNTER_MODULO, Command, State
from firmware_py.frames import PIN_ON, FrameCodec, mc_name

KINDS = {
    "forge": "ER_Price frames at ρ = 5, a guessed MAC         → every agent: auth",
    "corrupt": "ER_Price frames with ρ's top byte flipped        → every agent: auth",
    "dlc": "ER_Price frames with DLC 5                        → every agent: dlc",
    "range": "ER_Command PIN frames with GainK 3 (neither way)  → every agent: range",
    "unknown": "frames on IDs the DBC does not define            → every agent: unknown_id",
    "impersonate": "AGENT_<target>_MC frames not sent by it        → the target: impersonation",
    "flood": "random IDs, DLCs and payloads                     → no crash, all counted",
    "insider": "every other node's frames under --key-file's keys → auth, unsigned_price",
}


def frames(kind: str, count: int, target: int = 1, seed: int = 0,
           codec: FrameCodec | None = None) -> Iterator[can.Message]:
    """``count`` crafted frames of ``kind`` (KINDS), seeded: what `bess-ded inject`
    sends (``target``: the agent an impersonation claims to be)."""
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
            # every 6-bit Target is an agent (1..64), so the out-of-range value is a PIN's
            # GainK: only 1 (pin) and 2 (unpin) are in range (CMD-7)
            m = codec.encode("ER_Command", {"Command": int(Command.PIN), "Target": 0,
                                            "GainK": PIN_ON, "GainH": 0}, ctr)
            gk = codec.database.get_message_by_name("ER_Command").get_signal_by_name("GainK")
            start, length = gk.start, gk.length
            x = int.from_bytes(m.data, "little") & ~(((1 << length) - 1) << start) | 3 << start
            m.data[:] = x.to_bytes(8, "little")
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
        if codec.fd and not m.is_fd:  # the flood's own frames in the bus's format (GEN-1):
            m.is_fd = m.bitrate_switch = True  # else each would be only malformed
        yield m


def send(bus: can.BusABC, kind: str, count: int, target: int = 1, rate: float = 1000.0,
         seed: int = 0, codec: FrameCodec | None = None) -> int:
    """Send ``count`` frames of ``kind`` at about ``rate`` frames/s (in ``codec``'s frame
    format: classic, or FD with the FD DBC's codec); returns frames sent."""
    sent = 0
    period = 1.0 / rate if rate > 0 else 0.0
    next_t = time.monotonic()
    for m in frames(kind, count, target, seed, codec):
        bus.send(m, timeout=0.1)
        sent += 1
        next_t += period
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    return sent


# --------------------------------------------------------------------------- transport fuzz

FUZZ_SHARES = (("bytes", 0.30), ("fields", 0.25), ("exotic", 0.15), ("mutated", 0.30))


@dataclass(frozen=True)
class FuzzInput:
    """One fuzz input for udp_multicast: the datagram, and what every receiver must make
    of it: ``not_a_frame`` or ``invalid_frame`` (dropped and counted under that cause by
    firmware_py.node.GuardedBus), or ``frame``: a CAN frame (``msg``), which the nodes
    reject by its own cause (unknown_id, malformed, error_frame, dlc, range, auth, ...)."""

    label: str
    datagram: bytes
    msg: can.Message | None = None


def _fields(rng: random.Random) -> dict[str, Any]:
    """A python-can message's fields of which one is impossible (Message's check, or a
    wrong type): the receiver's python-can raises, or its GuardedBus refuses it."""
    f: dict[str, Any] = {"timestamp": 0.0, "arbitration_id": rng.randint(0, 0x7FF),
                         "is_extended_id": False, "is_remote_frame": False,
                         "is_error_frame": False, "channel": None, "dlc": 8,
                         "data": rng.randbytes(8), "is_fd": False, "bitrate_switch": False,
                         "error_state_indicator": False}
    how = rng.randrange(12)
    if how == 0:    # a standard frame's ID beyond 11 bits (the 0x800)
        f["arbitration_id"] = rng.randint(0x800, 0x1FFFFFFF)
    elif how == 1:  # an extended ID beyond 29 bits
        f.update(is_extended_id=True, arbitration_id=rng.randint(1 << 29, (1 << 32) - 1))
    elif how == 2:
        f["arbitration_id"] = -rng.randint(1, 1 << 20)
    elif how == 3:  # DLC > 8 on a classic frame
        n = rng.randint(9, 64)
        f.update(dlc=n, data=rng.randbytes(n))
    elif how == 4:  # data longer than its DLC
        f["dlc"] = rng.randint(0, 7)
    elif how == 5:  # a CAN FD remote frame
        f.update(is_remote_frame=True, is_fd=True, data=b"", dlc=0)
    elif how == 6:  # bit-rate switch on a classic frame
        f["bitrate_switch"] = True
    elif how == 7:  # a float ID: passes python-can's check, refused by GuardedBus
        f["arbitration_id"] = rng.randint(0, 0x7FF) + 0.5
    elif how == 8:
        f["arbitration_id"] = f"{rng.randint(0, 0x7FF):x}"
    elif how == 9:  # a flag of the wrong type
        f["is_extended_id"] = rng.choice(["no", 2, [0]])
    elif how == 10:  # data bytes out of range
        f["data"] = [rng.randint(256, 1000)] * 8
    else:  # a negative DLC
        f["dlc"] = -rng.randint(1, 8)
    return f


def _exotic(rng: random.Random, codec: FrameCodec) -> can.Message:
    """A CAN frame a classic 11-bit node must reject: extended ID, remote, FD, error
    frame, or a classic frame on an ID the DBC does not define."""
    how = rng.randrange(5)
    if how == 0:
        return can.Message(arbitration_id=rng.randint(0, 0x1FFFFFFF), is_extended_id=True,
                           data=rng.randbytes(rng.randint(0, 8)))
    if how == 1:
        return can.Message(arbitration_id=rng.choice(sorted(codec.frame_ids())),
                           is_extended_id=False, is_remote_frame=True, dlc=rng.randint(0, 8))
    if how == 2:
        n = rng.choice([0, 8, 12, 16, 20, 24, 32, 48, 64])
        return can.Message(arbitration_id=rng.choice(sorted(codec.frame_ids())),
                           is_extended_id=False, is_fd=True, bitrate_switch=rng.random() < 0.5,
                           data=rng.randbytes(n))
    if how == 3:
        # python-can's error frame: the error class in the ID (socketcan strips the flag)
        return can.Message(arbitration_id=rng.randint(1, 0x3FF), is_error_frame=True,
                           data=rng.randbytes(8))
    known = codec.frame_ids()
    fid = rng.randint(0, 0x7FF)
    while fid in known:
        fid = rng.randint(0, 0x7FF)
    return can.Message(arbitration_id=fid, is_extended_id=False,
                       data=rng.randbytes(rng.randint(0, 8)))


def mutate(rng: random.Random, real: can.Message) -> can.Message:
    """A copy of a real frame changed in one way, never left equal to it: one data bit
    flipped (a bad MAC), its length changed (bad DLC), or made extended, remote or
    FD."""
    data = bytearray(real.data)
    how = rng.randrange(6)
    fid = real.arbitration_id
    if how <= 2 and data:
        bit = rng.randrange(8 * len(data))
        data[bit // 8] ^= 1 << bit % 8
        return can.Message(arbitration_id=fid, is_extended_id=False, data=data)
    if how == 3:
        n = rng.choice([k for k in range(9) if k != len(data)])
        data = (data + rng.randbytes(8))[:n]
        return can.Message(arbitration_id=fid, is_extended_id=False, data=data)
    if how == 4:
        return can.Message(arbitration_id=fid, is_extended_id=True, data=data)
    if how == 5 and rng.random() < 0.5:
        return can.Message(arbitration_id=fid, is_extended_id=False, is_remote_frame=True,
                           dlc=len(data))
    return can.Message(arbitration_id=fid, is_extended_id=False, is_fd=True, data=data)


def fuzz_inputs(count: int, seed: int, real: list[can.Message],
                codec: FrameCodec | None = None) -> list[FuzzInput]:
    """``count`` seeded fuzz inputs for a udp_multicast bus, in FUZZ_SHARES (shuffled):
    random bytes, python-can messages with an impossible field, exotic CAN frames, and
    mutated copies of ``real`` frames (recorded from the fleet)."""
    from can.interfaces.udp_multicast.utils import pack_message

    codec = codec or FrameCodec()
    rng = random.Random(seed)
    out: list[FuzzInput] = []
    for kind, share in FUZZ_SHARES:
        for _ in range(round(share * count)):
            if kind == "bytes":  # ≥ 2 bytes: no lone msgpack value that could be a message
                out.append(FuzzInput("not_a_frame", rng.randbytes(rng.randint(2, 96))))
            elif kind == "fields":
                out.append(FuzzInput("invalid_frame", msgpack.packb(_fields(rng),
                                                                    use_bin_type=True)))
            else:
                m = _exotic(rng, codec) if kind == "exotic" else mutate(rng, rng.choice(real))
                out.append(FuzzInput("frame", pack_message(m), m))
    rng.shuffle(out)
    return out
