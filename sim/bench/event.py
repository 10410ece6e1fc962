"""Event-triggered λ transmission against periodic, in the lockstep (issue 23, item 1).

Each paper case (and each of its variants) runs twice on the same lockstep: every agent
sending its MC frame every tick, and event-triggered (firmware_py.config.Transmit, spec
TX-7). Counted: MC frames over the whole run, and "once settled", i.e. over the samples
after the periodic run's settling instant in each price segment (the same samples for
both runs); the settling time of each segment and the final error max_i |λ_i − ρ|.
Deterministic (no clock, no randomness), so the acceptance numbers are a test
(tests/test_event_transmit.py). ``python -m sim.bench.event`` prints the table of
docs/performance.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from firmware_py.config import Transmit
from sim.model.lockstep import run_lockstep
from sim.model.metrics import settling_times, worst_error
from sim.model.scenario import Scenario, load_case
from sim.model.trajectory import Trajectory

CASES = tuple(range(1, 8))
# issue 23's acceptance: fewer frames over the run and once settled, settling time and
# final error against periodic
MIN_SAVING, MIN_SETTLED_SAVING, MAX_SETTLING_RATIO, MAX_FINAL_ERROR = 0.5, 0.9, 1.1, 1e-3


@dataclass(frozen=True)
class Comparison:
    """One run of a case, periodic against event-triggered."""

    case: int
    label: str
    agents: int
    frames: tuple[int, int]            # MC frames over the run: periodic, event
    settled_frames: tuple[int, int]    # ... once settled
    settling: tuple[float, float]      # the slowest segment's settling time, s (inf: never)
    settling_ratio: float              # max over segments of event / periodic settling time
    final_error: tuple[float, float]   # cu/kWh

    @property
    def saving(self) -> float:
        """The fraction of MC frames event-triggering saves over the whole run."""
        return 1.0 - self.frames[1] / self.frames[0]

    @property
    def settled_saving(self) -> float:
        """The fraction saved once settled."""
        return 1.0 - self.settled_frames[1] / max(self.settled_frames[0], 1)

    @property
    def accepted(self) -> bool:
        """Meets issue 23's acceptance."""
        return (self.saving >= MIN_SAVING and self.settled_saving >= MIN_SETTLED_SAVING
                and self.settling_ratio <= MAX_SETTLING_RATIO
                and self.final_error[1] <= MAX_FINAL_ERROR)


def settled_samples(tr: Trajectory, ts: float) -> np.ndarray:
    """The samples after each segment's settling instant (the periodic run's: "once
    settled", sim.bench.fleetload too)."""
    out = np.zeros(len(tr.t), dtype=bool)
    for seg, st in zip(np.unique(tr.segment), settling_times(tr), strict=True):
        idx = np.flatnonzero(tr.segment == seg)
        if st is not None:
            out[idx[0] + round(st / ts):idx[-1] + 1] = True
    return out


def _slowest(times: list[float | None]) -> float:
    return max(float("inf") if t is None else t for t in times)


def compare(sc: Scenario, case: int = 0, label: str = "",
            transmit: Transmit | None = None) -> Comparison:
    """``sc`` periodic against ``sc`` with ``transmit`` (default: event mode, its default
    threshold and heartbeat)."""
    tx = transmit or Transmit("event")
    a = run_lockstep(replace(sc, transmit=Transmit()))
    b = run_lockstep(replace(sc, transmit=tx))
    assert a.mc_sent is not None and b.mc_sent is not None
    settled = settled_samples(a, sc.ts)
    st_a, st_b = settling_times(a), settling_times(b)
    ratio = max((float("inf") if y is None else y / x) if x else (1.0 if not y else
                                                                  float("inf"))
                for x, y in zip(st_a, st_b, strict=True))
    return Comparison(case, label or sc.controller.kind, sc.n,
                      (int(a.mc_sent.sum()), int(b.mc_sent.sum())),
                      (int(a.mc_sent[settled].sum()), int(b.mc_sent[settled].sum())),
                      (_slowest(st_a), _slowest(st_b)), ratio,
                      (float(worst_error(a)[-1]), float(worst_error(b)[-1])))


def paper_cases(transmit: Transmit | None = None, variants: bool = True) -> list[Comparison]:
    """Every paper case (each variant with ``variants``), periodic against ``transmit``."""
    out = []
    for case in CASES:
        sc = load_case(case)
        runs = sc.runs() if variants else [(sc.controller.kind, sc)]
        out += [compare(run, case, label, transmit) for label, run in runs]
    return out


HEADERS = ["case", "run", "N", "MC frames periodic → event", "saved", "settled: periodic → "
           "event", "saved", "settling s periodic → event", "ratio", "final error periodic → event"]


def rows(results: list[Comparison]) -> list[list[str]]:
    """The table's rows (HEADERS)."""
    return [[str(c.case), c.label, str(c.agents), f"{c.frames[0]} → {c.frames[1]}",
             f"{c.saving:.1%}", f"{c.settled_frames[0]} → {c.settled_frames[1]}",
             f"{c.settled_saving:.1%}", f"{c.settling[0]:.2f} → {c.settling[1]:.2f}",
             f"{c.settling_ratio:.3f}", f"{c.final_error[0]:.1e} → {c.final_error[1]:.1e}"]
            for c in results]


def main() -> int:
    """Print the comparison of every paper case at the default event settings."""
    from sim.report.textfmt import table

    tx = Transmit("event")
    results = paper_cases(tx)
    print(f"event-triggered MC (threshold {tx.threshold:g} cu/kWh, heartbeat {tx.heartbeat} "
          f"ticks) against periodic, lockstep")
    print(table(HEADERS, rows(results)))
    ok = all(c.accepted for c in results)
    print(f"acceptance (≥ {MIN_SAVING:.0%} fewer, ≥ {MIN_SETTLED_SAVING:.0%} fewer once "
          f"settled, settling ≤ {MAX_SETTLING_RATIO}× periodic, final error ≤ "
          f"{MAX_FINAL_ERROR:g}): {'met' if ok else 'NOT met'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
