"""One agent's configuration: a TOML file per node, checked before the node starts.

Example (``bess-ded up`` writes one per agent into DIR/agents/)::

    [agent]
    id = 2                  # 1..N_AGENTS_MAX (64 in the DBC), selects the AGENT_<id>_* frames
    lambda0 = 0.6           # λ(0), cu/kWh
    pinned = false          # hears the price in ξ (b_ii = 1)
    fleet_size = 4          # optional: agents in the run; frames of agents beyond it are
                            # counted as foreign (absent: unknown, not checked)
    resilient_f = 0         # optional: W-MSR trimming of F neighbour λ above and F below
                            # the own λ before ξ (0, the default: off; docs/security.md)

    [controller]            # firmware_py.controllers.ControllerConfig
    kind = "reset"
    k = 1.0
    h = 2.0
    ts = 0.01

    [[neighbour]]
    id = 1
    weight = 1.0

    [battery]               # λ → power setpoint
    alpha = 0.005
    beta = 0.18
    m = 0.08
    p_min = -100.0
    p_max = 100.0

    [timeouts]
    neighbour_periods = 3   # a neighbour silent this many of its periods drops out of ξ
    price_s = 0.25          # no valid price for this long → SAFE
    status_s = 0.25         # no PLANT_<id>_Status for this long → SAFE

Both timeouts default to 5 cycles of their frame (firmware_py.contract.timeout_s) at
the controller's Ts: 5 × 50 ms = 0.25 s at Ts = 10 ms, stretched in a time-scaled run.
An agent's inputs are all secured (SecOC), whose freshness window places up to 15 lost
frames in a row (AUTH-12): event mode's neighbour timeout goes up to 15 periods.

    [transmit]              # optional: when the MC frame goes out (firmware-spec TX-7)
    mode = "periodic"       # "periodic": every tick; "event": see below
    threshold = 3e-4        # event: send when |λ − λ last sent| exceeds this (cu/kWh) ...
    heartbeat = 13          # ... and at least every this many ticks (1..13)

In event mode the neighbour timeout defaults to heartbeat + 2 periods (a receiver holds
the last λ it heard until then). Skipped ticks cost the SecOC freshness nothing: the
message count C advances per frame sent, not per tick; the heartbeat is bounded so that
the timeout stays under the counter's 16-value window (15 lost frames in a row).

    [limits]
    lambda_min = -10.0      # plausibility range for any λ or ρ received
    lambda_max = 10.0
    rho_min = -5.0          # price plausibility (docs/safety-model.md): bounds, cu/kWh
    rho_max = 5.0
    price_step_max = 0.5    # largest accepted |Δρ| between accepted price frames ...
    price_persist = 3       # ... unless the same new price comes in this many frames in a row
    lambda_step_max = 0.1   # largest |Δλ| of a RUNNING neighbour per sample (default 10·k·Ts)
    k_min = 0.5             # SET_GAINS bounds (default ×0.5..×2 of the configured gains)
    k_max = 2.0
    h_min = 1.0
    h_max = 4.0
    untrusted_after = 5     # consecutive DLC, range or MAC failures from one source ID ...
    untrusted_s = 1.0       # ... make it untrusted this long (default 1 s × Ts/10 ms)

The safety limits (firmware_py.runtime, firmware_py.nodeio; docs/safety-model.md)
default to values no healthy run of the paper cases 1..7 comes near; the derived ones
(lambda_step_max, the gain bounds, untrusted_s) follow the controller, so a
time-scaled run keeps them per sample.

Any bad key stops the start with ConfigError naming the file and the key.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomli_w

from . import fixedpoint as fx
from .contract import (
    FV_TX_BITS,
    MC_CYCLE_S,
    N_AGENTS_MAX,
    raw_range,
    scale,
    status_name,
    timeout_s,
)
from .controllers import ControllerConfig
from .errors import ConfigError, ParameterError

# the largest gain ER_Command's SET_GAINS can carry (the DBC's GainK/GainH: 14 bits, 0.001)
GAIN_MAX = raw_range("ER_Command", "GainK")[1] * scale("ER_Command", "GainK")

__all__ = ["N_AGENTS_MAX", "AgentConfig", "DispatchParams", "Neighbour",
           "agent_configs_from_scenario", "load_agent_config", "parse_agent_config"]

# the contract's receive timeouts at the DBC's Ts (10 ms); a config derives its own
# from its controller's Ts (time-scaled runs stretch them)
PRICE_TIMEOUT_S = timeout_s("ER_Price", MC_CYCLE_S)
STATUS_TIMEOUT_S = timeout_s(status_name(1), MC_CYCLE_S)

# safety-model defaults (docs/safety-model.md)
# cu/kWh: the paper's prices are 0.6..1.0; day-ahead and intraday markets clear below
# zero often enough that a negative price is no sign of a fault (a scenario's [limits]
# sets its own bounds, sim/model/scenario.py)
RHO_MIN, RHO_MAX = -5.0, 5.0
PRICE_STEP_MAX = 0.5             # cu/kWh per accepted price frame: the paper steps ≤ 0.4
PRICE_PERSIST = 3                # frames of one new price level that make it accepted
LAMBDA_STEP_GAIN = 10.0          # lambda_step_max = 10·k·Ts (0.1 cu/kWh at k = 1, Ts = 10 ms;
                                 # the largest per-sample |Δλ| of cases 1..7 is 0.024)
GAIN_LO, GAIN_HI = 0.5, 2.0      # SET_GAINS bounds: × the configured k and h
UNTRUSTED_AFTER = 5              # consecutive receive failures (as opendbc's safety layer)
UNTRUSTED_S = 1.0                # s at Ts = 10 ms, stretched with Ts
# W-MSR's F: trimming 2F of at most N_AGENTS_MAX − 1 neighbours leaves one (WMSR-1)
RESILIENT_F_MAX = (N_AGENTS_MAX - 1) // 2


# event-triggered MC transmission (issue 23; docs/theory.md, docs/performance.md)
TRANSMIT_MODES = ("periodic", "event")
EVENT_THRESHOLD = 3e-4           # cu/kWh; the final-error cost is bounded in docs/theory.md
EVENT_HEARTBEAT = 13             # ticks: ≥ 90 % fewer frames once settled
NEIGHBOUR_PERIODS = 3            # periodic: a neighbour silent 3 Ts is timed out
HEARTBEAT_MARGIN = 2             # event: timed out after heartbeat + 2 Ts of silence
# a neighbour timeout of at most 15 periods: while a neighbour counts as alive, at most 15
# of its frames in a row can be lost, which the 4-bit counter window still places (AUTH-12)
HEARTBEAT_MAX = (1 << FV_TX_BITS) - 1 - HEARTBEAT_MARGIN  # 13


@dataclass(frozen=True)
class Transmit:
    """When an agent sends its MC frame: every tick ("periodic"), or ("event") when its
    wire λ moved more than ``threshold`` (cu/kWh) from the λ last sent, when its State
    changed, and at least every ``heartbeat`` ticks (firmware-spec TX-7)."""

    mode: str = "periodic"
    threshold: float = EVENT_THRESHOLD
    heartbeat: int = EVENT_HEARTBEAT

    def __post_init__(self) -> None:
        if self.mode not in TRANSMIT_MODES:
            raise ParameterError("mode", f"one of {', '.join(TRANSMIT_MODES)}", self.mode)
        if (isinstance(self.threshold, bool) or not isinstance(self.threshold, (int, float))
                or not (math.isfinite(self.threshold) and 0 <= self.threshold < 1)):
            raise ParameterError("threshold", "a number in [0, 1) cu/kWh", self.threshold)
        if (isinstance(self.heartbeat, bool) or not isinstance(self.heartbeat, int)
                or not 1 <= self.heartbeat <= HEARTBEAT_MAX):
            raise ParameterError("heartbeat", f"an integer number of ticks in "
                                 f"1..{HEARTBEAT_MAX}", self.heartbeat)

    @property
    def event(self) -> bool:
        """Event-triggered (else every tick)."""
        return self.mode == "event"

    @property
    def threshold_q24(self) -> int:
        """The threshold as a Q24 word (q24, NUM-4)."""
        return fx.to_fixed(float(self.threshold), "transmit.threshold")

    @property
    def neighbour_periods(self) -> int:
        """The default neighbour timeout in periods: a receiver holds a silent
        neighbour's λ for up to one heartbeat plus the margin."""
        return self.heartbeat + HEARTBEAT_MARGIN if self.event else NEIGHBOUR_PERIODS

    def to_doc(self) -> dict[str, Any]:
        """The [transmit] table (to_toml)."""
        return {"mode": self.mode, "threshold": self.threshold, "heartbeat": self.heartbeat}


def untrusted_s(ts: float) -> float:
    """The untrusted-source hold time at a controller period ``ts`` (1 s at 10 ms)."""
    return UNTRUSTED_S * ts / MC_CYCLE_S


@dataclass(frozen=True)
class Neighbour:
    """One neighbour of an agent: its id and the edge weight a_ij."""

    id: int
    weight: float = 1.0


@dataclass(frozen=True)
class DispatchParams:
    """What the firmware needs to turn λ into a power setpoint."""

    alpha: float
    beta: float
    m: float
    p_min: float
    p_max: float


@dataclass(frozen=True)
class AgentConfig:
    """Everything one agent node is configured with (its agent TOML, validated):
    identity, controller, neighbours, dispatch parameters, timeouts and limits."""

    id: int
    lambda0: float
    pinned: bool
    controller: ControllerConfig
    neighbours: tuple[Neighbour, ...]
    battery: DispatchParams
    neighbour_timeout_periods: int = NEIGHBOUR_PERIODS
    price_timeout_s: float = PRICE_TIMEOUT_S
    status_timeout_s: float = STATUS_TIMEOUT_S
    lambda_min: float = -10.0
    lambda_max: float = 10.0
    fleet_size: int | None = None   # None: unknown, foreign agent IDs not checked
    rho_min: float = RHO_MIN
    rho_max: float = RHO_MAX
    price_step_max: float = PRICE_STEP_MAX
    price_persist: int = PRICE_PERSIST
    # None: derived from the controller in __post_init__ (so to_toml writes the value)
    lambda_step_max: float | None = None
    k_min: float | None = None
    k_max: float | None = None
    h_min: float | None = None
    h_max: float | None = None
    untrusted_after: int = UNTRUSTED_AFTER
    untrusted_s: float | None = None
    resilient_f: int = 0            # W-MSR trimming (controllers.resilient_trim); 0: off
    transmit: Transmit = Transmit()
    # [security] signed_price (AUTH-31..33): take only the router's signed price (the key
    # file must hold the router's public price key); firmware_c too (src/agent_sig.c)
    signed_price: bool = False
    source: str = "<config>"

    def __post_init__(self) -> None:
        c = self.controller
        derived = {"lambda_step_max": LAMBDA_STEP_GAIN * c.k * c.ts,
                   "k_min": GAIN_LO * c.k, "k_max": GAIN_HI * c.k,
                   "h_min": GAIN_LO * c.h, "h_max": GAIN_HI * c.h,
                   "untrusted_s": untrusted_s(c.ts)}
        for name, value in derived.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)

    def to_toml(self) -> str:
        """The TOML load_agent_config reads back to an equal config (but ``source``)."""
        c, b = self.controller, self.battery
        agent: dict[str, Any] = {"id": self.id, "lambda0": self.lambda0, "pinned": self.pinned}
        if self.fleet_size is not None:
            agent["fleet_size"] = self.fleet_size
        if self.resilient_f:  # written only when on: the default files stay as they were
            agent["resilient_f"] = self.resilient_f
        doc = {
            "agent": agent,
            "controller": {"kind": c.kind, "k": c.k, "h": c.h, "ts": c.ts, "dwell": c.dwell,
                           "band": c.band, "ft_exponent": c.ft_exponent},
            "battery": {"alpha": b.alpha, "beta": b.beta, "m": b.m, "p_min": b.p_min,
                        "p_max": b.p_max},
            "timeouts": {"neighbour_periods": self.neighbour_timeout_periods,
                         "price_s": self.price_timeout_s, "status_s": self.status_timeout_s},
            "limits": {"lambda_min": self.lambda_min, "lambda_max": self.lambda_max,
                       "rho_min": self.rho_min, "rho_max": self.rho_max,
                       "price_step_max": self.price_step_max,
                       "price_persist": self.price_persist,
                       "lambda_step_max": self.lambda_step_max,
                       "k_min": self.k_min, "k_max": self.k_max,
                       "h_min": self.h_min, "h_max": self.h_max,
                       "untrusted_after": self.untrusted_after,
                       "untrusted_s": self.untrusted_s},
        }
        if self.transmit != Transmit():  # periodic files stay as they were
            doc["transmit"] = self.transmit.to_doc()
        if self.signed_price:  # unsigned files stay as they were
            doc["security"] = {"signed_price": True}
        # tomli-w inlines short arrays of tables; [[neighbour]] blocks read better when edited
        nbrs = "".join("\n[[neighbour]]\n" + tomli_w.dumps({"id": nb.id, "weight": nb.weight})
                       for nb in self.neighbours)
        return ("# bess-ded agent configuration (see firmware_py/config.py)\n"
                + tomli_w.dumps(doc) + nbrs)


def load_agent_config(path: str | Path) -> AgentConfig:
    """An agent TOML file, parsed and validated; ConfigError naming the file
    and key on any problem."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_bytes().decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError(str(path), "file", "expected an existing TOML file, but it does not "
                          "exist") from None
    except IsADirectoryError:
        raise ConfigError(str(path), "file", "expected a TOML file, but it is a directory")\
            from None
    except OSError as e:  # unreadable (permissions, I/O): the user's to fix
        raise ConfigError(str(path), "file", f"expected a readable TOML file, but got: "
                          f"{e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise ConfigError(str(path), "file", f"expected a UTF-8 text file, but byte {e.start} "
                          f"is 0x{e.object[e.start]:02x}, not text") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(str(path), "file", f"expected valid TOML, but got: {e}") from None
    return parse_agent_config(data, str(path))


def parse_agent_config(data: Mapping[str, Any], src: str) -> AgentConfig:
    """An agent configuration from parsed TOML ``data`` (``src`` names it in
    errors); ConfigError on an unknown, missing or out-of-range key."""
    def fail(key: str, problem: str) -> ConfigError:
        return ConfigError(src, key, problem)

    def table(key: str, allowed: set[str], required: bool = True) -> Mapping[str, Any]:
        t = data.get(key)
        if t is None and not required:
            return {}
        if not isinstance(t, Mapping):
            raise fail(key, f"expected a table, but got {t!r}")
        for k in t:
            if k not in allowed:
                raise fail(f"{key}.{k}",
                           f"unknown key; expected one of {', '.join(sorted(allowed))}")
        return t

    def num(t: Mapping[str, Any], key: str, name: str, lo: float = -math.inf,
            hi: float = math.inf, default: float | None = None) -> float:
        if name not in t:
            if default is None:
                raise fail(f"{key}.{name}", "is required")
            return default
        x = t[name]
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise fail(f"{key}.{name}", f"expected a number, but got {x!r}")
        if not lo <= x <= hi:
            raise fail(f"{key}.{name}", f"expected a value in [{lo:g}, {hi:g}], but got {x!r}")
        return float(x)

    def agent_id(x: Any, key: str) -> int:
        if isinstance(x, bool) or not isinstance(x, int) or not 1 <= x <= N_AGENTS_MAX:
            raise fail(key, f"expected an agent id in 1..{N_AGENTS_MAX}, but got {x!r}")
        return x

    for k in data:
        if k not in {"agent", "controller", "neighbour", "battery", "timeouts", "limits",
                     "transmit", "security"}:
            raise fail(k, "unknown table; expected agent, controller, neighbour, battery, "
                       "timeouts, limits, transmit or security")
    a = table("agent", {"id", "lambda0", "pinned", "fleet_size", "resilient_f"})
    ident = agent_id(a.get("id"), "agent.id")
    pinned = a.get("pinned", False)
    if not isinstance(pinned, bool):
        raise fail("agent.pinned", f"expected true or false, but got {pinned!r}")
    fleet = a.get("fleet_size")
    if fleet is not None and (isinstance(fleet, bool) or not isinstance(fleet, int)
                              or not ident <= fleet <= N_AGENTS_MAX):
        raise fail("agent.fleet_size", f"expected an agent count in {ident}..{N_AGENTS_MAX} "
                   f"(at least this agent's id), but got {fleet!r}")
    trim = a.get("resilient_f", 0)
    if isinstance(trim, bool) or not isinstance(trim, int) or not 0 <= trim <= RESILIENT_F_MAX:
        raise fail("agent.resilient_f", f"expected an integer in 0..{RESILIENT_F_MAX}, but got "
                   f"{trim!r}")

    c = table("controller", {"kind", "k", "h", "ts", "dwell", "band", "ft_exponent"})
    try:
        controller = ControllerConfig(**c)
    except ParameterError as e:
        raise fail(f"controller.{e.name}", f"expected {e.expected}, but got {e.got!r}") from None
    except TypeError as e:
        raise fail("controller", str(e)) from None

    raw_nbrs = data.get("neighbour", [])
    if not isinstance(raw_nbrs, list):
        raise fail("neighbour", f"expected [[neighbour]] tables, but got {raw_nbrs!r}")
    neighbours = []
    for i, nb in enumerate(raw_nbrs):
        key = f"neighbour[{i + 1}]"  # numbered from 1, as the agents are
        if not isinstance(nb, Mapping) or set(nb) - {"id", "weight"}:
            raise fail(key, f"expected a table with id and weight, but got {nb!r}")
        nid = agent_id(nb.get("id"), f"{key}.id")
        if nid == ident:
            raise fail(f"{key}.id", f"expected another agent than this one ({ident})")
        neighbours.append(Neighbour(nid, num(nb, key, "weight", 1e-3, 100, default=1.0)))
    if len({n.id for n in neighbours}) != len(neighbours):
        raise fail("neighbour", "expected each neighbour once, but got duplicates")

    b = table("battery", {"alpha", "beta", "m", "p_min", "p_max"})
    # the ranges of sim.model.scenario.BATTERY_RANGES: α > 0 (λ(P) invertible), m ≥ 0 (1 + m
    # divides), β within the λ range
    battery = DispatchParams(alpha=num(b, "battery", "alpha", 1e-9, 100),
                             beta=num(b, "battery", "beta", -100, 100),
                             m=num(b, "battery", "m", 0, 100), p_min=num(b, "battery", "p_min"),
                             p_max=num(b, "battery", "p_max"))
    if not battery.p_min < battery.p_max:
        raise fail("battery.p_max", f"expected p_min < p_max, but got {battery.p_min} ≥ "
                   f"{battery.p_max}")
    idle = battery.beta * (1.0 + battery.m)  # an ISOLATE sets λ to it (CMD-3), as firmware_c
    try:
        fx.to_fixed(idle, "battery.beta")
    except ParameterError:
        raise fail("battery.beta", f"expected an idle marginal cost β·(1+m) that fits int32 "
                   f"Q24 (|β·(1+m)| < 128, CMD-3), but got {idle:.17g}") from None
    for key, value in (("p_min", battery.p_min), ("p_max", battery.p_max)):
        if not -327.67 <= value <= 327.67:
            raise fail(f"battery.{key}", f"expected a limit within ±327.67 kW (the setpoint "
                       f"frame's range), but got {value}")

    tx = table("transmit", {"mode", "threshold", "heartbeat"}, required=False)
    try:
        transmit = Transmit(**tx)
    except ParameterError as e:
        raise fail(f"transmit.{e.name}", f"expected {e.expected}, but got {e.got!r}") from None
    sec = table("security", {"signed_price"}, required=False)
    signed_price = sec.get("signed_price", False)
    if not isinstance(signed_price, bool):
        raise fail("security.signed_price", f"expected true or false, but got "
                   f"{signed_price!r}")
    t = table("timeouts", {"neighbour_periods", "price_s", "status_s"}, required=False)
    periods = int(num(t, "timeouts", "neighbour_periods", 1, 100, transmit.neighbour_periods))
    if transmit.event and periods <= transmit.heartbeat:
        raise fail("timeouts.neighbour_periods", f"expected more than transmit.heartbeat = "
                   f"{transmit.heartbeat} periods (a neighbour may be silent that long), but "
                   f"got {periods}")
    lim = table("limits", {"lambda_min", "lambda_max", "rho_min", "rho_max", "price_step_max",
                           "price_persist", "lambda_step_max", "k_min", "k_max", "h_min",
                           "h_max", "untrusted_after", "untrusted_s"}, required=False)

    def opt(name: str, lo: float, hi: float) -> float | None:
        return num(lim, "limits", name, lo, hi) if name in lim else None

    def count(name: str, lo: int, hi: int, default: int) -> int:
        x = lim.get(name, default)
        if isinstance(x, bool) or not isinstance(x, int) or not lo <= x <= hi:
            raise fail(f"limits.{name}", f"expected an integer in {lo}..{hi}, but got {x!r}")
        return x

    cfg = AgentConfig(
        id=ident, lambda0=num(a, "agent", "lambda0", -100, 100), pinned=pinned,
        controller=controller, neighbours=tuple(neighbours), battery=battery,
        neighbour_timeout_periods=periods, transmit=transmit, signed_price=signed_price,
        price_timeout_s=num(t, "timeouts", "price_s", 0.01, 60,
                            timeout_s("ER_Price", controller.ts)),
        status_timeout_s=num(t, "timeouts", "status_s", 0.01, 60,
                             timeout_s(status_name(ident), controller.ts)),
        lambda_min=num(lim, "limits", "lambda_min", -127, 127, -10.0),
        lambda_max=num(lim, "limits", "lambda_max", -127, 127, 10.0), fleet_size=fleet,
        rho_min=num(lim, "limits", "rho_min", -127, 127, RHO_MIN),
        rho_max=num(lim, "limits", "rho_max", -127, 127, RHO_MAX),
        price_step_max=num(lim, "limits", "price_step_max", 1e-6, 127, PRICE_STEP_MAX),
        price_persist=count("price_persist", 1, 100, PRICE_PERSIST),
        lambda_step_max=opt("lambda_step_max", 1e-6, 127),
        k_min=opt("k_min", 0, GAIN_MAX), k_max=opt("k_max", 0, GAIN_MAX),
        h_min=opt("h_min", 0, GAIN_MAX), h_max=opt("h_max", 0, GAIN_MAX),
        untrusted_after=count("untrusted_after", 1, 1000, UNTRUSTED_AFTER),
        untrusted_s=opt("untrusted_s", 0, 3600), resilient_f=trim, source=src)
    if not cfg.lambda_min < cfg.lambda0 < cfg.lambda_max:
        raise fail("agent.lambda0", f"expected a value inside limits [{cfg.lambda_min}, "
                   f"{cfg.lambda_max}], but got {cfg.lambda0}")
    if not cfg.rho_min < cfg.rho_max:
        raise fail("limits.rho_max", f"expected rho_min < rho_max, but got {cfg.rho_min} ≥ "
                   f"{cfg.rho_max}")
    for lo, hi in (("k_min", "k_max"), ("h_min", "h_max")):
        if not getattr(cfg, lo) <= getattr(cfg, hi):
            raise fail(f"limits.{hi}", f"expected {lo} ≤ {hi}, but got {getattr(cfg, lo)} > "
                       f"{getattr(cfg, hi)}")
    # SET_GAINS may set k = k_max, h = h_max: their products with Ts must fit the
    # controller's int32 Q1.30 constants as k·ts and h·ts do (fixedpoint.to_q30)
    for name, gain in (("k_max", cfg.k_max), ("h_max", cfg.h_max)):
        assert gain is not None
        try:
            fx.to_q30(gain * controller.ts, f"{name}·ts")
        except ParameterError:
            given = "set" if name in lim else f"the default {GAIN_HI:g}·{name[0]}"
            raise fail(f"limits.{name}", f"expected {name}·ts < 2 (SET_GAINS may set the gain "
                       f"to {name}; int32 Q1.30), but got {name} = {gain:g} ({given}), "
                       f"{name}·ts = {gain * controller.ts:g}") from None
    return cfg


def agent_configs_from_scenario(sc: Any) -> list[AgentConfig]:
    """One AgentConfig per agent of a sim.model.scenario.Scenario (used by `bess-ded up`);
    ConfigError for a fleet larger than the DBC has frames for (the simulator's are)."""
    if sc.n > N_AGENTS_MAX:
        raise ConfigError(sc.source, "graph.agents", f"expected at most {N_AGENTS_MAX} agents "
                          f"on a bus (the DBC's AGENT_1..AGENT_{N_AGENTS_MAX} frames), but got "
                          f"{sc.n}: a larger fleet runs in the simulator only (bess-ded case)")
    out = []
    for i in range(1, sc.n + 1):
        b = sc.batteries[i - 1]
        out.append(AgentConfig(
            id=i, lambda0=sc.lambda0[i - 1], pinned=i in sc.pinned, controller=sc.controller,
            neighbours=tuple(Neighbour(j, w) for j, w in sc.neighbours(i)),
            battery=DispatchParams(b.alpha, b.beta, b.m, b.p_min, b.p_max),
            # 5 missed frames mean the price (the plant) is lost, at the run's Ts
            price_timeout_s=timeout_s("ER_Price", sc.ts),
            status_timeout_s=timeout_s(status_name(i), sc.ts),
            # SET_GAINS carries at most GAIN_MAX: the default 2·k (2·h) capped there, so a
            # fast variant (case 3's k = 10) writes a file its agent accepts
            k_max=min(GAIN_HI * sc.controller.k, GAIN_MAX),
            h_max=min(GAIN_HI * sc.controller.h, GAIN_MAX),
            # the scenario's price plausibility limits
            rho_min=sc.rho_min, rho_max=sc.rho_max, price_step_max=sc.price_step_max,
            resilient_f=sc.resilient_f, fleet_size=sc.n, transmit=sc.transmit,
            neighbour_timeout_periods=sc.transmit.neighbour_periods,
            signed_price=getattr(sc, "signed_price", False),
            source=f"{sc.source}#agent{i}"))
    return out
