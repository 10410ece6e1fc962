"""`bess-ded bench --realtime`'s fleet capacity (sim.bench.realtime): which bus each fleet
runs on, and that a run's missed ticks are read from the agents' own Diag frames for both
transmit modes. The figures themselves are measured, not asserted
(docs/performance.md)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from sim.bench.fleetload import BUS_LOAD_MAX, run_bus_load
from sim.bench.realtime import CapacityPlan, capacity_run, fleet_scenario


@pytest.mark.parametrize(("n", "transmit", "fd"), [
    (16, "periodic", False), (32, "periodic", True), (32, "event", False)])
def test_a_capacity_fleet_runs_on_classic_can_where_it_fits_else_on_fd(
        n: int, transmit: str, fd: bool) -> None:
    """32 periodic agents need 134 % of classic CAN at Ts = 10 ms and 101.5 % of CAN FD
    with λ tags (AUTH-34): the bench runs them on CAN FD without the tags (a bus run
    refuses a fleet over 100 %); event-triggered ones fit classic."""
    sc = fleet_scenario(n, transmit, 14.0)
    assert (sc.n, sc.transmit.mode, sc.fd) == (n, transmit, fd)
    assert sc.lambda_tags is not fd  # the tags are only left out where they do not fit
    assert run_bus_load(sc)[0] <= BUS_LOAD_MAX
    assert len(sc.pinned) == max(1, n // 4)


@pytest.mark.realtime
@pytest.mark.parametrize(("impl", "transmit"), [("py", "periodic"), ("py", "event"),
                                                ("c", "event")])
def test_a_capacity_run_counts_every_agents_ticks_in_either_mode(impl: str,
                                                                 transmit: str) -> None:
    """Four agents (Python two to a host, or C a process each, on udp_multicast) for 6 s:
    every agent's ticks over the steady window are counted from its Diag pages (an
    event-triggered agent sends no MC frame on most ticks, so MC frames cannot count
    them), and its misses are at most its ticks."""
    k = 2 if impl == "py" else 1
    r = capacity_run(4, k, CapacityPlan(seconds=6.0, impl=impl), transmit=transmit)
    assert "did_not_run" not in r, r
    assert (r["impl"], r["transmit"], r["bus"], r["per_process"]) == (impl, transmit,
                                                                      "classic", k)
    # 4 agents × at least one Diag page cycle (page 0 every ~1.3 s) of the 4 s window
    assert r["steady_ticks"] >= 4 * 100, r
    assert 0 <= r["steady_misses"] <= r["steady_ticks"]
    # a verdict, never a usage error: whether 6 s sufficed to settle is the load's (at
    # any load a run is judged, converged or not: bench reports it, docs/performance.md)
    assert r["exit_code"] in (0, 1, 3), r
    stalls = r["machine_stalls"]  # what the machine took away meanwhile, beside the fleet
    assert stalls is not None and stalls["stalls"] >= 0 and stalls["seconds"] == 3600


def test_the_stall_probe_stops_when_its_input_closes_and_reports_json() -> None:
    """The probe runs until the run it watches closes its stdin, then prints one JSON
    line; bad arguments are exit 2 with the expectation named."""
    p = subprocess.run([sys.executable, "-m", "sim.bench.stallprobe", "3600"], input="",
                       capture_output=True, text=True, timeout=30)
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout)
    assert set(got) == {"seconds", "realtime", "stalls", "stalled_s", "worst_s"}
    assert got["stalls"] >= 0 and got["worst_s"] >= 0
    bad = subprocess.run([sys.executable, "-m", "sim.bench.stallprobe", "0"],
                         capture_output=True, text=True, timeout=30)
    assert bad.returncode == 2 and bad.stderr.startswith("bess-ded: error: stallprobe: "
                                                         "expected SECONDS in (0, 3600]")
