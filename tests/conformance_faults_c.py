"""Single faults planted in firmware_c's agent, written from docs/firmware-spec.md: the
C half of issue 22's "Measure the suite on itself" (tests/conformance_faults.py is the
firmware_py half).

Each ``CFault`` is one plausible implementation slip against one requirement, written as
a source patch of firmware_c/src: ``(file, text, replacement)``, each text found exactly
once. ``library(fault)`` copies firmware_c to a build directory of its own, applies the
patch there and builds ``libbessded.so`` from the copy (firmware_c/Makefile, -Werror), so
the faulty code is never in the default sources, the default build or the golden vectors.
Libraries are cached beside the faultless one (``sim.cbind.cimpl.cache_dir()/faults``,
keyed by the sources' hash and the patch): a second run builds nothing.

The device under test is ``sim.cbind.cagent.CAgent`` on that library; the conformance
schedule drives it through ``sim.conformance.simulate``'s ``make_dut`` seam
(``make_dut(fault)``), judged as `bess-ded conformance` judges a device
(``conformance_faults.score``).

Every fault is a genuine deviation: its ``witness(runtime)`` is a short unit-level run (a
few frames and ticks through ``CRig``, ξ fed to the C controller, or one call of the C
function) whose output differs between the faulty library and the faultless one
(tests/test_conformance_faults_c.py checks each): none is an equivalent mutant.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import conformance_faults as cf

from firmware_py.config import AgentConfig, Neighbour
from firmware_py.contract import Command
from firmware_py.controllers import make_controller
from firmware_py.nodeio import FleetSender
from firmware_py.secoc import Keyring
from sim.cbind import cimpl
from sim.cbind.cagent import CAgent, Runtime, params_dict, parse_config
from sim.cbind.cagent import load as load_runtime

Patch = tuple[str, str, str]   # (file under firmware_c/src, text, replacement)


@dataclass(frozen=True)
class CFault:
    """One slip in firmware_c: ``name``, the requirement it breaks, what the faulty device
    does, the source ``patch``; ``group``: the issue's class of slips; ``witness(rt)``: a
    unit-level run's output on runtime ``rt`` (None: the faultless library)."""

    name: str
    requirement: str
    description: str
    patch: tuple[Patch, ...]
    group: str = ""
    witness: Callable[[Runtime | None], Any] | None = None

    @property
    def key(self) -> str:
        h = hashlib.sha256(repr((self.name, self.patch)).encode())
        return h.hexdigest()[:10]


# --------------------------------------------------------------------------- building


def _faults_dir() -> Path:
    return cimpl.cache_dir() / "faults"


def _copy_sources(dest: Path) -> Path:
    """firmware_c (without build output), dbc/ and firmware_py/ under ``dest``, as the
    Makefile and gen_contract.py expect them (``../dbc``, ``../firmware_py``: the contract
    tables come from this tree's firmware_py, not from whatever version is installed)."""
    src = cimpl.SOURCE_DIR
    shutil.copytree(src, dest / "firmware_c",
                    ignore=shutil.ignore_patterns("build", "__pycache__", "*.o", "*.so"))
    shutil.copytree(src.parent / "dbc", dest / "dbc")
    shutil.copytree(src.parent / "firmware_py", dest / "firmware_py",
                    ignore=shutil.ignore_patterns("__pycache__"))
    return dest / "firmware_c"


def apply_patch(source_dir: Path, patch: tuple[Patch, ...]) -> None:
    """Apply ``patch`` to the copy at ``source_dir`` (each text exactly once, else the
    fault no longer matches the sources: ValueError)."""
    for file, old, new in patch:
        path = source_dir / "src" / file
        text = path.read_text()
        if text.count(old) != 1:
            raise ValueError(f"{file}: the fault's text occurs {text.count(old)} times, not "
                             f"once: {old!r}")
        path.write_text(text.replace(old, new))


def library(fault: CFault) -> Path:
    """libbessded.so with ``fault`` planted, built on first use (cached)."""
    path = _faults_dir() / f"{fault.name}-{fault.key}" / "libbessded.so"
    if path.exists():
        return path
    tmp = _faults_dir() / f"tmp-{fault.name}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        source = _copy_sources(tmp)
        apply_patch(source, fault.patch)
        gen = _faults_dir() / "gen"
        if gen.is_dir():   # the DBC's generated sources, once for all faults
            shutil.copytree(gen, tmp / "build" / "gen")
        built = tmp / "build" / "libbessded.so"
        cimpl.build(tmp / "build", source_dir=source, target=str(built.resolve()))
        if not gen.is_dir():
            shutil.copytree(tmp / "build" / "gen", tmp / "gen")
            try:
                os.replace(tmp / "gen", gen)
            except OSError:
                pass   # another process put it there first
        path.parent.mkdir(parents=True, exist_ok=True)
        os.replace(built, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


_RUNTIMES: dict[str, Runtime] = {}


def runtime(fault: CFault | None) -> Runtime:
    """The runtime library with ``fault`` (None: the faultless cached one)."""
    if fault is None:
        return load_runtime()
    if fault.name not in _RUNTIMES:
        _RUNTIMES[fault.name] = Runtime(library(fault))
    return _RUNTIMES[fault.name]


def make_dut(fault: CFault | None, text: str | None = None
             ) -> Callable[[AgentConfig, Any, Keyring], CAgent]:
    """``simulate``'s ``make_dut``: a C agent on the library with ``fault``, configured
    from the configuration file ``text`` as the library's own loader reads it
    (bd_config_parse; None: firmware_py's arithmetic of the oracle's configuration)."""
    rt = runtime(fault)
    params = parse_config(text, runtime=rt) if text is not None else None
    return lambda cfg, _codec, ring: CAgent(cfg, ring, runtime=rt, params=params)


def score(fault: CFault | None, case: int = 1, dut: int = 3, jitter: float = 0.3,
          seed: int = 0, exact: bool = False, run: str = "") -> cf.Score:
    """The schedule played in process against the C agent with ``fault`` (None: none),
    configured from the file the tester writes (the configuration path, item 4), judged
    as `bess-ded conformance` does (``exact``: with the device's clock trusted)."""
    return cf.score(fault, case, dut, jitter, seed,
                    dut_from_text=lambda text: make_dut(fault, text), exact=exact, run=run)


# --------------------------------------------------------------------------- witnesses


class CRig(cf.Rig):
    """tests/conformance_faults.py's Rig on a C agent of runtime ``rt``."""

    def __init__(self, rt: Runtime | None, secure: bool = False, boot: int = 1,
                 **changes: Any) -> None:
        super().__init__(None, secure=secure, boot=boot, **changes)
        node = f"agent_{self.cfg.id}"
        if secure:
            ring = Keyring(node, cf.KEYS[node], 0, lambda _b: None, master=cf.MASTER)
            self.tx = FleetSender(cf.CODEC, cf.KEYS, boot=boot)
        else:
            ring = Keyring.insecure_for(node)
        self.rt = CAgent(self.cfg, ring, runtime=rt or load_runtime())  # type: ignore[assignment]

    def observed(self) -> Any:
        """What the agent sent, its counters, state and reset count."""
        c: Any = self.rt
        return self.out, dict(c.counters), c.state, c.resets


def drive(script: Callable[[CRig], Any], **rig: Any) -> Callable[[Runtime | None], Any]:
    """A witness: ``script`` run on a CRig (``rig``: its arguments); what it observed."""
    def witness(rt: Runtime | None) -> Any:
        r = CRig(rt, **rig)
        script(r)
        return r.observed()
    return witness


def steps(xis: Callable[[Any], list[int]] | list[int], **changes: Any
          ) -> Callable[[Runtime | None], Any]:
    """ξ fed to the C controller of the library (``xis(reference controller)`` or a list):
    the states it goes through."""
    def witness(rt: Runtime | None) -> Any:
        cfg = cf.config(**changes)
        core = cimpl.CCore((rt or load_runtime()).path)
        ctrl = cimpl.CController.from_config(cfg.controller, core=core)
        seq = xis(make_controller(cfg.controller, fixed=True)) if callable(xis) else xis
        s, out = ctrl.initial_state(cfg.lambda0), []
        for xi in seq:
            s, o = ctrl.step(s, xi)
            out.append((s, o.reset))
        return out
    return witness


def _start_boots(rt: Runtime | None) -> Any:
    """A C agent whose key file says boot 6: the Boot of its syncs at its start."""
    return cf.sync_boots(CAgent(cf.BASE, cf.filed_ring(), runtime=rt or load_runtime())
                         .tick(0.0))


def _signed(rt: Runtime | None) -> Any:
    """The C agent with signed_price fed the schedule's signed and refused prices."""
    cfg, ring = cf.signed_setup()
    return cf.signed_feed(CAgent(cfg, ring, runtime=rt or load_runtime()))


def _xi_at_int32_max(rt: Runtime | None) -> Any:
    core = cimpl.CCore((rt or load_runtime()).path)
    return core.xi((1 << 31) - 1, 1 << 24, 0, []), core.xi(-(1 << 31), 1 << 24, 0, [])


def _seq(*calls: Callable[[CRig], Any]) -> Callable[[CRig], None]:
    def script(r: CRig) -> None:
        for c in calls:
            c(r)
    return script


def _prices_every_tick(r: CRig, n: int, rho: float) -> None:
    for _ in range(n):
        r.price(rho)
        r.mc(1.2)
        if r.k % 5 == 0:
            r.status()
        r.tick()


def _mc_at_2_5_periods(r: CRig) -> None:
    """A neighbour frame 2.5 periods after the last (a tie of LAM-1's rne), λ one LSB
    over 2·lambda_step_max away."""
    r.run(4, lam=1.0)                 # neighbour frames at 0.5, …, 3.5 Ts
    r.run(2, nbr=False)
    step = cf.q(float(r.cfg.lambda_step_max or 0))
    r.mc(raw=cf.q(1.0) + 2 * step + 1, t=6.0 * r.ts)
    r.tick()
    r.run(2, lam=1.0)


def _gap_after_timeout(n: int) -> Callable[[CRig], None]:
    def script(r: CRig) -> None:
        r.run(3)
        r.run(5, nbr=False)   # timed out: its MC ID lost
        r.skip(r.nbr, n)
        r.run(3)
    return script


def _late_twice(r: CRig) -> None:
    r.run(3)
    held = r.mc_frame()
    r.run(2)
    for _ in range(2):
        r.deliver(can.Message(arbitration_id=held.arbitration_id, is_extended_id=False,
                              data=bytes(held.data)), 0.6)
        r.tick()


def _lost_then_in_step_sync_then_forged(r: CRig) -> None:
    r.secure_start()
    r.run(10)
    r.run(5, nbr=False)                    # timed out: lost
    r.deliver(r.tx.sync(r.nbr), 0.3)       # in step with the last frame: no longer lost
    r.forged(r.mc_frame())
    r.tick()


def _forged_after_start(r: CRig) -> None:
    r.secure_start()
    r.run(5)
    r.forged(r.mc_frame())
    r.run(120)   # every Diag page, SafetyCause's too


def _short_frames(valid_between: bool = False) -> Callable[[CRig], None]:
    """untrusted_after frames of the neighbour's MC ID one byte short (a valid one before
    the last, if ``valid_between``)."""
    def script(r: CRig) -> None:
        r.run(3)
        n = r.cfg.untrusted_after
        for k in range(n):
            if valid_between and k == n - 1:
                r.mc()
            good = r.mc_frame()
            r.deliver(can.Message(arbitration_id=good.arbitration_id, is_extended_id=False,
                                  data=bytes(good.data[:7])), 0.6)
        r.run(2)
    return script


def _fd_frame(r: CRig) -> None:
    r.run(3)
    m = r.mc_frame(lam=1.25)
    r.deliver(can.Message(arbitration_id=m.arbitration_id, is_extended_id=False,
                          data=bytes(m.data), is_fd=True), 0.6)
    r.run(2, nbr=False)


def _many_unknown(r: CRig) -> None:
    r.tick()
    for _ in range(3):
        r.deliver(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)))
    r.rt.note("unknown_id", 70000)   # as many unknown IDs: past RejectedUnknownId's 65535
    for _ in range(200):   # every Diag page at least once
        r.tick()


def _isolate_in_init_then_reconnect(r: CRig) -> None:
    r.run(2, price=False)
    r.command(Command.ISOLATE)
    r.tick()
    r.command(Command.RECONNECT)
    r.run(2, price=False)


# --------------------------------------------------------------------------- the set

ARITH, BOUND, CMDS, STATES, FRESH, DIAG = (cf.ARITH, cf.BOUND, cf.CMDS, cf.STATES, cf.FRESH,
                                           cf.DIAG)
RUNNING_ENTRY = ("bd_set_state(a, BD_STATE_RUNNING);\n        a->cs.nu = 0;")

FAULTS: list[CFault] = [
    # arithmetic at the edges
    CFault("c_mulq_floors", "NUM-2", "bd_mulq floors the Q48 product (no + 2^23): "
           "truncation toward −∞, not round half up",
           (("controller.c", "return bd_shr_floor(a * b + ((int64_t)1 << (Q - 1u)), Q);",
             "return bd_shr_floor(a * b, Q);"),), ARITH,
           drive(lambda r: r.run(5, lsb=3), neighbours=(Neighbour(1, 0.5),),
                 ctrl={"kind": "pc", "k": 150.0}, k_max=150.0)),
    CFault("c_wire_floors", "NUM-8", "the wire λ is the Q54 state floored (no + 2^29)",
           (("controller.c", "return (int32_t)bd_shr_floor(x + ((int64_t)1 << (GUARD - 1u)), "
             "GUARD);", "return (int32_t)bd_shr_floor(x, GUARD);"),), ARITH,
           drive(lambda r: r.run(10, lam=1.0))),
    CFault("c_sat32_counts_max", "XI-3", "sat32 counts a saturation at exactly INT32_MAX "
           "(≥ instead of >)",
           (("controller.c", "if (x > (int64_t)INT32_MAX) {", "if (x >= (int64_t)INT32_MAX) {"),),
           ARITH, _xi_at_int32_max),
    CFault("c_setpoint_floors", "SP-1", "the setpoint's (λ·G + 2^39) >> 40 without the "
           "2^39: floored, not rounded",
           (("agent.c", "+ (INT64_C(1) << 39);  /* < 2^40 */", ";  /* < 2^40 */"),), ARITH,
           drive(_seq(lambda r: r.run(10, lam=1.0), lambda r: r.run(10, lam=1.37)))),
    # pc's and ft's step, price_persist = 1: played on the runs that exercise them
    CFault("c_isqrt_32bit", "NUM-5", "bd_isqrt_u64 starts at the digit 2^30 (a 32-bit "
           "isqrt's): the root of x ≥ 2^32 is wrong",
           (("controller.c", "uint64_t bit = (uint64_t)1 << 62;",
             "uint64_t bit = (uint64_t)1 << 30;"),), ARITH,
           steps([3000, 50000, -7000], ctrl={"kind": "ft"})),
    CFault("c_pc_step_on_wire_grid", "STEP-10", "pc's Δλ rounded to Q24 before it is added "
           "(the step's guard bits lost)",
           (("controller.c", "dlam = bd_sat54(-((int64_t)cfg->kts * xi), &sats);",
             "dlam = bd_sat54(bd_shr_floor(-((int64_t)cfg->kts * xi) + ((int64_t)1 << "
             "(GUARD - 1u)), GUARD) * ((int64_t)1 << GUARD), &sats);"),), ARITH,
           steps([3, 50, -7], ctrl={"kind": "pc"})),
    CFault("c_persist_one_candidate_first", "PRICE-5", "price_persist = 1 special-cased: a "
           "step's first frame only makes it a candidate (taken at its second)",
           (("agent_rules.c", "if (a->has_price && abs64((int64_t)m->rho - a->price) > "
             "a->p.price_step_max) {",
             "if (a->has_price && abs64((int64_t)m->rho - a->price) > a->p.price_step_max) {\n"
             "        if (a->p.price_persist == 1u && candidate(a, 1, m->rho) == 1u) {\n"
             "            safety_reject(a, BD_C_IMPLAUSIBLE_PRICE, "
             "BD_SAFETY_CAUSE_IMPLAUSIBLE_PRICE, id);\n"
             "            return 0;\n"
             "        }"),), BOUND,
           drive(_seq(lambda r: r.run(5), lambda r: _prices_every_tick(r, 8, 1.5)),
                 pinned=True, price_persist=1)),
    # comparisons at exact boundaries
    CFault("c_rearm_ge", "BAND-3", "|ξ| = BAND re-arms (≥ instead of >)",
           (("controller.c", "(abs_xi > (int64_t)cfg->band)", "(abs_xi >= (int64_t)cfg->band)"),),
           BOUND, steps(lambda c: [5000, -5000, int(c.band), -3000])),
    CFault("c_dwell_gt", "DWELL-1", "a crossing resets only once since_reset > D",
           (("controller.c", "(s->since_reset >= cfg->dwell)", "(s->since_reset > cfg->dwell)"),),
           BOUND, steps(lambda c: [5000] * int(c.dwell_samples) + [-5000],
                        ctrl={"kind": "dwell", "dwell": 0.03})),
    CFault("c_nbr_timeout_strict", "LIVE-2", "a neighbour exactly neighbour_periods·Ts old is "
           "dead (< instead of ≤)",
           (("agent.c", "t - n->last_rx <= a->p.neighbour_timeout_ns",
             "t - n->last_rx < a->p.neighbour_timeout_ns"),), BOUND,
           drive(lambda r: cf._exact_neighbour_timeout(r, 3), ctrl={"ts": cf.EXACT_TS},
                 price_timeout_s=0.25, status_timeout_s=0.25)),
    CFault("c_price_timeout_strict", "STATE-2", "a price exactly price_s old is stale",
           (("agent.c", "t - a->price_rx <= a->p.price_timeout_ns",
             "t - a->price_rx < a->p.price_timeout_ns"),), BOUND,
           drive(cf._exact_price_timeout, ctrl={"ts": cf.EXACT_TS}, price_timeout_s=0.25,
                 status_timeout_s=0.25)),
    CFault("c_persist_one_late", "PRICE-4", "a new price level is taken one frame late "
           "(after price_persist + 1 frames)",
           (("agent_rules.c", "if (candidate(a, 1, m->rho) < a->p.price_persist) {",
             "if (candidate(a, 1, m->rho) <= a->p.price_persist) {"),), BOUND,
           drive(_seq(lambda r: r.run(5), lambda r: _prices_every_tick(r, 8, 1.5)),
                 pinned=True)),
    CFault("c_samples_ties_up", "LAM-1", "the samples between two neighbour frames round "
           "ties up, not to even",
           (("agent_rules.c", "(r2 == period && (q & 1) != 0)", "(r2 == period)"),), BOUND,
           drive(_mc_at_2_5_periods, ctrl={"ts": cf.EXACT_TS}, price_timeout_s=0.25,
                 status_timeout_s=0.25)),
    # commands at their limits
    CFault("c_gain_truncates", "CMD-5", "SET_GAINS' KTS, HTS truncated (no + D/2)",
           (("agent_rules.c", "int64_t num = 2 * (int64_t)raw * tsq + BD_GAIN_SCALE_DIV;",
             "int64_t num = 2 * (int64_t)raw * tsq;"),), CMDS,
           drive(_seq(lambda r: r.run(2, lam=-99.0), lambda r: r.command(
               Command.SET_GAINS, k=1.234, h=2.0), lambda r: r.run(3, lam=-99.0)),
               lambda0=99.0, lambda_min=-127.0, lambda_max=127.0)),
    CFault("c_gain_k_max_exclusive", "CMD-5", "SET_GAINS with GainK at the configured "
           "maximum is refused (≥ instead of >)",
           (("agent_rules.c", "m->gain_k > a->p.gain_k_raw_max",
             "m->gain_k >= a->p.gain_k_raw_max"),), CMDS,
           drive(_seq(lambda r: r.run(2), lambda r: r.command(
               Command.SET_GAINS, k=float(r.cfg.k_max or 0), h=2.0), lambda r: r.run(2)))),
    CFault("c_gains_only_running", "CMD-5", "SET_GAINS is taken in RUNNING only (not in any "
           "state)",
           (("agent_rules.c", "} else {   /* BD_CMD_SET_GAINS: the decoder checked the range */",
             "} else if (a->state == BD_STATE_RUNNING) {"),), CMDS,
           drive(_seq(lambda r: r.run(2, price=False), lambda r: r.command(
               Command.SET_GAINS, k=3.0, h=2.0), lambda r: r.run(2)))),
    CFault("c_reconnect_to_running", "STATE-8", "RECONNECT goes to RUNNING, not INIT",
           (("agent_rules.c", "bd_set_state(a, BD_STATE_INIT);",
             "bd_set_state(a, BD_STATE_RUNNING);"),), CMDS,
           drive(_isolate_in_init_then_reconnect)),
    # state entry and exit
    CFault("c_isolate_keeps_lambda", "STATE-7", "ISOLATE keeps the controller state (λ not "
           "the idle MC)",
           (("agent_rules.c", "bd_ctrl_init(&a->cs, a->p.idle_lambda);", "(void)0;"),), STATES,
           drive(_seq(lambda r: r.run(5, lam=1.0), lambda r: r.command(Command.ISOLATE),
                      lambda r: r.tick()))),
    CFault("c_entry_counts_reset", "STATE-6", "entering RUNNING counts a reset",
           (("agent.c", RUNNING_ENTRY, RUNNING_ENTRY + "\n        a->cs.resets++;"),), STATES,
           drive(lambda r: r.run(3))),
    CFault("c_steps_in_init", "STATE-10", "the controller steps in every state but ISOLATED "
           "(also INIT and SAFE)",
           (("agent.c", "if (active(a->state)) {\n        step(a);",
             "if (a->state != BD_STATE_ISOLATED) {\n        step(a);"),), STATES,
           drive(lambda r: r.run(5, price=False, lam=1.0))),
    CFault("c_fault_latched", "STATE-2", "a plant fault never clears (the flag is or-ed in)",
           (("agent_rules.c", "a->plant_fault = (uint8_t)fault;",
             "a->plant_fault = (uint8_t)(a->plant_fault | fault);"),), STATES,
           drive(_seq(lambda r: r.run(3), lambda r: r.run(5, FaultVoltage=1),
                      lambda r: r.run(6)))),
    # the freshness machinery
    CFault("c_lost_seven_windows", "AUTH-13", "a lost ID tries 7 windows, not 8",
           (("agent_rx.c", "#define LOST_WINDOWS 8u", "#define LOST_WINDOWS 7u"),), FRESH,
           drive(_gap_after_timeout(115))),
    CFault("c_stale_not_marked", "AUTH-25", "a stale frame's FV is not marked seen: its "
           "replay is stale again, not forged",
           (("agent_rx.c", "s->seen = (uint16_t)(s->seen | (1u << (s->fv - fv)));",
             "(void)0;"),), FRESH, drive(_late_twice)),
    CFault("c_lost_frames_plus_one", "AUTH-15", "lost_frames += FV − last (one too many)",
           (("agent_rx.c", "uint64_t gap = command ? 0u : fv - last - 1u;",
             "uint64_t gap = command ? 0u : fv - last;"),),
           FRESH, drive(lambda r: r.run(5))),
    CFault("c_in_step_sync_keeps_lost", "AUTH-16", "a sync in step with the sender does not "
           "end the lost state",
           (("agent_rx.c", "s->flags &= (uint8_t)~BD_RX_LOST;   /* in step with the sender */",
             "/* in step with the sender */"),), FRESH,
           drive(_lost_then_in_step_sync_then_forged, secure=True)),
    # the diagnostics and the receive path
    CFault("c_diag_wraps", "DIAG-2", "Diag values wrap past their maximum (v mod (max + "
           "1)), not saturate",
           (("agent_diag.c", "return v > max ? max : (uint32_t)v;",
             "return (uint32_t)(v % ((uint64_t)max + 1u));"),), DIAG, drive(_many_unknown)),
    CFault("c_plant_fault_level", "RX-11", "plant_faults counts every faulty status",
           (("agent_rules.c", "if (fault && !a->plant_fault) {", "if (fault) {"),), DIAG,
           drive(_seq(lambda r: r.run(3), lambda r: r.run(11, FaultOverCurrent=1)))),
    CFault("c_auth_no_last_safety", "AUTH-14", "an auth rejection is not recorded as the "
           "last safety event",
           (("agent_rx.c", "a->last_safety_cause = BD_SAFETY_CAUSE_AUTH;\n"
             "        a->last_safety_sender = id;", "(void)0;"),), DIAG,
           drive(_forged_after_start, secure=True)),
    CFault("c_dlc_no_streak", "RX-13", "a wrong DLC is counted but adds nothing to the "
           "untrusted streak",
           (("agent_rx.c", "fail(a, s, id, BD_C_DLC, t);", "reject(a, BD_C_DLC, id);"),), DIAG,
           drive(_short_frames())),
    CFault("c_streak_kept", "RX-10", "a valid frame does not end the untrusted streak",
           (("agent_rx.c", "s->streak = 0u;   /* valid and plausible", "/* valid and plausible"),),
           DIAG, drive(_short_frames(valid_between=True))),
    CFault("c_fd_taken", "RX-2", "a CAN FD frame is taken as a classical one (only remote "
           "and error frames are malformed)",
           (("agent_rx.c", "|| ((f->flags & BD_FRAME_FD) != 0u) != (a->p.fd != 0u)",
             "|| 0"),), DIAG, drive(_fd_frame)),
]



def _loaded(rt: Runtime | None, base: Any = None) -> Any:
    """A witness of a configuration fault: the tester's file for case 1, agent 3 (or
    ``base``) as the library's loader reads it (bd_config_parse: every field of
    bd_agent_params)."""
    from sim import conformance as conf

    text, _ = conf.written_config(cf.BASE if base is None else base)
    return params_dict(parse_config(text, runtime=rt or load_runtime()))


def _loaded_event(rt: Runtime | None) -> Any:
    """``_loaded`` for the file --event-transmit writes ([transmit] mode = "event")."""
    return _loaded(rt, cf.EVENT_BASE)


FAULTS += [
    # the boot counter (AUTH-3)
    CFault("c_boot_not_incremented", "AUTH-3", "the key file's boot counter used as it is "
           "at the start (B + 1 persisted, B used: the last run's freshness values again)",
           (("agent.c", "    a->boot += 1u;\n    return BD_OK;", "    return BD_OK;"),),
           FRESH, _start_boots),
    # event-triggered sending (--event-transmit)
    CFault("c_event_heartbeat_le", "TX-7", "in event mode the heartbeat goes one tick late "
           "(age ≤ heartbeat still quiet)",
           (("agent.c", "a->mc_age < a->p.tx_heartbeat", "a->mc_age <= a->p.tx_heartbeat"),),
           STATES, drive(cf._event_witness, **cf.EVENT)),
    CFault("c_cfg_threshold_misspelt", "CFG-9", "transmit.threshold looked up under a "
           "misspelt name: the default 3e-4, not the file's value",
           (("config.c", 'e = bd_toml_find(&d, "transmit", -1, "threshold");',
             'e = bd_toml_find(&d, "transmit", -1, "threshol");'),), cf.CONFIG,
           _loaded_event),
    # the signed price (--signed-price)
    CFault("c_signed_segment_ignored", "AUTH-33", "an ER_Price is taken when its PriceValid "
           "and ρ are the signed segment's, whatever its Segment",
           (("agent_sig.c", "m->rho == g->current.rho\n           && m->segment == "
             "((uint32_t)g->current.number & ((1u << BD_SIG_SEGMENT_LOW_BITS) - 1u));",
             "m->rho == g->current.rho;"),), FRESH, _signed),
    CFault("c_signature_page_overwritten", "AUTH-32", "a signature page repeated with other "
           "bytes overwrites the first (not sig_malformed)",
           (("agent_sig.c", "if ((g->have & bit) != 0u && g->part[page - 1u] != value) {",
             "if ((g->have & bit) != 0u && g->part[page - 1u] != value && page > 99u) {"),),
           FRESH, _signed),
]

CONFIG = cf.CONFIG
FAULTS += [
    # the configuration path (item 4)
    CFault("c_cfg_untrusted_after_misspelt", "CFG-7", "limits.untrusted_after looked up "
           "under a misspelt name: the default 5, not the file's value",
           (("config.c", 'count(&d, "untrusted_after", 1, 1000, 5, &p->untrusted_after)',
             'count(&d, "untrusted_afte", 1, 1000, 5, &p->untrusted_after)'),), CONFIG,
           _loaded),
    CFault("c_cfg_price_persist_misspelt", "CFG-7", "limits.price_persist looked up under a "
           "misspelt name: the default 3, not the file's value",
           (("config.c", 'count(&d, "price_persist", 1, 100, 3, &p->price_persist)',
             'count(&d, "price_persists", 1, 100, 3, &p->price_persist)'),), CONFIG, _loaded),
    CFault("c_cfg_tsq_from_ns", "CFG-3", "TSQ taken from the period rounded to whole ns, not "
           "from the file's ts", (("config.c", "double values[3] = {k * ts, h * ts, ts};",
                                   "double values[3] = {k * ts, h * ts, "
                                   "nearbyint(ts * 1e9) / 1e9};"),), CONFIG, _loaded),
    CFault("c_cfg_periods_rounded", "CFG-6", "neighbour_periods rounded to the nearest "
           "integer, not truncated (4.7 → 5)",
           (("config.c", "p->neighbour_timeout_ns = to_ns(trunc(periods) * ts);",
             "p->neighbour_timeout_ns = to_ns(nearbyint(periods) * ts);"),), CONFIG, _loaded),
]

BY_NAME = {f.name: f for f in FAULTS}
assert len(BY_NAME) == len(FAULTS)
