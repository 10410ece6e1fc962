"""A recorded run: the same arrays whether it came from the lockstep runner, the
continuous reference or a bus log, so metrics and plots treat them alike."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class Trajectory:
    """A run sampled at Ts: time, λ, price and segment, participation and power,
    and (where the runner records them) u, ξ and ν, and the resets."""

    t: np.ndarray          # (K,) s
    lam: np.ndarray        # (K, N) λ_i at t_k
    rho: np.ndarray        # (K,) price in force at t_k
    segment: np.ndarray    # (K,) index of the price segment
    active: np.ndarray     # (K, N) agent on the network (not isolated / timed out)
    p: np.ndarray          # (K, N) BESS power, kW
    u: np.ndarray | None = None    # (K, N) dλ/dt applied over [t_k, t_k+1)
    xi: np.ndarray | None = None   # (K, N)
    nu: np.ndarray | None = None   # (K, N) ν used at t_k (0 right after a reset)
    resets: list[list[float]] = field(default_factory=list)  # reset instants per agent
    saturations: int = 0
    label: str = ""
    # (K, N) agent meant to take part in the dispatch (the scenario's plan): the agents the
    # error is judged over, whatever state they are in. None: the same as ``active``.
    expected: np.ndarray | None = None
    state: np.ndarray | None = None  # (K, N) AGENT_i_MC.State (bus runs only)
    mc_sent: np.ndarray | None = None  # (K, N) agent sent its MC frame at t_k (lockstep)

    @classmethod
    def sampled(cls, batteries: Sequence[Any], ts: float, lam: np.ndarray, active: np.ndarray,
                **kw: Any) -> Trajectory:
        """A run sampled every ``ts`` from sample 0: its times, and each battery's power
        where its agent took part (0 kW where it was isolated) from λ (Battery.power)."""
        p = np.column_stack([np.where(active[:, i], b.power(lam[:, i]), 0.0)
                             for i, b in enumerate(batteries)])
        return cls(t=np.arange(len(lam)) * ts, lam=lam, active=active, p=p, **kw)

    @property
    def judged(self) -> np.ndarray:
        """(K, N) the agents the error is taken over: those meant to be dispatching."""
        return self.active if self.expected is None else self.expected

    @property
    def n(self) -> int:
        """The number of agents."""
        return int(self.lam.shape[1])

    @property
    def r(self) -> np.ndarray | None:
        """Dynamic gain r_i = ν_i/ξ_i (paper eq. 18), NaN where ξ ≈ 0."""
        if self.nu is None or self.xi is None:
            return None
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(np.abs(self.xi) > 1e-6, self.nu / self.xi, np.nan)

    def write_csv(self, path: Path) -> None:
        """Write the trajectory as CSV: t, rho, segment, then one column per agent
        of each recorded series (lam_1, ..., p_N, active_N)."""
        cols: list[tuple[str, np.ndarray]] = [("t", self.t), ("rho", self.rho),
                                              ("segment", self.segment)]
        for name in ("lam", "u", "xi", "nu", "p", "active"):
            arr = getattr(self, name)
            if arr is not None:
                cols += [(f"{name}_{i + 1}", arr[:, i]) for i in range(self.n)]
        with path.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow([c for c, _ in cols])
            for row in zip(*(a for _, a in cols), strict=True):
                w.writerow([f"{x:.9g}" if isinstance(x, float) else int(x) for x in
                            (v.item() for v in row)])
