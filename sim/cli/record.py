"""`bess-ded record --out FILE`: capture a CAN bus to a log that `bess-ded analyze` reads.

Records every frame of any python-can bus (the same bus flags as every node) until
--duration elapses or SIGINT/SIGTERM, in the format FILE's suffix names (.log:
candump -L, what `analyze`, `cantools decode` and can-utils read; .asc, .blf, .csv
also work). On udp_multicast, give the run's port: `bess-ded up` prints it. What the
bus delivers that is no CAN frame (a stray datagram, a message no CAN bus carries) is
left out of the log, counted by cause and reported at the end as an anomaly.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from firmware_py.cliargs import duration_s
    from firmware_py.nodeargs import add_bus_arguments

    from ._common import one_line_errors

    p = one_line_errors(sub.add_parser(
        "record", help="capture a CAN bus to a candump log", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter))
    add_bus_arguments(p)
    p.add_argument("--out", type=Path, required=True, metavar="FILE",
                   help="the log to write (.log for candump format)")
    p.add_argument("--duration", type=duration_s(), metavar="S",
                   help="stop after S seconds (default: until SIGINT/SIGTERM)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import can

    from firmware_py.node import GuardedBus, StopFlag, bus_kwargs, open_bus
    from sim.run.busopts import RECORDER_RCVBUF, enlarge_receive_buffer

    kw = {**bus_kwargs(args.interface, args.channel, args.bus_config),
          "receive_own_messages": False}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    raw = open_bus(**kw)
    stop = StopFlag()
    stop.install_signal_handlers()
    enlarge_receive_buffer(raw, RECORDER_RCVBUF)
    # what the bus delivers that is not a frame is counted and left out, never the end
    bus = GuardedBus(raw, lambda cause: None, who="bess-ded record")
    writer = can.Logger(str(args.out))
    frames = 0
    tty = sys.stderr.isatty()
    print(f"bess-ded record: {kw} → {args.out}" + (f" for {args.duration:g} s"
                                                    if args.duration else " until Ctrl-C"),
          file=sys.stderr)
    start = last_print = time.monotonic()
    try:
        while not stop.is_set():
            now = time.monotonic()
            if args.duration is not None and now - start >= args.duration:
                break
            msg = bus.recv(timeout=0.1)
            if msg is not None:
                writer.on_message_received(msg)
                frames += 1
            if now - last_print >= (1.0 if tty else 10.0):
                last_print = now
                print(("\r" if tty else "") + f"  {now - start:7.1f} s  {frames} frames",
                      end="" if tty else "\n", file=sys.stderr, flush=True)
        # what the kernel already queued for us belongs to the recording too
        while (msg := bus.recv(timeout=0)) is not None:
            writer.on_message_received(msg)
            frames += 1
    finally:
        writer.stop()
        raw.shutdown()
    print(("\n" if tty else "") + f"bess-ded record: {frames} frames in "
          f"{time.monotonic() - start:.1f} s to {args.out}", file=sys.stderr)
    dropped = {k: v for k, v in bus.counters.items() if v}
    if dropped:
        print("bess-ded record: anomaly: " + ", ".join(f"{v} {k}" for k, v in dropped.items())
              + " (bus inputs that are not CAN frames, left out of the log)", file=sys.stderr)
    return 0
