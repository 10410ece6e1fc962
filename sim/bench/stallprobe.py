"""How long this machine stops everything: a real-time sleeper above the nodes' priority.

`python -m sim.bench.stallprobe SECONDS [PRIORITY]` sleeps ``PERIOD_S`` at a time under
SCHED_FIFO ``PRIORITY`` (default 20, above the bus runs' nodes at 10) for SECONDS or
until its standard input closes, and prints, as one JSON line, how often and how long
a wake-up came more than ``STALL_S`` late. No process of the fleet can delay it, so
what it sees is the machine: on this 2-core VM, once its CPUs are saturated, both stop
for ~10 ms on a 100 ms grid (the hypervisor's CPU quota, by the look of it: seen beside
a 32-agent fleet and a compiler, 36 stalls of 9–10 ms in 18 s; beside the compiler
alone, one of 4.6 ms in 10 s), and every node misses those ticks together. `bess-ded
bench --realtime` runs it beside each capacity run, so that the table tells a fleet
that is too slow from a machine that was taken away.
"""

from __future__ import annotations

import json
import os
import select
import sys
import time

PERIOD_S = 0.002   # the probe's own tick: ~500 wake-ups/s, well under 1 % of a core
STALL_S = 0.003    # a wake-up this much later than asked is a stall (Ts/2 is 5 ms)


def probe(seconds: float, priority: int = 20) -> dict[str, object]:
    """Sleep PERIOD_S at a time for ``seconds`` or until standard input closes; the
    stalls seen, and whether the probe got its real-time priority (without it, nodes
    can delay it too)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        realtime = True
    except (OSError, AttributeError):
        realtime = False
    stalls: list[float] = []
    end = time.monotonic() + seconds
    prev = time.monotonic()
    while prev < end:
        if select.select([sys.stdin], [], [], PERIOD_S)[0]:
            break  # closed (or written to): the run it watched is over
        now = time.monotonic()
        if now - prev - PERIOD_S > STALL_S:
            stalls.append(now - prev - PERIOD_S)
        prev = now
    return {"seconds": seconds, "realtime": realtime, "stalls": len(stalls),
            "stalled_s": sum(stalls), "worst_s": max(stalls, default=0.0)}


def main(argv: list[str] | None = None) -> int:
    """The command line (used by sim.bench.realtime)."""
    args = sys.argv[1:] if argv is None else argv
    try:
        seconds = float(args[0])
        priority = int(args[1]) if len(args) > 1 else 20
        if not 0 < seconds <= 3600 or not 1 <= priority <= 99:
            raise ValueError
    except (IndexError, ValueError):
        print(f"bess-ded: error: stallprobe: expected SECONDS in (0, 3600] and a priority "
              f"in 1..99, but got {args}", file=sys.stderr)
        return 2
    print(json.dumps(probe(seconds, priority)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
