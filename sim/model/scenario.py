"""Scenarios as TOML files: graph, batteries, λ(0), price schedule, events, variants.

A user writes a new scenario without touching code (see sim/scenarios/case1.toml
for a commented example). Every key is checked; a bad file raises ConfigError
naming the file, the key and what is wrong. Unknown keys are errors too, so a
typo never silently falls back to a default.

Over 500 lines: one schema, each key's check next to the key's meaning.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from firmware_py.config import (
    PRICE_STEP_MAX,
    RESILIENT_F_MAX,
    RHO_MAX,
    RHO_MIN,
    AgentConfig,
    Transmit,
)
from firmware_py.contract import N_AGENTS_MAX
from firmware_py.controllers import ControllerConfig
from firmware_py.errors import ConfigError, ParameterError
from sim.model import graph
from sim.model.cost import Battery

SCENARIO_DIR = Path(__file__).resolve().parents[1] / "scenarios"
MAX_AGENTS = N_AGENTS_MAX  # on a bus: the DBC's AGENT_1..AGENT_N frames
SIM_MAX_AGENTS = 1000      # in the simulator (lockstep, references): no frame IDs to run out of
CONTROLLER_KEYS = {"kind", "k", "h", "dwell", "band", "ft_exponent"}
BATTERY_KEYS = {"alpha", "beta", "m", "p_min", "p_max", "capacity_kwh", "soc0", "v_nom",
                "r_internal", "lambda0"}
# physically possible ranges of a battery's parameters (units as in sim.model.cost.Battery);
# (lo, hi, lo excluded). Limits: the setpoint frame's range (AGENT_i_Setpoint, ±327.67 kW)
P_LIMIT_KW = 327.67
BATTERY_RANGES: dict[str, tuple[float, float, bool]] = {
    "alpha": (0.0, 100.0, True),           # cu/(kW²·h): > 0, or λ(P) is not invertible
    "beta": (-100.0, 100.0, False),        # cu/kWh, within the λ range
    "m": (0.0, 100.0, False),              # degradation adds cost: ≥ 0 (1 + m divides)
    "p_min": (-P_LIMIT_KW, P_LIMIT_KW, False),
    "p_max": (-P_LIMIT_KW, P_LIMIT_KW, False),
    "capacity_kwh": (0.0, 1e6, True),      # the SoC integrates P / capacity
    "soc0": (0.0, 1.0, False),
    "v_nom": (0.0, 1e4, True),             # V; the current is P / V
    "r_internal": (0.0, 100.0, False),     # Ω
}
# the longest run: agents × samples (duration / Ts), what the simulator and the log
# analysis hold in memory (80 MB per float array): e.g. 4 agents for 6.9 h at Ts = 10 ms
MAX_AGENT_SAMPLES = 10_000_000
# a price bound outside the agents' λ range is moot: the range check rejects the price first
PRICE_BOUND_RANGE = (AgentConfig.lambda_min, AgentConfig.lambda_max)


@dataclass(frozen=True)
class PriceStep:
    """The price ρ in force from time ``t`` on."""

    t: float
    rho: float


@dataclass(frozen=True)
class Event:
    """A scheduled plug-and-play event: ``agent`` isolated or reconnected at ``t``."""

    t: float
    agent: int
    action: str  # "isolate" | "reconnect"


@dataclass(frozen=True)
class Variant:
    """A named controller override of a case (``--variant``)."""

    label: str
    controller: Mapping[str, Any]


@dataclass(frozen=True)
class Scenario:
    """One case: graph, batteries, controller, price schedule, events and limits
    (a scenario TOML, validated)."""

    name: str
    title: str
    source: str
    ts: float
    duration: float
    load_kw: float
    controller: ControllerConfig
    n: int
    edges: tuple[tuple[float, ...], ...]
    pinned: tuple[int, ...]
    batteries: tuple[Battery, ...]
    lambda0: tuple[float, ...]
    prices: tuple[PriceStep, ...]
    events: tuple[Event, ...] = ()
    variants: tuple[Variant, ...] = field(default=())
    # price plausibility bounds every agent gets (limits.rho_min/rho_max of its config)
    rho_min: float = RHO_MIN
    rho_max: float = RHO_MAX
    price_step_max: float = PRICE_STEP_MAX  # a larger step is accepted once it persists
    resilient_f: int = 0  # W-MSR trimming in every agent's ξ (0: off; sim.model.robust)
    # when the agents send their MC frame (``transmit``, ``event_threshold``,
    # ``event_heartbeat``; firmware_py.config.Transmit): every tick unless "event"
    transmit: Transmit = Transmit()
    # the bus run's frame format (``[bus] fd``): CAN FD frames with the bit-rate switch, an
    # FD twin of the DBC (dbc/bess_ded_fd.dbc, ``lambda_tags``), instead of classic CAN
    fd: bool = False
    # [security] signed_price: the router signs each price segment (Ed25519), the agents
    # take only the signed price (AUTH-31..33, docs/security.md; firmware_py and firmware_c)
    signed_price: bool = False
    # [security] lambda_tags (CAN FD only): λ and its sync carry a 24-bit tag per receiver
    # under the pair's key (AUTH-34, dbc/bess_ded_fd.dbc); false: λ under its sender's node
    # key, 8 bytes (dbc/bess_ded_fd_untagged.dbc), for a bus that cannot afford the tags
    lambda_tags: bool = True

    # ---- derived views

    @property
    def adjacency(self) -> np.ndarray:
        """The weighted adjacency matrix A of the graph."""
        return graph.adjacency(self.n, self.edges)

    @property
    def h(self) -> np.ndarray:
        """H = L + B of the graph and its pinned agents."""
        return graph.h_matrix(self.adjacency, graph.pinning(self.n, self.pinned))

    def neighbours(self, agent: int) -> list[tuple[int, float]]:
        """(neighbour, weight) pairs of a 1-based agent."""
        a = self.adjacency
        return [(j + 1, float(a[agent - 1, j])) for j in range(self.n) if a[agent - 1, j]]

    def analysis(self) -> graph.GraphReport:
        """The graph's analysis for this controller (regular, discrete-stable)."""
        c = self.controller
        return graph.analyse(self.h, c.k, c.h, c.ts, c.kind)

    def price_at(self, t: float) -> tuple[float, int]:
        """(ρ, segment index) in force at time t."""
        seg = 0
        for i, step in enumerate(self.prices):
            if step.t <= t + 1e-12:
                seg = i
        return self.prices[seg].rho, seg

    @property
    def steps(self) -> int:
        """Samples in the run: duration / Ts, rounded."""
        return round(self.duration / self.ts)

    # ---- variants

    def with_controller(self, **overrides: Any) -> Scenario:
        """The scenario with controller fields replaced; ConfigError (naming the
        source) for a bad value."""
        try:
            return replace(self, controller=replace(self.controller, **overrides))
        except ParameterError as e:
            raise ConfigError(self.source, f"controller.{e.name}", str(e)) from None

    def variant(self, label: str) -> Scenario:
        """The variant named ``label``: exactly, else ignoring case (``pc`` for ``PC``)."""
        exact = [v for v in self.variants if v.label == label]
        folded = [v for v in self.variants if v.label.casefold() == label.casefold()]
        for v in exact or (folded if len(folded) == 1 else []):
            return replace(self.with_controller(**v.controller), variants=())
        known = ", ".join(v.label for v in self.variants) or "none"
        raise ConfigError(self.source, "variant", f"expected one of {known}, but got {label!r}")

    def runs(self) -> list[tuple[str, Scenario]]:
        """(label, scenario) for every variant, or the scenario itself if it has none."""
        if not self.variants:
            return [(self.controller.kind, self)]
        return [(v.label, self.variant(v.label)) for v in self.variants]


# --------------------------------------------------------------------------- loading


def case_path(case: int | str) -> Path:
    """The scenario file of paper case ``case``; ConfigError listing the known
    cases if there is none."""
    path = SCENARIO_DIR / f"case{case}.toml"
    if not path.exists():
        known = sorted(p.stem.removeprefix("case") for p in SCENARIO_DIR.glob("case*.toml"))
        raise ConfigError(str(path), "case", f"expected one of {', '.join(known)}, "
                          f"but got {case!r}")
    return path


def load_case(case: int | str) -> Scenario:
    """Paper case ``case`` (1..7) as a Scenario."""
    return load_scenario(case_path(case))


def load_scenario(path: str | Path) -> Scenario:
    """A scenario TOML file, parsed and validated; ConfigError naming the file
    and key on any problem."""
    path = Path(path)
    src = str(path)
    try:
        data = tomllib.loads(path.read_bytes().decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError(src, "file", "expected an existing TOML file, but it does not exist")\
            from None
    except IsADirectoryError:
        raise ConfigError(src, "file", "expected a TOML file, but it is a directory") from None
    except OSError as e:  # unreadable (permissions, I/O): the user's to fix
        raise ConfigError(src, "file", f"expected a readable TOML file, but got: "
                          f"{e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise ConfigError(src, "file", f"expected a UTF-8 text file, but byte {e.start} is "
                          f"0x{e.object[e.start]:02x}, not text") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(src, "file", f"expected valid TOML, but got: {e}") from None
    return parse_scenario(data, src)


def parse_scenario(data: Mapping[str, Any], src: str) -> Scenario:
    """A Scenario from parsed TOML ``data`` (``src`` names it in errors);
    ConfigError on an unknown, missing or out-of-range key."""
    r = _Reader(src)
    r.only(data, "", {"name", "title", "ts", "duration", "load_kw", "controller", "graph",
                      "price", "battery", "event", "variant", "limits", "resilient_f",
                      "transmit", "event_threshold", "event_heartbeat", "bus", "security"})
    ts = r.number(data, "ts", lo=1e-4, hi=1.0)
    duration = r.number(data, "duration", lo=ts, hi=1e5)

    g = r.table(data, "graph")
    r.only(g, "graph", {"agents", "edges", "pinned"})
    n = int(r.number(g, "agents", lo=1, hi=SIM_MAX_AGENTS, key="graph.agents", integer=True))
    # list items and tables are numbered from 1 in messages, as agents and batteries are
    edges = tuple(r.edge(e, n, f"graph.edges[{i}]") for i, e in
                  enumerate(r.list(g, "edges", "graph.edges"), start=1))
    pinned = tuple(r.agent(p, n, f"graph.pinned[{i}]") for i, p in
                   enumerate(r.list(g, "pinned", "graph.pinned"), start=1))
    if not pinned:
        raise ConfigError(src, "graph.pinned", "expected at least one agent that hears the price")
    if cut := [a for comp in graph.unpinned_components(n, edges, pinned) for a in comp]:
        # such agents never hear ρ, even through neighbours: H = L + B is singular
        names = ", ".join(str(a) for a in cut)
        raise ConfigError(src, "graph", f"agent{'s' if len(cut) > 1 else ''} {names} cannot "
                          f"reach a pinned agent (pinned: {', '.join(map(str, pinned))}); "
                          "expected every agent connected to one")

    ctrl = r.table(data, "controller")
    r.only(ctrl, "controller", CONTROLLER_KEYS)
    controller = r.controller(dict(ctrl), ts, "controller")

    bats = r.list(data, "battery", "battery")
    if len(bats) != n:
        raise ConfigError(src, "battery", f"expected {n} [[battery]] tables (graph.agents), "
                          f"but got {len(bats)}")
    batteries, lambda0 = [], []
    for i, b in enumerate(bats):
        key = f"battery[{i + 1}]"  # agent i + 1's: numbered from 1 as the agents are
        r.only(b, key, BATTERY_KEYS)
        for need in ("alpha", "beta", "m", "p_min", "p_max"):
            if need not in b:
                raise ConfigError(src, f"{key}.{need}", "is required")
        kw = {k: r.number(b, k, lo=lo, hi=hi, lo_open=lo_open, key=f"{key}.{k}")
              for k, (lo, hi, lo_open) in BATTERY_RANGES.items() if k in b}
        if not kw["p_min"] < kw["p_max"]:
            raise ConfigError(src, f"{key}.p_max", f"expected p_min < p_max, but got "
                              f"{kw['p_min']} ≥ {kw['p_max']}")
        if not abs(idle := kw["beta"] * (1 + kw["m"])) < 128:
            raise ConfigError(src, f"{key}.beta", f"expected an idle marginal cost β·(1+m) "
                              f"within ±128 cu/kWh (the agent's int32 Q24), but got {idle:g}")
        batteries.append(Battery(**kw))
        lambda0.append(r.number(b, "lambda0", lo=-100, hi=100, key=f"{key}.lambda0"))

    lim = data.get("limits", {})
    r.only(lim, "limits", {"rho_min", "rho_max", "price_step_max"})
    lo, hi = PRICE_BOUND_RANGE
    rho_min = r.number(lim, "rho_min", lo=lo, hi=hi, key="limits.rho_min") \
        if "rho_min" in lim else RHO_MIN
    rho_max = r.number(lim, "rho_max", lo=lo, hi=hi, key="limits.rho_max") \
        if "rho_max" in lim else RHO_MAX
    step_max = r.number(lim, "price_step_max", lo=1e-6, hi=hi - lo, key="limits.price_step_max")\
        if "price_step_max" in lim else PRICE_STEP_MAX
    if not rho_min < rho_max:
        raise ConfigError(src, "limits.rho_max", f"expected rho_min < rho_max, but got "
                          f"{rho_min:g} ≥ {rho_max:g}")

    prices = []
    for i, p in enumerate(r.list(data, "price", "price"), start=1):
        r.only(p, f"price[{i}]", {"t", "rho"})
        prices.append(PriceStep(r.number(p, "t", lo=0, key=f"price[{i}].t"),
                                r.number(p, "rho", lo=-100, hi=100, key=f"price[{i}].rho")))
    if out := [(i, p.rho) for i, p in enumerate(prices, start=1)
               if not rho_min <= p.rho <= rho_max]:
        i, rho = out[0]
        raise ConfigError(src, f"price[{i}].rho", f"expected a price within the agents' "
                          f"plausibility bounds [limits] rho_min..rho_max = {rho_min:g}.."
                          f"{rho_max:g} cu/kWh (they reject any other and go SAFE), but got "
                          f"{rho:g}: widen [limits] in the scenario")
    if not prices or prices[0].t != 0:
        raise ConfigError(src, "price", "expected a schedule whose first step is at t = 0")
    if any(b.t <= a.t for a, b in zip(prices, prices[1:], strict=False)):
        raise ConfigError(src, "price", "expected strictly increasing times")
    if late := [(i, p.t) for i, p in enumerate(prices, start=1) if p.t >= duration]:
        i, t = late[0]
        raise ConfigError(src, f"price[{i}].t", f"expected a time before the scenario's end "
                          f"(duration = {duration:g} s), but got {t:g}: the step would never "
                          "apply")
    if n * duration / ts > MAX_AGENT_SAMPLES:
        raise ConfigError(src, "duration", f"expected at most {MAX_AGENT_SAMPLES:.0e} "
                          f"agent-samples (graph.agents × duration / ts = {n} × "
                          f"{duration:g} / {ts:g}), but got {n * duration / ts:.3g}")

    events = []
    for i, e in enumerate(data.get("event", []), start=1):
        key = f"event[{i}]"
        r.only(e, key, {"t", "agent", "action"})
        action = e.get("action")
        if action not in ("isolate", "reconnect"):
            raise ConfigError(src, f"{key}.action", f"expected 'isolate' or 'reconnect', but "
                              f"got {action!r}")
        events.append(Event(r.number(e, "t", lo=0, hi=duration, key=f"{key}.t"),
                            r.agent(e.get("agent"), n, f"{key}.agent"), action))

    variants = []
    for i, v in enumerate(data.get("variant", []), start=1):
        key = f"variant[{i}]"
        r.only(v, key, CONTROLLER_KEYS | {"label"})
        label = v.get("label")
        if not isinstance(label, str) or not label:
            raise ConfigError(src, f"{key}.label", f"expected a non-empty string, but got "
                              f"{label!r}")
        overrides = {k: x for k, x in v.items() if k != "label"}
        r.controller({**ctrl, **overrides}, ts, key)  # validate now, not at run time
        variants.append(Variant(label, overrides))

    transmit = r.transmit(data)
    fd = r.switch(data, "bus", "fd", "true (CAN FD) or false (classic CAN)")
    security = frozenset({"signed_price", "lambda_tags"})
    signed_price = r.switch(data, "security", "signed_price",
                            "true (the router signs each price segment) or false",
                            others=security)
    lambda_tags = r.switch(data, "security", "lambda_tags", "true (on CAN FD, λ carries a "
                           "tag per receiver, AUTH-34) or false (λ under its sender's node "
                           "key)", default=True, others=security)
    if not lambda_tags and not fd:
        raise ConfigError(src, "security.lambda_tags", "expected it only with [bus] fd = true "
                          "(classic CAN has no room for the tags: λ is always under its "
                          "sender's node key there), but got false on a classic bus")
    sc = Scenario(
        name=str(data.get("name", Path(src).stem)), title=str(data.get("title", "")), source=src,
        ts=ts, duration=duration, load_kw=r.number(data, "load_kw", lo=-1e6, hi=1e6),
        controller=controller, n=n, edges=edges, pinned=pinned, batteries=tuple(batteries),
        lambda0=tuple(lambda0), prices=tuple(prices), events=tuple(events),
        variants=tuple(variants), rho_min=rho_min, rho_max=rho_max,
        price_step_max=step_max, transmit=transmit, fd=fd, signed_price=signed_price,
        lambda_tags=lambda_tags,
        resilient_f=int(r.number(data, "resilient_f", lo=0, hi=RESILIENT_F_MAX, integer=True))
        if "resilient_f" in data else 0)
    if n <= MAX_AGENTS:  # a fleet a bus can carry: its agents' configurations load too
        for label, run in sc.runs():
            check_agents(run, "variant " + label if sc.variants else "")
    return sc


def check_agents(sc: Scenario, where: str) -> None:
    """Every agent's configuration as `up` writes it loads in firmware_py (its λ(0) inside
    the agent's limits, k_max·Ts in Q1.30, timeouts ≤ 60 s, ...): a scenario, variant or
    time scale the nodes would refuse at their start is refused here, before any runs."""
    from firmware_py.config import agent_configs_from_scenario, parse_agent_config

    for cfg in agent_configs_from_scenario(sc):
        try:
            parse_agent_config(tomllib.loads(cfg.to_toml()), cfg.source)
        except ConfigError as e:
            raise ConfigError(sc.source, f"agent {cfg.id}" + (f", {where}" if where else ""),
                              f"expected values agent {cfg.id}'s configuration takes, but "
                              f"its [{e.key}] {e.problem}") from None


class _Reader:
    """Typed, range-checked access to parsed TOML that names the file and key on error."""

    def __init__(self, src: str) -> None:
        self.src = src

    def fail(self, key: str, problem: str) -> ConfigError:
        return ConfigError(self.src, key, problem)

    def only(self, table: Any, where: str, allowed: set[str]) -> None:
        if not isinstance(table, Mapping):
            raise self.fail(where or "file", f"expected a table, but got {table!r}")
        for key in table:
            if key not in allowed:
                raise self.fail(f"{where}.{key}" if where else key,
                                f"unknown key; expected one of {', '.join(sorted(allowed))}")

    def switch(self, data: Mapping[str, Any], table: str, key: str, what: str,
               default: bool = False, others: frozenset[str] = frozenset()) -> bool:
        """An optional table holding the optional boolean ``key`` (``[bus] fd``,
        ``[security] signed_price``) and ``others``: ``default`` when absent."""
        if table not in data:
            return default
        t = self.table(data, table)
        self.only(t, table, {key, *others})
        value = t.get(key, default)
        if not isinstance(value, bool):
            raise ConfigError(self.src, f"{table}.{key}", f"expected {what}, but got {value!r}")
        return value

    def table(self, data: Mapping[str, Any], key: str) -> Mapping[str, Any]:
        if key not in data:
            raise self.fail(key, "is required")
        value = data[key]
        if not isinstance(value, Mapping):
            raise self.fail(key, f"expected a table, but got {value!r}")
        return value

    def list(self, data: Mapping[str, Any], name: str, key: str) -> list[Any]:
        value = data.get(name)
        if not isinstance(value, list):
            raise self.fail(key, f"expected a list, but got {value!r}")
        return value

    def number(self, data: Mapping[str, Any], name: str, lo: float = -math.inf,
               hi: float = math.inf, key: str | None = None, integer: bool = False,
               lo_open: bool = False) -> float:
        key = key or name
        if name not in data:
            raise self.fail(key, "is required")
        x = data[name]
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise self.fail(key, f"expected a number, but got {x!r}")
        if integer and not float(x).is_integer():
            raise self.fail(key, f"expected an integer, but got {x!r}")
        if not lo <= x <= hi or (lo_open and x == lo):
            raise self.fail(key, f"expected a value in {'(' if lo_open else '['}{lo:g}, "
                            f"{hi:g}], but got {x!r}")
        return float(x)

    def transmit(self, data: Mapping[str, Any]) -> Transmit:
        kw: dict[str, Any] = {}
        if "transmit" in data:
            kw["mode"] = data["transmit"]
        if "event_threshold" in data:
            kw["threshold"] = self.number(data, "event_threshold", lo=0, hi=1)
        if "event_heartbeat" in data:
            kw["heartbeat"] = int(self.number(data, "event_heartbeat", lo=1, hi=1e6,
                                              integer=True))
        try:
            return Transmit(**kw)
        except ParameterError as e:
            key = "transmit" if e.name == "mode" else f"event_{e.name}"
            raise self.fail(key, f"expected {e.expected}, but got {e.got!r}") from None

    def agent(self, x: Any, n: int, key: str) -> int:
        if isinstance(x, bool) or not isinstance(x, int) or not 1 <= x <= n:
            raise self.fail(key, f"expected an agent number in 1..{n}, but got {x!r}")
        return x

    def edge(self, e: Any, n: int, key: str) -> tuple[float, ...]:
        if not isinstance(e, list) or len(e) not in (2, 3):
            raise self.fail(key, f"expected [i, j] or [i, j, weight], but got {e!r}")
        i, j = self.agent(e[0], n, key), self.agent(e[1], n, key)
        if i == j:
            raise self.fail(key, f"expected two different agents, but got a self-loop {e!r}")
        w = self.number({"w": e[2]}, "w", lo=1e-3, hi=100, key=key) if len(e) == 3 else 1.0
        return (i, j, w)

    def controller(self, table: Mapping[str, Any], ts: float, key: str) -> ControllerConfig:
        for name, value in table.items():
            if name != "kind" and (isinstance(value, bool) or not isinstance(value, (int, float))):
                raise self.fail(f"{key}.{name}", f"expected a number, but got {value!r}")
        try:
            return ControllerConfig(ts=ts, **table)
        except ParameterError as e:
            raise self.fail(f"{key}.{e.name}", f"expected {e.expected}, but got {e.got!r}")\
                from None


# --------------------------------------------------------------------------- time scaling


def scaled(sc: Scenario, factor: float) -> Scenario:
    """The same discrete system on a time axis stretched by ``factor``.

    Ts, durations and event/price times are multiplied by f; k by 1/f and h by
    1/f², so that k·Ts and h·Ts² (what the discrete step uses) are unchanged and
    the scaled run is the same per sample. Used to run a case in a slow emulated
    guest (QEMU without KVM) at a sample rate it can keep up with.
    """
    if not (math.isfinite(factor) and factor >= 1):
        raise ConfigError(sc.source, "time_scale", f"expected a factor ≥ 1, but got {factor!r}")
    if factor == 1:
        return sc
    c = sc.controller
    try:
        ctrl = replace(c, ts=c.ts * factor, k=c.k / factor, h=c.h / factor**2,
                       dwell=c.dwell * factor)
    except ParameterError as e:
        raise ConfigError(sc.source, "time_scale", f"expected a factor that keeps the "
                          f"controller valid (Ts·F ≤ 1 s: F ≤ {1 / c.ts:g} here), but got "
                          f"{factor:g}: {e}") from None
    out = replace(sc, ts=sc.ts * factor, duration=sc.duration * factor, controller=ctrl,
                  prices=tuple(PriceStep(p.t * factor, p.rho) for p in sc.prices),
                  events=tuple(Event(e.t * factor, e.agent, e.action) for e in sc.events),
                  name=f"{sc.name}-x{factor:g}", variants=())
    check_agents(out, f"time scale {factor:g}")
    return out


def to_toml(sc: Scenario) -> str:
    """Serialise a (variant-free) scenario back to the TOML schema load_scenario reads.

    Written by tomli_w, so any title or name (quotes, backslashes, newlines) round-trips.
    """
    c = sc.controller
    doc: dict[str, Any] = {
        "name": sc.name, "title": sc.title, "ts": sc.ts, "duration": sc.duration,
        "load_kw": sc.load_kw,
        "controller": {"kind": c.kind, "k": c.k, "h": c.h, "dwell": c.dwell, "band": c.band,
                       "ft_exponent": c.ft_exponent},
        "graph": {"agents": sc.n,
                  "edges": [[int(e[0]), int(e[1]), float(e[2]) if len(e) > 2 else 1.0]
                            for e in sc.edges],
                  "pinned": list(sc.pinned)},
        "price": [{"t": p.t, "rho": p.rho} for p in sc.prices],
        "limits": {"rho_min": sc.rho_min, "rho_max": sc.rho_max,
                   "price_step_max": sc.price_step_max},
        "battery": [{"lambda0": l0, **{k: float(getattr(b, k)) for k in sorted(BATTERY_KEYS)
                                       if k != "lambda0"}}
                    for b, l0 in zip(sc.batteries, sc.lambda0, strict=True)],
    }
    if sc.resilient_f:  # only when on: a default scenario's file stays as it was
        doc["resilient_f"] = sc.resilient_f
    if sc.transmit != Transmit():  # periodic scenarios are written as they were
        doc.update(transmit=sc.transmit.mode, event_threshold=sc.transmit.threshold,
                   event_heartbeat=sc.transmit.heartbeat)
    if sc.fd:  # classic scenarios are written as they were
        doc["bus"] = {"fd": True}
    if sc.signed_price:  # unsigned scenarios are written as they were
        doc["security"] = {"signed_price": True}
    if sc.fd and not sc.lambda_tags:
        doc.setdefault("security", {})["lambda_tags"] = False
    if sc.events:
        doc["event"] = [{"t": e.t, "agent": e.agent, "action": e.action} for e in sc.events]
    # the source path may hold anything; keep it out of the comment line's way
    origin = " ".join(sc.source.split())
    return f"# written by bess-ded from {origin}\n" + tomli_w.dumps(doc)
