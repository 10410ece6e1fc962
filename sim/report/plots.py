"""Figures of runs in the paper's layout: one column per run, one row per quantity.

Plain functions taking ``Trajectory`` objects, so every producer (lockstep runner,
continuous reference, a bus log) is drawn the same way. Each function writes one
PNG and returns its path. Rows whose quantity no run carries (a bus log has no
ξ, ν) are left out; a column whose run lacks a row another run has says so.

Figures are built on ``matplotlib.figure.Figure`` with the Agg canvas directly, not
through pyplot: no global backend state, no screen needed, safe from threads.

    consensus_figure(runs, path, title)          λ_i (ρ dashed, resets ticked), |λ−ρ|, u_i, ξ_i
    gain_figure(runs, path, title)               ν_i and the dynamic gain r_i = ν_i/ξ_i
    power_figure(runs, path, title, load_kw=D)   P_i and the grid exchange P_e = D − ΣP_i
    compare_figure(runs, path, title)            λ_i, |λ−ρ| over u_i, a column per controller
    figure(runs, rows, path, title, ...)         any rows from QUANTITIES

``runs`` is a sequence of (column label, Trajectory), or a single Trajectory.

Every λ_i row shows, per price segment, the settling band ρ ± SETTLING_BAND × (the
segment's initial worst error) shaded and the settling instant (sim.model.metrics.settling_times)
as a vertical line, labelled "never" when the run did not settle; it is followed by a
log-scale row of the worst error max_i|λ_i − ρ| over the agents on the network with the
band level drawn. ``batteries=`` draws each BESS's p_min/p_max on the P_i row, and
``time_scale=F`` puts a time-scaled run (``bess-ded up --time-scale``) back on the
scenario's time axis.

About 500 lines: one figure layout shared by every plot; the panels differ only
in the quantity drawn.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_hex
from matplotlib.figure import Figure
from matplotlib.layout_engine import ConstrainedLayoutEngine
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import LogLocator, MaxNLocator

from sim.model.cost import Battery
from sim.model.metrics import SETTLING_BAND, settling_times, worst_error
from sim.model.trajectory import Trajectory

DPI = 120
COL_WIDTH = 4.2      # inches per run column
MAX_WIDTH = 19.0     # inches; many columns share this
ROW_HEIGHT = 2.15    # inches per quantity row
R_MASK = 0.02        # r_i is drawn where |ξ_i| > 2 % of the run's largest |ξ|
Runs = Sequence[tuple[str, Trajectory]] | Trajectory


@dataclass(frozen=True)
class Quantity:
    """One row of a figure: what to draw and how to label it."""

    ylabel: str
    get: Callable[[Trajectory, float | None], np.ndarray | None]
    robust: bool = False  # clip the y-range to the bulk of the data (r_i spikes as ξ → 0)


@dataclass(frozen=True)
class Segment:
    """One price segment of a run, as the settling time sees it."""

    start: float             # s, first sample of the segment
    end: float               # s, first sample of the next segment (or the run's end)
    rho: float
    band: float              # SETTLING_BAND × the worst error at the segment's start
    settling: float | None   # s after ``start``; None: never settled within the segment

    @property
    def settled_at(self) -> float | None:
        """When the segment settled (s of the run), None if it never did."""
        return None if self.settling is None else self.start + self.settling


def segments(tr: Trajectory) -> list[Segment]:
    """The run's price segments with their settling band and settling time."""
    err = worst_error(tr)
    dt = float(tr.t[1] - tr.t[0]) if tr.t.size > 1 else 0.0
    out = []
    for seg, st in zip(np.unique(tr.segment), settling_times(tr), strict=True):
        idx = np.flatnonzero(tr.segment == seg)
        out.append(Segment(float(tr.t[idx[0]]), float(tr.t[idx[-1]]) + dt,
                           float(tr.rho[idx[0]]), SETTLING_BAND * float(err[idx[0]]), st))
    return out


def _grid(tr: Trajectory, load_kw: float | None) -> np.ndarray | None:
    if load_kw is None:
        return None
    return (load_kw - tr.p.sum(axis=1))[:, None]


QUANTITIES: dict[str, Quantity] = {
    "lam": Quantity("λ$_i$ [cu/kWh]", lambda tr, _: tr.lam),
    "err": Quantity("max$_i$|λ$_i$ − ρ|", lambda tr, _: worst_error(tr)[:, None]),
    "u": Quantity("u$_i$ [cu/kWh/s]", lambda tr, _: tr.u),
    "xi": Quantity("ξ$_i$ [cu/kWh]", lambda tr, _: tr.xi),
    "nu": Quantity("ν$_i$ [cu·s/kWh]", lambda tr, _: tr.nu),
    "r": Quantity("r$_i$ = ν$_i$/ξ$_i$ [s]", lambda tr, _: dynamic_gain(tr), robust=True),
    "p": Quantity("P$_i$ [kW]", lambda tr, _: tr.p),
    "grid": Quantity("grid P$_e$ [kW]", _grid),
}


def dynamic_gain(tr: Trajectory, rel: float = R_MASK) -> np.ndarray | None:
    """r_i = ν_i/ξ_i where |ξ_i| exceeds ``rel`` × the run's largest |ξ|, NaN elsewhere.

    Near equilibrium ξ is a few LSB and the ratio is quantisation noise that
    swamps the transient the paper plots; ``Trajectory.r`` keeps the raw ratio.
    """
    if tr.nu is None or tr.xi is None:
        return None
    floor = rel * float(np.abs(tr.xi).max() or 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(tr.xi) > floor, tr.nu / tr.xi, np.nan)


def view_end(tr: Trajectory, band: float = 0.02) -> float:
    """A time after which the picture no longer changes: the last reset, event, price
    change, or exit of max|λ_i − ρ| from its 2 % settling band, whichever is latest."""
    last = 0.0
    if any(tr.resets):
        last = max(max(r) for r in tr.resets if r)
    changes = np.flatnonzero(np.diff(tr.segment) != 0) + 1
    changes = np.union1d(changes, np.flatnonzero(np.any(np.diff(tr.active, axis=0), axis=1)) + 1)
    if changes.size:
        last = max(last, float(tr.t[changes[-1]]))
    err = worst_error(tr)
    for seg in np.unique(tr.segment):
        idx = np.flatnonzero(tr.segment == seg)
        out = idx[err[idx] > band * err[idx[0]]]
        if out.size:
            last = max(last, float(tr.t[out[-1]]))
    return last


def auto_t_max(runs: Runs, margin: float = 1.3) -> float:
    """The end of the time axis: every run's ``view_end`` with a margin, rounded up to a
    readable value, never past the end of the runs."""
    runs_ = _as_runs(runs)
    end = max(float(tr.t[-1]) for _, tr in runs_)
    want = max(view_end(tr) for _, tr in runs_) * margin + 1.0
    nice = next((x * 10.0**e for e in range(-1, 7) for x in (1, 1.5, 2, 2.5, 3, 4, 5, 6, 8)
                 if x * 10.0**e >= want), end)
    return min(end, nice)


def agent_colours(n: int) -> list[str]:
    """Distinct colours for n agents: tab10, then the light half of tab20."""
    from matplotlib import colormaps

    tab20 = colormaps["tab20"]
    order = [tab20(2 * i) for i in range(10)] + [tab20(2 * i + 1) for i in range(10)]
    if n > len(order):
        order = [colormaps["turbo"](x) for x in np.linspace(0.05, 0.95, n)]
    return [to_hex(c) for c in order[:n]]


def _as_runs(runs: Runs) -> list[tuple[str, Trajectory]]:
    if isinstance(runs, Trajectory):
        return [(runs.label, runs)]
    out = list(runs)
    if not out:
        raise ValueError("expected at least one run to plot, but got none")
    return out


OFF_MIN_SAMPLES = 5  # shorter spans off the dispatch (an agent's first sample in INIT) unshaded


def _off_intervals(tr: Trajectory) -> tuple[list[list[tuple[float, float]]],
                                            dict[tuple[float, float], str]]:
    """Per agent, the spans it was off the dispatch (not active); and one label per span,
    agents sharing a span named together, by the state a bus run recorded ("SAFE",
    "INIT") or else "isolated"."""
    from firmware_py.contract import State

    ts = float(tr.t[1] - tr.t[0]) if tr.t.size > 1 else 0.0
    off: list[list[tuple[float, float]]] = []
    names: dict[tuple[float, float], tuple[list[int], str]] = {}
    for i in range(tr.n):
        spans = [(a, b) for a, b in _intervals(~tr.active[:, i], tr.t)
                 if b - a >= OFF_MIN_SAMPLES * ts - 1e-9]
        off.append(spans)
        for a, b in spans:
            what = "isolated"
            if tr.state is not None:
                k = int(np.searchsorted(tr.t, a))
                state = int(tr.state[min(k, tr.t.size - 1), i])
                what = "isolated" if state == State.ISOLATED else State(state).name
            agents, _ = names.setdefault((a, b), ([], what))
            agents.append(i + 1)
    labels = {span: f"BESS {', '.join(map(str, agents))} {what}"
              for span, (agents, what) in names.items()}
    return off, labels


def _intervals(mask: np.ndarray, t: np.ndarray) -> list[tuple[float, float]]:
    """[t_start, t_end) of each run of True in mask."""
    if not mask.any():
        return []
    edges = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    dt = t[1] - t[0] if t.size > 1 else 0.0
    return [(float(t[s]), float(t[e - 1] + dt)) for s, e in zip(starts, ends, strict=True)]


def _robust_limits(y: np.ndarray) -> tuple[float, float] | None:
    finite = y[np.isfinite(y)]
    if finite.size < 10:
        return None
    lo, hi = np.percentile(finite, [1.0, 99.0])
    lo, hi = min(lo, 0.0), max(hi, 0.0)
    pad = 0.08 * (hi - lo or 1.0)
    return float(lo - pad), float(hi + pad)


def _comparable(ys: Sequence[np.ndarray | None], ratio: float = 4.0) -> bool:
    """Do these columns' ranges fit one y-scale (largest spans within ``ratio`` of each
    other)? A gain sweep's u differs tenfold between columns: then each keeps its own."""
    spans = [float(np.nanmax(y) - np.nanmin(y)) for y in ys
             if y is not None and np.isfinite(y).any()]
    return len(spans) > 1 and min(spans) > 0 and max(spans) / min(spans) <= ratio


BAND_COLOUR = "0.55"      # the settling band: shaded around ρ, and under its level on |λ − ρ|
SETTLE_COLOUR = "#1a7f37"  # settling instants
NEVER_COLOUR = "#c0392b"


def unscaled(tr: Trajectory, time_scale: float) -> Trajectory:
    """A run made at ``time_scale`` F (Ts·F, k/F, h/F²) on the scenario's own time axis:
    t and reset instants / F; u = dλ/dt × F; ν = ∫ξ dt / F (so r = ν/ξ / F too)."""
    if not (math.isfinite(time_scale) and time_scale > 0):
        raise ValueError(f"time_scale: expected a finite number > 0, but got {time_scale!r}")
    if time_scale == 1:
        return tr
    f = time_scale
    return replace(tr, t=tr.t / f, resets=[[x / f for x in r] for r in tr.resets],
                   u=None if tr.u is None else tr.u * f,
                   nu=None if tr.nu is None else tr.nu / f)


def _draw_cell(ax: Axes, key: str, tr: Trajectory, y: np.ndarray, colours: list[str],
               show_resets: bool, segs: list[Segment], show_settling: bool,
               batteries: Sequence[Battery] | None) -> None:
    t = tr.t
    if key == "grid":
        ax.plot(t, y[:, 0], color="k", lw=1.4)
    elif key == "err":
        _draw_error(ax, t, y[:, 0], segs, show_settling)
    else:
        lw = 1.1 if y.shape[1] <= 6 else 0.9
        for i in range(y.shape[1]):
            ax.plot(t, y[:, i], color=colours[i], lw=lw)
    if key == "lam":
        if show_settling:
            for sg in segs:
                ax.fill_between([sg.start, sg.end], sg.rho - sg.band, sg.rho + sg.band,
                                color=BAND_COLOUR, alpha=0.35, lw=0, zorder=0.5)
        ax.plot(t, tr.rho, color="k", ls="--", lw=1.3, zorder=5)
        if show_resets:
            for i, times in enumerate(tr.resets[: y.shape[1]]):
                if times:
                    idx = np.clip(np.searchsorted(t, np.asarray(times) - 1e-9), 0, t.size - 1)
                    ax.plot(t[idx], y[idx, i], ls="none", marker="|", ms=7, mew=1.3,
                            color=colours[i], zorder=6)
    if key in ("lam", "err") and show_settling:
        for sg in segs:
            if sg.settled_at is not None and sg.settling:
                ax.axvline(sg.settled_at, color=SETTLE_COLOUR, ls="-.", lw=1.0, zorder=4)
    if key == "p" and batteries:
        _draw_limits(ax, batteries[: y.shape[1]])
    if key in ("u", "xi", "nu", "r"):
        ax.axhline(0.0, color="0.4", lw=0.6, zorder=1)


def _draw_error(ax: Axes, t: np.ndarray, err: np.ndarray, segs: list[Segment],
                show_settling: bool) -> None:
    """max_i|λ_i − ρ| on a log scale, the band level shaded under it, t_s labelled."""
    ax.set_yscale("log")
    if (lim := _error_limits([err], [sg.band for sg in segs])) is not None:
        ax.set_ylim(*lim)
    ax.plot(t, np.where(err > 0, err, np.nan), color="k", lw=1.1, zorder=3)
    ax.yaxis.set_major_locator(LogLocator(numticks=6))
    if not show_settling:
        return
    for sg in segs:
        if sg.band > 0:
            ax.fill_between([sg.start, sg.end], 1e-300, sg.band, color=BAND_COLOUR, alpha=0.35,
                            lw=0, zorder=0.5)
            ax.hlines(sg.band, sg.start, sg.end, color=BAND_COLOUR, lw=0.9, zorder=1)
        # the label sits at the top of this row: the λ row's top holds "isolated" labels
        if sg.settled_at is None:
            ax.text(sg.end, 0.96, "never settled ", ha="right", va="top", fontsize=7.5,
                    color=NEVER_COLOUR, fontweight="bold", transform=ax.get_xaxis_transform(),
                    zorder=7)
        else:
            ax.text(sg.settled_at, 0.96, f" t$_s$ = {sg.settling:.2f} s", ha="left", va="top",
                    fontsize=7.5, color=SETTLE_COLOUR, transform=ax.get_xaxis_transform(),
                    clip_on=True, zorder=7)


def _error_limits(errs: Sequence[np.ndarray], bands: Sequence[float]
                  ) -> tuple[float, float] | None:
    """A log y-range for max|λ − ρ|: the data, but no more than 6 decades under the
    smallest band (below the Q24 resolution, 6e-8, nothing is left to see)."""
    positive = np.concatenate([e[e > 0] for e in errs])
    if not positive.size:
        return None
    hi = float(positive.max()) * 2.5
    floor = min((b for b in bands if b > 0), default=hi) * 1e-6
    return max(float(positive.min()) * 0.5, floor, 1e-12), hi


def _draw_limits(ax: Axes, batteries: Sequence[Battery]) -> None:
    """p_min/p_max as grey dashed lines, one per distinct value. Each side is labelled
    once, at its outermost line (per-line labels collide when limits are close)."""
    n = len(batteries)
    ax.set_ymargin(0.12)  # room for the labels outside the outermost lines
    for which, values in (("max", [b.p_max for b in batteries]),
                          ("min", [b.p_min for b in batteries])):
        distinct = sorted(set(values))
        for v in distinct:
            ax.axhline(v, color="0.3", ls=(0, (5, 3)), lw=0.9, zorder=1)
        if len(distinct) == 1:
            label = f"P$_{{{which}}}$"
        else:
            label = f"P$_{{{which}}}$ of the {n} BESSs: {distinct[0]:g} … {distinct[-1]:g} kW"
        outer = distinct[-1] if which == "max" else distinct[0]
        ax.annotate(label, (1.0, outer), xycoords=("axes fraction", "data"),
                    xytext=(-3, 2 if which == "max" else -2), textcoords="offset points",
                    ha="right", va="bottom" if which == "max" else "top", fontsize=7.5,
                    color="0.25", annotation_clip=False)


def time_label(time_scale: float = 1.0) -> str:
    """The time axis label: 't [s]', or 't (scenario s; run at ×F)' for a scaled run."""
    return "t [s]" if time_scale == 1 else f"t (scenario s; run at ×{time_scale:g})"


def figure(runs: Runs, rows: Sequence[str], path: str | Path, title: str = "", *,
           load_kw: float | None = None, sharey: bool = True, show_resets: bool = True,
           t_max: float | str | None = "auto", time_scale: float = 1.0,
           batteries: Sequence[Battery] | None = None, error_panel: bool = True,
           show_settling: bool = True) -> Path:
    """The general figure: ``rows`` (keys of QUANTITIES) × one column per run.

    Rows no run can provide are dropped. With ``sharey`` every row has one y-scale
    across its columns, so the runs compare at a glance. Isolated intervals (agent
    off the network) are shaded in the agent's colour; price changes are dotted
    vertical lines; reset instants are ticks on λ_i. ``t_max="auto"`` ends the time
    axis once nothing changes any more (``auto_t_max``); ``None`` shows the whole run.

    ``error_panel`` adds the log-scale row "err" (max_i|λ_i − ρ|) under "lam";
    ``show_settling`` draws the settling band and instants on both. ``batteries``
    (the scenario's, in agent order) draws p_min/p_max on "p". ``time_scale`` F > 0:
    the runs were made on a time axis stretched by F; they are drawn on the scenario's
    (t / F, see ``unscaled``) and ``t_max`` is in those seconds.
    """
    runs_ = [(label, unscaled(tr, time_scale)) for label, tr in _as_runs(runs)]
    rows = list(rows)
    if error_panel and "lam" in rows and "err" not in rows:
        rows.insert(rows.index("lam") + 1, "err")
    if t_max == "auto":
        t_max = auto_t_max(runs_)
    path = Path(path)
    data = {key: [QUANTITIES[key].get(tr, load_kw) for _, tr in runs_] for key in rows}
    keys = [k for k in rows if any(y is not None for y in data[k])]
    if not keys:
        raise ValueError(f"none of the rows {list(rows)} is recorded in these runs")
    n_agents = max(tr.n for _, tr in runs_)
    colours = agent_colours(n_agents)
    ncols, nrows = len(runs_), len(keys)

    width = min(MAX_WIDTH, max(9.0, 1.2 + COL_WIDTH * ncols))
    row_height = ROW_HEIGHT if ncols == 1 else min(3.0, max(ROW_HEIGHT, 0.7 * width / ncols))
    heights = [0.75 if k == "err" else 1.0 for k in keys]  # the error row needs less
    fig = Figure(figsize=(width, 1.5 + row_height * sum(heights)), dpi=DPI,
                 layout=ConstrainedLayoutEngine(w_pad=0.06, wspace=0.05))
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, sharex=True, squeeze=False,
                        gridspec_kw={"height_ratios": heights})
    if sharey:
        for r, key in enumerate(keys):
            if key == "err" or _comparable(data[key]):
                for c in range(1, ncols):
                    axes[r, c].sharey(axes[r, 0])
                    axes[r, c].tick_params(labelleft=False)
    any_resets = any_isolated = any_settled = any_limits = False
    for c, (label, tr) in enumerate(runs_):
        off, off_labels = _off_intervals(tr)
        changes = tr.t[np.flatnonzero(np.diff(tr.segment)) + 1]
        segs = segments(tr) if show_settling and ("lam" in keys or "err" in keys) else []
        for r, key in enumerate(keys):
            ax = axes[r, c]
            y = data[key][c]
            if y is None:
                ax.text(0.5, 0.5, "not recorded", ha="center", va="center",
                        transform=ax.transAxes, color="0.5")
                ax.tick_params(labelleft=False, left=False)
            else:
                _draw_cell(ax, key, tr, y, colours, show_resets, segs, show_settling,
                           batteries)
                if QUANTITIES[key].robust and (lim := _robust_limits(y)) is not None:
                    ax.set_ylim(*lim)
            for i, spans in enumerate(off):
                for a, b in spans:
                    ax.axvspan(a, b, color=colours[i], alpha=0.13, lw=0, zorder=0)
            if r == 0:
                for (a, b), text in off_labels.items():
                    ax.text((a + b) / 2, 0.97, text, ha="center", va="top", fontsize=7.5,
                            color="0.25", transform=ax.get_xaxis_transform())
            for tc in changes:
                ax.axvline(tc, color="0.55", ls=":", lw=0.9, zorder=1)
            ax.grid(alpha=0.3, lw=0.6)
            ax.tick_params(labelsize=8)
            if c == 0:
                ax.set_ylabel(QUANTITIES[key].ylabel, fontsize=9)
            if r == nrows - 1:
                ax.set_xlabel(time_label(time_scale), fontsize=9)
        axes[0, c].set_title(label, fontsize=10, fontweight="bold")
        axes[0, c].xaxis.set_major_locator(MaxNLocator(nbins=7, steps=[1, 2, 5, 10]))
        axes[0, c].set_xlim(tr.t[0], float(t_max) if t_max is not None else tr.t[-1])
        any_resets |= show_resets and "lam" in keys and any(tr.resets)
        any_isolated |= any(off)
        any_settled |= any(sg.settled_at for sg in segs)
        any_limits |= bool(batteries) and "p" in keys
    if sharey and ncols > 1 and "err" in keys:  # one range that fits every column
        lim = _error_limits([worst_error(tr) for _, tr in runs_],
                            [sg.band for _, tr in runs_ for sg in segments(tr)])
        if lim is not None:
            axes[keys.index("err"), 0].set_ylim(*lim)

    handles: list[Line2D | Patch] = [Line2D([], [], color=colours[i], lw=1.6,
                                           label=f"BESS {i + 1}") for i in range(n_agents)]
    if "lam" in keys:
        handles.append(Line2D([], [], color="k", ls="--", lw=1.3, label="ρ (price)"))
    if "err" in keys:
        handles.append(Line2D([], [], color="k", lw=1.1, label="max$_i$|λ$_i$ − ρ|"))
    if segs_drawn := show_settling and ("lam" in keys or "err" in keys):
        handles.append(Patch(color=BAND_COLOUR, alpha=0.5,
                             label=f"{SETTLING_BAND:.0%} settling band"))
    if segs_drawn and any_settled:
        handles.append(Line2D([], [], color=SETTLE_COLOUR, ls="-.", lw=1.0,
                              label="settled (t$_s$ after the price step)"))
    if "grid" in keys:
        handles.append(Line2D([], [], color="k", lw=1.4, label="grid P$_e$ = D − ΣP$_i$"))
    if any_limits:
        handles.append(Line2D([], [], color="0.3", ls=(0, (5, 3)), lw=0.9,
                              label="P$_{min}$ / P$_{max}$"))
    if any_resets:
        handles.append(Line2D([], [], color="0.3", ls="none", marker="|", ms=7, mew=1.3,
                              label="reset of ν$_i$"))
    if any_isolated:
        handles.append(Patch(color="0.6", alpha=0.3, label="off the dispatch"))
    ncol = min(len(handles), max(4, int(width / 1.6)))
    fig.legend(handles=handles, loc="outside lower center", ncol=ncol, fontsize=8,
               frameon=False, handlelength=1.8, columnspacing=1.2)
    if title:
        fig.suptitle(title, fontsize=11)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    return path


# The figures below take figure()'s other keywords too (time_scale, batteries, ...).


def consensus_figure(runs: Runs, path: str | Path, title: str = "", *, sharey: bool = True,
                     t_max: float | str | None = "auto", **kw: Any) -> Path:
    """λ_i with ρ(t) dashed, the settling band and reset ticks; max|λ_i − ρ|; u_i; ξ_i
    (the paper's main figure)."""
    return figure(runs, ("lam", "u", "xi"), path, title, sharey=sharey, t_max=t_max, **kw)


def gain_figure(runs: Runs, path: str | Path, title: str = "", *, sharey: bool = True,
                t_max: float | str | None = "auto", **kw: Any) -> Path:
    """ν_i and the dynamic gain r_i = ν_i/ξ_i (paper eq. 18)."""
    return figure(runs, ("nu", "r"), path, title, sharey=sharey, t_max=t_max, **kw)


def power_figure(runs: Runs, path: str | Path, title: str = "", *, load_kw: float,
                 sharey: bool = True, t_max: float | str | None = "auto", **kw: Any) -> Path:
    """BESS powers P_i (with ``batteries=``: their limits) and the grid exchange
    P_e = D − ΣP_i (> 0: drawn from the grid)."""
    return figure(runs, ("p", "grid"), path, title, load_kw=load_kw, sharey=sharey,
                  t_max=t_max, **kw)


def compare_figure(runs: Runs, path: str | Path, title: str = "", *, sharey: bool = True,
                   t_max: float | str | None = "auto", **kw: Any) -> Path:
    """λ_i on top, max|λ_i − ρ|, u_i below, one column per controller."""
    return figure(runs, ("lam", "u"), path, title, sharey=sharey, t_max=t_max, **kw)
