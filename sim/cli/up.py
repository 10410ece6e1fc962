"""`bess-ded up`: run a case with every node a separate process on a CAN bus.

The router, the plant and one firmware process per agent start on one bus; this
process records every frame to DIR/run.log, shows progress, stops the nodes at the
end (or on Ctrl-C / SIGTERM) and judges the run from the recording alone
(docs/runs.md). It writes DIR/metrics.json (with the verdict and the anomalies),
DIR/trajectory.csv and DIR/bus_run.png, and exits with:

  0    converged, no anomaly
  1    not converged (an agent SAFE/INIT/ISOLATED at the end, a node died, the last
       price segment never settled, a final λ more than --tolerance from ρ, ...): the
       reasons and the most likely cause are printed
  2    bad input (nothing was run)
  3    converged, but with anomalies (listed); --insecure runs exit 3 at best
  130  interrupted: the outputs cover what was recorded until then

On udp_multicast, a run without a port of its own (--bus-config '{"port": N}' or
CAN_CONFIG) gets a private one, so concurrent runs never hear each other.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_py.errors import ConfigError, ParameterError
from firmware_py.nodeargs import add_bus_arguments

if TYPE_CHECKING:
    from ..busrun import BusOptions
    from ..runreport import Recording
    from ..scenario import Scenario

# In tools/vcan-run's QEMU TCG guest (VCAN_RUN_GUEST=1) Python runs ~20x slower: at
# Ts = 10 ms the agents miss most deadlines and starve the router, which then never
# starts (docs/vcan.md, "The vcan tier"). Ts = 50 ms keeps every deadline there.
GUEST_TIME_SCALE = 5.0
# interfaces whose buses live inside one process: `up` runs every node in its own
IN_PROCESS_INTERFACES = ("virtual",)


def register(sub: argparse._SubParsersAction) -> None:
    from ._common import one_line_errors

    p = one_line_errors(sub.add_parser(
        "up", help="run router, plant and every agent as processes on a bus",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter))
    add_run_arguments(p)
    c = p.add_mutually_exclusive_group()
    c.add_argument("--agent-impl", choices=("py", "c"), default="py",
                   help="the agents' firmware: firmware_py (default) or firmware_c's node "
                   "program (SocketCAN only: --interface socketcan --channel vcan0)")
    c.add_argument("--c-agents", metavar="I,J,...",
                   help="run these agents on firmware_c, the others on firmware_py "
                   "(SocketCAN only)")
    p.add_argument("--obey-inconsistent", action="store_true",
                   help="the plant follows a setpoint that is not its agent's dispatch rule "
                   "at the λ it publishes (still reported: setpoint_inconsistent); default: "
                   "it holds the last consistent one (docs/security.md)")
    p.set_defaults(func=run)


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    """The options of a fleet run on a bus (`up`, `restbus`): scenario, bus, duration,
    output, time scale, keys."""
    from firmware_py.cliargs import duration_s, time_scale

    from ._common import add_case_option, add_no_plot_argument

    add_case_option(p)
    p.add_argument("--variant", metavar="LABEL",
                   help="for a scenario with variants (cases 2, 3, 6): which one to run "
                   "(default: the first)")
    add_bus_arguments(p)
    p.add_argument("--duration", type=duration_s(), metavar="S",
                   help="seconds of price time (default: the scenario's duration)")
    p.add_argument("--out", type=Path, help="output directory (default: runs/<command>-"
                   "<scenario>)")
    p.add_argument("--time-scale", type=time_scale, metavar="F",
                   help="stretch the time axis by F (Ts·F, k/F, h/F²: the same discrete "
                   "system) for hosts too slow for Ts = 10 ms, e.g. an emulated guest "
                   f"(default: 1, or {GUEST_TIME_SCALE:g} under tools/vcan-run)")
    add_no_plot_argument(p, "bus_run.png")
    add_tolerance_argument(p)
    k = p.add_mutually_exclusive_group()
    k.add_argument("--keys", type=Path, metavar="DIR",
                   help="sign with this key set from `bess-ded keys --fleet` (its boot "
                        "counters advance); default: a fresh key set for this run in "
                        "OUT/keys")
    k.add_argument("--insecure", action="store_true",
                   help="demo mode: every node signs with the public all-zero key and warns "
                        "(docs/security.md)")


def add_tolerance_argument(p: argparse.ArgumentParser) -> None:
    from firmware_py.cliargs import positive_float

    from ..verdict import TOLERANCE

    p.add_argument("--tolerance", type=positive_float(), default=TOLERANCE, metavar="CU",
                   help="converged only if every dispatching agent's final λ is within CU "
                   f"cu/kWh of ρ (default: {TOLERANCE:g}); a λ this far off the others' "
                   "is a lambda_outlier")


@dataclass
class RunPlan:
    """A fleet run as the options describe it, checked and announced."""

    sc: Scenario          # variant chosen, time scale applied
    bus: BusOptions
    duration: float       # s of (scaled) price time
    scale: float
    out: Path


def plan_run(args: argparse.Namespace, command: str, nodes: str) -> RunPlan:
    """Check the options of a fleet run and print its banner (``nodes``: what runs)."""
    from .. import busrun
    from ..scenario import MAX_AGENT_SAMPLES, scaled
    from ._common import resolve_scenario

    base = resolve_scenario(args.case)
    sc, chosen = pick_variant(base, args.variant, command)
    bus = busrun.BusOptions(args.interface, args.channel, args.bus_config)
    kw = bus.resolved()  # checks the JSON (and the keys) before anything starts
    if kw["interface"] in IN_PROCESS_INTERFACES:
        raise ParameterError("--interface", "a bus that connects processes (udp_multicast, "
                             f"socketcan, ...): `{command}` runs every node as its own "
                             f"process, and python-can's {kw['interface']!r} bus exists "
                             "inside one process only", kw["interface"])
    scale = args.time_scale
    if scale is None and os.environ.get("VCAN_RUN_GUEST") == "1":
        scale = GUEST_TIME_SCALE
        print(f"bess-ded {command}: --time-scale {scale:g} (VCAN_RUN_GUEST=1: the emulated "
              f"guest is too slow for Ts = {sc.ts * 1000:g} ms; give --time-scale 1 to "
              "insist)")
    scale = scale or 1.0
    sc = scaled(sc, scale)
    duration = sc.duration if args.duration is None else args.duration * scale
    if sc.n * duration / sc.ts > MAX_AGENT_SAMPLES:  # its log could not be analysed
        raise ParameterError("--duration", f"at most {MAX_AGENT_SAMPLES * sc.ts / sc.n / scale:g}"
                             f" s for {sc.n} agents at Ts = {sc.ts / scale:g} s (the analysis "
                             f"holds {MAX_AGENT_SAMPLES:.0e} agent-samples)",
                             args.duration)
    out = args.out or Path("runs") / f"{command}-{sc.name}"
    bus, port = busrun.private_port(bus)
    print(f"bess-ded {command}: {sc.title or sc.name}{chosen}: {nodes.format(n=sc.n)} for "
          f"{duration / scale:g} s" + (f" (run at ×{scale:g}: {duration:g} s)"
                                       if scale != 1 else ""))
    print(f"  bus: {bus.resolved()}" + (f" (port {port} private to this run; name one with "
                                         "--bus-config '{\"port\": N}')" if port else ""))
    for line in sc.analysis().describe()[1:]:
        print(f"  {line}")
    if args.keys is not None:
        fleet = check_key_set(args.keys, sc.n, sc)
        print(f"  keys: {args.keys}/ (fleet id {fleet})")
    elif args.insecure:
        print("  keys: INSECURE (--insecure): the public demo key, anyone on the bus can "
              "forge frames")
    else:
        print(f"  keys: a fresh key set for this run in {out / 'keys'}/")
    return RunPlan(sc, bus, duration, scale, out)


def print_report(plan: RunPlan, rec: Recording) -> int:
    """The summary, the files written; the exit code of the verdict."""
    from ..runreport import summary_lines

    for line in summary_lines(rec.metrics, rec.verdict, plan.scale):
        print(line)
    print(f"  wrote {', '.join(map(str, [plan.out / 'run.log', *rec.written]))}")
    return rec.verdict.exit_code


def run(args: argparse.Namespace) -> int:
    from .. import busrun

    c_flag, c_ids = c_agent_choice(args)
    if c_flag:
        kw = busrun.BusOptions(args.interface, args.channel, args.bus_config).resolved()
        if kw["interface"] != "socketcan" or not kw.get("channel"):
            raise ParameterError(c_flag, "--interface socketcan with a --channel (the C agent "
                                 "is a Linux SocketCAN program: vcan0, can0, ...)",
                                 f"{kw['interface']} {kw.get('channel') or ''}".strip())
    plan = plan_run(args, "up", "{n} agents + plant + router")
    c_agents: frozenset[int] = frozenset()
    c_node = None
    if c_flag:
        c_agents = frozenset(range(1, plan.sc.n + 1)) if c_ids is None else c_ids
        if max(c_agents) > plan.sc.n:
            raise ParameterError("--c-agents", f"agents of this run (1..{plan.sc.n})",
                                 args.c_agents)
        c_node = c_node_program(c_flag)
        print(f"  agents in C: {', '.join(map(str, sorted(c_agents)))} ({c_node.name})")
    rec = busrun.record(plan.sc, plan.out, plan.bus, duration=plan.duration,
                        plot=not args.no_plot, time_scale=plan.scale, keys=args.keys,
                        insecure=args.insecure, c_agents=c_agents, c_node=c_node,
                        tolerance=args.tolerance,
                        extra={"plant": ["--obey-inconsistent"]} if args.obey_inconsistent
                        else None)
    return print_report(plan, rec)


def c_agent_choice(args: argparse.Namespace) -> tuple[str | None, frozenset[int] | None]:
    """Which flag asks for C agents (None: none), and which agents (None: every one)."""
    if args.c_agents is not None:
        try:
            ids = frozenset(int(x) for x in args.c_agents.split(","))
        except ValueError:
            ids = frozenset()
        if not ids or min(ids) < 1:
            raise ParameterError("--c-agents", "agent ids like 3,5", args.c_agents)
        return "--c-agents", ids
    return ("--agent-impl c", None) if args.agent_impl == "c" else (None, None)


def c_node_program(flag: str) -> Path:
    """firmware_c's bessded-agent, built on first use (an error names the cause)."""
    from ..cagent import node_program
    from ..cimpl import CBuildError

    try:
        return node_program()
    except (CBuildError, OSError) as e:
        first = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        raise ParameterError(flag, "firmware_c to build (make, a C compiler, libmbedtls-dev: "
                             "tools/install-c-deps)", first) from None


def check_key_set(keys: Path, n: int, sc: Scenario | None = None) -> str:
    """Load every key file a fleet of ``n`` agents needs from ``keys`` before anything
    starts, and check what a node would refuse at its start: permissions (the directory's
    too), format, one fleet, a boot counter left to start with, and the keys of the peers
    it receives from (with ``sc``, whose graph says who that is), so a bad set is exit 2
    here, never a node refusing its file mid-start; the fleet id."""
    import stat

    from firmware_py import secoc

    from .keys import peers_of

    if not keys.is_dir():
        raise ParameterError("--keys", "a key set directory (bess-ded keys --fleet ... --out "
                             "DIR)", str(keys))
    mode = stat.S_IMODE(keys.stat().st_mode)
    if mode & 0o077:
        raise ParameterError("--keys", f"a directory only its owner may access (chmod 700 "
                             f"{keys})", f"{keys} with mode {mode:04o}")
    fleets = set()
    loaded = {}
    for node in secoc.fleet_nodes(n):
        path = keys / f"{node}.key"
        if not path.exists() and not path.is_symlink():
            raise ParameterError("--keys", f"a key set with {node}.key (bess-ded keys --fleet "
                                 f"... --out {keys})", str(keys))
        k = loaded[node] = secoc.load_node_key(path)
        if k.node != node:
            raise ParameterError("--keys", f"{node}.key to hold the key of {node}",
                                 f"the key of {k.node}")
        if k.boot_counter >= secoc.DEFAULT_LAYOUT.max_boot:
            raise ParameterError("--keys", f"{node}.key with a boot counter below "
                                 f"{secoc.DEFAULT_LAYOUT.max_boot} (each start uses the next; "
                                 "re-provision with bess-ded keys --fleet ... --force)",
                                 f"{k.boot_counter}, exhausted")
        fleets.add(k.fleet_id)
    if len(fleets) != 1:
        raise ParameterError("--keys", "key files of one fleet", f"fleet ids {sorted(fleets)}")
    sc_peers = peers_of(sc) if sc is not None else {}
    for node, k in loaded.items():
        if missing := [p for p in sc_peers.get(node, []) if p not in k.peers]:
            raise ParameterError("--keys", f"{node}.key with the keys of the nodes it receives "
                                 f"from ({', '.join(sc_peers[node])})",
                                 f"none for {', '.join(missing)}")
    return fleets.pop()


def pick_variant(sc: Scenario, label: str | None, command: str = "up"
                 ) -> tuple[Scenario, str]:
    """The scenario to run and how to name the choice in the banner."""
    if not sc.variants:
        if label is not None:
            raise ConfigError(sc.source, "variant", f"expected no --variant: {sc.name} has "
                              f"no variants, but got {label!r}")
        return sc, ""
    labels = [v.label for v in sc.variants]
    if label is None:
        print(f"bess-ded {command}: {sc.name} has variants {', '.join(labels)}; running the first, "
              f"{labels[0]!r} (choose one with --variant)")
        label = labels[0]
    run = sc.variant(label)  # ignores case: name the label as the scenario spells it
    if label not in labels:
        label = next(x for x in labels if x.casefold() == label.casefold())
    return run, f" [variant {label}]"
