"""The random-loss fault mode of the bus runs (issue 23, item 2; docs/faults.md, "Random
frame loss"): ``run_in_process(loss=, loss_seed=)`` and ``bess-ded up --loss``.

Every node loses each frame it receives with probability P, from its own generator
seeded from the run's seed and its name; the drops are counted per node in the metrics'
``injected_loss`` and the verdict keeps what they explain (timeouts, SAFE episodes)
apart from the anomalies, while a run that does not converge is still not converged.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import can
import pytest

from firmware_py.faultinject import FaultyBus, RxFaults, every_frame, node_seed
from sim.model.scenario import load_case
from sim.run import busrun
from sim.run.runreport import run_facts_path
from sim.run.verdict import Anomaly, RunFacts, _verdict

CASE = load_case(1)
FINAL_TOL = 1e-3


def _inject(dropped: dict[str, int]) -> dict[str, object]:
    received = {n: 1000 for n in dropped}
    return {"probability": 0.3, "seed": 0, "frames": "every frame each node receives",
            "dropped": dropped, "received": received,
            "dropped_total": sum(dropped.values()), "received_total": 1000 * len(dropped)}


@pytest.mark.slow
def test_case1_converges_with_10_percent_loss_on_the_simulated_clock(tmp_path: Path) -> None:
    """Case 1 in process (deterministic) with 10 % of every frame each node receives
    dropped: converged with final max|λ−ρ| ≤ 1e-3, no anomaly at all (nothing blamed on
    a node), every node's drops counted (≈ 10 % of what it received) and written to
    run_facts.json for `analyze`."""
    m = busrun.run_in_process(replace(CASE, duration=10.0), tmp_path, 10.0,
                              channel="busloss-case1", loss=0.1, loss_seed=0)
    assert m["verdict"]["converged"] and m["final_error"] <= FINAL_TOL, m["verdict"]
    assert m["anomalies"] == [], m["anomalies"]
    inj = m["injected_loss"]
    assert set(inj["dropped"]) == {"agent_1", "agent_2", "agent_3", "agent_4", "plant",
                                   "router"}
    for node, k in inj["dropped"].items():
        share = k / inj["received"][node]
        assert 0.08 <= share <= 0.12, (node, k, inj["received"][node])
    assert inj["dropped_total"] == sum(inj["dropped"].values()) > 0
    # the agents noticed the loss themselves (E2E counters): the frames really went missing
    assert all(d["LostFrames"] > 0 for d in m["node_diagnostics"].values())
    facts = json.loads(run_facts_path(tmp_path).read_text())
    assert facts["injected_loss"]["dropped"] == inj["dropped"]


@pytest.mark.slow
def test_the_loss_is_seeded(tmp_path: Path) -> None:
    """The same seed drops the same frames at the same nodes: two runs record the same
    bus traffic (public demo keys, so the MACs are the same too) and count the same
    drops; another seed drops others."""
    def run(name: str, seed: int) -> tuple[dict[str, int], str]:
        m = busrun.run_in_process(replace(CASE, duration=2.0), tmp_path / name, 2.0,
                                  channel=f"busloss-seed-{name}", insecure=True,
                                  loss=0.2, loss_seed=seed)
        log = (tmp_path / name / "run.log").read_text()
        return m["injected_loss"]["dropped"], log.replace(f"busloss-seed-{name}", "bus")

    a, b, c = run("a", 5), run("b", 5), run("c", 6)
    assert a == b
    assert a[0] != c[0]
    assert node_seed(5, "agent_1") != node_seed(5, "agent_2") != node_seed(6, "agent_2")


def test_the_verdict_keeps_what_the_loss_explains_apart() -> None:
    """With the fault mode on, the timeouts at a node that lost frames and the SAFE
    episodes of an agent that timed out are the loss's doing: out of the anomalies, into
    ``loss_explained``. Anything else stays an anomaly; without injected loss nothing
    moves; a run that did not converge stays not converged, the loss named as the cause
    when no anomaly is left to explain it."""
    out = [Anomaly("price_timeout", "agent_2", "2 price timeouts"),
           Anomaly("agent_safe", "agent_2", "in SAFE for 0.04 s", 3.0),
           Anomaly("agent_safe", "agent_3", "in SAFE for 1.00 s", 4.0),
           Anomaly("setpoint_timeout", "plant", "4 setpoint timeouts"),
           Anomaly("node_died", "agent_4", "exited with code 1")]
    facts = RunFacts(injected_loss=_inject({"agent_2": 50, "agent_3": 0, "plant": 40}))
    v = _verdict([], list(out), facts)
    assert v.converged
    assert [(a.kind, a.node) for a in v.loss_explained] == [
        ("price_timeout", "agent_2"), ("agent_safe", "agent_2"), ("setpoint_timeout", "plant")]
    assert [(a.kind, a.node) for a in v.anomalies] == [("agent_safe", "agent_3"),
                                                       ("node_died", "agent_4")]
    assert _verdict([], list(out), RunFacts()).anomalies == out
    v = _verdict(["the final λ is 2e-03 cu/kWh from ρ"], out[:2], facts)
    assert not v.converged and v.exit_code == 1 and v.anomalies == []
    assert v.cause is not None and v.cause.startswith("injected loss")


def test_up_gives_every_node_its_own_loss_flags(tmp_path: Path) -> None:
    """`up --loss P --loss-seed N`: every agent (on every frame but its echo:
    --inject-rx-all), the plant and the router get --inject-rx-loss P and a seed of
    their own; other fault flags stay."""
    extra = busrun.loss_argv(CASE, 0.1, 7, {"plant": ["--obey-inconsistent"]})
    assert set(extra) == {"agent_1", "agent_2", "agent_3", "agent_4", "plant", "router"}
    assert extra["plant"][0] == "--obey-inconsistent"
    seeds = set()
    for name, argv in extra.items():
        i = argv.index("--inject-rx-loss")
        assert argv[i + 1] == "0.1"
        seeds.add(int(argv[argv.index("--inject-seed") + 1]))
        assert ("--inject-rx-all" in argv) == name.startswith("agent_")
    assert len(seeds) == 6


def test_faultybus_spares_the_echo_of_its_own_frames() -> None:
    """With ``spare_own``, frames on an ID the node sent through the wrapper (its echo)
    are never dropped nor counted; every other frame is, at the given rate."""
    ch = "busloss-spare-own"
    tx = can.Bus(interface="virtual", channel=ch, receive_own_messages=False)
    rx = can.Bus(interface="virtual", channel=ch, receive_own_messages=False)
    try:
        fb = FaultyBus(rx, RxFaults(loss=0.5, seed=1, match=every_frame, spare_own=True))
        fb.send(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\0"))
        for k in range(400):
            fid = 0x123 if k % 2 else 0x200
            tx.send(can.Message(arbitration_id=fid, is_extended_id=False, data=bytes([k % 256])))
        got = []
        while (m := fb.recv(timeout=0)) is not None:
            got.append(m)
        assert sum(m.arbitration_id == 0x123 for m in got) == 200
        assert fb.matched == 200 and 70 <= fb.dropped <= 130
        assert sum(m.arbitration_id == 0x200 for m in got) == 200 - fb.dropped
    finally:
        tx.shutdown()
        rx.shutdown()
