"""Conformance of an agent node on the bus (`bess-ded conformance`).

The tester is the rest of the bus for one device under test (DUT), agent I: it plays
the router (price, commands), the plant (agent I's status) and I's neighbours (their MC
frames), all signed with the run's keys, along a fixed schedule of steps (``plan``):
start-up, control with moving neighbours, forged and replayed frames, malformed and
implausible content, every command, and every timeout. It records what the DUT sends.

Verdict (``check``): firmware_py's own agent runtime is the oracle. It receives the same
frames at the times the tester sent them and ticks when the DUT ticked (the receive time
of each DUT MC frame); every DUT frame must then equal the oracle's at the signal level
(MC: State, Lambda, Resets; Setpoint: Enable, PowerSetpoint; Diag: every page value but
DeadlineMisses, which depends on the DUT's host), and every secured DUT frame must carry
a MAC that verifies with the DUT's key at consecutive freshness values. Where the bus
leaves the order open (a frame sent while the DUT was ticking), the oracle tries each
order and keeps the one that explains the DUT, so a conformant DUT passes at any load.

After a difference the oracle re-synchronises to what the DUT's frames show (λ, state,
counters, syncs) and checks on; a difference fails the requirements the schedule was
exercising at that moment (a noted frame of the tester, a state change or an edge of the
oracle's controller), narrowed by the signal (``attribute``), and the report lists the
first divergence first. When a known deviation (``MUTANTS``: e.g. the band
re-armed at the reset sample) explains the DUT's frames from the start, the report names
that requirement.

The DUT's configuration file (``written_config``) is the scenario's agent with every key
the schedule observes off its default; the oracle reads the same file with the reference
parser, and a known misreading of it (``mutants.misreads``: a default taken, a value
rounded otherwise) that explains the DUT is named like a known deviation (CFG-3/4/6/7).
``plan(..., quick=True)``: the steps of ``QUICK`` only (`bess-ded conformance --quick`;
``verdict(..., played=...)`` lists the others' requirements "not run").

The package: ``schedule`` (the steps and the frames), ``oracle`` (the record and its check),
``results`` (per requirement, JUnit), ``mutants`` (known deviations), ``drive`` (running
it in process or on a bus) and ``bus`` (the check of a device, what ``bess-ded conformance``
runs). The names below are its API (docs/api.md).
"""

from sim.conformance.drive import drive, simulate
from sim.conformance.mutants import MUTANTS
from sim.conformance.oracle import (
    LATE_TICKS,
    MAX_HYPOTHESES,
    SIGNAL_MUSTS,
    WMSR_TIE,
    Frame,
    Mismatch,
    Outcome,
    check,
)
from sim.conformance.results import (
    MOMENTS,
    REQUIREMENTS_FILE,
    Result,
    attribute,
    explain,
    junit,
    other_runs,
    spec_requirements,
    verdict,
)
from sim.conformance.schedule import (
    FILED_BOOT,
    ON_WHAT,
    ONLY_ON,
    PRICE_PERSIST,
    PULSE,
    QUICK,
    STEPS,
    Planned,
    Step,
    conformance_config,
    exercised_on,
    kind_exercised,
    plan,
    played_steps,
    read_config,
    written_config,
)

__all__ = [
    "FILED_BOOT",
    "Frame",
    "ONLY_ON",
    "ON_WHAT",
    "LATE_TICKS",
    "MAX_HYPOTHESES",
    "MOMENTS",
    "MUTANTS",
    "Mismatch",
    "Outcome",
    "PRICE_PERSIST",
    "PULSE",
    "QUICK",
    "Planned",
    "REQUIREMENTS_FILE",
    "Result",
    "SIGNAL_MUSTS",
    "STEPS",
    "WMSR_TIE",
    "Step",
    "attribute",
    "check",
    "conformance_config",
    "exercised_on",
    "kind_exercised",
    "drive",
    "explain",
    "junit",
    "other_runs",
    "plan",
    "played_steps",
    "read_config",
    "simulate",
    "spec_requirements",
    "verdict",
    "written_config",
]
