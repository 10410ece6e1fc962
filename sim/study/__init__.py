"""Studies over many runs: sweeps of the lockstep over graphs, gains and seeds."""
