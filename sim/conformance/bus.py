"""A conformance check of an agent node on the bus: what ``bess-ded conformance`` runs
(docs/api.md, docs/conformance.md). The device under test (DUT) takes agent I's place;
the tester plays the rest of the bus for it along sim.conformance's schedule, and
firmware_py's agent runtime, fed the same frames, is the oracle.

Three steps, so that a caller can start the device in between and show progress:

* ``prepare_conformance``: the DUT's configuration and key file in ``out``, the
  tester's frames; announces the run and the command that starts the device;
* ``ConformanceSetup.drive``: waits for the device's Diag frame, plays the schedule
  (a TimeoutError when the device is not heard);
* ``ConformanceSetup.judge``: writes out/conformance.log, checks the device's frames
  against the oracle; ``write_report`` writes out/conformance.json (and JUnit XML).
"""

from __future__ import annotations

import json
import os
import shlex
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

from firmware_py.errors import ParameterError
from firmware_py.nodeargs import fd_argv

if TYPE_CHECKING:
    from firmware_py.config import AgentConfig
    from firmware_py.frames import FrameCodec
    from firmware_py.secoc import Keyring
    from sim.conformance import Frame, Outcome, Planned, Result
    from sim.model.scenario import Scenario
    from sim.run.busrun import BusOptions


@dataclass
class ConformanceSetup:
    """A conformance run ready to start: the DUT's configuration, keys and bus."""

    sc: Scenario          # variant chosen, time scale applied
    dut: int              # the agent the device replaces
    cfg: AgentConfig      # its configuration (written to out/agents/agent_I.toml)
    ring: Keyring         # its keyring, as the oracle's
    dut_key: bytes
    bus: BusOptions
    out: Path
    planned: list[Planned]
    quick: bool = False   # --quick: the steps of sim.conformance.schedule.QUICK only
    config_text: str | None = None  # the configuration file written (cfg: its reading)

    @property
    def node(self) -> str:
        """The DUT's node label, e.g. "agent_2"."""
        return f"agent_{self.dut}"

    @cached_property
    def codec(self) -> FrameCodec:
        """The bus's codec: the DBC of the scenario's frame format (``[bus] fd``, --fd);
        built once (a DBC load)."""
        from dbc import dbc_path
        from firmware_py.frames import FrameCodec

        return FrameCodec(dbc_path(self.sc.fd, self.sc.lambda_tags))

    def drive(self, wait: float, rt_priority: int = 0,
              progress: Callable[[str], None] | None = None) -> tuple[list[Frame], float]:
        """Wait up to ``wait`` s for the device's Diag frame, then play the schedule (under
        SCHED_FIFO ``rt_priority``, if given): the frames on the bus and how late the
        tester sent any of its own (s). A TimeoutError if the device is not heard."""
        from firmware_py import contract
        from firmware_py.frames import diag_name, mc_name, setpoint_name
        from firmware_py.node import open_bus
        from firmware_py.nodeargs import set_realtime
        from sim import conformance as conf
        from sim.run import busrun

        codec = self.codec
        i = self.dut
        dut_ids = {codec.frame_id(n(i)) for n in (mc_name, setpoint_name, diag_name)}
        dut_ids |= {contract.SYNC_OF[codec.frame_id(n(i))] for n in (mc_name, setpoint_name,
                                                                     diag_name)}
        with open_bus(busrun.RECORDER_RCVBUF,  # the tester reads while the DUT may starve it
                      **{**self.bus.resolved(), "receive_own_messages": False}) as b:
            if rt_priority:
                set_realtime(rt_priority)
            try:
                return conf.drive(b, self.planned, dut_ids, codec.frame_id(diag_name(i)),
                                  wait, self.cfg.controller.ts, progress=progress)
            finally:
                if rt_priority:  # the verdict is no real-time work
                    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))

    def judge(self, frames: Sequence[Frame], late: float,
              say: Callable[[str], None] = print) -> tuple[Outcome, list[Result]]:
        """Write out/conformance.log and check the device's ``frames`` against firmware_py
        (``say`` announces the check): the outcome and the verdict per requirement."""
        import can

        from sim import conformance as conf

        with can.Logger(str(self.out / "conformance.log")) as log:
            for f in frames:
                log.on_message_received(can.Message(
                    timestamp=f.t, arbitration_id=f.msg.arbitration_id,
                    is_extended_id=f.msg.is_extended_id, data=bytes(f.msg.data),
                    dlc=len(f.msg.data), is_fd=f.msg.is_fd,
                    bitrate_switch=f.msg.bitrate_switch))
        say(f"  the tester sent each frame at most {late * 1000:.1f} ms late; checking the "
            f"device's frames against firmware_py ...")
        codec = self.codec
        ts = self.cfg.controller.ts
        # firmware_py's agent filters on SocketCAN (GEN-5): model that first there
        outcome = conf.check(self.cfg, self.ring, self.dut_key, frames, codec,
                             filtered_first=self.bus.resolved()["interface"] == "socketcan")
        conf.explain(self.cfg, self.ring, self.dut_key, frames, outcome, codec,
                     config_text=self.config_text)
        if outcome.mismatches and late > ts:
            outcome.problems.append(
                f"the tester was up to {late * 1000:.0f} ms late (Ts = {ts * 1000:g} ms): on "
                "a host this busy the device may have timed out on frames the tester thought "
                "in time; rerun with --rt-priority N (and the device too) or --time-scale F")
        played = conf.played_steps(self.planned) if self.quick else None
        return outcome, conf.verdict(outcome, played=played)


def prepare_conformance(case: str, dut: str, *, variant: str | None = None,
                        bus: BusOptions | None = None, time_scale: float | None = None,
                        out: Path | None = None, keys: Path | None = None,
                        insecure: bool = False, rt_priority: int = 0,
                        wait: float = 60.0, say: Callable[[str], None] = print,
                        quick: bool = False, fd: bool = False,
                        no_lambda_tags: bool = False,
                        resilient_f: int | None = None,
                        price_persist: int | None = None,
                        signed_price: bool = False,
                        event_transmit: bool = False) -> ConformanceSetup:
    """Set up a conformance run of scenario ``case`` with the device in agent ``dut``'s
    place ("1".."N") on ``bus`` (one that connects processes): its configuration and
    key file (from ``keys``, a fresh set in ``out``/keys, or ``insecure``) in ``out``
    (default runs/conformance-<scenario>-agent<I>). ``say`` announces the run and the
    command that starts the device (at ``rt_priority``, and the ``wait`` it has).
    ``quick``: play the steps of ``QUICK`` only (the others' requirements "not run");
    ``fd``: on a CAN FD bus (as the scenario's ``[bus] fd``): every frame of the tester
    and of the device an FD frame with the bit-rate switch (GEN-1); ``no_lambda_tags``:
    λ under its sender's node key there, not a tag per receiver (AUTH-34);
    ``resilient_f``: the device's resilient_f (default: the scenario's), judged on WMSR-1/2;
    ``price_persist``: the device's (default ``PRICE_PERSIST``; 1: judged on PRICE-5);
    ``signed_price``: the router's price signed (as the scenario's ``[security]
    signed_price``): the tester signs every price it plays, the device's key file holds
    the router's public key; judged on AUTH-31..33; ``event_transmit``: the device sends
    its MC frame event-triggered (``[transmit] mode = "event"``), judged on TX-7, CFG-9."""
    from dbc import dbc_path
    from firmware_py import pricesig, secoc
    from firmware_py.config import agent_configs_from_scenario
    from firmware_py.frames import FrameCodec, diag_name
    from sim import conformance as conf
    from sim.model.scenario import scaled
    from sim.model.scenario_select import pick_variant, resolve_scenario, with_fd
    from sim.run import busrun
    from sim.run.busopts import c_node_bus_argv
    from sim.run.fleet_plan import GUEST_TIME_SCALE, IN_PROCESS_INTERFACES
    from sim.run.keyset import check_key_set, load_key_set

    sc, chosen = pick_variant(resolve_scenario(case), variant, "conformance", say)
    if not (dut.isdigit() and 1 <= int(dut) <= sc.n):
        raise ParameterError("--dut", f"an agent number in 1..{sc.n}", dut)
    i = int(dut)
    bus = bus or busrun.BusOptions()
    kw = bus.resolved()
    if kw["interface"] in IN_PROCESS_INTERFACES:
        raise ParameterError("--interface", "a bus that connects processes (udp_multicast, "
                             "socketcan, ...): the device under test is another process",
                             kw["interface"])
    scale = time_scale
    if scale is None:
        scale = GUEST_TIME_SCALE if os.environ.get("VCAN_RUN_GUEST") == "1" else 1.0
    sc = scaled(with_fd(sc, fd, no_lambda_tags), scale)
    if signed_price:
        sc = replace(sc, signed_price=True)
    if sc.signed_price and insecure:  # the public keys have no signing key of the router
        raise ParameterError("--insecure", "a key set with the router's price key for a "
                             "signed price (--signed-price, [security] signed_price)",
                             "--insecure")
    # the scenario's agent with every key the schedule observes off its default
    # (conf.conformance_config): the DUT reads the file, the oracle reads it too, with
    # the reference parser (a device that misreads it fails a CFG-n requirement)
    agent = agent_configs_from_scenario(sc)[i - 1]
    if resilient_f is not None:  # --resilient F: the device runs the resilient update
        agent = replace(agent, resilient_f=resilient_f)
    if event_transmit:  # its threshold and heartbeat: conformance_config's
        agent = replace(agent, transmit=replace(agent.transmit, mode="event"))
    text, cfg = conf.written_config(agent, price_persist or conf.PRICE_PERSIST)
    out = out or Path("runs") / f"conformance-{sc.name}-agent{i}"
    node = f"agent_{i}"
    (out / "agents").mkdir(parents=True, exist_ok=True)
    cfg_path = out / "agents" / f"{node}.toml"
    cfg_path.write_text(text)
    tester_keys: dict[str, bytes] | None
    if insecure:
        tester_keys = None
        ring = secoc.Keyring.insecure_for(node)
        dut_key = ring.key
        key_argv = ["--insecure"]
    else:
        key_dir = keys
        if key_dir is None:
            key_dir = busrun.provision_keys(sc, out / "keys")
            # a key file that has seen starts before: the device starts at boot
            # FILED_BOOT + 1, which its syncs show (AUTH-3; a fresh file's 0 + 1 leaves
            # a device that keeps the file's counter no boot to send)
            secoc.save_boot_counter(key_dir / f"{node}.key", conf.FILED_BOOT)
        else:
            check_key_set(key_dir, sc.n, sc)
        tester_keys = load_key_set(key_dir)
        if sc.signed_price:  # the tester signs the price as the router does (AUTH-32)
            sign = secoc.load_node_key(key_dir / "router.key").price_sign
            # check_key_set and provision_keys refuse a signed set without it
            assert sign is not None, "a signed_price key set without the router's seed"
            tester_keys[pricesig.TESTER_SIGN] = sign
        own = secoc.load_node_key(key_dir / f"{node}.key")
        ring = secoc.Keyring(node, own.key, own.boot_counter, lambda _b: None,
                             peers=own.peers, fleet=own.fleet_id, floors=own.floors,
                             frames=own.frames, commands=own.commands, tags=own.tags,
                             price_verify=own.price_verify)
        dut_key = own.key
        key_argv = ["--key", str(key_dir / f"{node}.key")]
    bus, port = busrun.private_port(bus)
    ts = cfg.controller.ts
    # the tester plays every sender at a boot the DUT's floors accept (AUTH-21)
    boot = max([secoc.INSECURE_BOOT, *ring.floors.values()])
    # a classic SocketCAN bus (vcan0 at the classic MTU) carries no FD frame: RX-2's
    # frame of the other format is left out there
    planned = conf.plan(cfg, tester_keys, sc.prices[0].rho, boot=boot, quick=quick,
                        codec=FrameCodec(dbc_path(sc.fd, sc.lambda_tags)),
                        other_format=bus.resolved()["interface"] != "socketcan")
    played = conf.played_steps(planned)
    length = played[-1].end * ts
    say(f"bess-ded conformance: {sc.title or sc.name}{chosen}, device under test: {node} "
        f"(Ts = {ts * 1000:g} ms{f', time scale {scale:g}' if scale != 1 else ''}); the "
        f"schedule takes {length:.1f} s"
        + (f" (a quick run: steps {played[0].name} to {played[-1].name} of "
           f"{conf.STEPS[-1].end * ts:.1f} s)" if quick else ""))
    say(f"  bus: {bus.resolved()}" + (f" (port {port} private to this run)" if port else "")
        + (", CAN FD frames" if sc.fd else ""))
    # the device at the tester's --rt-priority, else as `up` runs its nodes (SCHED_FIFO)
    rt = ["--rt-priority", str(rt_priority or busrun.RT_PRIORITY)]

    def device(program: list[str], bus_argv: list[str]) -> str:
        """The command line that starts ``program`` as the device on this run's bus."""
        return shlex.join([*program, "--config", str(cfg_path), *key_argv, *bus_argv,
                           *fd_argv(sc.fd, sc.lambda_tags), *rt])

    say("  start the device with its configuration and key, e.g.: "
        + device(["bess-ded", "agent"], bus.argv()))
    c_bus = c_node_bus_argv(bus)
    if c_bus is not None:  # the same device as firmware_c's node program takes it
        say("  or firmware_c's node program (firmware_c/build/bessded-agent): "
            + device(["bessded-agent"], c_bus))
    say(f"  waiting up to {wait:g} s for its {diag_name(i)} frame ...")
    return ConformanceSetup(sc, i, cfg, ring, dut_key, bus, out, planned, quick, text)


def write_report(outcome: Outcome, results: Sequence[Result], out: Path,
                 junit_path: Path | None, name: str) -> tuple[bool, list[Path]]:
    """Write out/conformance.json (and JUnit XML to ``junit_path``): whether the device
    passed (every requirement, no problem with the run) and the files written."""
    from sim import conformance as conf

    failed = [r.must for r in results if r.failed]
    ok = not failed and not outcome.problems
    doc: dict[str, Any] = {
        "passed": ok, "quick": any(r.not_run for r in results),
        "not_run": [r.must for r in results if r.not_run],
        "ticks": outcome.ticks, "problems": outcome.problems,
        "filtered": outcome.filtered,
        "explained_by": outcome.explained_by,
        # the requirements only another run judges (ONLY_ON), by what that run is
        "judged_on_other_runs": conf.other_runs(outcome),
        "results": [{"requirement": r.must, "passed": r.passed, "not_run": r.not_run,
                     "detail": r.detail}
                    for r in results],
        "mismatches": [str(m) for m in outcome.mismatches],
        "auth_errors": outcome.auth_errors,
        "format_errors": [what for _, what in outcome.format_errors]}
    (out / "conformance.json").write_text(json.dumps(doc, indent=1, ensure_ascii=False))
    written = [out / "conformance.log", out / "conformance.json"]
    if junit_path is not None:
        conf.junit(results, junit_path, name)
        written.append(junit_path)
    return ok, written


def report(outcome: Outcome, results: list[Result], out: Path, junit_path: Path | None,
           name: str) -> int:
    """Print the verdict per requirement, write OUT/conformance.json (and --junit)."""
    from sim.conformance import other_runs

    for problem in outcome.problems:
        print(f"  problem with the run: {problem}")
    if outcome.filtered:
        print("  the device filters foreign IDs (GEN-5): judged as receiving its inputs only")
    for r in results:
        mark = "NOT RUN" if r.not_run else "PASS" if r.passed else "FAIL"
        print(f"  {mark}  {r.must:<9} {r.detail}")
    for what, musts in other_runs(outcome).items():  # ONLY_ON: judged by another run
        print(f"  not judged on this run: {', '.join(musts)} ({what})")
    failed = [r.must for r in results if r.failed]
    not_run = [r.must for r in results if r.not_run]
    ok = not failed and not outcome.problems
    run = len(results) - len(not_run)
    print(f"bess-ded conformance: {'PASS' if ok else 'FAIL'}"
          + (" (a quick run)" if not_run else "")
          + f": {run - len(failed)} of {run} requirements passed over {outcome.ticks} "
          f"ticks of the device" + (f"; failed: {', '.join(failed)}" if failed else "")
          + (f"; {len(not_run)} not run (--quick): run without --quick to accept a device"
             if not_run else ""))
    ok, written = write_report(outcome, results, out, junit_path, name)
    print(f"  wrote {', '.join(map(str, written))}")
    return 0 if ok else 1
