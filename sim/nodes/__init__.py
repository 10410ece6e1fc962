"""The simulated nodes on the bus besides the agents: the plant (batteries and DC-DC
choppers), the energy router (price, commands, cost ledger), what they share
(``nodeclock``), the setpoint check (``consistency``) and crafted bad traffic (``inject``)."""
