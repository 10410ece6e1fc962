#!/usr/bin/env python3
"""How long an in-process conformance check takes: the schedule played against
firmware_py's agent (``sim.conformance.simulate``) and judged (``check``, ``explain``,
``verdict``), as tests/test_conformance.py does, for the whole schedule and for
`bess-ded conformance --quick`'s steps (docs/conformance.md, "Measured").

Usage::

    python tools/conformance_time.py                     # case 1 agent 3, case 7 agent 5
    python tools/conformance_time.py --case 4:2
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

from firmware_py import secoc
from firmware_py.config import agent_configs_from_scenario
from firmware_py.secoc import Keyring
from sim import conformance as conf
from sim.model.scenario import load_case

MASTER = bytes(range(16))
KEYS = {n: secoc.derive_node_key(MASTER, n) for n in secoc.fleet_nodes(12)}


def measure(case: int, dut: int, quick: bool, jitter: float = 0.3) -> tuple[float, float, str]:
    """(simulate s, check s, a summary of the verdict) for one run."""
    sc = load_case(case)
    _, cfg = conf.written_config(agent_configs_from_scenario(sc)[dut - 1])
    node = f"agent_{dut}"

    def ring() -> Keyring:
        return Keyring(node, KEYS[node], 0, lambda _b: None, master=MASTER,
                       floors={n: 2 for n in KEYS if n != node})

    planned = conf.plan(cfg, KEYS, sc.prices[0].rho, boot=2, quick=quick)
    t0 = time.perf_counter()
    frames = conf.simulate(cfg, ring(), planned, jitter=jitter)
    t1 = time.perf_counter()
    outcome = conf.check(cfg, ring(), KEYS[node], frames)
    conf.explain(cfg, ring(), KEYS[node], frames, outcome)
    results = conf.verdict(outcome, played=conf.played_steps(planned))
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1, (f"{sum(r.passed for r in results)} passed, "
                              f"{sum(r.failed for r in results)} failed, "
                              f"{sum(r.not_run for r in results)} not run")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--case", action="append", metavar="N:I",
                   help="scenario N, the device in agent I's place (default: 1:3, 7:5)")
    args = p.parse_args(argv)
    logging.disable(logging.CRITICAL)
    for spec in args.case or ["1:3", "7:5"]:
        case, dut = (int(x) for x in spec.split(":"))
        for quick in (False, True):
            sim_s, check_s, summary = measure(case, dut, quick)
            print(f"case {case} agent {dut} {'--quick' if quick else 'whole  '}: simulate "
                  f"{sim_s:.2f} s, check {check_s:.2f} s ({summary})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
