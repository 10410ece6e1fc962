"""firmware_c's node program on python-can's udp_multicast bus (src/linux_udp_multicast.c,
src/udp_msgpack.c).

* The datagram: the C writer's bytes are python-can's ``pack_message`` byte for byte
  (classic and FD frames, every ID width), and the C reader takes python-can's datagrams
  to the same frame; whatever the bytes (truncated, retyped, oversized, mutated, random:
  a fuzz loop with a fixed seed), the reader never takes what python-can would refuse,
  and what it takes is python-can's frame field for field (through libbessded.so).
* A running agent on a private group and port fed hostile datagrams: it stays alive,
  counts them (not_a_frame, invalid_frame, as firmware_py on udp_multicast), still reads
  the frames after them, tells its own echo from impersonation, and reports them in its
  exit summary.
* Realtime tier: `bess-ded up --case 1` with every agent in C, and a mixed fleet
  (``--c-agents 2,4``), on a private port at time scale 2: they converge.
"""

from __future__ import annotations

import json
import os
import random
import re
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can
import msgpack
import pytest
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

from dbc import FD_DBC_PATH
from firmware_py.config import agent_configs_from_scenario
from firmware_py.node import frame_fault
from sim.cbind.cagent import UDP_DATAGRAM_MAX, built, node_program, udp_datagram, udp_frame
from sim.model.scenario import load_case

SEED = 20261127
FD_LENGTHS = (*range(9), 12, 16, 20, 24, 32, 48, 64)


def python_can_reads(datagram: bytes) -> can.Message | None:
    """What a firmware_py node on udp_multicast takes from ``datagram``: python-can's
    unpack (check=True, the timestamp replaced by its receive time) then
    firmware_py.node.frame_fault; None if either refuses it."""
    try:
        msg = unpack_message(datagram, replace={"timestamp": 0.0}, check=True)
    except Exception:
        return None
    return None if frame_fault(msg) else msg


def fields(msg: can.Message) -> tuple[Any, ...]:
    return (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame,
            msg.is_fd, msg.bitrate_switch, msg.dlc, bytes(msg.data))


def message(fid: int, data: bytes, fd: bool = False, extended: bool = False) -> can.Message:
    return can.Message(arbitration_id=fid, is_extended_id=extended, data=data, is_fd=fd,
                       bitrate_switch=fd, check=True)


# --------------------------------------------------------------------------- the codec


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_c_writes_python_cans_datagram_byte_for_byte(fd: bool) -> None:
    """Every ID width (fixint, uint8, uint16, uint32 as msgpack packs them), every length
    a node sends (0..8), standard and extended IDs, the timestamp as given (the node
    sends 0.0, as firmware_py's frames carry)."""
    rng = random.Random(SEED)
    for fid in (0, 0x7F, 0x80, 0xFF, 0x100, 0x7FF):
        for n in range(9):
            msg = message(fid, rng.randbytes(n), fd)
            assert udp_datagram(msg) == pack_message(msg), (fid, n)
    for fid in (0x800, 0xFFFF, 0x10000, 0x1FFFFFFF):
        msg = message(fid, rng.randbytes(8), fd, extended=True)
        assert udp_datagram(msg) == pack_message(msg)
    msg = message(0x123, bytes(8), fd)
    msg.timestamp = 1795815003.689101
    assert udp_datagram(msg, msg.timestamp) == pack_message(msg)


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_c_reads_python_cans_datagram_as_python_can_does(fd: bool) -> None:
    """Every length of the format (FD: up to 64 bytes), both ID widths, python-can's
    own timestamps and a channel name; and the C node's own datagram back to its frame."""
    rng = random.Random(SEED + 1)
    for n in FD_LENGTHS if fd else range(9):
        for fid, ext in ((0, False), (0x7FF, False), (0x1ABCDEF, True), (0x1FFFFFFF, True)):
            msg = message(fid, rng.randbytes(n), fd, ext)
            msg.timestamp, msg.channel = rng.uniform(0, 2e9), rng.choice([None, "vcan0", 3])
            verdict, got = udp_frame(pack_message(msg))
            assert verdict == "frame" and got is not None
            assert fields(got) == fields(msg), n
            if n <= 8:
                assert fields(udp_frame(udp_datagram(msg))[1]) == fields(msg)


def _packed(**change: Any) -> bytes:
    """python-can's map of a classic frame with entries changed (a value of None under
    the key "-drop" deletes those keys)."""
    d: dict[Any, Any] = {"timestamp": 0.0, "arbitration_id": 0x101, "is_extended_id": False,
                         "is_remote_frame": False, "is_error_frame": False, "channel": None,
                         "dlc": 8, "data": bytes(range(8)), "is_fd": False,
                         "bitrate_switch": False, "error_state_indicator": False}
    for k in change.pop("_drop", ()):
        del d[k]
    d.update(change)
    return msgpack.packb(d, use_bin_type=True)


GOOD = _packed()
BIN32 = b"\xc6"


def hostile() -> list[tuple[str, bytes]]:
    """Named datagrams no node may take (each refused by python-can as well, or by the
    C reader's stricter rules: every key present once, a real FD length)."""
    key_pos = GOOD.index(b"\xa4data")
    cases = [
        ("empty", b""),
        ("nil", b"\xc0"),
        ("an int", b"\x05"),
        ("an array", msgpack.packb([1, 2, 3])),
        ("trailing byte", GOOD + b"\x00"),
        ("two maps", GOOD + GOOD),
        ("never-used tag", GOOD[:-1] + b"\xc1"),
        ("oversized", GOOD + bytes(UDP_DATAGRAM_MAX)),
        ("huge bin32", GOOD[:key_pos + 5] + BIN32 + struct.pack(">I", 0xFFFFFFFF) + b"\0" * 8),
        ("huge map32", b"\xdf" + struct.pack(">I", 0xFFFFFFFF) + GOOD[1:]),
        ("huge array32 channel", _packed(channel=None).replace(
            b"\xa7channel\xc0", b"\xa7channel\xdd" + struct.pack(">I", 0xFFFFFFFF))),
        ("huge str32 key", b"\x8b\xdb" + struct.pack(">I", 0x7FFFFFFF) + b"timestamp"),
        ("deep nesting", _packed(channel=None).replace(b"\xa7channel\xc0",
                                                       b"\xa7channel" + b"\x91" * 60 + b"\xc0")),
        ("unknown key", _packed(colour="red")),
        ("missing key", _packed(_drop=("dlc",))),
        ("int key", msgpack.packb({1: 2})),
        ("duplicate key", b"\x8c" + GOOD[1:] + b"\xa3dlc\x08"),
        ("float id", _packed(arbitration_id=1.5)),
        ("str id", _packed(arbitration_id="0x101")),
        ("negative id", _packed(arbitration_id=-1)),
        ("12-bit id", _packed(arbitration_id=0x800)),
        ("30-bit id", _packed(arbitration_id=0x20000000, is_extended_id=True)),
        ("str flag", _packed(is_fd="no")),
        ("int flag", _packed(is_extended_id=0)),
        ("nil flag", _packed(is_remote_frame=None)),
        ("str data", _packed(data="abcdefgh")),
        ("list data", _packed(data=list(range(8)))),
        ("float dlc", _packed(dlc=8.0)),
        ("negative dlc", _packed(dlc=-1)),
        ("dlc above data", _packed(dlc=8, data=bytes(7))),
        ("dlc below data", _packed(dlc=7)),
        ("9 bytes classic", _packed(dlc=9, data=bytes(9))),
        ("65 bytes FD", _packed(dlc=65, data=bytes(65), is_fd=True)),
        ("FD length 9", _packed(dlc=9, data=bytes(9), is_fd=True)),
        ("FD length 33", _packed(dlc=33, data=bytes(33), is_fd=True)),
        ("BRS on classic", _packed(bitrate_switch=True)),
        ("ESI on classic", _packed(error_state_indicator=True)),
        ("remote FD", _packed(is_remote_frame=True, is_fd=True, data=b"", dlc=0)),
        ("remote error", _packed(is_remote_frame=True, is_error_frame=True, data=b"", dlc=0)),
        ("list channel", _packed(channel=[1])),
        ("str timestamp", _packed(timestamp="now")),
    ]
    cases += [(f"truncated to {n}", GOOD[:n]) for n in range(len(GOOD))]
    return cases


def test_c_reader_refuses_every_hostile_datagram() -> None:
    for name, datagram in hostile():
        verdict, msg = udp_frame(datagram)
        assert verdict in ("not_a_frame", "invalid_frame") and msg is None, name
    # structure before values, as msgpack.unpackb before can.Message
    assert udp_frame(GOOD[:-1])[0] == udp_frame(b"\x05")[0] == "not_a_frame"
    assert udp_frame(_packed(arbitration_id=1.5))[0] == "invalid_frame"
    assert udp_frame(_packed(dlc=9, data=bytes(9), is_fd=True))[0] == "invalid_frame"
    assert udp_frame(_packed(colour="red"))[0] == "not_a_frame"


def test_c_reader_takes_nothing_python_can_refuses_on_fuzzed_datagrams() -> None:
    """A fixed-seed fuzz loop: random bytes, byte flips, insertions and deletions in
    python-can's datagrams (classic and FD, remote and error frames). The C reader never
    fails, never reads past the datagram (its bytes are copied to a buffer of exactly
    their length), takes only what python-can takes, and takes it as python-can does."""
    rng = random.Random(SEED + 2)
    seeds = [GOOD, pack_message(message(0x7FF, bytes(range(64)), fd=True)),
             pack_message(can.Message(arbitration_id=0x12, is_extended_id=False,
                                      is_remote_frame=True, dlc=4)),
             pack_message(can.Message(arbitration_id=0x20, is_error_frame=True))]
    taken = refused = 0
    for k in range(6000):
        if k % 4 == 0:
            datagram = rng.randbytes(rng.randrange(0, 300))
        else:
            b = bytearray(rng.choice(seeds))
            for _ in range(rng.randrange(1, 4)):
                op, at = rng.randrange(3), rng.randrange(len(b) + 1)
                if op == 0 and at < len(b):
                    b[at] = rng.randrange(256)
                elif op == 1:
                    b[at:at] = rng.randbytes(rng.randrange(1, 5))
                else:
                    del b[at:at + rng.randrange(1, 5)]
            datagram = bytes(b)
        verdict, msg = udp_frame(bytes(datagram))
        theirs = python_can_reads(datagram)
        if verdict == "frame":
            assert msg is not None and theirs is not None, datagram.hex()
            assert fields(msg) == fields(theirs), datagram.hex()
            taken += 1
        else:
            assert verdict in ("not_a_frame", "invalid_frame"), verdict
            refused += 1
    assert taken > 50 and refused > 3000, (taken, refused)


def test_c_reader_under_address_sanitizer_fuzz_loop() -> None:
    """firmware_c/tools/udp_fuzz.c (`make udp-fuzz`: AddressSanitizer and UBSan): half a
    million random and mutated datagrams, each in a heap buffer of exactly its length;
    a read past one, or any undefined behaviour, aborts it."""
    res = subprocess.run([str(built("udp_fuzz")), "500000", str(SEED)], capture_output=True,
                         text=True, timeout=600, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    counts = dict(zip(res.stdout.split()[::2], map(int, res.stdout.split()[1::2]),
                      strict=True))
    assert sum(counts.values()) == 500000 and counts["frame"] > 0, counts
    assert counts["not_a_frame"] > 0 and counts["invalid_frame"] > 0, counts


# --------------------------------------------------------------------------- a running agent


GROUP4 = "239.74.163.2"   # python-can's IPv4 default group (its IPv6 one is `up`'s default)
LOAD_TOLERANT_S = 120.0   # waiting for a process: a deadline, not a duration
SUMMARY = re.compile(r"agent (\d+) \(C\): state=(\w+) .* counters: (.*)$", re.M)


def summary_counters(log: str) -> dict[str, int]:
    m = SUMMARY.search(log)
    assert m, log[-2000:]
    return {} if m.group(3) == "none" else {
        k: int(v) for k, v in (item.split("=") for item in m.group(3).split(", "))}


class Agent1:
    """Case 1's agent 1 as the C node program on a private udp_multicast group and port,
    beside a python-can ``bus`` there; on exit, the bus shut and the agent stopped
    (SIGTERM), its exit code and its output in ``returncode`` and ``log``."""

    def __init__(self, tmp_path: Path, group: str, port: int, *flags: str) -> None:
        cfg = next(c for c in agent_configs_from_scenario(load_case(1)) if c.id == 1)
        self.path = tmp_path / "agent_1.toml"
        self.path.write_text(cfg.to_toml())
        self.argv = [str(node_program()), "--config", str(self.path), "--insecure",
                     "--interface", "udp_multicast", "--channel", group, "--port", str(port),
                     *flags]
        self.group, self.port = group, port
        self.log = ""
        self.returncode: int | None = None

    def __enter__(self) -> Agent1:
        self.bus = can.Bus(interface="udp_multicast", channel=self.group, port=self.port)
        self.proc = subprocess.Popen(self.argv, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT)
        return self

    def heard(self) -> None:
        """Wait until the agent is heard (only it is on this group and port)."""
        deadline = time.monotonic() + LOAD_TOLERANT_S
        while self.bus.recv(0.5) is None:
            assert self.proc.poll() is None and time.monotonic() < deadline, "agent 1 not heard"

    def __exit__(self, *exc: object) -> None:
        self.bus.shutdown()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        out, _ = self.proc.communicate(timeout=LOAD_TOLERANT_S)
        self.log, self.returncode = out.decode(errors="replace"), self.proc.returncode


def test_running_agent_counts_hostile_datagrams_and_reads_on(tmp_path: Path,
                                                            udp_port: int) -> None:
    """Agent 1 of case 1, alone on a private IPv4 group and port. Once it is heard, the
    hostile datagrams (fewer than BD_DRAIN_MAX in all, so its own echo is always read
    before its next sends, at any load), then valid extended frames. At any load: it is
    alive throughout, exits 0 on SIGTERM, and its summary counts the hostile datagrams
    under not_a_frame and invalid_frame (no more than were sent of each: the kernel may
    drop some of a starved reader's), the extended frames after them (unknown_id) and no
    impersonation: its own frames came back as its echo."""
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
    sent = {"not_a_frame": 0, "invalid_frame": 0}
    with Agent1(tmp_path, GROUP4, udp_port) as agent:
        proc, bus = agent.proc, agent.bus
        agent.heard()
        cases = hostile()
        rng = random.Random(SEED + 3)
        cases += [("random", rng.randbytes(rng.randrange(0, 400))) for _ in range(40)]
        assert len(cases) < 256   # BD_DRAIN_MAX
        for k, (_, datagram) in enumerate(cases):
            verdict, _ = udp_frame(datagram)
            assert verdict != "frame"
            sent[verdict] += 1
            tx.sendto(datagram, (GROUP4, udp_port))
            if k % 20 == 19:
                time.sleep(0.02)
                assert proc.poll() is None, "the agent died"
        time.sleep(0.2)
        for _ in range(5):
            bus.send(can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, data=bytes(8)))
            time.sleep(0.05)
        time.sleep(0.3)
        assert proc.poll() is None, "the agent died"
    tx.close()
    assert agent.returncode == 0, agent.log[-2000:]
    counters = summary_counters(agent.log)
    print(f"sent {sent}, agent 1 counted {counters}")
    for cause, n in sent.items():
        assert 1 <= counters.get(cause, 0) <= n, (cause, counters)
    assert counters.get("unknown_id", 0) >= 1, counters
    assert "impersonation" not in counters and "rx_error" not in counters, counters


def test_acceptance_filter_on_udp_multicast_is_asked_for(tmp_path: Path,
                                                        udp_port: int) -> None:
    """--acceptance-filter on udp_multicast: the frames the kernel's filter would drop are
    dropped in user space, uncounted (firmware_py's AcceptanceBus); a datagram that is no
    frame is still counted. (Without it, the default there, the agent counts them:
    test_running_agent_counts_hostile_datagrams_and_reads_on's unknown_id.)"""
    with Agent1(tmp_path, GROUP4, udp_port, "--acceptance-filter") as agent:
        bus = agent.bus
        agent.heard()
        for _ in range(5):
            bus.send(can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, data=bytes(8)))
            bus.send(can.Message(arbitration_id=0x7F3, is_extended_id=False, data=bytes(8)))
            bus._multicast._socket.sendto(b"\xc1", (GROUP4, udp_port))  # not msgpack
            time.sleep(0.05)
        time.sleep(0.3)
    assert agent.returncode == 0, agent.log[-2000:]
    counters = summary_counters(agent.log)
    assert 1 <= counters.get("not_a_frame", 0) <= 5, counters
    assert "unknown_id" not in counters and "impersonation" not in counters, counters


def test_running_agent_on_an_fd_bus_sends_fd_frames(tmp_path: Path, udp_port: int) -> None:
    """--fd on udp_multicast (GEN-1) on the IPv6 group: every frame the agent sends is an
    FD datagram with the bit-rate switch, python-can reads it as such, and a classic
    frame sent to it is counted malformed (RX-2). At any load: the frames heard within
    the deadline are all FD, the classic ones sent are counted (at most as many). Its MC
    and MC sync are 32 bytes (AUTH-34): Mac 0, a tag for each neighbour by index, the
    plant and the router."""
    from can.interfaces.udp_multicast import UdpMulticastBus

    heard: list[can.Message] = []
    with Agent1(tmp_path, UdpMulticastBus.DEFAULT_GROUP_IPv6, udp_port, "--fd") as agent:
        proc, bus = agent.proc, agent.bus
        deadline = time.monotonic() + LOAD_TOLERANT_S
        while len(heard) < 20:
            assert proc.poll() is None and time.monotonic() < deadline, heard
            if (msg := bus.recv(0.5)) is not None:
                heard.append(msg)
        for _ in range(3):
            bus.send(can.Message(arbitration_id=0x7F3, is_extended_id=False, data=bytes(8)))
            time.sleep(0.05)
        time.sleep(0.3)
    assert agent.returncode == 0, agent.log[-2000:]
    assert all(m.is_fd and m.bitrate_switch for m in heard), heard
    tagged = [m for m in heard if m.arbitration_id in (0x101, 0x501)]
    assert tagged and all(m.dlc == 32 and m.data[:3] == bytes(3) for m in tagged), tagged
    assert all(m.dlc == 8 for m in heard if m not in tagged), heard
    cfg = next(c for c in agent_configs_from_scenario(load_case(1)) if c.id == 1)
    want = sorted(n.id for n in cfg.neighbours) + [0xFE, 0xFF]
    assert all(list(m.data[8::4]) == want + [0] * (6 - len(want)) for m in tagged), tagged
    assert 1 <= summary_counters(agent.log).get("malformed", 0) <= 3, agent.log[-2000:]


def test_up_passes_the_bus_to_the_c_agent_or_refuses_it(capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    """The C agent's flags of a bus: python-can's default group and port where none is
    named; a bus it cannot speak (virtual, a hop limit but 1, a setting it does not take)
    is refused by `up` before anything runs (exit 2), naming what it expects."""
    from can.interfaces.udp_multicast import UdpMulticastBus

    from sim.cli import main
    from sim.run.busopts import BusOptions, c_node_bus_argv

    assert c_node_bus_argv(BusOptions("udp_multicast")) == [
        "--interface", "udp_multicast", "--channel", UdpMulticastBus.DEFAULT_GROUP_IPv6,
        "--port", "43113"]
    assert c_node_bus_argv(BusOptions("udp_multicast", GROUP4, '{"port": 43999}')) == [
        "--interface", "udp_multicast", "--channel", GROUP4, "--port", "43999"]
    assert c_node_bus_argv(BusOptions("socketcan", "vcan0")) == ["--channel", "vcan0"]
    assert c_node_bus_argv(BusOptions("virtual")) is None
    assert c_node_bus_argv(BusOptions("udp_multicast", None, '{"hop_limit": 2}')) is None
    for flags in (["--agent-impl", "c", "--interface", "virtual"],
                  ["--c-agents", "2", "--interface", "udp_multicast", "--bus-config",
                   '{"hop_limit": 4}']):
        assert main(["up", "--case", "1", *flags]) == 2
        err = capsys.readouterr().err
        assert "expected --interface socketcan with a --channel" in err, err
        assert "--interface udp_multicast" in err, err


# --------------------------------------------------------------------------- bus runs

SCALE = "2"   # Ts = 20 ms: robust on a loaded 2-CPU host (as test_by_hand.py)
FINAL_TOL = 1e-3
# anomalies that blame a node or an outsider (tests/test_bus.py BLAME)
BLAME = {"auth_failed", "untrusted_source", "foreign_traffic", "impersonation", "sync_jump",
         "setpoint_inconsistent", "lambda_outlier", "malformed_frames", "rejected_frames",
         "key_mismatch", "wrong_keys", "node_died"}


def _up(tmp_path: Path, port: int, *c_flags: str) -> dict[str, Any]:
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "sim.cli", "up", "--case", "1", *c_flags,
                          "--interface", "udp_multicast", "--bus-config",
                          json.dumps({"port": port}), "--duration", "8", "--time-scale", SCALE,
                          "--no-plot", "--out", str(out)],
                         capture_output=True, text=True, timeout=600, check=False,
                         env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert res.returncode in (0, 3), res.stdout[-3000:] + res.stderr[-3000:]
    m = json.loads((out / "metrics.json").read_text())
    assert all(code == 0 for code in m["exit_codes"].values()), m["exit_codes"]
    assert m["final_error"] < FINAL_TOL, res.stdout[-3000:]
    blamed = {(a["kind"], a.get("node")) for a in m["anomalies"] if a["kind"] in BLAME}
    assert not blamed, blamed
    return {"stdout": res.stdout, "out": out, "logs": {
        p.stem: p.read_text(errors="replace") for p in (out / "logs").glob("agent_*.log")}}


@pytest.mark.realtime
def test_up_case1_every_agent_in_c_on_udp_multicast(tmp_path: Path, udp_port: int) -> None:
    """`bess-ded up --case 1 --agent-impl c` on python-can's default bus (a private port):
    at any load it converges (exit 0, or 3 with anomalies none of which blames a node:
    no impersonation, the agents tell their own echo), every node exits 0, and each C
    agent's summary is RUNNING with no datagram it could not read."""
    run = _up(tmp_path, udp_port, "--agent-impl", "c")
    assert "agents in C: 1, 2, 3, 4 (bessded-agent)" in run["stdout"]
    for i in range(1, 5):
        log = run["logs"][f"agent_{i}"]
        m = SUMMARY.search(log)
        assert m and m.group(2) == "RUNNING", log[-1000:]
        counters = summary_counters(log)
        assert not {"not_a_frame", "invalid_frame", "impersonation"} & set(counters), counters


@pytest.mark.realtime
@pytest.mark.parametrize("fd", [(), ("--fd",)], ids=["classic", "fd"])
def test_up_case1_mixed_fleet_on_udp_multicast(tmp_path: Path, udp_port: int,
                                               fd: tuple[str, ...]) -> None:
    """`--c-agents 2,4`: agents 2 and 4 in C, 1 and 3 on firmware_py, one bus: at any load
    it converges and blames no node; on CAN FD too (``--fd``: λ tagged per receiver under
    the key files' [lambda_tag_keys], AUTH-34), where every recorded frame is CAN FD with
    the bit-rate switch and the cantools CLI decodes the whole log against the FD DBC."""
    run = _up(tmp_path, udp_port, "--c-agents", "2,4", *fd)
    assert "agents in C: 2, 4 (bessded-agent)" in run["stdout"]
    assert SUMMARY.search(run["logs"]["agent_2"]) and SUMMARY.search(run["logs"]["agent_4"])
    assert not SUMMARY.search(run["logs"]["agent_1"])
    if not fd:
        return
    out = run["out"]
    assert (out / "scenario.toml").read_text().count("[bus]\nfd = true") == 1
    frames = list(can.LogReader(str(out / "run.log")))
    assert frames and all(f.is_fd and f.bitrate_switch for f in frames)
    with (out / "run.log").open() as log:
        decoded = subprocess.run([sys.executable, "-m", "cantools", "decode", str(FD_DBC_PATH)],
                                 stdin=log, capture_output=True, text=True, check=True).stdout
    assert "Unknown frame" not in decoded and "AGENT_4_MC" in decoded
