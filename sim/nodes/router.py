"""The energy-router node (``ER``): price broadcast, commands, and the cost ledger.

* ``ER_Price`` every price cycle (the DBC's GenMsgCycleTime, 50 ms at Ts = 10 ms;
  every cadence here stretches with the scenario's Ts, ``contract.cycle_s``): ρ(t) of the scenario's
  schedule, ``Rho`` as raw int32 Q24 = round(ρ·2**24), ``Segment`` = the index of
  the schedule step in force, ``PriceValid`` = 1. t = 0 of the schedule is the
  router's first tick; a bus run's time axis starts at the first price frame.
* ``ER_Command`` at each scenario event time (ISOLATE / RECONNECT to the event's
  agent), sent ``COMMAND_REPEATS`` = 3 times, ``COMMAND_SPACING_S`` = 10 ms apart
  (each with a fresh freshness value, so none is a replay or "repeated data"; the agent treats the
  second and third as idempotent). An event fires at the first tick at or after
  its time. ``send_command`` queues the same for tools and tests.
* ``ER_Balance`` every balance cycle (100 ms), both its pages (0: P_e and F_c, 1: F_c*) in
  the same tick, signed like every frame, from the ``PLANT_Totals`` frames it receives
  (the plant's ΣP_i and Σ(1+m_i)(α_i P_i² + β_i P_i), under a key that only the plant and
  the router hold: no agent can misreport its battery to the ledger): P_e = D − ΣP_i,
  F_c = Σ(1+m_i)(α_i P_i² + β_i P_i) + ρ P_e (both held from the last accepted frame, 0
  before the first)
  and the KKT optimum's F_c* (``sim.model.cost.kkt_optimum`` for the current ρ and D).
  Both rates (cu/h) are integrated over the router's own tick intervals into
  ``cost`` and ``optimal_cost`` (cu), rectangle rule with the values at each tick.
* Silent windows (fault tests): between t_start and t_end (s from the first tick)
  the router sends nothing: no price, no balance, no command. What falls due
  meanwhile is not sent later (a silent router is a dead router); the periodic
  cadence and the ledger go on. Counted in ``silenced_frames``.

Pinned-agent failover (issue 23.5; docs/faults.md): the router also takes every agent's
``AGENT_<i>_MC`` (verified like any secured input) to know which agents are up: heard
within the agents' own neighbour timeout (``neighbour_timeout_periods``·Ts) and not
ISOLATED. When an agent it counts as pinned (the scenario's ``pinned``, and every agent
it pinned since) is lost (heard once, then silent for that timeout; or ISOLATED, which
takes it out of the consensus just as well), it looks at the graph of the agents up
(the scenario's edges between two agents up): every connected component of it without a
pinned agent up no longer hears the price, and gets one: the agent of that component
with the most neighbours up, ties by the lowest id (``sim.model.graph.failover_choice``),
pinned by an authenticated ``ER_Command`` PIN (CMD-7, repeated like every command).
Counted in ``failovers`` (one per agent pinned), listed in ``failover_log`` and the
summary. An agent it pinned that restarts (heard again after it was lost, or INIT after
RUNNING) starts from its configuration, unpinned: the router pins it again. Nothing
happens while no pinned agent is lost (a fleet starting up, an unpinned agent isolated),
so a run without a lost pinned agent sends exactly what it sent before.
``failover=False`` turns it off (the MC frames are then not taken at all).

Totals reception uses the receive checks of the agent runtime: rejections by cause,
``lost_frames``, foreign traffic (firmware_py.nodeio); totals older than 5 status
cycles (``contract.timeout_s``: 250 ms at Ts = 10 ms) count one ``totals_timeouts`` (the
last ones are still used).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import can

from dbc import dbc_path
from firmware_py.config import agent_configs_from_scenario, untrusted_s
from firmware_py.contract import TOTALS, Command, State, cycle_s, mc_name, timeout_s
from firmware_py.errors import ConfigError, ParameterError
from firmware_py.frames import LAMBDA_Q, PIN_OFF, PIN_ON, FrameCodec, target_raw
from firmware_py.nodeio import HOST_ECHO_DEPTH, LOST_SEARCH_COUNTS, NodeIO
from firmware_py.pricesig import SEGMENT_MOD, SignedSegment, pages, sign
from firmware_py.secoc import Keyring
from sim.model.cost import kkt_optimum
from sim.model.graph import failover_choice
from sim.model.scenario import Scenario
from sim.nodes.nodeclock import SimNodeClock, TimeWindow
from sim.nodes.plant import Cyclic

log = logging.getLogger(__name__)

COMMAND_REPEATS = 3
COMMAND_SPACING_S = 0.010
SCHEDULE_EPS_S = 1e-6   # float slack when comparing a tick time with a schedule time

COMMANDS = {"isolate": Command.ISOLATE, "reconnect": Command.RECONNECT,
            "set_gains": Command.SET_GAINS, "pin": Command.PIN, "unpin": Command.PIN}
PIN_GAIN_K = {"pin": PIN_ON, "unpin": PIN_OFF}   # a PIN's GainK says which way (CMD-7)
EVENT_COMMANDS = {"isolate": "isolate", "reconnect": "reconnect"}


@dataclass(frozen=True)
class SilentWindow(TimeWindow):
    """The router sends nothing for t_start ≤ t < t_end (s from its first tick)."""

    t_start: float
    t_end: float

    @classmethod
    def parse(cls, spec: str) -> SilentWindow:
        """``T0:T1`` (the CLI's --silent), e.g. ``5:8``."""
        parts = spec.split(":")
        try:
            if len(parts) != 2:
                raise ValueError
            window = cls(float(parts[0]), float(parts[1]))
        except ValueError:
            raise ParameterError("--silent", "T0:T1 in seconds from the router's start, e.g. 5:8",
                                 spec) from None
        return window.check()

    def check(self) -> SilentWindow:
        """The window itself, if valid (ParameterError otherwise)."""
        self.check_window("silent window", "router")
        return self


def as_window(w: SilentWindow | Sequence[float] | str) -> SilentWindow:
    """A SilentWindow from a window, a (T0, T1) pair or "T0:T1"; validated."""
    if isinstance(w, SilentWindow):
        return w.check()
    if isinstance(w, str):
        return SilentWindow.parse(w)
    try:
        t0, t1 = w
        return SilentWindow(float(t0), float(t1)).check()
    except (TypeError, ValueError):
        raise ParameterError("silent window", "(t_start, t_end) in seconds", w) from None


@dataclass
class _PendingCommand:
    raw: dict[str, int]
    left: int = COMMAND_REPEATS
    next_due: float | None = None   # None: the next tick


@dataclass
class _AgentSlot:
    """What the router knows of one agent from its MC frames (the failover's input)."""

    rx: float | None = None     # last accepted MC frame
    state: int = State.INIT
    up: bool = False            # heard within the timeout
    lost: bool = False          # heard once, then silent for the timeout


@dataclass(frozen=True)
class Failover:
    """One failover: when (s from the router's first tick), the pinned agents lost, and
    the agents the router pinned."""

    t: float
    lost: tuple[int, ...]
    pinned: tuple[int, ...]

    def line(self) -> str:
        """``t=5.07 s: pinned agents lost 1; pinned 2, 3, 4``."""
        return (f"t={self.t:.2f} s: pinned agents lost {', '.join(map(str, self.lost))}; "
                f"pinned {', '.join(map(str, self.pinned))}")


@dataclass
class _Totals:
    """The plant's last accepted PLANT_Totals: ΣP_i (kW), Σ battery cost rate (cu/h)."""
    power: float = 0.0
    cost_rate: float = 0.0
    rx: float | None = None
    fresh: bool = False


class RouterNode(SimNodeClock):
    """Node (firmware_py.node) of the energy router for one scenario.

    ``counters``: rejected input frames by cause (``dlc``, ``range``, ``unknown_id``,
    ``malformed``, ``impersonation``, ``auth``, ``unsynced``, ...), ``lost_frames``,
    ``foreign`` (with ``impersonation``, ``foreign_id``), ``totals_frames`` (accepted
    PLANT_Totals), ``totals_timeouts``,
    ``price_frames``, ``command_frames``, ``balance_frames`` (pages), ``silenced_frames``,
    ``events`` (scenario events fired), ``failovers`` (agents pinned by the failover),
    ``encode_saturations``, and the loop's
    ``deadline_miss`` / ``send_failure``. Ledger: ``cost`` and ``optimal_cost`` (cu),
    ``grid_power`` (last P_e, kW), ``cost_rate`` / ``optimal_cost_rate`` (cu/h).
    """

    def __init__(self, scenario: Scenario, period: float = 0.01,
                 silent: Iterable[SilentWindow | Sequence[float] | str] = (),
                 codec: FrameCodec | None = None, keys: Keyring | None = None,
                 failover: bool = True) -> None:
        if not (math.isfinite(period) and period > 0):
            raise ParameterError("period", "a positive number of seconds", period)
        self.scenario = scenario
        self.period = period
        self.codec = codec or FrameCodec(dbc_path(scenario.fd, scenario.lambda_tags))
        self.silent = tuple(as_window(w) for w in silent)

        c = self.codec
        tol = period / 2
        # the DBC's cycles are for Ts = 10 ms; a time-scaled scenario stretches them
        self.price_cycle = cycle_s("ER_Price", scenario.ts)
        self.balance_cycle = cycle_s("ER_Balance", scenario.ts)
        self.totals_timeout = timeout_s(TOTALS, scenario.ts)
        self._price = Cyclic(self.price_cycle, tol)
        self._balance = Cyclic(self.balance_cycle, tol)
        self._events = sorted(scenario.events, key=lambda e: e.t)
        self._next_event = 0
        self._pending: list[_PendingCommand] = []
        self._lock = threading.Lock()
        self._totals_id = c.frame_id(TOTALS)
        self.totals = _Totals()
        # the failover's view of the agents: their MC frames, the graph, who is pinned
        self.failover = failover
        self._mc = ({c.frame_id(mc_name(i)): i for i in range(1, scenario.n + 1)}
                    if failover else {})
        self._agents = {i: _AgentSlot() for i in range(1, scenario.n + 1)}
        cfgs = agent_configs_from_scenario(scenario)
        self.agent_timeout = cfgs[0].neighbour_timeout_periods * scenario.ts
        self.pinned = set(scenario.pinned)      # whom the router counts as pinned
        self._commanded: set[int] = set()       # of those, the ones it pinned itself
        self.failover_log: list[Failover] = []
        # signed_price (AUTH-31): the router signs each price segment with its Ed25519 key
        self.signed_price = scenario.signed_price
        if self.signed_price and (keys is None or keys.price_sign is None):
            raise ConfigError("keyring", "router", "expected the price signing key "
                              "([price_signature] sign_key) for a signed_price scenario, but "
                              "the key file has none: re-provision with bess-ded keys")
        self.io = NodeIO(c, "the router", own=("ER_Price", "ER_Command", "ER_Balance",
                                               *(("ER_PriceSig",) if self.signed_price else ())),
                         wanted=[self._totals_id, *self._mc], fleet_size=scenario.n,
                         untrusted_s=untrusted_s(scenario.ts), keys=keys,
                         sync_s=cycle_s("ER_Price_Sync", scenario.ts),
                         echo_depth=HOST_ECHO_DEPTH, timed=[self._totals_id, *self._mc])
        # AUTH-30: an agent sees only the commands to it; the count is re-announced
        # halfway through the windows its search covers (a burst of commands to others)
        self.io.resync_after("ER_Command", LOST_SEARCH_COUNTS // 2)
        self.counters = self.io.counters
        self.last_error = self.io.last_error
        self._rho_lo, self._rho_hi = c.raw_range("ER_Price", "Rho")
        self._segment_hi = c.raw_range("ER_Price", "Segment")[1]  # Segment counts mod 8
        self._kkt_cache: dict[float, float] = {}
        self.sig_cycle = cycle_s("ER_Price_Sync", scenario.ts)  # the signature's repeat (1 s)
        self._signed: tuple[SignedSegment, bytes] | None = None  # the last one signed
        self._sig_sent: SignedSegment | None = None   # the last one sent
        self._sig_next = 0.0                          # its next repeat (s from the first tick)

        self._init_clock()
        self.rho = scenario.prices[0].rho
        self.segment = 0
        self.grid_power = scenario.load_kw
        self.cost_rate = 0.0
        self.optimal_cost_rate = 0.0
        self.cost = 0.0
        self.optimal_cost = 0.0

    # ------------------------------------------------------------------ commands

    def send_command(self, kind: str, target: int, k: float | None = None,
                     h: float | None = None) -> None:
        """Queue an ER_Command (sent at the next tick, then repeated: 3 frames 10 ms apart).

        ``kind``: "isolate", "reconnect", "set_gains" (it needs ``k`` and ``h``, 0..16.383
        in steps of 0.001: the DBC's GainK/GainH), "pin" or "unpin" (CMD-7). Thread-safe: a
        tool may call it while run_node runs.
        """
        key = str(kind).lower()
        if key not in COMMANDS:
            raise ParameterError("command", f"one of {', '.join(COMMANDS)}", kind)
        n = self.scenario.n
        if isinstance(target, bool) or not isinstance(target, int) or not 1 <= target <= n:
            raise ParameterError("command target", f"an agent in 1..{n}", target)
        gains = {"GainK": 0, "GainH": 0}
        if key == "set_gains":
            for sig, v in (("GainK", k), ("GainH", h)):
                lo, hi = self.codec.raw_range("ER_Command", sig)
                raw = round(v * 1000) if isinstance(v, (int, float)) and math.isfinite(v) else None
                if raw is None or not lo <= raw <= hi:
                    raise ParameterError(f"set_gains {sig[-1].lower()}",
                                         f"a gain in {lo / 1000:g}..{hi / 1000:g}", v)
                gains[sig] = raw
        elif k is not None or h is not None:
            raise ParameterError("command gains", "k and h only with set_gains", (k, h))
        elif key in PIN_GAIN_K:
            gains["GainK"] = PIN_GAIN_K[key]
        with self._lock:
            self._pending.append(_PendingCommand({"Command": int(COMMANDS[key]),
                                                  "Target": target_raw(target),
                                                  **gains}))

    # ------------------------------------------------------------------ receive

    def on_frame(self, msg: can.Message, t: float) -> None:
        """Take one received frame at time ``t``: the plant's totals, for the grid
        balance and the cost ledger, or an agent's MC frame, for the failover."""
        f = self.io.receive(msg, t)
        if f is None:
            return
        agent = self._mc.get(f.frame_id)
        if agent is not None:
            a = self._agents[agent]
            restarted = a.lost or (a.state != State.INIT and f.raw["State"] == State.INIT)
            if restarted and agent in self._commanded:
                log.info("router: agent %d (pinned by the failover) is back: pinning it "
                         "again", agent)
                self.send_command("pin", agent)
            a.rx, a.state, a.up, a.lost = t, f.raw["State"], True, False
            return
        self.counters["totals_frames"] += 1
        self.totals = _Totals(f.phys("BatteryPower"), f.phys("BatteryCostRate"), t, True)

    # ------------------------------------------------------------------ periodic

    def tick(self, t: float) -> list[can.Message]:
        """One router period at ``t``: the price schedule, the scheduled commands
        and the ledger advanced; the frames due (none inside a silent window)."""
        dt, t_rel = self._advance(t)
        self.rho, self.segment = self.scenario.price_at(t_rel + SCHEDULE_EPS_S)
        self._update_ledger(t, dt)
        silent = any(w.active(t_rel) for w in self.silent)

        frames: list[tuple[str, dict[str, int]]] = []
        if self.signed_price:  # before the first ER_Price of a new segment (AUTH-31)
            frames += self._signature_pages(t_rel, silent)
        if self._price.due(t_rel):
            frames.append(("ER_Price", self._price_raw()))
        while (self._next_event < len(self._events)
               and self._events[self._next_event].t <= t_rel + SCHEDULE_EPS_S):
            e = self._events[self._next_event]
            self._next_event += 1
            self.counters["events"] += 1
            log.info("router: t = %.3f s: %s agent %d", t_rel, e.action, e.agent)
            self.send_command(EVENT_COMMANDS[e.action], e.agent)
        if self._mc:
            self._failover(t, t_rel)
        frames += self._due_commands(t_rel)
        if self._balance.due(t_rel):  # both pages: the ledger pairs rates of one instant
            frames += [("ER_Balance", raw) for raw in self._balance_raw()]

        if silent:
            self.counters["silenced_frames"] += len(frames)
            return []
        out = self.io.syncs(t)
        for name, raw in frames:  # a burst of commands re-announces its count mid-way
            out += self.io.syncs(t) if name == "ER_Command" else []
            out.append(self._send(name, raw))
        return out

    def _failover(self, t: float, t_rel: float) -> None:
        """Agents up or lost by their MC frames; if a pinned agent is lost, pin one agent
        in every component of the agents up that holds no pinned agent up."""
        newly_lost = []
        for i, a in self._agents.items():
            up = a.rx is not None and t - a.rx <= self.agent_timeout + 1e-9
            if a.up and not up:
                a.lost = True
                self.io.sender_lost(self.codec.frame_id(mc_name(i)))  # its gap aliases
                log.info("router: AGENT_%d_MC timed out", i)
                if i in self.pinned:
                    newly_lost.append(i)
            a.up = up
        lost = sorted(i for i in self.pinned
                      if self._agents[i].lost or self._agents[i].state == State.ISOLATED)
        if not lost:
            return
        live = [i for i, a in self._agents.items() if a.up and a.state != State.ISOLATED]
        chosen = failover_choice(self.scenario.n, self.scenario.edges, self.pinned, live)
        if not chosen:
            return
        for i in chosen:
            self.pinned.add(i)
            self._commanded.add(i)
            self.counters["failovers"] += 1
            self.send_command("pin", i)
        event = Failover(t_rel, tuple(lost), tuple(sorted(chosen)))
        self.failover_log.append(event)
        log.warning("router: failover at %s", event.line())

    def _due_commands(self, t_rel: float) -> list[tuple[str, dict[str, int]]]:
        out = []
        with self._lock:
            for p in self._pending:
                if p.next_due is None or t_rel >= p.next_due - SCHEDULE_EPS_S:
                    out.append(("ER_Command", dict(p.raw)))
                    p.left -= 1
                    p.next_due = t_rel + COMMAND_SPACING_S
            self._pending = [p for p in self._pending if p.left > 0]
        return out

    def _update_ledger(self, t: float, dt: float) -> None:
        sc = self.scenario
        tot = self.totals
        if tot.fresh and tot.rx is not None and t - tot.rx > self.totals_timeout + 1e-9:
            tot.fresh = False
            self.io.sender_lost(self._totals_id)  # an outage's counter gap aliases
            self.counters["totals_timeouts"] += 1
            log.info("router: %s timed out; holding ΣP = %.2f kW", TOTALS, tot.power)
        self.grid_power = sc.load_kw - tot.power
        self.cost_rate = tot.cost_rate + self.rho * self.grid_power
        opt = self._kkt_cache.get(self.rho)
        if opt is None:
            opt = self._kkt_cache[self.rho] = kkt_optimum(sc.batteries, self.rho, sc.load_kw)[1]
        self.optimal_cost_rate = opt
        self.cost += self.cost_rate * dt / 3600.0
        self.optimal_cost += opt * dt / 3600.0

    # ------------------------------------------------------------------ transmit

    def _rho_raw(self) -> tuple[int, bool]:
        """ρ as the raw Q24 Rho, and whether it had to be clamped to the DBC's range."""
        raw = round(self.rho * (1 << LAMBDA_Q))
        clamped = min(self._rho_hi, max(self._rho_lo, raw))
        return clamped, clamped != raw

    def _price_raw(self) -> dict[str, int]:
        raw, saturated = self._rho_raw()
        if saturated:
            self.counters["encode_saturations"] += 1
        return {"PriceValid": 1, "Rho": raw, "Segment": self.segment % (self._segment_hi + 1)}

    def _signature_pages(self, t_rel: float, silent: bool) -> list[tuple[str, dict[str, int]]]:
        """signed_price: the ER_PriceSig pages due at ``t_rel``: at a new segment (signed
        then, before its first ER_Price) and every ``sig_cycle``; a signature that falls
        due in a silent window goes out at its end."""
        seg = SignedSegment(self.io.boot, self.segment % SEGMENT_MOD, 1, self._rho_raw()[0])
        if seg == self._sig_sent and t_rel < self._sig_next - SCHEDULE_EPS_S:
            return []
        if self._signed is None or self._signed[0] != seg:
            self._signed = (seg, sign(self.io.keys.price_sign or b"", self.io.keys.fleet_id,
                                      seg))
            self.counters["price_signatures"] += 1
        if silent:
            return []
        self._sig_sent, self._sig_next = seg, t_rel + self.sig_cycle
        return [("ER_PriceSig", raw) for raw in pages(*self._signed)]

    def _balance_raw(self) -> list[dict[str, int]]:
        """Every ER_Balance page, in page order, from the ledger's values now."""
        values = {"GridPower": self.grid_power, "CostRate": self.cost_rate,
                  "OptimalCostRate": self.optimal_cost_rate}
        out = []
        for page, sigs in self.codec.pages("ER_Balance").items():
            raw = {"Page": page}
            for sig in sigs:
                lo, hi = self.codec.raw_range("ER_Balance", sig)
                r = round(values[sig] / self.codec.scale("ER_Balance", sig))
                if not lo <= r <= hi:
                    self.counters["encode_saturations"] += 1
                    r = min(hi, max(lo, r))
                raw[sig] = r
            out.append(raw)
        return out

    def _send(self, name: str, raw: dict[str, int]) -> can.Message:
        if name == "ER_PriceSig":
            self.counters["signature_frames"] += 1
            return self.io.send_transfer(name, raw)
        msg = self.io.send(name, raw)
        self.counters[{"ER_Price": "price_frames", "ER_Command": "command_frames",
                       "ER_Balance": "balance_frames"}[name]] += 1
        return msg

    # ------------------------------------------------------------------ reporting

    def summary(self) -> str:
        """The router's summary at exit: ρ, grid power, cost against the optimum
        and counters."""
        t = self.elapsed
        c = ", ".join(f"{k}={v}" for k, v in sorted(self.counters.items()) if v) or "none"
        extra = (f" ({100 * (self.cost / self.optimal_cost - 1):+.2f} % vs optimal)"
                 if self.optimal_cost > 0 else "")
        fo = "".join(f"; failover {e.line()}" for e in self.failover_log)
        return (f"router: t={t:.2f} s, ρ={self.rho:g} (segment {self.segment}), "
                f"P_e={self.grid_power:.2f} kW, cost={self.cost:.4f} cu, optimal="
                f"{self.optimal_cost:.4f} cu{extra}, counters: {c}{fo}")
