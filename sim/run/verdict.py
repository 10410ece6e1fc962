"""One honest verdict on a bus run: did the fleet converge, and what went wrong on the way.

``judge`` looks at everything a run leaves — the decoded recording, the trajectory on
the Ts grid, each agent's diagnostics frames, the plant's and router's counters, the
node processes' exit codes — and returns the anomalies and the verdict that
``bess-ded up`` and ``bess-ded analyze`` print, write to metrics.json and turn into
their exit code. Every rule is listed in docs/runs.md.

A run *converged* when every agent that the scenario means to be dispatching at the end
is RUNNING there, the last price segment settled into its 2 % band, every such agent's
final λ is within ``tolerance`` of ρ, and no node died.
Anything else that should not happen in a healthy run is an *anomaly*; a converged run
with anomalies is not a success either.

Over 500 lines: every rule of docs/runs.md in one place, in the order the
document lists them, so that a rule and its anomaly are read together.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from firmware_py.contract import MC_CYCLE_S, State, every_ticks
from firmware_py.nodeio import JOIN_FRACTION, SYNC_S
from firmware_py.secoc import SYNC_BOOT_JUMP_MAX
from sim.model.scenario import Scenario
from sim.model.trajectory import Trajectory
from sim.run.buslog import LogContents, failed_over

EXIT_OK = 0              # converged, no anomaly
EXIT_NOT_CONVERGED = 1   # the fleet did not converge (reasons in the verdict)
EXIT_ANOMALIES = 3       # converged, but with anomalies
EXIT_INTERRUPTED = 130   # SIGINT/SIGTERM: outputs written for what was recorded
# (2 is every command's exit code for bad input)

SILENCE_TS = 3            # a bus silence longer than this many Ts is an anomaly
SILENCE_CLUSTER_S = 1.0   # (scenario s) silences closer than this are reported as one
STATE_GRACE_TS = 10       # INIT/ISOLATED/RUNNING may lag the plan by this many Ts
# an agent (re)started takes no frame in its join window (AUTH-26): INIT that much longer
INIT_GRACE_TS = STATE_GRACE_TS + round(JOIN_FRACTION * SYNC_S / MC_CYCLE_S)
DEADLINE_MISS_FRACTION = 0.01
# genuine frames that arrived late or out of order (valid MAC, old freshness: AUTH-25):
# a few are what a loaded host does; more than this fraction of what was received (the
# recording's frames; a plant's or router's ticks) is a load anomaly, never auth_failed
STALE_FRACTION = 0.01
POWER_LIMIT_HOLD_S = 1.0  # (scenario s) a battery limited over the run's last second
LEDGER_MISMATCH_S = 1.0   # (scenario s) PLANT_Totals off the statuses for this long
LEDGER_TOLERANCE = 0.1    # kW and cu/h: one step of BatteryPower and BatteryCostRate
TOLERANCE = 1e-3          # cu/kWh: the final λ of every dispatching agent within this of ρ
OUTLIER_WINDOW_S = 1.0    # (scenario s) the λ outlier test looks at the run's last second
HOST_OVERLOAD_SHARE = 0.75  # this share of the nodes (≥ 2) all late: the host, not the nodes
# timeouts a starved host causes at every node (reported inside host_overloaded)
_LATE_KINDS = ("deadline_misses", "price_timeout", "status_timeout", "setpoint_timeout")
# the anomaly kinds most likely to explain a run that did not converge, most likely first
_CAUSES = ("wrong_keys", "key_mismatch", "node_died", "node_not_started", "no_price",
           "setpoint_inconsistent", "lambda_outlier", "insecure_keys", "impersonation",
           "unsigned_price", "bad_signature", "auth_failed", "sync_jump", "untrusted_source",
           "foreign_traffic", "host_overloaded", "agent_safe_at_end",
           "agent_init_at_end", "agent_isolated_at_end", "agent_silent", "node_silent",
           "plant_fault", "price_timeout", "status_timeout", "setpoint_timeout",
           "deadline_misses", "bus_silence", "agent_safe", "power_limit")
INIT, RUNNING, ISOLATED, SAFE = State.INIT, State.RUNNING, State.ISOLATED, State.SAFE

# a node heard frames on its own IDs that it did not send (its echo is told apart by
# NodeIO, firmware-spec RX-3): someone speaks as it, with or without its key
_IMPERSONATION = ("frames on its own IDs that it did not send: another sender speaks as it "
                  "(forged, or a key holder's)")
# foreign traffic other than impersonation (which ForeignFrames/foreign also count)
_FOREIGN = "frames that cannot come from its own fleet (IDs of agents outside the run)"
# AGENT_i_Diag counters that a healthy run keeps at 0: (signal, anomaly kind, what)
_AGENT_FAULT_COUNTERS = (
    ("PriceTimeouts", "price_timeout", "price timeouts (no valid ER_Price for the timeout)"),
    ("StatusTimeouts", "status_timeout", "plant-status timeouts"),
    ("PlantFaults", "plant_fault", "plant faults reported by PLANT_i_Status"),
    ("RejectedImpersonation", "impersonation", _IMPERSONATION),
    ("ForeignFrames", "foreign_traffic", _FOREIGN),
    ("RejectedDlc", "rejected_frames", "frames with a bad length"),
    ("RejectedRange", "rejected_frames", "frames with a value out of range"),
    ("RejectedUnknownId", "rejected_frames", "frames with an ID outside the DBC"),
    ("Untrusted", "untrusted_source", "untrusted-source alarms (a source ID with 5 "
     "consecutive DLC, range or authentication failures)"),
    ("ImplausiblePrice", "implausible_frames", "prices rejected as implausible (bounds or step)"),
    ("ImplausibleLambda", "implausible_frames", "neighbour λ rejected as implausible (step per "
     "sample)"),
    ("ImplausibleGains", "implausible_frames", "SET_GAINS rejected (gains outside bounds)"),
    ("RejectedAuth", "auth_failed", "secured frames or syncs whose MAC does not verify "
     "(forged, replayed or corrupted)"),
)
_SYNC_JUMP = ("syncs with a valid MAC that would move their sender's boot counter more than "
              f"{SYNC_BOOT_JUMP_MAX} ahead (AUTH-27: a key holder's forgery), refused")
# the plant's and router's counters (logs/*.counters.json) that a healthy run keeps at 0
_SIM_FAULT_COUNTERS = (
    ("setpoint_timeouts", "setpoint_timeout", "setpoint timeouts"),
    ("status_timeouts", "status_timeout", "status timeouts"),
    ("totals_timeouts", "status_timeout", "plant totals timeouts (the router's ledger held "
     "the last PLANT_Totals)"),
    ("impersonation", "impersonation", _IMPERSONATION),
    ("foreign", "foreign_traffic", _FOREIGN),
    ("dlc", "rejected_frames", "frames with a bad length"),
    ("range", "rejected_frames", "frames with a value out of range"),
    ("unknown_id", "rejected_frames", "frames with an ID outside the DBC"),
    ("malformed", "rejected_frames", "remote, error or FD frames"),
    ("not_a_frame", "malformed_frames", "bus inputs that are not CAN messages at all (e.g. a "
     "stray UDP datagram on the run's port)"),
    ("invalid_frame", "malformed_frames", "messages no CAN bus can carry (an ID beyond 11/29 "
     "bits, DLC > 8 on a classic frame, data longer than the DLC, fields of the wrong type)"),
    ("rx_error", "receive_error", "failed receives (socket error, interface down)"),
    ("rx_overflow", "recorder_missed_frames", "frames the kernel dropped at its full receive "
     "buffer (a reader the host starved)"),
    ("error_frame", "bus_errors", "CAN error frames"),
    ("send_failure", "send_failure", "frames it failed to send"),
    ("untrusted_sources", "untrusted_source", "untrusted-source alarms (a source ID with 5 "
     "consecutive DLC, range or authentication failures)"),
    ("auth", "auth_failed", "secured frames or syncs whose MAC does not verify (forged, "
     "replayed or corrupted)"),
    ("sync_jump", "sync_jump", _SYNC_JUMP),
    # signed_price (AUTH-32, AUTH-33): an agent's counters, in-process runs
    ("unsigned_price", "unsigned_price", "ER_Price frames with a valid MAC whose price is not "
     "the router's signed segment (a key holder's forgery, or before the first signature)"),
    ("bad_signature", "bad_signature", "ER_PriceSig transfers whose Ed25519 signature does "
     "not verify, or older than the one held (a replay)"),
    ("sig_malformed", "rejected_frames", "malformed ER_PriceSig pages (out of order, "
     "repeated with other bytes, a bad length or range)"),
)


@dataclass(frozen=True)
class Anomaly:
    """One thing a run did wrong: its kind, the node, what happened and when."""

    kind: str            # e.g. "node_died", "agent_safe", "bus_silence" (docs/runs.md)
    node: str            # "agent_3", "plant", "router", "bus", "recorder", "run"
    detail: str
    t: float | None = None  # s from the first price frame (run time), where it has one

    def text(self, time_scale: float = 1.0) -> str:
        """The anomaly as a report line, times shown in unstretched seconds."""
        at = "" if self.t is None else f" at t = {self.t / time_scale:.2f} s"
        return f"{self.kind} [{self.node}]{at}: {self.detail}"


@dataclass
class Verdict:
    """A run's outcome: converged or not and why, its anomalies, interrupted,
    and the most likely cause of a failure."""

    converged: bool
    reasons: list[str]           # why not converged (empty when it did)
    anomalies: list[Anomaly]
    interrupted: bool = False
    cause: str | None = None     # not converged: the most likely cause, from the anomalies
    # what the injected random loss (--loss, RunFacts.injected_loss) explains: the
    # timeouts and SAFE episodes it caused, kept apart from the anomalies
    loss_explained: list[Anomaly] = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        """The command's exit code: interrupted, not converged, anomalies, or OK."""
        if self.interrupted:
            return EXIT_INTERRUPTED
        if not self.converged:
            return EXIT_NOT_CONVERGED
        return EXIT_ANOMALIES if self.anomalies else EXIT_OK

    @property
    def ok(self) -> bool:
        """True when the run converged without anomalies and was not interrupted."""
        return self.exit_code == EXIT_OK

    def as_json(self) -> dict[str, Any]:
        """The verdict as metrics.json holds it."""
        return {"converged": self.converged, "reasons": self.reasons,
                "interrupted": self.interrupted, "exit_code": self.exit_code,
                "ok": self.ok, "cause": self.cause}


@dataclass
class RunFacts:
    """What the harness knows beyond the recording (all optional: ``analyze`` of a
    foreign log has none of it)."""

    exit_codes: dict[str, int | None] | None = None
    deaths: list[tuple[str, float, int]] | None = None   # (node, s after t0, exit code)
    node_counters: dict[str, Any] | None = None          # plant/router counters JSON
    recorder_counters: dict[str, int] | None = None      # bus inputs it dropped, by cause
    interrupted: bool = False
    insecure: bool = False   # signed with the public demo keys (--insecure)
    # the random-loss fault mode (--loss): probability, seed, frames dropped per node
    # (sim.run.inprocess.injected_loss); None: no loss injected
    injected_loss: dict[str, Any] | None = None

    def as_json(self) -> dict[str, Any]:
        """What ``up`` leaves in DIR/logs/run_facts.json, for ``analyze`` of the run."""
        return {"exit_codes": self.exit_codes, "deaths": self.deaths,
                "interrupted": self.interrupted, "insecure": self.insecure,
                "recorder_counters": self.recorder_counters,
                "injected_loss": self.injected_loss}

    @classmethod
    def from_json(cls, d: dict[str, Any], node_counters: dict[str, Any] | None
                  ) -> RunFacts:
        """The facts ``as_json`` wrote, with the plant's and router's counters."""
        return cls(exit_codes=d.get("exit_codes"),
                   deaths=[tuple(x) for x in d["deaths"]] if d.get("deaths") else None,
                   node_counters=node_counters, interrupted=bool(d.get("interrupted")),
                   insecure=bool(d.get("insecure")),
                   recorder_counters=d.get("recorder_counters"),
                   injected_loss=d.get("injected_loss"))


def judge(sc: Scenario, log: LogContents, tr: Trajectory | None, m: dict[str, Any],
          facts: RunFacts | None = None, tolerance: float = TOLERANCE) -> Verdict:
    """``tolerance`` (cu/kWh): how close to ρ every dispatching agent's final λ must be."""
    facts = facts or RunFacts()
    out: list[Anomaly] = []
    reasons: list[str] = []
    t0 = log.t_first_price
    if facts.interrupted:
        out.append(Anomaly("interrupted", "run", "stopped by a signal before the scenario's "
                           "end: results cover what was recorded"))
    if facts.insecure:
        out.append(Anomaly("insecure_keys", "run", "the nodes signed with the public demo "
                           "key (--insecure): anyone on the bus could forge any frame, so "
                           "nothing in this run is authenticated"))
    _node_exits(facts, out, reasons)
    if _wrong_keys(log, out, reasons):
        return _verdict(reasons, out, facts)
    if t0 is None or tr is None:
        out.append(Anomaly("no_price", "router", "no ER_Price frame in the recording: the "
                           "router never spoke (or the recorder heard another bus)"))
        reasons.append("no price was ever heard")
        return _verdict(reasons, out, facts)
    _agent_states(sc, log, tr, out, reasons)
    _recording(sc, log, out)
    _counters(sc, log, facts, out)
    _power_limits(sc, log, tr, out)
    _ledger(sc, log, out)
    _setpoints(sc, log, facts, out)
    _lambda_outliers(sc, tr, tolerance, out)
    _key_mismatch(log, facts, out, reasons)
    st = m.get("settling_times_s") or [None]
    err = m.get("final_error", float("nan"))
    if st[-1] is None:
        reasons.append(f"the last price segment never settled into its 2 % band (final "
                       f"error {err:.2e} cu/kWh)")
    elif not err <= tolerance:
        reasons.append(f"the final λ is {err:.2e} cu/kWh from ρ, more than the tolerance "
                       f"{tolerance:g} cu/kWh")
    return _verdict(reasons, _host_overload(log, facts, out), facts)


# what frames lost at random cause by themselves: no valid price, status or setpoint
# for a timeout (5 periods), and an agent's SAFE until they come back
LOSS_KINDS = ("price_timeout", "status_timeout", "setpoint_timeout", "agent_safe")


def _loss_explained(facts: RunFacts, out: list[Anomaly]
                    ) -> tuple[list[Anomaly], list[Anomaly]]:
    """(the anomalies, what the injected loss explains): with the random-loss fault mode
    on (``facts.injected_loss`` with frames dropped), the timeouts at the nodes that
    lost frames and the SAFE episodes of an agent that timed out are the fault mode's
    doing, not a node's fault: moved out of the anomalies (the run still reports them,
    under the injected loss). Everything else stays an anomaly."""
    inj = facts.injected_loss or {}
    lost = {n for n, k in (inj.get("dropped") or {}).items() if k}
    if not lost:
        return out, []
    timed_out = {a.node for a in out if a.kind in LOSS_KINDS[:3] and a.node in lost}
    mine = [a for a in out if a.node in timed_out and a.kind in LOSS_KINDS]
    return [a for a in out if a not in mine], mine


def loss_text(inj: dict[str, Any], explained: list[Anomaly]) -> str:
    """One line on the injected loss: what it dropped and what it explains."""
    kinds = Counter(a.kind for a in explained)
    folded = "; it explains " + ", ".join(f"{k} ×{v}" for k, v in kinds.items()) \
        if kinds else ""
    share = inj["dropped_total"] / max(inj["received_total"], 1)
    return (f"injected loss (fault mode, p = {inj['probability']:g}, seed {inj['seed']}, "
            f"{inj['frames']}): {inj['dropped_total']} of {inj['received_total']} frames "
            f"dropped ({100 * share:.1f} %){folded}")


def _mac_failures(log: LogContents) -> Counter[str]:
    """The recorder's MAC failures (forged or replayed syncs and frames) by sender."""
    failed: Counter[str] = Counter()
    for name, k in log.forged.items():
        failed[sender_of(name)] += k
    return failed


def _wrong_keys(log: LogContents, out: list[Anomaly], reasons: list[str]) -> bool:
    """Keys under which no sender's sync or frame verifies are not this log's keys (an
    `analyze` given another run's key set): said so, instead of "no price"."""
    failed = _mac_failures(log)
    if not log.keys_checked or log.verified or not failed:
        return False
    out.append(Anomaly("wrong_keys", "recorder", f"none of the {sum(failed.values())} syncs "
                       f"and secured frames of {len(failed)} senders ({_top(failed)}) verifies "
                       "under the keys given: the keys do not belong to this log — analyze "
                       "it with the key set of the run that recorded it (its DIR/keys)"))
    reasons.append("the keys do not belong to the log: no sender's frames verify under them")
    return True


def _key_mismatch(log: LogContents, facts: RunFacts, out: list[Anomaly],
                  reasons: list[str]) -> None:
    """A sender none of whose syncs and frames verifies at the recorder, while others'
    do, signs with another key than the fleet's: one key_mismatch anomaly per such node,
    in place of the MAC failures and untrusted-source alarms its frames cause."""
    failed = _mac_failures(log)
    bad = sorted(n for n in failed if not log.verified[n])
    if not log.keys_checked or not bad:
        return
    receivers = {f"agent_{a}" for a, d in log.diag.items() if d.get("RejectedAuth", 0)}
    receivers |= {n for n, c in (facts.node_counters or {}).items()
                  if c.get("counters", {}).get("auth", 0)}
    # every MAC failure on the bus is theirs: the receivers' alarms are these frames (and,
    # for a node whose whole key file is another key set's, its rejecting everyone else's)
    explained = set(failed) <= set(bad)
    out[:] = [a for a in out
              if not (a.kind == "auth_failed" and a.node == "bus"
                      and sender_of(a.detail.split(":")[0]) in bad)
              and not (explained and a.kind in ("auth_failed", "untrusted_source")
                       and a.node not in ("bus", "recorder"))
              # its frames are on the bus, only left out: not silent
              and not (a.kind in ("agent_silent", "node_silent") and a.node in bad)]
    reasons[:] = [r for r in reasons if r not in {f"{n} was never heard" for n in bad}]
    for node in bad:
        at = sorted(receivers - {node})
        heard = (f"; {len(at)} receivers count MAC failures ({_names(at)})" if at else "")
        out.append(Anomaly("key_mismatch", node, f"{node}'s frames fail the MAC at every "
                           f"receiver: it signs with another key than the fleet's key set — "
                           f"check its key file (none of its {failed[node]} syncs and frames "
                           f"on the bus verifies{heard})"))
        reasons.append(f"{node}'s frames fail authentication everywhere (key mismatch)")


def _verdict(reasons: list[str], out: list[Anomaly], facts: RunFacts) -> Verdict:
    out, explained = _loss_explained(facts, out)
    cause = None
    if reasons:
        ranked = [a for k in _CAUSES for a in out if a.kind == k]
        inj = facts.injected_loss or {}
        if ranked:
            cause = f"{ranked[0].kind} [{ranked[0].node}]: {ranked[0].detail}"
        elif inj.get("dropped_total"):
            cause = loss_text(inj, explained)
        else:
            cause = "no anomaly explains it: " + reasons[0]
    return Verdict(not reasons, reasons, out, facts.interrupted, cause, explained)


def _setpoints(sc: Scenario, log: LogContents, facts: RunFacts, out: list[Anomaly]) -> None:
    """Each agent's setpoints against its own dispatch rule at the λ it publishes (the
    check the plant makes, sim.nodes.consistency), from the recording."""
    from firmware_py.config import agent_configs_from_scenario
    from sim.nodes.consistency import Check, Setpoint, SetpointCheck, mc_lag

    t0 = log.t_first_price or 0.0
    plant = ((facts.node_counters or {}).get("plant") or {}).get("counters", {})
    for cfg in agent_configs_from_scenario(sc):
        check = SetpointCheck(cfg.battery, period=sc.ts, lag=mc_lag(cfg))
        bad: list[tuple[Setpoint, int]] = []   # (the setpoint, the λ raw it ignored)
        total = 0
        for t, what, a, b in log.dispatch.get(cfg.id, []):
            if what == "mc":
                done = check.mc(a, b, t)
                decided = [done] if done else []
            else:
                total += 1
                decided = check.setpoint(Setpoint(bool(a), b, t))
            bad += [(sp, check.mcs[-1][1] if check.mcs else 0)
                    for c, sp in decided if c is Check.INCONSISTENT]
        if not bad:
            continue
        sp, lam = bad[0]
        _, raw = check.expected(1, lam)
        held = plant.get(f"setpoint_inconsistent_agent_{cfg.id}", 0)
        out.append(Anomaly(
            "setpoint_inconsistent", f"agent_{cfg.id}",
            f"{len(bad)} of its {total} setpoints are not its dispatch rule at the λ it "
            f"publishes (first: {sp.raw / 100:.2f} kW{'' if sp.enable else ' disabled'} "
            f"where λ = {lam / (1 << 24):.4f} gives {raw / 100:.2f} kW): a compromised or "
            "faulty agent" + (f"; the plant held its last consistent setpoint {held} times"
                              if held else ""), sp.t - t0))


def _lambda_outliers(sc: Scenario, tr: Trajectory, tolerance: float,
                     out: list[Anomaly]) -> None:
    """An agent whose told λ stays off the median of the other dispatching agents' over
    the run's last OUTLIER_WINDOW_S: what a liar that keeps its setpoints consistent with
    its lie still gives away. Off by more than a quarter of ``tolerance`` while no other
    agent is off by even a third as much (one agent apart from a fleet that agrees; a
    fleet still converging has every agent apart alike, and names nobody). The median of
    the others, not of its graph neighbours: robust to one liar among ≥ 3 others, where a
    neighbour of the liar, averaging over two, would look off too."""
    assert tr.state is not None
    # OUTLIER_WINDOW_S scenario seconds are that many samples at any time scale
    k = min(tr.t.size, max(1, round(OUTLIER_WINDOW_S / MC_CYCLE_S)))
    lam = tr.lam[-k:]
    on = tr.judged[-k:] & (tr.state[-k:] == RUNNING)
    if sc.n < 4 or on.sum(axis=1).min() < 4:
        return  # with fewer than 3 others the median cannot tell who is off
    dev = np.zeros(sc.n)
    for i in range(sc.n):
        others = np.where(on, lam, np.nan)
        others[:, i] = np.nan
        dev[i] = np.median(np.abs(lam[:, i] - np.nanmedian(others, axis=1)))
    named = 0
    for i in range(sc.n):
        if not on[:, i].all():
            continue
        rest = np.delete(dev, i)
        # apart from every other agent: a fleet still converging has no one agent apart
        if dev[i] > tolerance / 4 and dev[i] > 3 * rest.max():
            named += 1
            out.append(Anomaly("lambda_outlier", f"agent_{i + 1}",
                               f"its λ stayed {dev[i]:.2e} cu/kWh off the median of the other "
                               f"dispatching agents over the last {OUTLIER_WINDOW_S:g} s (the "
                               f"others: at most {rest.max():.1e}; tolerance {tolerance:g}): "
                               "it tells its neighbours a λ the consensus does not explain",
                               float(tr.t[-k])))
    # every λ agrees, but not with ρ: only the pinned agents hear ρ and pull the
    # consensus to it, so one of them tells a λ off ρ (a liar pinned to the price drags
    # the whole fleet along, and no agent stands out)
    gap = np.abs(np.median(lam, axis=1) - tr.rho[-k:])
    off = float(np.median(gap))
    approaching = float(gap[0] - gap[-1]) > tolerance / 4  # an honest fleet not yet settled
    if not named and not approaching and dev.max() <= tolerance / 4 and off > tolerance:
        for i in sc.pinned:
            out.append(Anomaly("lambda_outlier", f"agent_{i}",
                               f"the whole fleet agrees on a λ {off:.2e} cu/kWh off ρ over the "
                               f"last {OUTLIER_WINDOW_S:g} s (tolerance {tolerance:g}); agent "
                               f"{i} is pinned to the price, and only the pinned agents "
                               f"({', '.join(map(str, sc.pinned))}) pull the consensus to ρ: "
                               "one of them tells a λ the price does not explain",
                               float(tr.t[-k])))


def _host_overload(log: LogContents, facts: RunFacts, out: list[Anomaly]) -> list[Anomaly]:
    """When most nodes missed their deadlines (HOST_OVERLOAD_SHARE of them, ≥ 2), the host
    was starved, not each node: one ``host_overloaded`` with its measure replaces the
    per-node deadline and timeout anomalies. Fewer late nodes are named one by one."""
    rates = {n: m / max(t, 1) for n, (m, t) in node_deadlines(log, facts.node_counters).items()
             if t}
    late = {n: r for n, r in rates.items() if r > DEADLINE_MISS_FRACTION}
    if len(late) < 2 or len(late) < HOST_OVERLOAD_SHARE * len(rates):
        return out
    folded = [a for a in out if a.kind in _LATE_KINDS]
    worst = max(late, key=lambda n: late[n])
    kinds = ", ".join(f"{k} ×{sum(a.kind == k for a in folded)}" for k in _LATE_KINDS
                      if any(a.kind == k for a in folded))
    host = Anomaly("host_overloaded", "host",
                   f"{len(late)} of {len(rates)} nodes missed more than "
                   f"{100 * DEADLINE_MISS_FRACTION:g} % of their deadlines (median "
                   f"{100 * float(np.median(list(late.values()))):.1f} %, worst "
                   f"{100 * late[worst]:.1f} % at {worst}): the host starved every node at "
                   "once, not a fault of one" + (f"; folded in: {kinds}" if kinds else ""))
    return [a for a in out if a.kind not in _LATE_KINDS] + [host]


def _node_exits(facts: RunFacts, out: list[Anomaly], reasons: list[str]) -> None:
    died = set()
    for name, t, code in facts.deaths or []:
        died.add(name)
        out.append(Anomaly("node_died", name, f"exited with code {code} during the run", t))
        reasons.append(f"{name} died (exit code {code})")
    for name, exit_code in (facts.exit_codes or {}).items():
        if name in died:
            continue
        if exit_code is None:
            out.append(Anomaly("node_not_started", name, "was never started"))
            reasons.append(f"{name} never ran")
        elif exit_code != 0:
            out.append(Anomaly("node_died", name, f"exited with code {exit_code}"))
            reasons.append(f"{name} exited abnormally (code {exit_code})")


def _intervals(mask: np.ndarray, t: np.ndarray, ts: float) -> list[tuple[float, float]]:
    """(start, duration) of each run of True in ``mask``."""
    out = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        out.append((float(t[a]), float((b - a) * ts)))
    return out


def _agent_states(sc: Scenario, log: LogContents, tr: Trajectory, out: list[Anomaly],
                  reasons: list[str]) -> None:
    assert tr.state is not None and tr.expected is not None
    ts, grace = sc.ts, STATE_GRACE_TS * sc.ts
    gone = failed_over(log)  # dead and failed over: their held State is no state
    for i in range(sc.n):
        name = f"agent_{i + 1}"
        if log.mc_frames(i + 1) == 0:
            out.append(Anomaly("agent_silent", name, "sent no AGENT_MC frame at all"))
            reasons.append(f"{name} was never heard")
            continue
        state, expected = tr.state[:, i], tr.expected[:, i]
        end = int(state[-1])
        if expected[-1] and end != RUNNING:
            what = State(end).name if end in State._value2member_map_ else str(end)
            out.append(Anomaly(f"agent_{what.lower()}_at_end", name,
                               f"in {what} at the end, where the scenario has it dispatching",
                               float(tr.t[-1])))
            reasons.append(f"{name} ended in {what}")
        for t, d in _intervals(state == SAFE, tr.t, ts):
            out.append(Anomaly("agent_safe", name, f"in SAFE for {d:.2f} s (the scenario "
                               "plans none)", t))
        for s, what, lag in ((ISOLATED, "ISOLATED", grace), (INIT, "INIT", INIT_GRACE_TS * ts)):
            for t, d in _intervals((state == s) & expected, tr.t, ts):
                if d > lag:
                    out.append(Anomaly(f"agent_{what.lower()}", name, f"in {what} for {d:.2f} s "
                                       f"where the scenario has it dispatching", t))
        for t, d in _intervals((state == RUNNING) & ~expected, tr.t, ts):
            if d > grace and i + 1 not in gone:
                out.append(Anomaly("agent_not_isolated", name, f"RUNNING for {d:.2f} s where "
                                   "the scenario has it isolated", t))


def silence_ts(sc: Scenario) -> int:
    """The longest quiet bus that is no anomaly, in Ts: SILENCE_TS; with event-triggered
    λ a settled fleet's MC frames fall silent too and the bus carries the price, status
    and setpoint cadence (every 5 Ts): SILENCE_TS more than that."""
    if not sc.transmit.event:
        return SILENCE_TS
    return every_ticks("ER_Price") + SILENCE_TS


def _recording(sc: Scenario, log: LogContents, out: list[Anomaly]) -> None:
    t0 = log.t_first_price or 0.0
    for cluster in _clusters(log.silences, SILENCE_CLUSTER_S * sc.ts / MC_CYCLE_S):
        a, b = cluster[0][0], cluster[-1][1]
        longest = max(y - x for x, y in cluster)
        what = (f"no frame for {longest:.3f} s ({longest / sc.ts:.0f} Ts)" if len(cluster) == 1
                else f"{len(cluster)} gaps without a frame between t = {a - t0:.2f} and "
                f"{b - t0:.2f} s, the longest {longest:.3f} s ({longest / sc.ts:.0f} Ts)")
        out.append(Anomaly("bus_silence", "bus", f"{what}; more than {silence_ts(sc)} Ts",
                           a - t0))
    by_sender: dict[str, list[tuple[float, float, str]]] = {}
    for name, gaps in log.message_silences.items():
        by_sender.setdefault(sender_of(name), []).extend((a, b, name) for a, b in gaps)
    for node, silent in sorted(by_sender.items()):
        merged: list[tuple[float, float, list[str]]] = []
        for a, b, name in sorted(silent):
            if merged and a <= merged[-1][1]:
                merged[-1] = (merged[-1][0], max(b, merged[-1][1]), merged[-1][2] + [name])
            else:
                merged.append((a, b, [name]))
        for a, b, names in merged:
            end = " (to the end of the recording)" if b >= log.t_end else ""
            out.append(Anomaly("node_silent", node, f"sent no {_names(names)} for "
                               f"{b - max(a, t0):.2f} s{end}", max(a, t0) - t0))
    if not log.start_recorded:
        out.append(Anomaly("start_not_recorded", "recorder", "an agent's first recorded MC "
                           "frame is not INIT: the recording started late, so t = 0 and every "
                           "settling time are late too"))
    missed = log.counter_gaps
    if missed:
        out.append(Anomaly("recorder_missed_frames", "recorder",
                           f"{sum(missed.values())} frames missing from the recording "
                           f"(from the counter jumps: {_top(missed)})"))
    for name, k in sorted(log.out_of_sequence.items()):
        out.append(Anomaly("foreign_traffic", "bus", f"{name}: {k} frames out of its counter "
                           "sequence (a second sender on the ID, or a replay)"))
    if log.outside_run:
        out.append(Anomaly("foreign_traffic", "bus", f"{sum(log.outside_run.values())} frames "
                           f"of messages outside this {sc.n}-agent run ({_top(log.outside_run)})"))
    for name, k in sorted(log.forged.items()):
        out.append(Anomaly("auth_failed", "bus", f"{name}: {k} frames whose MAC does not "
                           "verify with its sender's key (forged, or replayed from an earlier "
                           "window or run); the analysis left them out"))
    for name, k in sorted(log.unsigned.items()):  # signed_price (AUTH-32, AUTH-33)
        what = ("frames with a valid layout whose price is not the router's signed segment "
                "(before the first signature, or a key holder's forgery)"
                if name == "ER_Price" else "pages refused (malformed, a signature that does "
                "not verify, or an older one)")
        out.append(Anomaly("unsigned_price" if name == "ER_Price" else "bad_signature", "bus",
                           f"{name}: {k} {what}; the analysis left them out"))
    for name, k in sorted(log.sync_jump.items()):
        out.append(Anomaly("sync_jump", "bus", f"{name}: {k} syncs with a valid MAC whose boot "
                           f"counter jumps more than {SYNC_BOOT_JUMP_MAX} above its sender's "
                           "(AUTH-27: forged by a key holder); the nodes and the analysis "
                           "refused them"))
    for name, k in sorted(log.sync_undone.items()):
        out.append(Anomaly("sync_jump", "bus", f"{name}: {k} genuine syncs of its sender's "
                           "current boot after a sync had advanced that boot (that advance "
                           "was forged by a key holder: held and dropped, AUTH-35, or taken "
                           "with a forged frame and undone, AUTH-27, by the nodes and the "
                           "analysis)"))
    stale = sum(log.stale.values())
    if stale > STALE_FRACTION * max(log.frames, 1):
        out.append(Anomaly("stale_frames", "bus", f"{stale} genuine secured frames of "
                           f"{log.frames} recorded arrived late or out of order (valid MAC, "
                           f"old freshness: {_top(log.stale)}; more than "
                           f"{100 * STALE_FRACTION:g} %): a loaded host or bus, not a forgery; "
                           "the analysis left them out"))
    for label, (boot, floor) in sorted(log.stale_boot.items()):
        out.append(Anomaly("stale_boot", label, f"syncs of {label} with a valid MAC but boot "
                           f"{boot}, below its boot {floor} in this run: a replay of an "
                           f"earlier run or boot, or {label}'s key file rolled back (AUTH-21); "
                           "the analysis left them out"))
    if log.undecodable:
        out.append(Anomaly("malformed_frames", "bus", f"{sum(log.undecodable.values())} frames "
                           f"that fail the DBC's checks ({_top(log.undecodable)})"))


def _clusters(gaps: list[tuple[float, float]], within: float
              ) -> list[list[tuple[float, float]]]:
    """Gaps grouped when each starts less than ``within`` s after the previous one ends."""
    out: list[list[tuple[float, float]]] = []
    for g in sorted(gaps):
        if out and g[0] - out[-1][-1][1] < within:
            out[-1].append(g)
        else:
            out.append([g])
    return out


def sender_of(message: str) -> str:
    """The node that sends a message: ER_* → router, PLANT_* → plant, AGENT_i_* → agent_i."""
    if message.startswith("ER_"):
        return "router"
    if message.startswith("PLANT_"):
        return "plant"
    return "agent_" + message.split("_")[1]


def _names(names: list[str]) -> str:
    unique = sorted(set(names), key=names.index)
    return ", ".join(unique[:3]) + (f" (+{len(unique) - 3} more)" if len(unique) > 3 else "")


def _top(c: Any, k: int = 4) -> str:
    items = sorted(c.items(), key=lambda x: -x[1])
    more = f", … {len(items) - k} more" if len(items) > k else ""
    return ", ".join(f"{n}: {v}" for n, v in items[:k]) + more


def _counters(sc: Scenario, log: LogContents, facts: RunFacts, out: list[Anomaly]) -> None:
    for a, d in sorted(log.diag.items()):
        name = f"agent_{a}"
        # ForeignFrames counts the impersonations too, reported on their own: the rest is
        # its two other parts (pages sent at other times, so not ForeignFrames minus one)
        d = {**d, "ForeignFrames": d.get("ForeignIds", 0) + d.get("InterleavedCounters", 0)}
        for sig, kind, what in _AGENT_FAULT_COUNTERS:
            if d.get(sig, 0):
                if kind in ("untrusted_source", "implausible_frames", "auth_failed"):
                    what += _last_rejected(d)
                out.append(Anomaly(kind, name, f"{d[sig]} {what}"))
    for node, c in sorted((facts.node_counters or {}).items()):
        counters = dict(c.get("counters", {}))
        counters["foreign"] = max(0, counters.get("foreign", 0)
                                  - counters.get("impersonation", 0))
        for key, kind, what in _SIM_FAULT_COUNTERS:
            if counters.get(key, 0):
                out.append(Anomaly(kind, node, f"{counters[key]} {what}"))
    recorder = facts.recorder_counters or {}
    for key, kind, what in _SIM_FAULT_COUNTERS:
        if recorder.get(key, 0):
            out.append(Anomaly(kind, "recorder", f"{recorder[key]} {what}, heard on the bus "
                               "and left out of the recording"))
    for node, c in sorted((facts.node_counters or {}).items()):
        stale, ticks = c.get("counters", {}).get("stale", 0), c.get("ticks", 0)
        if stale > STALE_FRACTION * max(ticks, 1):
            out.append(Anomaly("stale_frames", node, f"{stale} genuine secured frames "
                               f"arrived late or out of order in {ticks} ticks (valid MAC, "
                               f"old freshness; more than {100 * STALE_FRACTION:g} % of the "
                               "ticks): a loaded host or bus, not a forgery"))
    for node, (misses, ticks) in node_deadlines(log, facts.node_counters).items():
        if misses and misses > DEADLINE_MISS_FRACTION * max(ticks, 1):
            out.append(Anomaly("deadline_misses", node, f"{misses} deadline misses in {ticks} "
                               f"ticks ({100 * misses / max(ticks, 1):.1f} %, more than "
                               f"{100 * DEADLINE_MISS_FRACTION:g} %)"))


def node_deadlines(log: LogContents, node_counters: dict[str, Any] | None
                   ) -> dict[str, tuple[int, int]]:
    """(deadline misses, ticks) per node: an agent's from its last AGENT_i_Diag and the
    ticks its recorded frames show it ran (LogContents.ticks_run) plus the misses; the
    plant's and router's
    from the counters they wrote at exit."""
    out = {}
    for a, d in sorted(log.diag.items()):
        misses = d.get("DeadlineMisses", 0)
        out[f"agent_{a}"] = (misses, log.ticks_run(a) + misses)
    for node, c in (node_counters or {}).items():
        out[node] = (c.get("counters", {}).get("deadline_miss", 0), c.get("ticks", 0))
    return out


def _last_rejected(d: dict[str, int]) -> str:
    """The claimed sender and cause of the agent's last safety rejection (Diag page 7)."""
    from firmware_py.errors import UnknownFrameError
    from firmware_py.frames import FrameCodec
    from firmware_py.runtime import SAFETY_CAUSES

    sender, cause = d.get("SafetySender", 0), d.get("SafetyCause", 0)
    if not sender:
        return ""
    try:
        who = f"{FrameCodec().name_of(sender)}, 0x{sender:03X}"
    except UnknownFrameError:  # an ID outside the DBC is still worth naming
        who = f"0x{sender:03X}"
    why = SAFETY_CAUSES[cause] if 0 <= cause < len(SAFETY_CAUSES) else str(cause)
    return f"; the last one claimed to come from {who} ({why})"


def _power_limits(sc: Scenario, log: LogContents, tr: Trajectory, out: list[Anomaly]) -> None:
    t_end = (log.t_first_price or 0.0) + float(tr.t[-1])
    hold = POWER_LIMIT_HOLD_S * sc.ts / MC_CYCLE_S
    for i in range(1, sc.n + 1):
        flags = [(t, v) for t, v in log.series.get((f"PLANT_{i}_Status", "PowerLimited"), [])
                 if t >= t_end - hold]
        if flags and all(v for _, v in flags):
            out.append(Anomaly("power_limit", f"plant (BESS {i})", "held at a power or current "
                               f"limit over the run's last {POWER_LIMIT_HOLD_S:g} s",
                               float(tr.t[-1])))


def _ledger(sc: Scenario, log: LogContents, out: list[Anomaly]) -> None:
    """PLANT_Totals (the router's ledger, AUTH-29: a key only the plant and the router
    hold) against the statuses the plant sent with it, the cycles whose every status was
    recorded: a plant that tells the router other powers or costs than it tells the
    agents (compromised or faulty), on every such cycle for LEDGER_MISMATCH_S."""
    hold = LEDGER_MISMATCH_S * sc.ts / MC_CYCLE_S
    agents = range(1, sc.n + 1)
    since: tuple[float, float, float, float, float] | None = None
    for t, power, cost, statuses in log.totals:
        if any(i not in statuses for i in agents):
            continue  # a status of this cycle not recorded: nothing to compare
        p = [statuses[i] for i in agents]
        want_p = sum(p)
        want_c = float(sum(b.cost_rate(x) for b, x in zip(sc.batteries, p, strict=True)))
        if abs(power - want_p) <= LEDGER_TOLERANCE and abs(cost - want_c) <= LEDGER_TOLERANCE:
            since = None
            continue
        if since is None:
            since = (t, power, want_p, cost, want_c)
        if t - since[0] >= hold:
            t0, power0, want_p0, cost0, want_c0 = since
            out.append(Anomaly(
                "ledger_mismatch", "plant",
                f"PLANT_Totals said {power0:.1f} kW and {cost0:.1f} cu/h where the statuses "
                f"sent with it sum to {want_p0:.2f} kW and {want_c0:.2f} cu/h, and disagreed "
                f"on every fully recorded cycle for {LEDGER_MISMATCH_S:g} s: the router's "
                "ledger is not the batteries' (a compromised or faulty plant)",
                t0 - (log.t_first_price or 0.0)))
            return


def anomalies_json(v: Verdict) -> list[dict[str, Any]]:
    """The verdict's anomalies as metrics.json holds them."""
    return [asdict(a) for a in v.anomalies]
