"""The model: the BESS cost model, scenarios, the communication graph, trajectories and
their metrics, and the references a bus run is judged against (the fixed-point lockstep and
the continuous-time hybrid). Pure computation: no bus, no processes."""
