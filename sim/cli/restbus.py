"""`bess-ded restbus --case N --dut I`: the rest of the bus for a device under test.

Runs a scenario's fleet as `bess-ded up` does, except one node, agent I (`--dut 3`) or
the plant (`--dut plant`), whose place a device under test takes on the same bus: a
third-party agent on can0 in a HIL rig, a C build on vcan0, a firmware_py agent started
by hand. Before any node starts it writes what the device needs: its configuration
(OUT/agents/agent_I.toml: neighbours, gains, limits) and its key file (OUT/keys/<node>.key,
unless --keys DIR or --insecure). It then starts the other nodes, waits until the
device is heard (its MC and setpoint frames, or the plant's status frames; --wait S),
starts the router (t = 0 of the price schedule), and reports the run as `up` does:
metrics, anomalies and verdict over the whole fleet, the device's frames included.

  0    converged, no anomaly       1  not converged       2  bad input
  3    converged with anomalies    130 interrupted
"""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from firmware_py.errors import ParameterError


def register(sub: argparse._SubParsersAction) -> None:
    from firmware_py.cliargs import duration_s

    from ._common import one_line_errors
    from .fleetopts import add_run_arguments

    p = one_line_errors(sub.add_parser(
        "restbus", help="run the fleet but one node, for a device under test on the bus",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter))
    add_run_arguments(p)
    p.add_argument("--dut", required=True, metavar="I|plant",
                   help="the node the device under test replaces: an agent number, or "
                        "'plant' (real choppers)")
    p.add_argument("--wait", type=duration_s(), default=60.0, metavar="S",
                   help="how long to wait for the device before giving up (default: 60 s)")
    p.set_defaults(func=run)


def dut_node(spec: str, n: int) -> str:
    """'plant' or 'agent_<i>' for --dut, checked against the fleet size."""
    if spec == "plant":
        return "plant"
    if spec.isdigit() and 1 <= int(spec) <= n:
        return f"agent_{int(spec)}"
    raise ParameterError("--dut", f"an agent number in 1..{n} or 'plant'", spec)


def run(args: argparse.Namespace) -> int:
    from sim.run import busrun

    from .fleetopts import plan_run, print_report

    plan = plan_run(args, "restbus", "{n} agents + plant + router, but the device under test")
    dut = dut_node(args.dut, plan.sc.n)

    def tell(key_dir: Path | None) -> None:
        if dut == "plant":
            cmd = ["bess-ded", "plant", "--case", str(plan.out / "scenario.toml"),
                   "--period", repr(plan.sc.ts)]
        else:
            cmd = ["bess-ded", "agent", "--config", str(plan.out / "agents" / f"{dut}.toml")]
        cmd += ["--insecure"] if key_dir is None else ["--key", str(key_dir / f"{dut}.key")]
        # the fleet's nodes run at this SCHED_FIFO priority; a device without it misses
        # deadlines on a busy host (needs root or CAP_SYS_NICE, else the node warns)
        cmd += ["--rt-priority", str(busrun.RT_PRIORITY)]
        print(f"  device under test: {dut}, waited for up to {args.wait:g} s; e.g. "
              f"{shlex.join(cmd + plan.bus.argv())}", flush=True)

    rec = busrun.record(plan.sc, plan.out, plan.bus, duration=plan.duration,
                        plot=not args.no_plot, time_scale=plan.scale, keys=args.keys,
                        insecure=args.insecure, dut=dut, dut_wait_s=args.wait, on_ready=tell,
                        tolerance=args.tolerance)
    return print_report(plan, rec)
