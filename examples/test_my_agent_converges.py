"""Example: my agent, as agent 3 of the paper's case 1, converges to the price.

The rest of the bus (the router, the plant and agents 1, 2 and 4) runs as `bess-ded`
processes; the device under test takes agent 3's place. Copy this file into your tests
and replace ``start_my_device`` by whatever starts your device on the test's bus
(``pytest --bess-interface socketcan --bess-channel can0`` for a rig, docs/testing.md).
"""

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.realtime]


def start_my_device(fleet, node="agent_3"):
    """YOUR DEVICE GOES HERE: start (flash, power on) your agent for ``node`` on the test's
    bus, configured from ``fleet.config_path(node)`` (neighbours, gains, limits, Ts) with
    the key file ``fleet.key_path(node)``. Here it is our own node, `bess-ded agent`."""
    fleet.start([node])


def test_my_agent_converges(bess_fleet, bess_tester):
    fleet = bess_fleet(case=1, nodes=["plant", 1, 2, 4])     # the fleet but agent 3, no router yet
    start_my_device(fleet)
    bess_tester.expect("AGENT_3_MC", timeout_s=60)             # the device is on the bus
    fleet.start(["router"])                                    # its first price is t = 0
    rho = bess_tester.expect("ER_Price", timeout_s=60)["Rho"]

    # λ_3 reaches ρ within 1e-3 while RUNNING (case 1 settles in a few seconds of its own
    # ticks; the timeout is generous for a loaded machine: bus time is wall time here)
    near = {"State": "RUNNING", "Lambda": lambda lam: abs(lam - rho) < 1e-3}
    bess_tester.expect("AGENT_3_MC", timeout_s=120, where=near)
    for i in (1, 2, 4):                                        # and so does the fleet
        bess_tester.expect(f"AGENT_{i}_MC", timeout_s=60, where=near)

    # nothing of the fleet's was rejected as forged or corrupt
    bess_tester.assert_diagnostics(3, RejectedAuth=0, RejectedDlc=0, Untrusted=0)
    assert bess_tester.rejected["auth"] == 0, bess_tester.summary()
    fleet.assert_alive()
