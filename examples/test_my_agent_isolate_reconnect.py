"""Example: the tester plays the energy router; my agent obeys ISOLATE and RECONNECT.

The fleet is the plant and agents 1, 2 and 4; the tester sends the price every 50 ms
(ER_Price's DBC cycle) and the commands, signed with the router's key. Copy this file
and replace ``start_my_device`` by whatever starts your device (docs/testing.md).
"""

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.realtime]


def start_my_device(fleet, node="agent_3"):
    """YOUR DEVICE GOES HERE (see test_my_agent_converges.py). Here: `bess-ded agent`."""
    fleet.start([node])


def test_my_agent_obeys_isolate_and_reconnect(bess_fleet, bess_tester):
    fleet = bess_fleet(case=1, nodes=["plant", 1, 2, 4])      # no router: the tester is it
    start_my_device(fleet)
    price = bess_tester.send_periodic("ER_Price", Rho=0.8, Segment=0, PriceValid=1)
    bess_tester.expect("AGENT_3_MC", timeout_s=60, where={"State": "RUNNING"})

    no_gains = {"GainK": 0, "GainH": 0}                         # used by SET_GAINS only
    bess_tester.send("ER_Command", Command="ISOLATE", Target=3, **no_gains)
    bess_tester.expect("AGENT_3_MC", timeout_s=10, where={"State": "ISOLATED"})

    bess_tester.send("ER_Command", Command="RECONNECT", Target=3, **no_gains)
    bess_tester.expect("AGENT_3_MC", timeout_s=10, where={"State": "RUNNING"})
    price.stop()
    fleet.assert_alive()
