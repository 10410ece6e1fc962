"""Example: my agent, as agent 3 of case 1, rejects a forged price and counts it.

A price frame signed with the wrong key (agent 1's, not the router's) must not move λ,
and must show in the device's diagnostics (``AGENT_3_Diag.RejectedAuth``). Copy this
file and replace ``start_my_device`` by whatever starts your device (docs/testing.md).
"""

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.realtime]


def start_my_device(fleet, node="agent_3"):
    """YOUR DEVICE GOES HERE (see test_my_agent_converges.py). Here: `bess-ded agent`."""
    fleet.start([node])


def test_my_agent_rejects_a_forged_price(bess_fleet, bess_tester):
    fleet = bess_fleet(case=1, nodes=["plant", 1, 2, 4])
    start_my_device(fleet)
    bess_tester.expect("AGENT_3_MC", timeout_s=60)
    fleet.start(["router"])
    bess_tester.expect("AGENT_3_MC", timeout_s=60, where={"State": "RUNNING"})
    before = bess_tester.diagnostics(3, timeout_s=30)["RejectedAuth"]

    # a price of 2.0 cu/kWh "from the router", signed with agent 1's key: a forgery
    bess_tester.send("ER_Price", Rho=2.0, Segment=0, PriceValid=1, as_node="agent_1")

    # the device counts it (the diagnostics page carrying RejectedAuth goes up) ...
    bess_tester.expect("AGENT_3_Diag", timeout_s=30,
                       where={"RejectedAuth": lambda n: n > before})
    # ... and keeps following the genuine price (0.8), never the forged one
    bess_tester.expect_none("AGENT_3_MC", duration_s=2.0,
                            where={"Lambda": lambda lam: lam > 1.0})
    assert bess_tester.expect("AGENT_3_MC", timeout_s=10)["State"] != 0  # not back in INIT
    fleet.assert_alive()
