"""Figures: the settling band and instants, the error row, power limits and the
time-scaled axis are drawn from the same numbers the metrics report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim.model.cost import Battery
from sim.model.metrics import settling_times
from sim.model.trajectory import Trajectory
from sim.report import plots


def synthetic(scale: float = 1.0, settle_second: bool = False) -> Trajectory:
    """Two agents, ρ = 0.8 then 1.0 at 5 s: settles in the first segment; in the second
    only when ``settle_second``. ``scale`` stretches time as `up --time-scale` does."""
    t = np.arange(0, 1000) * 0.01
    seg = (t >= 5).astype(int)
    rho = np.where(seg == 0, 0.8, 1.0)
    first = 0.8 + np.outer(np.exp(-2 * t), [-0.5, 0.4])
    tail = np.exp(-2 * (t - 5)) if settle_second else np.full_like(t, 0.5)
    second = 1.0 - np.outer(tail, [0.2, 0.3])
    lam = np.where(seg[:, None] == 0, first, second)
    u = np.gradient(lam, t, axis=0)
    return Trajectory(t=t * scale, lam=lam, rho=rho, segment=seg,
                      active=np.ones_like(lam, dtype=bool), p=50 * lam, u=u / scale,
                      xi=lam - rho[:, None], nu=np.cumsum(lam - rho[:, None], axis=0) * 0.01
                      * scale, resets=[[1.0 * scale], []], label="synthetic")


def test_segments_match_the_metrics() -> None:
    tr = synthetic()
    segs = plots.segments(tr)
    assert [s.settling for s in segs] == settling_times(tr)
    assert segs[1].settling is None and segs[1].settled_at is None
    assert segs[0].settled_at == pytest.approx(segs[0].settling)
    assert (segs[0].start, segs[1].start, segs[1].end) == pytest.approx((0, 5, 10))
    assert segs[0].band == pytest.approx(0.02 * 0.5)
    assert segs[1].rho == 1.0


def test_unscaled_puts_a_scaled_run_back_on_the_scenario_axis() -> None:
    plain, scaled = synthetic(), synthetic(scale=5.0)
    back = plots.unscaled(scaled, 5.0)
    assert np.allclose(back.t, plain.t) and back.resets == [[1.0], []]
    assert back.u is not None and plain.u is not None and np.allclose(back.u, plain.u)
    assert back.nu is not None and plain.nu is not None and np.allclose(back.nu, plain.nu)
    a, b = plots.segments(back), plots.segments(plain)
    assert a[0].settling == pytest.approx(b[0].settling) and a[1].settling is b[1].settling
    assert plots.unscaled(plain, 1.0) is plain
    with pytest.raises(ValueError, match="time_scale: expected a finite number > 0"):
        plots.unscaled(plain, 0.0)


def test_time_label() -> None:
    assert plots.time_label() == "t [s]"
    assert plots.time_label(5.0) == "t (scenario s; run at ×5)"


def _texts(fig_path: Path) -> None:
    assert fig_path.stat().st_size > 20_000


def test_figure_draws_band_instants_and_never(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Capture the figure before it is saved and look at what it holds."""
    from matplotlib.figure import Figure

    saved: list[Figure] = []
    real = Figure.savefig

    def keep(self: Figure, *a: object, **k: object) -> None:
        saved.append(self)
        real(self, *a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(Figure, "savefig", keep)
    bats = [Battery(0.004, 0.2, 0.1, -120.0, 120.0), Battery(0.005, 0.2, 0.1, -90.0, 100.0)]
    path = plots.figure([("a", synthetic(scale=5.0))], ("lam", "u", "p"), tmp_path / "f.png",
                        "t", batteries=bats, time_scale=5.0, t_max=None)
    _texts(path)
    fig = saved[-1]
    axes = fig.axes
    ylabels = [ax.get_ylabel() for ax in axes]
    assert ylabels[:2] == ["λ$_i$ [cu/kWh]", "max$_i$|λ$_i$ − ρ|"]  # the error row follows λ
    err_ax = axes[1]
    assert err_ax.get_yscale() == "log"
    texts = [t.get_text() for t in err_ax.texts]
    st = plots.segments(plots.unscaled(synthetic(scale=5.0), 5.0))[0].settling
    assert f" t$_s$ = {st:.2f} s" in texts and "never settled " in texts
    assert axes[-1].get_xlabel() == "t (scenario s; run at ×5)"
    assert axes[0].get_xlim()[1] == pytest.approx(9.99)  # scenario seconds, not 49.95
    p_ax = axes[ylabels.index("P$_i$ [kW]")]
    hlines = {round(line.get_ydata()[0], 6) for line in p_ax.get_lines()
              if len(set(line.get_ydata())) == 1 and len(line.get_ydata()) == 2}
    assert {-120.0, 120.0, -90.0, 100.0} <= hlines
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "2% settling band" in labels and "P$_{min}$ / P$_{max}$" in labels


def test_backwards_compatible_calls(tmp_path: Path) -> None:
    """The positional/keyword calls busrun and older scripts make still work; a bus
    run has no u, ξ, ν."""
    tr = synthetic(settle_second=True)
    bus = Trajectory(t=tr.t, lam=tr.lam, rho=tr.rho, segment=tr.segment, active=tr.active,
                     p=tr.p)
    _texts(plots.figure([("over the CAN bus", bus)], ("lam", "p", "grid"),
                        tmp_path / "bus.png", title="x", load_kw=200.0, t_max=None))
    _texts(plots.consensus_figure(tr, tmp_path / "c.png", "x"))
    _texts(plots.power_figure(tr, tmp_path / "p.png", "x", load_kw=200.0))
    _texts(plots.compare_figure([("a", tr), ("b", tr)], tmp_path / "cmp.png", "x",
                                error_panel=False))
