"""No frame vcan0 can carry kills a node (issue 19, deliverable 1): raw frames from a
CAN_RAW socket into `bess-ded up`'s path, agent 3 on firmware_c.

A case-1 fleet (8 s, stretched by vcanrun.TIME_SCALE) runs while, from its first
second, a raw socket sends FUZZ_COUNT seeded frames in bursts: extended IDs, remote
frames, error-flag IDs (CAN_ERR_FLAG), CAN FD frames (when vcan0's MTU carries them),
classic frames of random IDs and payloads, and mutated copies of the fleet's own
frames (a bit flipped, the DLC changed, made remote or extended). What the kernel
refuses to put on the bus (DLC > 8; FD frames on a classic vcan0) is counted here and
is not an input. Every node must live to the end with the honest dispatch, every
frame the kernel took must be in the recording, the nodes count the ones their
acceptance filter passes (remote and FD frames on their IDs: `malformed`; error
frames: `error_frame`) and the verdict names the traffic. The udp_multicast twin,
with datagrams that are no frames, is tests/test_transport_fuzz.py.
"""

from __future__ import annotations

import errno
import random
import re
import socket
import struct
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import pytest
from vcanrun import FINAL_TOL, TIME_SCALE, Run, assert_clean_exit, run_on_vcan

from firmware_py.frames import FrameCodec
from sim.cbind.cagent import node_program
from sim.model.scenario import load_case
from sim.run import busrun

pytestmark = pytest.mark.vcan

FUZZ_COUNT = 3000
SEED = 19
BURST, BURST_GAP_S = 20, 0.02      # ~1000 frames/s
REAL_FRAMES = 100
EFF, RTR, ERR = socket.CAN_EFF_FLAG, socket.CAN_RTR_FLAG, socket.CAN_ERR_FLAG
CAN_FRAME = struct.Struct("=IB3x8s")     # struct can_frame (16 bytes)
CANFD_FRAME = struct.Struct("=IBBBB64s")  # struct canfd_frame (72 bytes)
CODEC = FrameCodec()


def _fd_capable(channel: str) -> bool:
    return int(Path(f"/sys/class/net/{channel}/mtu").read_text()) >= CANFD_FRAME.size


def _classic(can_id: int, data: bytes, dlc: int | None = None) -> bytes:
    return CAN_FRAME.pack(can_id, len(data) if dlc is None else dlc, data.ljust(8, b"\0"))


def raw_frames(rng: random.Random, real: list[tuple[int, bytes]], count: int,
               fd: bool) -> list[tuple[str, bytes]]:
    """``count`` (kind, raw frame) pairs. The kinds ending in "!" the kernel refuses."""
    ids = sorted(CODEC.frame_ids())
    out: list[tuple[str, bytes]] = []
    for _ in range(count):
        how = rng.randrange(8)
        if how == 0:
            out.append(("eff", _classic(EFF | rng.randint(0, 0x1FFFFFFF), rng.randbytes(8))))
        elif how == 1:
            out.append(("rtr", _classic(RTR | rng.choice(ids), b"", rng.randint(0, 8))))
        elif how == 2:
            out.append(("err", _classic(ERR | rng.randint(1, 0x3FF), rng.randbytes(8))))
        elif how == 3:
            n = rng.choice([8, 12, 16, 32, 64])
            frame = CANFD_FRAME.pack(rng.choice(ids), n, rng.randint(0, 1), 0, 0,
                                     rng.randbytes(n).ljust(64, b"\0"))
            out.append(("fd" if fd else "fd!", frame))
        elif how == 4:
            out.append(("dlc!", _classic(rng.choice(ids), rng.randbytes(8),
                                         rng.randint(9, 15))))
        elif how == 5:
            out.append(("random", _classic(rng.randint(0, 0x7FF),
                                           rng.randbytes(rng.randint(0, 8)))))
        else:
            fid, data = rng.choice(real)
            b = bytearray(data)
            if how == 6 and b:
                bit = rng.randrange(8 * len(b))
                b[bit // 8] ^= 1 << bit % 8
                out.append(("flipped", _classic(fid, bytes(b))))
            else:
                out.append(("rtr", _classic(RTR | fid, b"", len(b))))
    return out


def _key(m: can.Message) -> tuple[Any, ...]:
    if m.is_error_frame:
        return ("err",)
    if m.is_remote_frame:
        return ("rtr", m.arbitration_id)
    return (m.arbitration_id, m.is_extended_id, m.is_fd, bytes(m.data))


def _raw_key(kind: str, frame: bytes) -> tuple[Any, ...]:
    if kind == "err":
        return ("err",)
    if kind.startswith("fd"):
        can_id, n, _, _, _, data = CANFD_FRAME.unpack(frame)
        return (can_id, False, True, data[:n])
    can_id, n, data = CAN_FRAME.unpack(frame)
    if can_id & RTR:
        return ("rtr", can_id & 0x7FF)
    ext = bool(can_id & EFF)
    return (can_id & (0x1FFFFFFF if ext else 0x7FF), ext, False, data[:n])


def _counters(log: Path) -> Counter[str]:
    lines = [ln for ln in log.read_text(errors="replace").splitlines() if "counters:" in ln]
    assert lines, f"{log.name}: no summary at exit"
    return Counter({k: int(v) for k, v in re.findall(r"(\w+)=(\d+)",
                                                      lines[-1].split("counters:")[1])})


@pytest.fixture(scope="module")
def fuzzed(vcan_channel: str, tmp_path_factory: pytest.TempPathFactory
           ) -> tuple[Run, Counter[str], Counter[tuple[Any, ...]]]:
    ch = vcan_channel
    fd = _fd_capable(ch)
    accepted: Counter[str] = Counter()
    keys: Counter[tuple[Any, ...]] = Counter()

    def fuzz(_specs: list[busrun.NodeSpec], _logdir: Path) -> None:
        with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as sock:
            sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FD_FRAMES, 1)
            sock.bind((ch,))
            sock.settimeout(0.5)
            real: list[tuple[int, bytes]] = []
            deadline = time.monotonic() + 60.0
            while len(real) < REAL_FRAMES and time.monotonic() < deadline:
                try:
                    raw = sock.recv(CANFD_FRAME.size)
                except TimeoutError:
                    continue
                if len(raw) == CAN_FRAME.size:
                    can_id, n, data = CAN_FRAME.unpack(raw)
                    if not can_id & (EFF | RTR | ERR):
                        real.append((can_id, data[:n]))
            assert real, "no frame of the fleet heard"
            frames = raw_frames(random.Random(SEED), real, FUZZ_COUNT, fd)
            for k in range(0, len(frames), BURST):
                for kind, frame in frames[k:k + BURST]:
                    if _send(sock, frame):
                        accepted[kind] += 1
                        keys[_raw_key(kind, frame)] += 1
                    else:
                        accepted["refused " + kind] += 1
                time.sleep(BURST_GAP_S)

    sc = replace(load_case(1), duration=8.0)
    run = run_on_vcan(sc, tmp_path_factory.mktemp("fuzz"), ch, c_agents=frozenset({3}),
                      c_node=node_program(), actions=[(1.0 * TIME_SCALE, fuzz)])
    print(f"vcan fuzz: {dict(accepted)}")
    return run, accepted, keys


def _send(sock: socket.socket, frame: bytes) -> bool:
    """True if the kernel took the frame; False if it refused it (EINVAL: not a frame
    this interface carries). A full queue is waited out."""
    for _ in range(1000):
        try:
            sock.send(frame)
            return True
        except OSError as e:
            if e.errno == errno.EINVAL:
                return False
            if e.errno != errno.ENOBUFS:
                raise
            time.sleep(0.001)
    raise AssertionError("vcan0 stayed full for 1 s")


def test_every_node_lives_and_the_dispatch_holds(
        fuzzed: tuple[Run, Counter[str], Counter[tuple[Any, ...]]]) -> None:
    run, accepted, _ = fuzzed
    assert sum(v for k, v in accepted.items() if not k.startswith("refused")) > 1000
    assert not accepted["dlc!"] and not accepted["fd!"]   # the kernel refuses those
    assert_clean_exit(run)
    assert "node_died" not in {a["kind"] for a in run.m["anomalies"]}
    assert run.m["final_error"] < FINAL_TOL, run.m["anomalies"]
    assert run.m["verdict"]["converged"], run.m["verdict"]["reasons"]


def test_every_frame_is_recorded_and_counted(
        fuzzed: tuple[Run, Counter[str], Counter[tuple[Any, ...]]]) -> None:
    run, accepted, keys = fuzzed
    logged = Counter(_key(m) for m in can.LogReader(str(run.out / "run.log")))
    missing = {k: n - logged[k] for k, n in keys.items() if logged[k] < n}
    assert not missing, list(missing.items())[:5]
    counters = {role: Counter(run.m["node_counters"][role]["counters"])
                for role in ("plant", "router")}
    counters.update({f"agent_{i}": _counters(run.out / "logs" / f"agent_{i}.log")
                     for i in range(1, 5)})
    print(f"vcan fuzz counters: { {n: dict(c) for n, c in counters.items()} }")
    for node, c in counters.items():
        # remote (and FD) frames on the IDs its filter passes; error frames always pass
        assert c["malformed"] > 0, (node, c)
        if accepted["err"]:
            assert 0 < c["error_frame"] <= accepted["err"], (node, c)
        assert c["not_a_frame"] == c["invalid_frame"] == 0, (node, c)  # a kernel frame


def test_the_verdict_names_the_traffic(
        fuzzed: tuple[Run, Counter[str], Counter[tuple[Any, ...]]]) -> None:
    run, accepted, _ = fuzzed
    named = {(a["kind"], a["node"]) for a in run.m["anomalies"]}
    assert ("malformed_frames", "bus") in named, run.m["anomalies"]
    assert ("rejected_frames", "plant") in named, run.m["anomalies"]
    if accepted["err"]:
        assert ("bus_errors", "plant") in named, run.m["anomalies"]
    assert run.m["verdict"]["exit_code"] == 3
