"""The authentication schemes' bench (sim.bench.auth, sim.bench.canframe): frame
lengths against the CAN formulas worked by hand, the bus load of a known fleet against
the DBC by hand, what an insider still forges, the table's shape and `bench --auth`.
No timing figure is asserted (they are measured and printed)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from firmware_py import contract
from firmware_py.frames import diag_name, mc_name, setpoint_name, status_name
from sim.bench import auth
from sim.bench.canframe import (
    classic_frame_bits,
    classic_frame_time,
    fd_frame_bits,
    fd_frame_time,
    fd_payload,
)
from sim.cli import main
from sim.model.scenario import load_case


def test_classic_frame_lengths_by_hand() -> None:
    # 11-bit ID, 8 bytes: 34 + 64 + 13 + floor((34 + 64 - 1)/4) = 111 + 24 = 135 bits
    assert classic_frame_bits(8) == 135
    # 29-bit ID: 54 + 64 + 13 + floor(117/4) = 131 + 29 = 160 bits
    assert classic_frame_bits(8, extended=True) == 160
    # 0 bytes, 11-bit ID: 34 + 13 + floor(33/4) = 55
    assert classic_frame_bits(0) == 55
    assert classic_frame_time(8, 500_000) == pytest.approx(270e-6)
    with pytest.raises(ValueError):
        classic_frame_bits(9)


def test_fd_frame_lengths_against_the_iso_frame_by_hand() -> None:
    # nominal rate: 17 header bits (SOF, ID 11, RRS, IDE, FDF, res, BRS) + floor(16/4) = 4
    # stuff bits + 13 tail (CRC delimiter, ACK, ACK delimiter, EOF 7, IFS 3) = 34
    # 8 bytes: SOF..data = 17 + 5 + 64 = 86 bits, floor(85/4) = 21 stuff bits, 17 in the
    # data phase; data phase = ESI + DLC 4 + 64 + 17 + stuff count 4 + CRC-17
    # + ceil(21/4) = 6 fixed stuff bits = 113
    assert fd_frame_bits(8) == (34, 113)
    # 64 bytes: 22 + 512 = 534 bits, floor(533/4) = 133 stuff bits, 129 in the data phase;
    # 5 + 512 + 129 + 4 + CRC-21 + ceil(25/4) = 7 → 678
    assert fd_frame_bits(64) == (34, 678)
    assert fd_frame_time(8, 500_000, 2_000_000) == pytest.approx(34 / 5e5 + 113 / 2e6)
    assert fd_frame_time(64, 500_000, 2_000_000) == pytest.approx(68e-6 + 339e-6)
    # padded to the next FD size: 21 bytes go as 24
    assert fd_payload(21) == 24 and fd_frame_bits(21) == fd_frame_bits(24)
    with pytest.raises(ValueError):
        fd_payload(65)


def test_case_1_bus_load_today_equals_the_dbc_by_hand() -> None:
    """Scheme a (today) on case 1 (4 agents, Ts = 10 ms): every frame a classic 8-byte
    frame of 135 bits at the DBC's 500 kbit/s; the rates are the DBC's cycle times."""
    n, per_s = 4, lambda name: 1000 / contract.cycle_ms(name)
    agent = sum(per_s(f(1)) for f in (mc_name, setpoint_name, status_name, diag_name))
    router = per_s("ER_Price") + 2 * per_s("ER_Balance")       # ER_Balance: 2 pages
    plant = per_s("PLANT_Totals")                               # the router's ledger input
    syncs = 4 * n + 4        # one <name>_Sync a second per secured ID: 4 per agent + 4
    fps = n * agent + router + plant + syncs
    assert fps == 4 * (100 + 20 + 20 + 10) + 20 + 2 * 10 + 20 + 20 == 680
    got = auth.bus_load(auth.SCHEMES[0], load_case(1))
    assert auth.dbc_bitrate() == 500_000
    assert got["frames_per_s"] == pytest.approx(fps)
    assert got["load"] == pytest.approx(fps * 135 / 500_000)


def test_pairwise_tags_on_classic_can_take_extra_frames_per_receiver() -> None:
    """Case 1's star: agent 1's λ has 5 receivers (3 leaves, the plant, the router):
    1 frame with one tag + ceil(4 / 2) frames of two tags; a leaf's λ 3 (hub, plant,
    router): 2 frames; a setpoint (one receiver) stays one frame."""
    sc = load_case(1)
    by_name = {m.name: m for m in auth.fleet_messages(sc)}
    b = next(s for s in auth.SCHEMES if s.key == "b")
    bus = auth.Bus(auth.dbc_bitrate())
    assert len(by_name[mc_name(1)].receivers) == 5
    assert auth.occurrence(b, by_name[mc_name(1)], bus) == (pytest.approx(3 * 270e-6), 3)
    assert auth.occurrence(b, by_name[mc_name(2)], bus)[1] == 2
    assert auth.occurrence(b, by_name[setpoint_name(1)], bus)[1] == 1
    # on CAN FD the hub's λ is one frame: 5 payload bytes + 5 tags of 3 = 20 bytes
    c = next(s for s in auth.SCHEMES if s.key == "c")
    t, k = auth.occurrence(c, by_name[mc_name(1)], bus)
    assert k == 1 and t == pytest.approx(fd_frame_time(20, 500_000, auth.FD_DATA_RATE))
    # the price of a 32-agent ring: 33 receivers, 5 + 99 = 104 bytes: 64 + 40 (→ 48)
    ring = {m.name: m for m in auth.fleet_messages(auth.ring_scenario())}
    t, k = auth.occurrence(c, ring["ER_Price"], bus)
    assert k == 2 and t == pytest.approx(bus.fd(64) + bus.fd(48))


def test_ring_scenario_is_a_ring() -> None:
    sc = auth.ring_scenario(32)
    assert sc.n == 32 and all(len(sc.neighbours(i)) == 2 for i in range(sc.n))


def test_what_agent_3s_insider_forges_per_scheme() -> None:
    """Case 1: agent 3 holds the router's and agent 1's node keys, and PLANT_3_Status's
    link key (agent 3 its one receiver: the router's ledger takes PLANT_Totals); no
    report key but its own Diag's (AUTH-29), no command key but its own (AUTH-30):
    ER_Command_Sync is all it can forge of commands."""
    sc = load_case(1)
    s = {x.key: x for x in auth.SCHEMES}
    today = auth.insider_forges(s["a"], sc)
    assert today == {n: "forge" for n in (
        "ER_Price", "ER_Price_Sync", "ER_Command_Sync", mc_name(1), mc_name(1) + "_Sync")}
    assert not {diag_name(1), "ER_Balance", "ER_Command", "PLANT_Totals"} & set(today)
    assert not any(n.startswith(("AGENT_2", "AGENT_4", "PLANT_", "AGENT_3")) for n in today)
    for key in ("b", "c", "e"):
        assert auth.insider_forges(s[key], sc) == {}
    signed = auth.insider_forges(s["d"], sc)
    assert signed == {"ER_Price": "bound", "ER_Price_Sync": "forge",
                      "ER_Command_Sync": "forge"}
    # the classic-CAN step: λ stays under agent 1's node key, the links and reports go
    # pairwise (AGENT_1_Diag out of reach)
    assert auth.insider_forges(s["d-min"], sc) == {
        **signed, mc_name(1): "forge", mc_name(1) + "_Sync": "forge"}
    assert auth.forged_summary({}) == "nothing (own frames only)"


def test_scheme_table_structure() -> None:
    rows, data = auth.run(quick=True)
    keys = [s.key for s in auth.SCHEMES]
    assert len(set(keys)) == len(keys) >= 8
    assert len(rows) == len(auth.SCHEMES) and all(len(r) == len(auth.HEADERS) for r in rows)
    assert list(data["schemes"]) == keys
    for v in data["schemes"].values():
        assert set(v["loads"]) == {"case 1", "case 7", "ring-32"}
        assert all(x["load"] > 0 and x["frames_per_s"] > 0 for x in v["loads"].values())
        assert math.isfinite(v["sign_us"]) and math.isfinite(v["verify_us"])
    # more tags never cost less bus than today's frame on the same bus
    loads = {k: v["loads"]["ring-32"]["load"] for k, v in data["schemes"].items()}
    assert loads["b"] > loads["a"] and loads["c"] > loads["a-fd"]


def test_cli_bench_auth_writes_json_and_png(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    out, png = tmp_path / "auth.json", tmp_path / "auth.png"
    assert main(["bench", "--auth", "--quick", "--json", str(out), "--png", str(png)]) == 0
    text = capsys.readouterr().out
    assert "Authentication schemes" in text and "ring-32" in text
    doc = json.loads(out.read_text())
    (table,) = doc["tables"]
    assert table["headers"] == auth.HEADERS
    assert set(table["data"]["schemes"]) == {s.key for s in auth.SCHEMES}
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["bench", "--auth", "--realtime"]) != 0
