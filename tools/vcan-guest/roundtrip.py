"""Time python-can socketcan round trips on vcan0 (the numbers quoted in docs/vcan.md).

    tools/vcan-run python3 tools/vcan-guest/roundtrip.py [N]

loopback:  one process, bus A sends a frame, bus B (same process) receives it; N times.
ping-pong: a second process echoes every 0x7A0 frame back as 0x7A1; the first sends and
           waits for the echo; N times.  This is a true request/response round trip
           between two processes, including two scheduler wake-ups.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import time

import can

CHANNEL = "vcan0"
PING, PONG = 0x7A0, 0x7A1


def echo() -> None:
    filt = [{"can_id": PING, "can_mask": 0x7FF, "extended": False}]
    with can.Bus(interface="socketcan", channel=CHANNEL, can_filters=filt) as bus:
        print("ready", flush=True)
        while True:
            msg = bus.recv()
            if msg.data == b"stop":
                return
            bus.send(can.Message(arbitration_id=PONG, is_extended_id=False, data=msg.data))


def report(name: str, n: int, total: float, trips: list[float]) -> None:
    trips_ms = sorted(t * 1e3 for t in trips)
    print(
        f"{name:9s} {n} trips in {total:.2f} s: median {statistics.median(trips_ms):.3f} ms, "
        f"p99 {trips_ms[int(0.99 * (n - 1))]:.3f} ms, max {trips_ms[-1]:.3f} ms"
    )


def main(n: int) -> None:
    # loopback: send on a, receive on b
    with (
        can.Bus(interface="socketcan", channel=CHANNEL) as a,
        can.Bus(
            interface="socketcan",
            channel=CHANNEL,
            can_filters=[{"can_id": PING, "can_mask": 0x7FF, "extended": False}],
        ) as b,
    ):
        trips = []
        t0 = time.perf_counter()
        for i in range(n):
            t = time.perf_counter()
            a.send(
                can.Message(arbitration_id=PING, is_extended_id=False, data=i.to_bytes(4, "little"))
            )
            msg = b.recv(timeout=5)
            assert msg is not None and int.from_bytes(msg.data, "little") == i
            trips.append(time.perf_counter() - t)
        report("loopback", n, time.perf_counter() - t0, trips)

    # ping-pong with an echo process
    peer = subprocess.Popen([sys.executable, __file__, "--echo"], stdout=subprocess.PIPE, text=True)
    assert peer.stdout is not None and peer.stdout.readline().strip() == "ready"
    filt = [{"can_id": PONG, "can_mask": 0x7FF, "extended": False}]
    with can.Bus(interface="socketcan", channel=CHANNEL, can_filters=filt) as bus:
        trips = []
        t0 = time.perf_counter()
        for i in range(n):
            t = time.perf_counter()
            bus.send(
                can.Message(arbitration_id=PING, is_extended_id=False, data=i.to_bytes(4, "little"))
            )
            msg = bus.recv(timeout=5)
            assert msg is not None and int.from_bytes(msg.data, "little") == i
            trips.append(time.perf_counter() - t)
        report("ping-pong", n, time.perf_counter() - t0, trips)
        bus.send(can.Message(arbitration_id=PING, is_extended_id=False, data=b"stop"))
    peer.wait(timeout=30)


if __name__ == "__main__":
    if sys.argv[1:] == ["--echo"]:
        echo()
    else:
        main(int(sys.argv[1]) if len(sys.argv) > 1 else 1000)
