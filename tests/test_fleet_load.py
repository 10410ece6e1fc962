"""The bus load per fleet size (sim.bench.fleetload, `bench --fleet-load`, issue 23 item
4): one configuration against the DBC and canframe's formulas by hand, the event-triggered
lines below the periodic ones, the largest-N column against the rows, the CLI's JSON.
Computed figures only (no timing is asserted)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from firmware_py import contract
from firmware_py.frames import N_AGENTS_MAX, diag_name, mc_name, setpoint_name, status_name
from sim.bench import fleetload
from sim.bench.auth import ring_scenario
from sim.bench.canframe import fd_frame_bits, fd_frame_time
from sim.cli import main

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "ring64_lockstep.toml"
TORUS = EXAMPLE.with_name("torus64.toml")   # issue 23's 64-agent fleet that converges


@pytest.fixture(scope="module")
def small() -> tuple[list[str], list[list[str]], dict[str, Any]]:
    """The table for rings of 4, 8 and 16 agents and cases 1 and 7, every ratio measured."""
    return fleetload.run(quick=False, sizes=(4, 8, 16))


def _config(key: str) -> fleetload.Config:
    return next(c for c in fleetload.CONFIGS if c.key == key)


def test_fd_periodic_64_agents_equals_the_dbc_by_hand() -> None:
    """64 agents on a ring, FD periodic, Ts = 10 ms: every frame an 8-byte FD frame with
    the bit-rate switch (34 bits at 500 kbit/s, 113 at 2 Mbit/s) but λ and its sync, 32
    bytes with their receivers' tags (AUTH-34: 34 + 358 bits); every agent's frames are
    the DBC's own (it has 64), so the frames/s are 64 agents' of its cycle times."""
    n, per_s = 64, lambda name: 1000 / contract.cycle_ms(name)
    # header 17 + its 4 stuff bits + tail 13; ESI + DLC 5, 64 data bits, 17 more stuff
    # bits (floor((17 + 5 + 64 - 1)/4) = 21 in all), stuff count 4, CRC-17 and its 6 fixed
    # stuff bits
    assert fd_frame_bits(8) == (17 + 4 + 13, 5 + 64 + 17 + 4 + 17 + 6) == (34, 113)
    frame_s = 34 / 500_000 + 113 / 2_000_000
    assert fd_frame_time(8, 500_000, 2_000_000) == pytest.approx(frame_s)
    # 256 data bits, 65 more stuff bits (floor((17 + 5 + 256 - 1)/4) = 69 in all), CRC-21
    # and its 7 fixed stuff bits
    assert fd_frame_bits(32) == (34, 5 + 256 + 65 + 4 + 21 + 7) == (34, 358)
    tagged_s = 34 / 500_000 + 358 / 2_000_000
    agent = sum(per_s(f(1)) for f in (mc_name, setpoint_name, status_name, diag_name))
    router = per_s("ER_Price") + 2 * per_s("ER_Balance")       # ER_Balance: 2 pages
    plant = per_s("PLANT_Totals")                               # the router's ledger input
    syncs = 4 * n + 4        # one <name>_Sync a second per secured ID: 4 per agent + 4
    fps = n * agent + router + plant + syncs
    assert fps == 64 * (100 + 20 + 20 + 10) + 20 + 2 * 10 + 20 + 260 == 9920

    fleet = fleetload.Fleet("ring-64", n, ring_scenario(n))
    frames = fleetload.fleet_frames(fleet)
    assert len({m.name for m in frames}) == len(frames)
    assert sum(fleetload.is_mc(m) for m in frames) == n
    names = {m.name for m in frames}
    assert {"AGENT_33_MC", "AGENT_64_MC", "PLANT_64_Status_Sync"} <= names
    assert N_AGENTS_MAX == 64 and "AGENT_65_MC" not in names
    got = fleetload.config_load(_config("fd"), fleet, None, msgs=frames)
    assert got is not None
    assert got["frames_per_s"] == pytest.approx(fps)
    tagged = n * per_s(mc_name(1)) + n  # λ every tick and its sync every second
    assert got["load"] == pytest.approx((fps - tagged) * frame_s + tagged * tagged_s)
    # the same fleet's frames on classic CAN: 135 bits each
    classic = fleetload.config_load(_config("classic"), fleet, None, msgs=frames)
    assert classic is not None and classic["load"] == pytest.approx(fps * 135 / 500_000)


def test_event_ratio_scales_only_the_mc_frames() -> None:
    fleet = fleetload.Fleet("ring-4", 4, ring_scenario(4))
    ratio = fleetload.EventRatio(0.25, 0.1, 1.0, "ring-4", 30.0)
    periodic = fleetload.config_load(_config("classic"), fleet, ratio)
    event = fleetload.config_load(_config("classic-event"), fleet, ratio)
    assert periodic is not None and event is not None
    assert periodic["frames_per_s"] - event["frames_per_s"] == pytest.approx(0.75 * 4 * 100)


def test_event_triggered_lines_are_below_the_periodic_ones(
        small: tuple[list[str], list[list[str]], dict[str, Any]]) -> None:
    _, _, data = small
    loads = data["loads"]
    for f, ratio in data["event_ratio"].items():
        assert ratio["measured_on"] == f            # every ratio measured on its fleet
        assert 0 < ratio["settled"] < ratio["whole"] < 1 and ratio["peak"] <= 1
        for bus in ("classic", "fd"):
            periodic = loads[bus][f]["load"]
            assert loads[f"{bus}-event"][f]["load"] < periodic
            assert loads[f"{bus}-event-settled"][f]["load"] < loads[f"{bus}-event"][f]["load"]
            assert loads[f"{bus}-event-peak"][f]["load"] <= periodic
        assert loads["fd"][f]["load"] < loads["classic"][f]["load"]
        assert loads["fd-packed"][f]["load"] < loads["fd"][f]["load"]


def test_largest_n_column_agrees_with_the_rows(
        small: tuple[list[str], list[list[str]], dict[str, Any]]) -> None:
    headers, rows, data = small
    assert headers[0] == "configuration" and headers[-1] == "largest N ≤ 60 %"
    labels = list(data["fleets"])
    assert len(headers) == len(labels) + 2
    for cfg, row in zip(fleetload.CONFIGS, rows, strict=True):
        loads = data["loads"][cfg.key]
        fits = [data["fleets"][f]["agents"] for f in labels if loads[f]["load"] <= 0.6]
        assert data["largest_n"][cfg.key] == max(fits, default=None)
        assert row[-1].split()[0] == str(max(fits))
        for f, cell in zip(labels, row[1:-1], strict=True):
            assert cell.endswith("*") == (loads[f]["load"] > 0.6)
    # classic periodic: 12 agents fit (case 7), 16 do not
    assert data["largest_n"]["classic"] == 12


def test_periodic_capacity_at_any_n_is_the_last_fleet_under_the_limit(
        small: tuple[list[str], list[list[str]], dict[str, Any]]) -> None:
    """The affine solution for the periodic lines: N fits, N + 1 does not."""
    _, _, data = small
    for key in ("classic", "fd"):
        n = data["largest_n_any_periodic"][key]
        cfg = _config(key)
        at = [fleetload.config_load(cfg, fleetload.Fleet(f"ring-{m}", m, ring_scenario(m)),
                                    None) for m in (n, n + 1)]
        assert at[0] is not None and at[1] is not None
        assert at[0]["load"] <= 0.6 < at[1]["load"]


def test_quick_borrows_the_largest_measured_ring_and_says_so() -> None:
    fl = fleetload.fleets((4, 48), cases=False)
    ratios = fleetload.event_ratios(fl, quick=True)
    assert ratios["ring-48"] is ratios["ring-4"] and ratios["ring-48"].source == "ring-4"


def test_cli_fleet_load_writes_its_json(tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "fleet.json"
    assert main(["bench", "--fleet-load", "--quick", "--json", str(out),
                 "--case", str(TORUS), "--scenario", "1"]) == 0
    stdout = capsys.readouterr().out
    assert "Bus load per fleet size at Ts = 10 ms" in stdout
    assert "--measured DIR" in stdout and "--case CASE" in stdout
    tables = json.loads(out.read_text())["tables"]
    assert len(tables) == 2
    # --case: each scenario's fleet at its Ts, on both buses (the torus: the lockstep's
    # ratio over its 20 s; case 1: periodic)
    torus, case1 = tables[1]["data"]["scenarios"]
    assert (torus["scenario"], torus["fd"], torus["transmit"]) == ("torus64", True, "event")
    assert torus["load"] == torus["load_fd"] == pytest.approx(0.540, abs=2e-3)
    assert torus["fits"] and torus["load_classic"] == pytest.approx(1.171, abs=2e-3)
    assert (case1["mc_ratio"], case1["load"]) == (1.0, pytest.approx(0.184, abs=1e-3))
    assert "torus64       64     event" in stdout
    data = tables[0]["data"]
    assert set(data["largest_n"]) == {c.key for c in fleetload.CONFIGS}
    assert data["fleets"]["ring-64"]["agents"] == 64
    assert data["event_ratio"]["ring-64"]["measured_on"] == "ring-32"   # --quick


def test_cli_refuses_fleet_load_with_auth(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--fleet-load", "--auth"]) == 2
    assert "bess-ded: error: --fleet-load" in capsys.readouterr().err
    assert main(["bench", "--case", "1"]) == 2
    assert "bess-ded: error: --case: expected --fleet-load with it" in capsys.readouterr().err


def test_the_64_agent_example_is_the_benchs_ring_and_runs_in_the_lockstep() -> None:
    from dataclasses import replace

    from sim.model.lockstep import run_lockstep
    from sim.model.scenario import load_scenario

    sc = load_scenario(EXAMPLE)
    ring = ring_scenario(64, 150.0)
    assert (sc.n, sc.ts, sc.duration) == (64, 0.01, 150.0)
    assert sorted(map(sorted, sc.edges)) == sorted(map(sorted, ring.edges))
    assert sc.pinned == ring.pinned and sc.batteries == ring.batteries
    assert sc.lambda0 == ring.lambda0
    tr = run_lockstep(replace(sc, duration=1.0))
    assert tr.lam.shape == (101, 64)


@pytest.mark.parametrize("argv", [
    ["deploy", "--insecure"], ["deploy"], ["up"], ["restbus", "--dut", "3"],
    ["plant", "--interface", "virtual", "--duration", "0.1", "--insecure"],
    ["router", "--interface", "virtual", "--duration", "0.1", "--insecure"],
])
def test_bus_runs_refuse_the_64_agent_example_before_writing(
        argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    extra = ["--out", str(out)] if argv[0] in ("deploy", "up", "restbus") else []
    assert main([argv[0], "--case", str(EXAMPLE), *argv[1:], *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: ") and "bess-ded: error: " in err
    # its λ every tick: 267 % of a classic bus (every frame of the DBC, computed)
    assert ("[graph.agents] expected a fleet whose computed bus load on classic CAN at Ts = "
            "10 ms is at most 100 %, but got 267.8 % for 64 agents (every frame periodic") in err
    assert not out.exists()


def test_the_bus_load_check_follows_the_time_scale_and_the_dbc_limit() -> None:
    """A time scale F stretches every cycle by F: the 64-agent ring's 267 % fits at
    F = 3 (89 %); a fleet above the DBC's 64 agents is refused by the agent count."""
    from firmware_py.config import agent_configs_from_scenario
    from firmware_py.errors import ConfigError
    from sim.model.generate import random_scenario
    from sim.model.scenario import load_scenario, scaled

    sc = load_scenario(EXAMPLE)
    assert fleetload.check_bus_load(scaled(sc, 3.0)) == pytest.approx(2.678 / 3, abs=1e-3)
    with pytest.raises(ConfigError, match="at most 100 %, but got 133.9 %"):
        fleetload.check_bus_load(scaled(sc, 2.0))
    with pytest.raises(ConfigError, match=r"expected at most 64 agents on a bus \(the DBC's "
                                          r"AGENT_1..AGENT_64 frames\), but got 65"):
        agent_configs_from_scenario(random_scenario(65, 2, 0))


def test_the_64_agent_event_example_fits_fd_only() -> None:
    """examples/ring64.toml: event-triggered λ (the lockstep's ratio over its run, ~9 %)
    puts it at ~110 % of a classic bus, refused, and at ~51 % of its FD one."""
    from dataclasses import replace

    from firmware_py.errors import ConfigError
    from sim.model.scenario import load_scenario

    sc = load_scenario(EXAMPLE.with_name("ring64.toml"))
    assert sc.n == 64 and sc.transmit.mode == "event" and sc.fd
    with pytest.raises(ConfigError, match=r"on classic CAN .* but got 110\.8 % for 64 agents "
                                          r"\(MC frames event-triggered, 9\.1 % of periodic"):
        fleetload.check_bus_load(replace(sc, fd=False))
    assert fleetload.check_bus_load(sc) == pytest.approx(0.511, abs=1e-3)


def test_the_64_agent_torus_converges_in_the_lockstep_on_60_percent_of_an_fd_bus() -> None:
    """examples/torus64.toml, issue 23's acceptance in the lockstep: 64 agents on an 8 × 8
    torus (4-regular, 16 pinned), event-triggered λ on CAN FD at Ts = 10 ms, reach
    max|λ−ρ| ≤ 1e-3 well within 15 s (6.4 s) with the reset-PI regular and stable at Ts,
    and its computed FD bus load over the run is ≤ 60 % (54.0 %; 117.1 % classic,
    refused). Deterministic: the vectorised lockstep, the DBC's frames."""
    from dataclasses import replace

    import numpy as np

    from firmware_py.errors import ConfigError
    from sim.model.lockstep import run_lockstep
    from sim.model.scenario import load_scenario

    sc = load_scenario(TORUS)
    assert (sc.n, sc.ts, sc.fd, sc.transmit.mode) == (64, 0.01, True, "event")
    assert len(sc.edges) == 128 and sorted(len(sc.neighbours(i)) for i in (1, 64)) == [4, 4]
    assert len(sc.pinned) == 16
    ring = load_scenario(EXAMPLE.with_name("ring64.toml"))   # the same fleet, another graph
    assert sc.batteries == ring.batteries and sc.lambda0 == ring.lambda0
    report = sc.analysis()
    assert report.regular and report.discrete_stable
    tr = run_lockstep(sc)
    err = np.max(np.abs(tr.lam - tr.rho[:, None]), axis=1)
    late = np.flatnonzero(err > 1e-3)
    converged_at = (late[-1] + 1) * sc.ts if len(late) else 0.0
    assert err[-1] <= 1e-3 and converged_at <= 10.0, (err[-1], converged_at)
    load = fleetload.check_bus_load(sc)
    assert load <= fleetload.LOAD_LIMIT and load == pytest.approx(0.540, abs=2e-3)
    with pytest.raises(ConfigError, match=r"on classic CAN .* but got 117\.1 % for 64 agents"):
        fleetload.check_bus_load(replace(sc, fd=False))


def test_the_id_plan_has_room_for_64_agents() -> None:
    """The per-agent bases of the DBC (0x100 MC, 0x200 Setpoint, 0x280 Status, 0x300
    Diag, their syncs 0x500, 0x600, 0x680, 0x700): Setpoint and Status are 0x80 apart, so
    127 agents fit without moving a base; Diag runs up to ER_Balance (0x3E0)."""
    room = fleetload.id_plan_room()
    assert room["AGENT_<i>_Setpoint"] == room["PLANT_<i>_Status"] == 0x80 - 1
    assert room["AGENT_<i>_MC"] == 0xFF and room["AGENT_<i>_Diag"] == 0x3E0 - 0x300 - 1
    assert len(room) == 8 and min(room.values()) == 127 >= max(fleetload.SIZES)


def test_docs_table_is_what_the_bench_computes() -> None:
    """docs/performance.md's table is `bess-ded bench --fleet-load`'s (computed: exact)."""
    doc = (Path(__file__).resolve().parent.parent / "docs" / "performance.md").read_text()
    lines = doc.split("| configuration | case 1 (4) |", 1)[1].split("\n\n", 1)[0]
    table = [[c.strip() for c in ("| configuration | case 1 (4) |" + line if i == 0 else line)
              .strip().strip("|").split("|")]
             for i, line in enumerate(lines.splitlines()) if not line.startswith("|---")]
    headers, rows, _ = fleetload.run(quick=False)
    assert table == [headers, *rows]
