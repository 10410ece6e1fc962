"""Communication-graph analysis: Laplacian, pinning, H = L + B and the stability tests.

Agents are numbered 1..N in scenarios and in the DBC; arrays here are 0-based.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np


def adjacency(n: int, edges: Iterable[Sequence[float]]) -> np.ndarray:
    """Symmetric adjacency from 1-based (i, j) or (i, j, weight) edges."""
    a = np.zeros((n, n))
    for edge in edges:
        i, j = int(edge[0]) - 1, int(edge[1]) - 1
        w = float(edge[2]) if len(edge) > 2 else 1.0
        a[i, j] = a[j, i] = w
    return a


def laplacian(a: np.ndarray) -> np.ndarray:
    return np.diag(a.sum(axis=1)) - a


def pinning(n: int, pinned: Iterable[int], weight: float = 1.0) -> np.ndarray:
    b = np.zeros((n, n))
    for i in pinned:
        b[i - 1, i - 1] = weight
    return b


def h_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return laplacian(a) + b


def eigenvalues(h: np.ndarray) -> np.ndarray:
    """Eigenvalues of the symmetric H, ascending."""
    return np.linalg.eigvalsh(h)


def base_eigenvalues(h: np.ndarray, k: float, hgain: float) -> np.ndarray:
    """μ = (−kη ± √(k²η² − 4hη))/2 for every η of H: the PI base system's spectrum."""
    eta = eigenvalues(h).astype(complex)
    root = np.sqrt(k * k * eta * eta - 4 * hgain * eta)
    return np.concatenate([(-k * eta + root) / 2, (-k * eta - root) / 2])


@dataclass(frozen=True)
class GraphReport:
    eta: tuple[float, ...]
    eta_max: float
    eta_min: float
    regular: bool          # Theorem 1: k > 0 and 4h > η_max k²
    discrete_stable: bool  # forward Euler at Ts: |1 + Ts μ| < 1 for every μ
    spectral_radius: float  # max |1 + Ts μ|


def analyse(h: np.ndarray, k: float, hgain: float, ts: float, kind: str = "reset") -> GraphReport:
    """Regularity (continuous) and forward-Euler stability (discrete) of the base system.

    For PC the base system is λ̇ = −kHλ, so the check is |1 − Ts k η| < 1.
    """
    eta = eigenvalues(h)
    if kind in ("pc", "ft"):
        mus = -k * eta.astype(complex)
    else:
        mus = base_eigenvalues(h, k, hgain)
    radius = float(np.max(np.abs(1 + ts * mus)))
    return GraphReport(eta=tuple(float(e) for e in eta), eta_max=float(eta[-1]),
                       eta_min=float(eta[0]), regular=bool(k > 0 and 4 * hgain > eta[-1] * k * k),
                       discrete_stable=radius < 1, spectral_radius=radius)
