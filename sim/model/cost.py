"""The BESS cost model (paper §II, typos fixed in ../shared/DESIGN.md §2).

Units: P in kW (positive = discharge into the grid), λ and ρ in cu/kWh
(currency units per kWh), costs in cu/h.

Per BESS: inner loss ratio π = αP + β, degradation f_L = m π P, so the
expenditure is F_c = Σ (1+m)(αP² + βP) + ρ P_e with P_e = D − Σ P.
The marginal cost is λ = (1+m)(2αP + β); the KKT optimum puts every λ at ρ.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Battery:
    """One BESS: cost coefficients, limits and the physical pack."""

    alpha: float           # cu/(kW²·h), quadratic loss coefficient
    beta: float            # cu/kWh, linear loss coefficient
    m: float               # capacity-degradation coefficient (dimensionless)
    p_min: float           # kW (negative = charging limit)
    p_max: float           # kW
    capacity_kwh: float = 200.0
    soc0: float = 0.6      # initial state of charge, 0..1
    v_nom: float = 700.0   # V, open-circuit voltage at 50 % SoC
    r_internal: float = 0.05  # Ω, pack resistance (sets the voltage drop under load)

    def power(self, lam: float | np.ndarray) -> float | np.ndarray:
        """P(λ) from λ = (1+m)(2αP+β), clipped to [p_min, p_max]."""
        p = (np.asarray(lam) / (1 + self.m) - self.beta) / (2 * self.alpha)
        out = np.clip(p, self.p_min, self.p_max)
        return float(out) if np.ndim(out) == 0 else out

    def marginal_cost(self, p: float | np.ndarray) -> float | np.ndarray:
        """(1+m)(2αP + β): the marginal cost at power ``p``, cu/kWh."""
        return (1 + self.m) * (2 * self.alpha * np.asarray(p) + self.beta)

    def cost_rate(self, p: float | np.ndarray) -> float | np.ndarray:
        """(1+m)(αP² + βP): loss plus degradation, cu/h."""
        p = np.asarray(p)
        return (1 + self.m) * (self.alpha * p * p + self.beta * p)

    @property
    def idle_lambda(self) -> float:
        """MC at P = 0: where an isolated BESS's λ sits while it is off the network."""
        return float(self.marginal_cost(0.0))


def expenditure(batteries: Sequence[Battery], powers: Sequence[float], rho: float,
                load_kw: float) -> float:
    """F_c = Σ (1+m)(αP²+βP) + ρ P_e, with P_e = D − ΣP (cu/h)."""
    p = np.asarray(powers, dtype=float)
    grid = load_kw - p.sum()
    return float(sum(b.cost_rate(pi) for b, pi in zip(batteries, p, strict=True)) + rho * grid)


def kkt_optimum(batteries: Sequence[Battery], rho: float, load_kw: float) -> tuple[np.ndarray,
                                                                                   float]:
    """The optimal dispatch P_i* = clip((ρ/(1+m) − β)/(2α)) and its expenditure.

    F_c is separable once P_e is eliminated (∂F_c/∂P_i = λ_i − ρ), so each BESS's
    box-constrained optimum is its unconstrained one clipped to its limits.
    """
    p = np.array([b.power(rho) for b in batteries], dtype=float)
    return p, expenditure(batteries, p.tolist(), rho, load_kw)
