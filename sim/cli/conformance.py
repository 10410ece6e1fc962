"""`bess-ded conformance --case N --dut I`: prove an agent node conformant on the bus.

The device under test (DUT) takes agent I's place: its configuration is the scenario's
agent I (written to OUT/agents/agent_I.toml) and its key file OUT/keys/agent_I.key
(a fresh key set, unless --keys DIR or --insecure). Start the device with them on the
same bus; this command waits for its Diag frame (--wait S), then plays the rest of the
bus for it: the router's price and commands, its plant's status and its neighbours' MC
frames, along a fixed schedule of 16.2 s at Ts = 10 ms (stretched by --time-scale):
start-up, control with moving neighbours, forged and replayed frames, malformed and
implausible content, every command, and every timeout (sim/conformance/).

firmware_py's agent runtime, fed the same frames at the times they were sent, is the
oracle: every frame of the device must carry the same signals (MC, Setpoint, Diag) and
a MAC that verifies at consecutive freshness values. It prints PASS or FAIL for each
requirement of docs/firmware-spec.md the schedule exercises (the first difference's
first) and writes OUT/conformance.log, OUT/conformance.json and JUnit XML (--junit FILE).

The tester writes the scenario's agent with every key the schedule observes off its
default (timeouts, limits, gains, band, weights; fixed-point values rounding up): a device
that misreads its file fails, named CFG-3, 4, 6 or 7 by a known misreading explaining it.
--resilient F, --price-persist 1, --signed-price, --event-transmit, --insecure, --fd, a
dwell device, case 2's variants PC and finite-time: more requirements
(docs/conformance.md).

--quick plays the first steps only (start to commands: 7.1 of 16.2 s at Ts = 10 ms),
for development: the later steps' requirements are NOT RUN (JUnit: skipped), never
passed, and the verdict says it was a quick run. Exit codes:

  0    every requirement run passed (--quick: of the steps played; no acceptance)
  1    a requirement failed, or the device was not heard
  2    bad input                    130 interrupted
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from firmware_py.cliargs import duration_s, int_in, time_scale
    from firmware_py.config import RESILIENT_F_MAX as F_MAX
    from firmware_py.nodeargs import add_bus_arguments, add_rt_argument
    from sim.conformance import PRICE_PERSIST as PERSIST

    from ._common import add_case_option, one_line_errors

    p = one_line_errors(sub.add_parser(
        "conformance", help="prove an agent node conformant: the rest of the bus, "
        "firmware_py as the oracle, pass/fail per requirement",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter))
    add_case_option(p)
    p.add_argument("--variant", metavar="LABEL", help="for a scenario with variants")
    p.add_argument("--dut", required=True, metavar="I", help="the agent the device replaces")
    add_bus_arguments(p)
    p.add_argument("--time-scale", type=time_scale, metavar="F", help="the device runs "
                   "Ts·F, k/F, h/F² (its file says so); default 1, or 5 under tools/vcan-run")
    p.add_argument("--out", type=Path, help="output directory (default: runs/conformance-"
                   "<scenario>-agent<I>)")
    p.add_argument("--wait", type=duration_s(), default=60.0, metavar="S", help="how long "
                   "to wait for the device (default: 60 s)")
    p.add_argument("--junit", type=Path, metavar="FILE", help="write JUnit XML here")
    p.add_argument("--fd", action="store_true",
                   help="a CAN FD bus: every frame FD with the bit-rate switch (the device "
                        "runs with --fd; default: the scenario's [bus] fd, else classic)")
    p.add_argument("--no-lambda-tags", action="store_true", help="with --fd: λ under its "
                   "sender's node key, not a tag per receiver (AUTH-34; the device's too)")
    p.add_argument("--resilient", type=int_in(1, F_MAX), metavar="F",
                   help="the device runs the resilient update (its resilient_f = F), judged "
                        "on WMSR-1/2 (default: the scenario's resilient_f)")
    p.add_argument("--price-persist", type=int_in(1, PERSIST), metavar="N", help="the "
                   f"device's price_persist (default {PERSIST}; 1: judged on PRICE-5)")
    p.add_argument("--signed-price", action="store_true", help="the price signed: AUTH-31..33")
    p.add_argument("--event-transmit", action="store_true", help="the device's MC frame "
                   "event-triggered ([transmit] mode = \"event\"): TX-7, CFG-9")
    p.add_argument("--quick", action="store_true",
                   help="play the first steps only (start to commands), for development: "
                        "the later steps' requirements are NOT RUN, never passed")
    add_rt_argument(p)
    k = p.add_mutually_exclusive_group()
    k.add_argument("--keys", type=Path, metavar="DIR", help="the fleet's key set (bess-ded "
                   "keys --fleet); default: a fresh one in OUT/keys")
    k.add_argument("--insecure", action="store_true", help="the device runs --insecure (the "
                   "public demo keys)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from sim.conformance.bus import prepare_conformance, report
    from sim.run import busrun

    setup = prepare_conformance(
        args.case, args.dut, variant=args.variant,
        bus=busrun.BusOptions(args.interface, args.channel, args.bus_config),
        time_scale=args.time_scale, out=args.out, keys=args.keys, insecure=args.insecure,
        rt_priority=args.rt_priority, wait=args.wait, say=_say, quick=args.quick,
        fd=args.fd, no_lambda_tags=args.no_lambda_tags, resilient_f=args.resilient,
        price_persist=args.price_persist, signed_price=args.signed_price,
        event_transmit=args.event_transmit)
    try:
        frames, late = setup.drive(args.wait, args.rt_priority, progress=_progress)
    except TimeoutError as e:
        print(f"\nbess-ded conformance: FAIL: {e}: is the device running on this bus "
              "with the configuration above?", file=sys.stderr)
        return 1
    if sys.stdout.isatty():
        print()
    outcome, results = setup.judge(frames, late, say=_say)
    return report(outcome, results, setup.out, args.junit,
                  f"conformance {setup.sc.name} {setup.node}")


def _say(line: str) -> None:
    print(line, flush=True)


def _progress(line: str) -> None:  # one line rewritten on a terminal, else a line each
    tty = sys.stdout.isatty()
    print(f"\r  {line:<60}" if tty else f"  {line}", end="" if tty else "\n", flush=True)
