"""Turn a recorded candump log back into a Trajectory, plus each node's diagnostics.

The bus run's metrics come only from what crossed the bus: λ_i from AGENT_i_MC,
ρ from ER_Price, P_i from PLANT_i_Status, counters from AGENT_i_Diag. Values are
sampled on the Ts grid by holding the last frame received (what a neighbour sees).
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from firmware_py.errors import FrameError
from firmware_py.frames import FrameCodec

from .scenario import Scenario
from .trajectory import Trajectory

INIT, ISOLATED, SAFE = 0, 2, 3  # AGENT_i_MC.State: before the first price; off the network


@dataclass
class LogContents:
    frames: int = 0
    undecodable: Counter[str] = field(default_factory=Counter)
    series: dict[tuple[str, str], list[tuple[float, float]]] = field(
        default_factory=lambda: defaultdict(list))
    diag: dict[int, dict[str, int]] = field(default_factory=lambda: defaultdict(dict))
    t_first_price: float | None = None
    t_end: float = 0.0
    # frames the recorder missed, per message, from the jumps of its rolling counter (mod
    # 16: an outage of 16+ frames aliases; a restarted node's counter restarts at 0)
    counter_gaps: Counter[str] = field(default_factory=Counter)
    # State of each agent's first recorded MC frame: an agent is INIT until the first
    # price, so anything else means the recorder missed the start and t = 0 is late
    first_mc_state: dict[str, int] = field(default_factory=dict)

    @property
    def start_recorded(self) -> bool:
        return all(s == INIT for s in self.first_mc_state.values())


def read_log(path: Path, codec: FrameCodec | None = None) -> LogContents:
    codec = codec or FrameCodec()
    out = LogContents()
    last_counter: dict[str, int] = {}
    for msg in can.LogReader(str(path)):
        out.frames += 1
        out.t_end = msg.timestamp
        try:
            f = codec.decode(msg)
        except FrameError as e:
            out.undecodable[e.cause] += 1
            continue
        if "Counter" in f.raw:
            ctr, prev = f.raw["Counter"], last_counter.get(f.name)
            if prev is not None and (ctr - prev - 1) % 16 and ctr != prev:  # equal: a repeat
                out.counter_gaps[f.name] += (ctr - prev - 1) % 16
            last_counter[f.name] = ctr
        if f.name == "ER_Price":
            if out.t_first_price is None:
                out.t_first_price = msg.timestamp
            out.series[("price", "Rho")].append((msg.timestamp, f.phys("Rho")))
            out.series[("price", "Segment")].append((msg.timestamp, f.raw["Segment"]))
        elif f.name.endswith("_MC"):
            out.first_mc_state.setdefault(f.name, f.raw["State"])
            for sig in ("Lambda", "State", "Resets"):
                out.series[(f.name, sig)].append((msg.timestamp, f.phys(sig)))
        elif f.name.endswith("_Status"):
            out.series[(f.name, "Power")].append((msg.timestamp, f.phys("Power")))
        elif f.name.endswith("_Diag"):
            out.diag[f.agent or 0].update({k: v for k, v in f.raw.items()
                                           if k not in ("CRC", "Counter", "Page")})
        elif f.name == "ER_Balance":
            for sig in ("GridPower", "CostRate", "OptimalCostRate"):
                out.series[("balance", sig)].append((msg.timestamp, f.phys(sig)))
    return out


def _hold(series: list[tuple[float, float]], grid: np.ndarray, before: float) -> np.ndarray:
    """Last value at or before each grid time (``before`` where nothing was received yet)."""
    if not series:
        return np.full(grid.shape, before)
    t, v = np.array(series).T
    idx = np.searchsorted(t, grid, side="right") - 1
    return np.where(idx >= 0, v[np.clip(idx, 0, None)], before)


def trajectory_from_log(sc: Scenario, log: LogContents, label: str = "bus") -> Trajectory:
    if log.t_first_price is None:
        raise ValueError("the log holds no ER_Price frame: the router never spoke")
    t0, ts = log.t_first_price, sc.ts
    grid = t0 + np.arange(0.0, log.t_end - t0, ts)
    lam = np.column_stack([_hold(log.series[(f"AGENT_{i}_MC", "Lambda")], grid, sc.lambda0[i - 1])
                           for i in range(1, sc.n + 1)])
    state = np.column_stack([_hold(log.series[(f"AGENT_{i}_MC", "State")], grid, 0)
                             for i in range(1, sc.n + 1)])
    p = np.column_stack([_hold(log.series[(f"PLANT_{i}_Status", "Power")], grid, 0.0)
                         for i in range(1, sc.n + 1)])
    resets = []
    for i in range(1, sc.n + 1):
        r = log.series[(f"AGENT_{i}_MC", "Resets")]
        resets.append([t - t0 for (t, v), (_, v0) in zip(r[1:], r, strict=False) if v != v0])
    u = np.vstack([np.diff(lam, axis=0) / ts, np.zeros((1, sc.n))])
    return Trajectory(t=grid - t0, lam=lam, rho=_hold(log.series[("price", "Rho")], grid, np.nan),
                      segment=_hold(log.series[("price", "Segment")], grid, 0).astype(int),
                      active=(state != ISOLATED) & (state != SAFE), p=p, u=u, resets=resets,
                      label=label)


def node_diagnostics(log: LogContents) -> dict[str, Any]:
    """Per agent: the last value of every diagnostics counter it broadcast."""
    return {f"agent_{a}": dict(sorted(d.items())) for a, d in sorted(log.diag.items())}
