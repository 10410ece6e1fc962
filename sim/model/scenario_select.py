"""Naming a scenario to run: a case number or a scenario file (``resolve_scenario``), and
which of its variants (``pick_variant``), as every ``bess-ded`` command and the test kit
name them (docs/api.md)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from firmware_py.config import TRANSMIT_MODES, Transmit
from firmware_py.errors import ConfigError, ParameterError
from sim.model.scenario import SCENARIO_DIR, Scenario, load_case, load_scenario


def resolve_scenario(spec: str) -> Scenario:
    """A case number → the bundled sim/scenarios/caseN.toml; anything else → a path."""
    path = Path(spec)
    if spec.isdigit() and (SCENARIO_DIR / f"case{int(spec)}.toml").exists():
        return load_case(int(spec))
    if not spec.isdigit() and (path.suffix == ".toml" or path.exists() or "/" in spec):
        return load_scenario(path)
    known = sorted((p.stem.removeprefix("case") for p in SCENARIO_DIR.glob("case*.toml")),
                   key=lambda k: (len(k), k))
    raise ConfigError(spec, "case", f"expected a case number ({', '.join(known)}) or a path to "
                      f"a scenario .toml, but got {spec!r}")


def pick_variant(sc: Scenario, label: str | None, command: str = "up",
                 say: Callable[[str], None] = print) -> tuple[Scenario, str]:
    """The scenario to run and how to name the choice in a banner (" [variant LABEL]", or
    "" for a scenario without variants). No ``label`` picks the first variant and says so
    through ``say`` (a line naming ``command``)."""
    if not sc.variants:
        if label is not None:
            raise ConfigError(sc.source, "variant", f"expected no --variant: {sc.name} has "
                              f"no variants, but got {label!r}")
        return sc, ""
    labels = [v.label for v in sc.variants]
    if label is None:
        say(f"bess-ded {command}: {sc.name} has variants {', '.join(labels)}; running the first, "
            f"{labels[0]!r} (choose one with --variant)")
        label = labels[0]
    run = sc.variant(label)  # ignores case: name the label as the scenario spells it
    if label not in labels:
        label = next(x for x in labels if x.casefold() == label.casefold())
    return run, f" [variant {label}]"


def with_fd(sc: Scenario, fd: bool, no_lambda_tags: bool = False) -> Scenario:
    """``sc`` on a CAN FD bus when ``fd`` (the command line's --fd), else as the scenario
    says (its ``[bus] fd``): the flag selects FD, it never turns a scenario's FD off;
    ``no_lambda_tags`` (--no-lambda-tags): λ under its sender's node key on that FD bus
    (ParameterError on a classic one)."""
    if fd and not sc.fd:
        sc = replace(sc, fd=True)
    if no_lambda_tags:
        if not sc.fd:
            raise ParameterError("--no-lambda-tags", "it with --fd or a scenario's [bus] fd "
                                 "(classic CAN has no room for the tags)", "a classic bus")
        sc = replace(sc, lambda_tags=False)
    return sc


def with_transmit(sc: Scenario, mode: str | None) -> Scenario:
    """``sc`` with its agents sending the MC frame ``mode`` ("periodic" or "event", the
    command line's --transmit; None: as the scenario says). Event mode keeps the scenario's
    threshold and heartbeat (event_threshold, event_heartbeat), else the defaults."""
    if mode is None or mode == sc.transmit.mode:
        return sc
    if mode not in TRANSMIT_MODES:
        raise ConfigError(sc.source, "transmit", f"expected one of {', '.join(TRANSMIT_MODES)}"
                          f", but got {mode!r}")
    tx = sc.transmit
    return replace(sc, transmit=Transmit(mode, tx.threshold, tx.heartbeat))
