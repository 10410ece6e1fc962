"""bess-ded firmware: the per-agent reset-PI marginal-cost consensus node.

`fixedpoint` and `controllers` are the pure control core (integer maths and the
standard library only, portable to an MCU bit for bit). `frames`, `runtime` and
`node` are the agent's runtime and CAN I/O around it.
"""
