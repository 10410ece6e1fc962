"""Negative prices end to end (issue 20): a scenario whose price goes below zero runs
in the lockstep simulator and on the bus (router → agents → plant → verdict) and
converges, with no agent rejecting the price or going SAFE."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sim.cli import main
from sim.model.scenario import case_path, load_scenario
from sim.run import busrun

# case 1 on a shorter axis: 0.8 cu/kWh, then -0.3 from t = 4 s (a 1.1 cu/kWh step, above
# the default price_step_max: the scenario raises it, so no frame is rejected)
NEGATIVE = (case_path(1).read_text()
            .replace('name = "case1"', 'name = "negative"')
            .replace("duration = 20.0", "duration = 10.0")
            .replace("t = 0.0\nrho = 0.8\n", "t = 0.0\nrho = 0.8\n\n[[price]]\nt = 4.0\n"
                     "rho = -0.3\n")
            + "\n[limits]\nrho_min = -1.0\nrho_max = 2.0\nprice_step_max = 1.5\n")


@pytest.fixture
def scenario_file(tmp_path: Path) -> Path:
    path = tmp_path / "negative.toml"
    path.write_text(NEGATIVE)
    assert load_scenario(path).prices[-1].rho == -0.3
    return path


@pytest.mark.parametrize("impl", ["py", "c"])
def test_lockstep_case_with_a_negative_price(scenario_file: Path, tmp_path: Path,
                                             impl: str) -> None:
    out = tmp_path / "o"
    assert main(["case", str(scenario_file), "--impl", impl, "--out", str(out),
                 "--no-plots"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["final_error"] < 1e-3 and len(m["settling_times_s"]) == 2
    # below zero every battery charges: the marginal cost -0.3 is under every β(1+m)
    tr = np.genfromtxt(out / "trajectory.csv", delimiter=",", names=True)
    powers = [n for n in tr.dtype.names if n.startswith("p_")]
    assert powers and all(tr[n][-1] < 0 for n in powers)


@pytest.mark.slow
def test_bus_run_with_a_negative_price_converges(scenario_file: Path, tmp_path: Path) -> None:
    """On the simulated clock: the router sends ρ = -0.3, every agent accepts it (no
    implausible price, no SAFE) and the verdict is a clean CONVERGED."""
    sc = load_scenario(scenario_file)
    m = busrun.run_in_process(sc, tmp_path, duration=sc.duration, channel="test-negative")
    assert m["verdict"]["converged"] and m["verdict"]["ok"], m["anomalies"]
    assert m["anomalies"] == [] and m["final_error"] < 1e-3
    diag = m["node_diagnostics"]
    assert sorted(diag) == [f"agent_{i}" for i in range(1, 5)]
    assert all(d["ImplausiblePrice"] == 0 and d["PriceTimeouts"] == 0 for d in diag.values())
