"""Planning a fleet run on a bus (``bess-ded up``, ``bess-ded restbus``): the scenario,
its variant and time scale, the bus, the duration, the output directory and the keys,
checked before anything starts and announced (docs/api.md, docs/runs.md). The run
itself is ``sim.run.busrun.record(plan.sc, plan.out, plan.bus, duration=plan.duration,
time_scale=plan.scale, ...)``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_py.errors import ParameterError

if TYPE_CHECKING:  # sim.run.busrun imports numpy and python-can: only where a run starts
    from sim.model.scenario import Scenario
    from sim.run.busrun import BusOptions

# In tools/vcan-run's QEMU TCG guest (VCAN_RUN_GUEST=1) Python runs ~20x slower: at
# Ts = 10 ms the agents miss most deadlines and starve the router, which then never
# starts (docs/vcan.md, "The vcan tier"). Ts = 50 ms keeps every deadline there.
GUEST_TIME_SCALE = 5.0
# interfaces whose buses live inside one process: `up` runs every node in its own
IN_PROCESS_INTERFACES = ("virtual",)


@dataclass
class RunPlan:
    """A fleet run as the options describe it, checked and announced."""

    sc: Scenario          # variant chosen, time scale applied
    bus: BusOptions
    duration: float       # s of (scaled) price time
    scale: float
    out: Path


def plan_fleet_run(case: str, *, variant: str | None = None, bus: BusOptions | None = None,
                   duration: float | None = None, out: Path | None = None,
                   time_scale: float | None = None, keys: Path | None = None,
                   insecure: bool = False, command: str = "up",
                   nodes: str = "{n} agents + plant + router",
                   say: Callable[[str], None] = print,
                   transmit: str | None = None, fd: bool = False, no_lambda_tags: bool = False,
                   check: Callable[[Scenario], object] | None = None) -> RunPlan:
    """Check a fleet run of scenario ``case`` (a case number or a .toml) and announce it
    through ``say``, line by line (``nodes``: what runs, ``{n}`` the number of agents).
    ``bus`` must connect processes (not python-can's ``virtual``); a udp_multicast bus
    without a port gets a private one. ``duration``: s of price time (default: the
    scenario's); ``time_scale``: default 1, or GUEST_TIME_SCALE under tools/vcan-run;
    ``keys``: a key set directory (checked), else ``insecure`` or a fresh set in
    ``out``/keys at the run; ``out``: default runs/<command>-<scenario>; ``transmit``:
    "periodic" or "event" (None: the scenario's, scenario_select.with_transmit); ``fd``: a
    CAN FD bus (else the scenario's ``[bus] fd``, scenario_select.with_fd); ``check``: a
    further check of the fleet as it will run, before anything is announced (the CLI's:
    its computed bus load, sim.bench.fleetload.check_bus_load)."""
    from firmware_py.config import agent_configs_from_scenario
    from sim.model.scenario import MAX_AGENT_SAMPLES, scaled
    from sim.model.scenario_select import pick_variant, resolve_scenario, with_fd, with_transmit
    from sim.run import busrun
    from sim.run.keyset import check_key_set

    base = resolve_scenario(case)
    sc, chosen = pick_variant(base, variant, command, say)
    sc = with_transmit(sc, transmit)
    sc = with_fd(sc, fd, no_lambda_tags)
    bus = bus or busrun.BusOptions()
    kw = bus.resolved()  # checks the JSON (and the keys) before anything starts
    if kw["interface"] in IN_PROCESS_INTERFACES:
        raise ParameterError("--interface", "a bus that connects processes (udp_multicast, "
                             f"socketcan, ...): `{command}` runs every node as its own "
                             f"process, and python-can's {kw['interface']!r} bus exists "
                             "inside one process only", kw["interface"])
    scale = time_scale
    if scale is None and os.environ.get("VCAN_RUN_GUEST") == "1":
        scale = GUEST_TIME_SCALE
        say(f"bess-ded {command}: --time-scale {scale:g} (VCAN_RUN_GUEST=1: the emulated "
            f"guest is too slow for Ts = {sc.ts * 1000:g} ms; give --time-scale 1 to "
            "insist)")
    scale = scale or 1.0
    sc = scaled(sc, scale)
    # a fleet larger than the DBC's frames (a simulator-only scenario), or one the bus
    # cannot carry, is refused here, before the run writes its directory
    agent_configs_from_scenario(sc)
    if check is not None:
        check(sc)
    run_s = sc.duration if duration is None else duration * scale
    if sc.n * run_s / sc.ts > MAX_AGENT_SAMPLES:  # its log could not be analysed
        raise ParameterError("--duration", f"at most {MAX_AGENT_SAMPLES * sc.ts / sc.n / scale:g}"
                             f" s for {sc.n} agents at Ts = {sc.ts / scale:g} s (the analysis "
                             f"holds {MAX_AGENT_SAMPLES:.0e} agent-samples)",
                             duration)
    out = out or Path("runs") / f"{command}-{sc.name}"
    bus, port = busrun.private_port(bus)
    say(f"bess-ded {command}: {sc.title or sc.name}{chosen}: {nodes.format(n=sc.n)} for "
        f"{run_s / scale:g} s" + (f" (run at ×{scale:g}: {run_s:g} s)" if scale != 1 else ""))
    say(f"  bus: {bus.resolved()}" + ((", CAN FD frames" + ("" if sc.lambda_tags else
                                                              ", λ untagged"))
                                      if sc.fd else "")
        + (f" (port {port} private to this run; name one with --bus-config "
           "'{\"port\": N}')" if port else ""))
    for line in sc.analysis().describe()[1:]:
        say(f"  {line}")
    if sc.resilient_f:  # the agents trim: say whether the graph lets it tolerate liars
        from sim.model.robust import resilience

        for line in resilience(sc.n, sc.edges, sc.pinned, sc.resilient_f).describe():
            say(f"  {line}")
    if keys is not None:
        fleet = check_key_set(keys, sc.n, sc)
        say(f"  keys: {keys}/ (fleet id {fleet})")
    elif insecure:
        if sc.signed_price:  # AUTH-31: the demo keys hold no price signing key
            raise ParameterError("--insecure", "a key set for a [security] signed_price "
                                 "scenario (the router's price signing key is in its key "
                                 "file): drop --insecure", "--insecure")
        say("  keys: INSECURE (--insecure): the public demo key, anyone on the bus can "
            "forge frames")
    else:
        say(f"  keys: a fresh key set for this run in {out / 'keys'}/")
    return RunPlan(sc, bus, run_s, scale, out)


def c_node_program(flag: str) -> Path:
    """firmware_c's bessded-agent, built on first use (a ParameterError naming ``flag``
    and the cause when it does not build)."""
    from sim.cbind.cagent import node_program
    from sim.cbind.cimpl import CBuildError

    try:
        return node_program()
    except (CBuildError, OSError) as e:
        first = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        raise ParameterError(flag, "firmware_c to build (make, a C compiler, libmbedtls-dev: "
                             "tools/install-c-deps)", first) from None
