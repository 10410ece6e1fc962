"""Real-time figures of multi-process bus runs, for `bess-ded bench --realtime`.

What depends on how busy the machine is — deadline misses, frame rates, bus silences,
settling measured on the wall clock — is measured here and written to the docs with the
machine it ran on, never asserted by a test (the tests assert what holds at any load:
docs/runs.md). Each run is `bess-ded up`'s own path (``busrun.record``) on a private
udp_multicast port, or on the bus the caller names.
"""

from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

from sim.model.scenario import load_case
from sim.run import busrun


def realtime_run(case: int, seconds: float, bus: busrun.BusOptions | None = None
                 ) -> dict[str, Any]:
    """One case for ``seconds`` as node processes; the figures of its recording."""
    sc = load_case(case)
    sc = replace(sc, duration=seconds) if not sc.variants else sc.runs()[0][1]
    bus, _ = busrun.private_port(bus or busrun.BusOptions("udp_multicast"))
    with tempfile.TemporaryDirectory(prefix=f"bess-ded-bench-case{case}-") as tmp:
        rec = busrun.record(sc, Path(tmp), bus, duration=seconds, quiet=True, plot=False)
    m, log = rec.metrics, rec.log
    t0 = log.t_first_price or 0.0
    span = max(log.t_end - t0, 1e-9)
    price = log.sequences.get("ER_Price")
    miss_pct = {k: 100.0 * m["deadline_misses"][k] / max(t, 1)
                for k, t in m["node_ticks"].items()}
    return {
        "case": case, "agents": sc.n, "seconds": seconds,
        "frames_per_s": log.frames / span,
        "price_frames_per_s": (price.frames if price else 0) / span,
        "deadline_miss_pct_max": max(miss_pct.values()) if miss_pct else 0.0,
        "deadline_miss_pct": miss_pct,
        "bus_silences": m["bus_silences"],
        "frames_missed_by_recorder": m["frames_missed_by_recorder"],
        "settling_time_s": m.get("settling_time_s"),
        "final_error": m.get("final_error"),
        "anomalies": [a["kind"] for a in m["anomalies"]],
        "exit_code": m["verdict"]["exit_code"],
    }
