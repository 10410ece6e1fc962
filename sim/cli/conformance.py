"""`bess-ded conformance --case N --dut I`: prove an agent node conformant on the bus.

The device under test (DUT) takes agent I's place: its configuration is the scenario's
agent I (written to OUT/agents/agent_I.toml) and its key file OUT/keys/agent_I.key
(a fresh key set, unless --keys DIR or --insecure). Start the device with them on the
same bus; this command waits for its Diag frame (--wait S), then plays the rest of the
bus for it: the router's price and commands, its plant's status and its neighbours' MC
frames, along a fixed schedule of about 9 s at Ts = 10 ms (stretched by --time-scale):
start-up, control with moving neighbours, forged and replayed frames, malformed and
implausible content, every command, and every timeout (sim/conformance.py).

firmware_py's agent runtime, fed the same frames at the times they were sent, is the
oracle: every frame of the device must carry the same signals (MC, Setpoint, Diag) and
a MAC that verifies at consecutive freshness values. It prints PASS or FAIL for each
requirement of docs/firmware-spec.md the schedule exercises, names the requirement a
known deviation violates (e.g. BAND-2: the reset band re-armed at the reset sample),
and writes OUT/conformance.log (candump), OUT/conformance.json and, with --junit FILE,
JUnit XML for CI. Exit codes:

  0    every requirement passed     1  a requirement failed, or the device was not heard
  2    bad input                    130 interrupted
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_py.errors import ParameterError

if TYPE_CHECKING:
    from ..conformance import Outcome, Result


def register(sub: argparse._SubParsersAction) -> None:
    from firmware_py.cliargs import duration_s, time_scale
    from firmware_py.nodeargs import add_bus_arguments, add_rt_argument

    from ._common import add_case_option, one_line_errors

    p = one_line_errors(sub.add_parser(
        "conformance", help="prove an agent node conformant: the rest of the bus, "
        "firmware_py as the oracle, pass/fail per requirement",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter))
    add_case_option(p)
    p.add_argument("--variant", metavar="LABEL", help="for a scenario with variants")
    p.add_argument("--dut", required=True, metavar="I", help="the agent the device replaces")
    add_bus_arguments(p)
    p.add_argument("--time-scale", type=time_scale, metavar="F",
                   help="the device runs Ts·F, k/F, h/F² (its configuration says so); "
                        "default 1, or 5 under tools/vcan-run")
    p.add_argument("--out", type=Path, help="output directory (default: "
                   "runs/conformance-<scenario>-agent<I>)")
    p.add_argument("--wait", type=duration_s(), default=60.0, metavar="S",
                   help="how long to wait for the device (default: 60 s)")
    p.add_argument("--junit", type=Path, metavar="FILE", help="write JUnit XML here")
    add_rt_argument(p)
    k = p.add_mutually_exclusive_group()
    k.add_argument("--keys", type=Path, metavar="DIR",
                   help="the fleet's key set (bess-ded keys --fleet); default: a fresh one "
                        "in OUT/keys")
    k.add_argument("--insecure", action="store_true",
                   help="the device runs --insecure (the public demo keys)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import can

    from firmware_py import contract, secoc
    from firmware_py.config import agent_configs_from_scenario
    from firmware_py.frames import FrameCodec, diag_name, mc_name, setpoint_name
    from firmware_py.node import open_bus
    from firmware_py.nodeargs import set_realtime

    from .. import busrun
    from .. import conformance as conf
    from ..scenario import scaled
    from ._common import resolve_scenario
    from .keys import load_key_set
    from .up import GUEST_TIME_SCALE, IN_PROCESS_INTERFACES, check_key_set, pick_variant

    sc, chosen = pick_variant(resolve_scenario(args.case), args.variant, "conformance")
    if not (args.dut.isdigit() and 1 <= int(args.dut) <= sc.n):
        raise ParameterError("--dut", f"an agent number in 1..{sc.n}", args.dut)
    i = int(args.dut)
    bus = busrun.BusOptions(args.interface, args.channel, args.bus_config)
    kw = bus.resolved()
    if kw["interface"] in IN_PROCESS_INTERFACES:
        raise ParameterError("--interface", "a bus that connects processes (udp_multicast, "
                             "socketcan, ...): the device under test is another process",
                             kw["interface"])
    scale = args.time_scale
    if scale is None:
        scale = GUEST_TIME_SCALE if os.environ.get("VCAN_RUN_GUEST") == "1" else 1.0
    sc = scaled(sc, scale)
    cfg = agent_configs_from_scenario(sc)[i - 1]
    out = args.out or Path("runs") / f"conformance-{sc.name}-agent{i}"
    node = f"agent_{i}"
    (out / "agents").mkdir(parents=True, exist_ok=True)
    cfg_path = out / "agents" / f"{node}.toml"
    cfg_path.write_text(cfg.to_toml())
    if args.insecure:
        keys = None
        ring = secoc.Keyring.insecure_for(node)
        dut_key = ring.key
        key_argv = ["--insecure"]
    else:
        key_dir = args.keys
        if key_dir is None:
            key_dir = busrun.provision_keys(sc, out / "keys")
        else:
            check_key_set(key_dir, sc.n, sc)
        keys = load_key_set(key_dir)
        own = secoc.load_node_key(key_dir / f"{node}.key")
        ring = secoc.Keyring(node, own.key, own.boot_counter, lambda _b: None,
                             peers=own.peers, fleet=own.fleet_id, floors=own.floors)
        dut_key = own.key
        key_argv = ["--key", str(key_dir / f"{node}.key")]
    bus, port = busrun.private_port(bus)
    ts = cfg.controller.ts
    # the tester plays every sender at a boot the DUT's floors accept (AUTH-21)
    boot = max([secoc.INSECURE_BOOT, *ring.floors.values()])
    planned = conf.plan(cfg, keys, sc.prices[0].rho, boot=boot)
    length = conf.STEPS[-1].end * ts
    print(f"bess-ded conformance: {sc.title or sc.name}{chosen}, device under test: {node} "
          f"(Ts = {ts * 1000:g} ms{f', time scale {scale:g}' if scale != 1 else ''}); the "
          f"schedule takes {length:.1f} s")
    print(f"  bus: {bus.resolved()}" + (f" (port {port} private to this run)" if port else ""))
    # the device at the tester's --rt-priority, else as `up` runs its nodes (SCHED_FIFO)
    rt = ["--rt-priority", str(args.rt_priority or busrun.RT_PRIORITY)]
    cmd = ["bess-ded", "agent", "--config", str(cfg_path), *key_argv, *bus.argv(), *rt]
    print(f"  start the device with its configuration and key, e.g.: {shlex.join(cmd)}")
    print(f"  waiting up to {args.wait:g} s for its {diag_name(i)} frame ...", flush=True)

    codec = FrameCodec()
    dut_ids = {codec.frame_id(n(i)) for n in (mc_name, setpoint_name, diag_name)}
    dut_ids |= {contract.SYNC_OF[codec.frame_id(n(i))] for n in (mc_name, setpoint_name,
                                                                 diag_name)}
    with open_bus(**{**bus.resolved(), "receive_own_messages": False}) as b:
        busrun.enlarge_receive_buffer(b)
        if args.rt_priority:
            set_realtime(args.rt_priority)
        try:
            frames, late = conf.drive(b, planned, dut_ids, codec.frame_id(diag_name(i)),
                                      args.wait, ts, progress=_progress)
        except TimeoutError as e:
            print(f"\nbess-ded conformance: FAIL: {e}: is the device running on this bus "
                  "with the configuration above?", file=sys.stderr)
            return 1
        finally:
            if args.rt_priority:  # the verdict is no real-time work
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    if sys.stdout.isatty():
        print()
    with can.Logger(str(out / "conformance.log")) as log:
        for f in frames:
            log.on_message_received(can.Message(
                timestamp=f.t, arbitration_id=f.msg.arbitration_id,
                is_extended_id=f.msg.is_extended_id, data=bytes(f.msg.data),
                dlc=len(f.msg.data)))
    print(f"  the tester sent each frame at most {late * 1000:.1f} ms late; checking the "
          f"device's frames against firmware_py ...", flush=True)
    # firmware_py's agent filters on SocketCAN (GEN-5): model that first there
    outcome = conf.check(cfg, ring, dut_key, frames, codec,
                         filtered_first=kw["interface"] == "socketcan")
    conf.explain(cfg, ring, dut_key, frames, outcome, codec)
    if outcome.mismatches and late > ts:
        outcome.problems.append(
            f"the tester was up to {late * 1000:.0f} ms late (Ts = {ts * 1000:g} ms): on a "
            "host this busy the device may have timed out on frames the tester thought "
            "in time; rerun with --rt-priority N (and the device too) or --time-scale F")
    results = conf.verdict(outcome)
    return report(outcome, results, out, args.junit, f"conformance {sc.name} {node}")


def _progress(line: str) -> None:
    if sys.stdout.isatty():
        print(f"\r  {line:<60}", end="", flush=True)
    else:
        print(f"  {line}", flush=True)


def report(outcome: Outcome, results: list[Result], out: Path, junit_path: Path | None,
           name: str) -> int:
    """Print the verdict per requirement, write OUT/conformance.json (and --junit)."""
    from .. import conformance as conf

    for problem in outcome.problems:
        print(f"  problem with the run: {problem}")
    if outcome.filtered:
        print("  the device filters foreign IDs in its CAN controller (GEN-5): it was judged "
              "as receiving only its own and its input IDs")
    for r in results:
        print(f"  {'PASS' if r.passed else 'FAIL'}  {r.must:<9} {r.detail}")
    failed = [r.must for r in results if not r.passed]
    ok = not failed and not outcome.problems
    print(f"bess-ded conformance: {'PASS' if ok else 'FAIL'}: {len(results) - len(failed)} of "
          f"{len(results)} requirements passed over {outcome.ticks} ticks of the device"
          + (f"; failed: {', '.join(failed)}" if failed else ""))
    doc = {"passed": ok, "ticks": outcome.ticks, "problems": outcome.problems,
           "filtered": outcome.filtered,
           "explained_by": outcome.explained_by,
           "results": [{"requirement": r.must, "passed": r.passed, "detail": r.detail}
                       for r in results],
           "mismatches": [str(m) for m in outcome.mismatches],
           "auth_errors": outcome.auth_errors}
    (out / "conformance.json").write_text(json.dumps(doc, indent=1, ensure_ascii=False))
    written = [out / "conformance.log", out / "conformance.json"]
    if junit_path is not None:
        conf.junit(results, junit_path, name)
        written.append(junit_path)
    print(f"  wrote {', '.join(map(str, written))}")
    return 0 if ok else 1
