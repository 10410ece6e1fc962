"""A sweep's results as one PNG: settling time over the swept axes, and where runs failed.

Left: the settling time of every converged point over the first numeric axis that varies
(the number of agents of a random fleet, a gain, ...), one colour per controller (or per
value of the first categorical axis), the runs that did not converge or had no valid
scenario as red crosses at the top (the map of failures). Right: with two numeric axes
varying (e.g. k and h), the median settling time over their grid as a heat map;
otherwise the distribution of settling times per colour.
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

CATEGORICAL = ("controller", "graph")
REPLICATES = ("graph_seed", "loss_seed")  # repeat a point: not axes to plot over
HEAT_MAP_MAX = 25             # distinct values per axis for a heat map (a grid), else a histogram


def varying(rows: list[dict[str, Any]], columns: list[str]) -> tuple[list[str], list[str]]:
    """(numeric, categorical) parameter columns whose value differs between rows."""
    numeric: list[str] = []
    categorical: list[str] = []
    for c in columns:
        values = {str(r[c]) for r in rows}
        if len(values) < 2 or c in REPLICATES:
            continue
        (categorical if c in CATEGORICAL else numeric).append(c)
    return numeric, categorical


def plot_sweep(rows: list[dict[str, Any]], columns: list[str], path: Path, title: str) -> None:
    """Write the sweep's figure (see the module doc) to ``path``."""
    numeric, categorical = varying(rows, columns)
    colour_by = categorical[0] if categorical else None
    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        groups[str(r[colour_by]) if colour_by else "all"].append(r)

    fig = Figure(figsize=(11, 4.2), layout="constrained")
    FigureCanvasAgg(fig)
    left, right = fig.subplots(1, 2)
    x_axis = numeric[0] if numeric else None
    ok = [r for r in rows if r["converged"] == 1]
    top = max((r["settling_time_s"] for r in ok), default=1.0) * 1.08 or 1.0
    for label, rs in sorted(groups.items()):
        good = [r for r in rs if r["converged"] == 1]
        xs = [r[x_axis] if x_axis else i for i, r in enumerate(good)]
        left.scatter(xs, [r["settling_time_s"] for r in good], s=10, alpha=0.6, label=label)
    failed = [r for r in rows if r["converged"] != 1]
    if failed:
        xs = [r[x_axis] if x_axis else i for i, r in enumerate(failed)]
        left.scatter(xs, [top] * len(failed), marker="x", color="red",
                     label=f"not converged or invalid ({len(failed)})")
    left.set_xlabel(x_axis or "point")
    left.set_ylabel("settling time [s]")
    left.set_title("settling time per point")
    left.grid(alpha=0.3)
    left.legend(fontsize=8)

    if len(numeric) >= 2 and all(len({r[a] for r in rows}) <= HEAT_MAP_MAX
                                 for a in numeric[:2]):
        _heat_map(right, rows, numeric[0], numeric[1])
    else:
        for label, rs in sorted(groups.items()):
            st = [r["settling_time_s"] for r in rs if r["converged"] == 1]
            if st:
                right.hist(st, bins=min(30, max(5, len(st) // 5)), alpha=0.5, label=label)
        right.set_xlabel("settling time [s]")
        right.set_ylabel("points")
        right.set_title("distribution")
        right.legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)


def _heat_map(ax: Any, rows: list[dict[str, Any]], xa: str, ya: str) -> None:
    xs = sorted({r[xa] for r in rows})
    ys = sorted({r[ya] for r in rows})
    grid = np.full((len(ys), len(xs)), math.nan)
    cells: dict[tuple[int, int], list[float]] = defaultdict(list)
    for r in rows:
        if r["converged"] == 1:
            cells[(ys.index(r[ya]), xs.index(r[xa]))].append(r["settling_time_s"])
    for (i, j), v in cells.items():
        grid[i, j] = float(np.median(v))
    im = ax.imshow(grid, origin="lower", aspect="auto", cmap="viridis")
    ax.set_xticks(range(len(xs)), [f"{x:g}" for x in xs], fontsize=7)
    ax.set_yticks(range(len(ys)), [f"{y:g}" for y in ys], fontsize=7)
    ax.set_xlabel(xa)
    ax.set_ylabel(ya)
    ax.set_title("median settling time [s] (blank: none converged)")
    ax.figure.colorbar(im, ax=ax)
