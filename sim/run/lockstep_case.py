"""A scenario in the lockstep simulator, every variant: what ``bess-ded case`` runs
(docs/api.md). ``run_case`` simulates, computes the metrics (docs/metrics.md) and writes
the result files; ``summary_table`` is the text table of the command's output.

Files written into the output directory (default runs/<scenario name>):
  metrics.json              the first run's metrics; with variants also "runs": {label: metrics}
  trajectory.csv            the first run, one row per sample
  trajectory_<label>.csv    every variant (scenarios with variants only)
  lambda_u_xi.png, nu_r.png, power.png   the figures (``plot=True``)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

from firmware_py.errors import ParameterError
from sim.model.graph import GraphReport
from sim.model.scenario import Scenario
from sim.model.trajectory import Trajectory
from sim.report.textfmt import (
    Progress,
    fmt_pct,
    fmt_resets,
    fmt_sci,
    fmt_times,
    slug,
    table,
    write_json,
)

DEFAULT_DWELL_S = 1.0  # Δ for `--controller dwell` on a scenario that sets none (paper case 6)


class CaseRun(NamedTuple):
    """One lockstep run of a case: its label, scenario, trajectory and metrics."""

    label: str
    scenario: Scenario
    trajectory: Trajectory
    metrics: dict[str, Any]


@dataclass
class CaseResult:
    """What ``run_case`` ran and wrote."""

    scenario: Scenario
    runs: list[CaseRun]   # in the scenario's variant order (one run with ``controller``)
    out: Path
    written: list[Path]   # metrics.json, the trajectories, the figures


def plan(sc: Scenario, controller: str | None = None, band: float | None = None,
         dwell: float | None = None) -> list[tuple[str, Scenario]]:
    """(label, scenario) for each run: the scenario's variants, or one run of
    ``controller``; ``band``/``dwell`` override every run's controller."""
    over: dict[str, Any] = {}
    if band is not None:
        over["band"] = band
    if dwell is not None:
        over["dwell"] = dwell
    if controller is not None:
        if controller == "dwell" and dwell is None and sc.controller.dwell < sc.ts:
            over["dwell"] = DEFAULT_DWELL_S
        return [(controller, sc.with_controller(kind=controller, **over))]
    return [(label, s.with_controller(**over) if over else s) for label, s in sc.runs()]


def simulate(runs: list[tuple[str, Scenario]], fixed: bool, impl: str = "py"
             ) -> list[CaseRun]:
    """Run each (label, scenario) in lockstep: (label, scenario, trajectory, metrics);
    a progress line on a terminal's stderr for the long ones."""
    from sim.model.lockstep import run_lockstep
    from sim.model.metrics import compute

    out: list[CaseRun] = []
    for label, s in runs:
        progress = Progress(label)
        try:
            tr = run_lockstep(s, fixed=fixed, progress=progress, impl=impl)
        finally:
            progress.done()
        tr.label = label
        m = compute(s, tr)
        m["arithmetic"] = "fixed" if fixed else "float"
        m["implementation"] = "firmware_c" if impl == "c" else "firmware_py"
        if s.transmit.event and tr.mc_sent is not None:  # periodic metrics stay as they were
            m["transmit"] = s.transmit.to_doc()
            m["mc_frames"] = int(tr.mc_sent.sum())
            m["mc_frames_periodic"] = int(tr.mc_sent.size)  # every agent every sample
        out.append(CaseRun(label, s, tr, m))
    return out


def check_c_core(fixed: bool) -> None:
    """impl "c": fixed point, and the C core builds (else a ParameterError naming
    --impl c)."""
    from sim.cbind.cimpl import CBuildError, load

    if not fixed:
        raise ParameterError("--impl c", "--fixed (the C core is fixed point only)", "--float")
    try:
        load()
    except (CBuildError, OSError) as e:
        last = (str(e).strip().splitlines() or [type(e).__name__])[-1]
        raise ParameterError("--impl c", "firmware_c to build (make and a C compiler: "
                             "tools/install-c-deps)", last) from None


def run_case(sc: Scenario, *, controller: str | None = None, band: float | None = None,
             dwell: float | None = None, fixed: bool = True, impl: str = "py",
             out: Path | None = None, plot: bool = True) -> CaseResult:
    """Run ``sc`` in the lockstep simulator: its variants, or one run of ``controller``
    (a kind of firmware_py.controllers.KINDS), with ``band``/``dwell`` overriding every
    run's; in fixed point (``fixed``) or float; on firmware_py's controllers or the C
    core (``impl="c"``). Writes metrics.json, the trajectories and (``plot``) the figures
    into ``out`` (default runs/<scenario name>)."""
    from sim.report import plots

    runs = plan(sc, controller, band, dwell)
    if impl == "c":
        check_c_core(fixed)
    out = out or Path("runs") / slug(sc.name)
    out.mkdir(parents=True, exist_ok=True)
    results = simulate(runs, fixed, impl)

    first = results[0].metrics
    top: dict[str, Any] = {**first, "title": sc.title, "source": sc.source}
    written = []
    if len(results) > 1:
        top["runs"] = {r.label: r.metrics for r in results}
    write_json(out / "metrics.json", top)
    written.append(out / "metrics.json")
    results[0].trajectory.write_csv(out / "trajectory.csv")
    written.append(out / "trajectory.csv")
    if len(results) > 1:
        for r in results:
            path = out / f"trajectory_{slug(r.label)}.csv"
            r.trajectory.write_csv(path)
            written.append(path)

    if plot:
        title = sc.title or sc.name
        if controller:
            title += f" — {controller}"
        if not fixed:
            title += " (float)"
        trs = [(r.label, r.trajectory) for r in results]
        written.append(plots.consensus_figure(trs, out / "lambda_u_xi.png", title))
        written.append(plots.gain_figure(trs, out / "nu_r.png", title))
        written.append(plots.power_figure(trs, out / "power.png", title, load_kw=sc.load_kw,
                                          batteries=sc.batteries))
    return CaseResult(sc, results, out, written)


def summary_table(rows: list[tuple[str, dict[str, Any]]],
                  reports: Sequence[GraphReport] | None = None) -> str:
    """The summary; with ``reports`` (one per row) the regular column says 'n/a' for the
    controllers Theorem 1 is not about, and '; unstable at Ts' when the Euler step is."""
    headers = ["run", "settling [s]", "overshoot", "final error", "resets/agent", "TV(u)",
               "regular", "cost [cu/h]", "vs optimal"]
    body = []
    for r, (label, m) in enumerate(rows):
        tv = m.get("control_total_variation")
        body.append([
            label, fmt_times(m["settling_times_s"]), fmt_pct(m["overshoot"]),
            fmt_sci(m["final_error"]), fmt_resets(m["resets"]),
            "-" if tv is None else f"{tv:.2f}",
            reports[r].verdict() if reports else (
                ("yes" if m["regular"] else "no")
                + ("" if m["discrete_stable"] else "; unstable at Ts")),
            f"{m['cost']:.4f}", f"{m['cost'] - m['optimal_cost']:+.1e}"])
    return table(headers, body, align="lrrrlrlrr")
