"""CAN FD framing (issue 23 item 3, firmware-spec GEN-1, RX-2, LOOP-6): the FD twin of the
DBC, the codec and the agent on either format, the scenario key, and FD fleets on the
simulated-clock virtual bus and on udp_multicast."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import can
import cantools
import pytest

from dbc import DBC_PATH, FD_DBC_PATH, dbc_path
from firmware_py import fixedpoint as fx
from firmware_py.config import agent_configs_from_scenario
from firmware_py.errors import ConfigError, FrameError
from firmware_py.frames import FrameCodec, mc_name
from firmware_py.nodeio import FleetSender
from firmware_py.runtime import AgentRuntime
from sim.bench import fleetload
from sim.model.scenario import load_case, load_scenario, parse_scenario, to_toml
from sim.run import busrun
from sim.run.analysis import prepare_analysis
from sim.run.buslog import read_log

ROOT = Path(__file__).resolve().parent.parent
CLASSIC, FD = FrameCodec(), FrameCodec(FD_DBC_PATH)


def _layout(m: cantools.database.can.Message) -> list[tuple[object, ...]]:
    return [(s.name, s.start, s.length, s.is_signed, s.scale, s.offset, s.minimum, s.maximum,
             s.multiplexer_ids) for s in m.signals]


def test_the_fd_dbc_is_the_classic_one_as_fd_frames() -> None:
    """GEN-1: the same messages, IDs, senders and 8-byte layouts, every one a CAN FD frame
    with the bit-rate switch, but λ and its sync: the classic layout, then 6 slots of a
    receiver code and its 24-bit tag (AUTH-34), 32 bytes; the bus an FD bus with its data
    phase's bit rate."""
    classic = cantools.database.load_file(DBC_PATH, strict=True)
    fd = cantools.database.load_file(FD_DBC_PATH, strict=True)
    assert isinstance(classic, cantools.database.can.Database)
    assert isinstance(fd, cantools.database.can.Database)
    assert [m.name for m in fd.messages] == [m.name for m in classic.messages]
    tagged = 0
    for a, b in zip(classic.messages, fd.messages, strict=True):
        slots = [s for s in b.signals if s.name.startswith("Tag")]
        assert (b.frame_id, b.length - 4 * len(slots) // 2, b.senders, b.cycle_time) == \
            (a.frame_id, a.length, a.senders, a.cycle_time)
        assert _layout(b)[:len(a.signals)] == _layout(a), b.name
        assert b.is_fd and not a.is_fd
        if slots:
            tagged += 1
            assert b.name.endswith(("_MC", "_MC_Sync")) and b.length == 32
            assert [(s.name, s.start, s.length) for s in slots] == [
                (f"Tag{'Rx' if j % 2 == 0 else ''}{j // 2}", 64 + 8 * (j % 2) + 32 * (j // 2),
                 8 if j % 2 == 0 else 24) for j in range(12)]
            assert slots[0].choices == {0: "EMPTY", 254: "PLANT", 255: "ROUTER"}
    assert tagged == 2 * 64  # every agent's MC and MC_Sync
    assert fd.dbc is not None and classic.dbc is not None
    assert fd.dbc.attributes["BusType"].value == "CAN FD"
    assert fd.dbc.attributes["BaudrateCANFD"].value == 2_000_000
    assert fd.dbc.attribute_definitions["CANFD_BRS"].default_value == "1"
    assert "BaudrateCANFD" not in classic.dbc.attributes
    assert (CLASSIC.fd, FD.fd) == (False, True)
    assert dbc_path(True) == FD_DBC_PATH and dbc_path(False) == DBC_PATH


def test_each_codec_sends_its_format_and_rejects_the_other() -> None:
    """RX-2: the same bytes either way; an FD frame (with the bit-rate switch) from the FD
    codec, a classic one from the classic codec; each rejects the other's as malformed."""
    raw = {"State": 1, "Lambda": fx.to_fixed(0.8), "Resets": 2}
    fd, classic = FD.encode(mc_name(3), raw, 5), CLASSIC.encode(mc_name(3), raw, 5)
    assert (fd.is_fd, fd.bitrate_switch, classic.is_fd) == (True, True, False)
    # λ: the classic bytes, then its 6 tag slots (empty until NodeIO signs it, AUTH-34)
    assert bytes(fd.data) == bytes(classic.data) + bytes(24) and fd.dlc == 32
    sp = {"Enable": 1, "PowerSetpoint": 1234}
    assert bytes(FD.encode("AGENT_3_Setpoint", sp, 5).data) == \
        bytes(CLASSIC.encode("AGENT_3_Setpoint", sp, 5).data)
    got = FD.decode(fd).raw
    assert {k: v for k, v in got.items() if not k.startswith("Tag")} == \
        CLASSIC.decode(classic).raw
    assert [got[f"TagRx{k}"] for k in range(6)] == [0] * 6
    for codec, msg, want, got in ((FD, classic, "a CAN FD", "a classic CAN frame"),
                                  (CLASSIC, fd, "a classic CAN", "a CAN FD frame")):
        with pytest.raises(FrameError, match=f"expected {want} data frame, but got {got}") as e:
            codec.decode(msg)
        assert e.value.cause == "malformed"
    # an FD frame without the bit-rate switch is still an FD frame (RX-2)
    slow = can.Message(arbitration_id=fd.arbitration_id, data=fd.data, is_extended_id=False,
                       is_fd=True, bitrate_switch=False)
    assert FD.decode(slow).raw == FD.decode(fd).raw


def test_an_agent_on_an_fd_bus_takes_fd_frames_and_counts_classic_ones() -> None:
    """GEN-1, RX-2: agent 2 of case 1 with the FD codec takes the router's FD price, counts
    the same price as a classic frame under malformed, and sends FD frames only."""
    cfg = agent_configs_from_scenario(load_case(1))[1]
    for codec, other in ((FD, CLASSIC), (CLASSIC, FD)):
        agent = AgentRuntime(cfg, codec)
        price = {"PriceValid": 1, "Segment": 0, "Rho": fx.to_fixed(0.8)}
        agent.on_frame(FleetSender(other).frame("ER_Price", price), 0.0)
        assert agent.counters["malformed"] == 1
        agent.on_frame(FleetSender(codec).frame("ER_Price", price), 0.0)
        assert agent.counters["malformed"] == 1 and sum(agent.counters.values()) == 1
        sent = [m for k in range(1, 30) for m in agent.tick(k * cfg.controller.ts)]
        assert sent and all(m.is_fd == codec.fd == m.bitrate_switch for m in sent)


def test_the_scenario_key_selects_fd_and_round_trips() -> None:
    sc = load_case(1)
    assert not sc.fd and "[bus]" not in to_toml(sc)
    fd = replace(sc, fd=True)
    text = to_toml(fd)
    assert "[bus]\nfd = true" in text
    import tomllib

    assert parse_scenario(tomllib.loads(text), "fd.toml").fd
    for bad, why in (({"fd": "yes"}, "bus.fd. expected true .CAN FD. or false"),
                     ({"fdd": True}, "unknown key")):
        doc = tomllib.loads(to_toml(sc))
        doc["bus"] = bad
        with pytest.raises(ConfigError, match=why):
            parse_scenario(doc, "bad.toml")
    ring = load_scenario(ROOT / "examples" / "ring64.toml")
    assert ring.fd and ring.n == 64 and ring.transmit.mode == "event"


@pytest.mark.slow
def test_case1_on_an_fd_virtual_bus_converges_with_fd_frames_only(tmp_path: Path) -> None:
    """Every node (agents, plant, router) sends FD frames with the bit-rate switch, the
    recorder and the analysis read them with the FD DBC: case 1 converges, nothing is
    rejected or undecodable (simulated clock: deterministic)."""
    sc = replace(load_case(1), duration=8.0, fd=True)
    m = busrun.run_in_process(sc, tmp_path, duration=8.0, channel="test-fd-case1")
    assert m["final_error"] < 1e-3 and m["frames_undecodable"] == {}
    diag = m["node_diagnostics"]
    assert all(a["RejectedAuth"] == 0 and a["RejectedDlc"] == 0 for a in diag.values())
    frames = list(can.LogReader(str(tmp_path / "run.log")))
    assert len(frames) == m["frames_recorded"] > 1000
    assert all(f.is_fd and f.bitrate_switch for f in frames)
    # the classic codec reads none of them
    assert read_log(tmp_path / "run.log", CLASSIC, n=sc.n).undecodable
    # the load of the recorded frames is the computed one: every node ticks on time here
    run = fleetload.measured_run(tmp_path)
    assert run["fd_frames"] == run["frames"] and run["time_scale"] == 1.0
    assert run["load_measured"] == pytest.approx(run["load_computed"], rel=0.03), run
    # `bess-ded analyze run.log --case 1` (a classic scenario) reads the log's format
    notes: list[str] = []
    rec = prepare_analysis(tmp_path / "run.log", "1", out=tmp_path / "an",
                           say=notes.append).run(plot=False)
    assert any("CAN FD frames: read with the FD DBC" in n for n in notes), notes
    assert rec.metrics["frames_undecodable"] == {} and rec.metrics["final_error"] < 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("lambda_tags", [True, False])
def test_case1_on_an_fd_bus_with_c_agents_converges(tmp_path: Path, lambda_tags: bool) -> None:
    """AUTH-34 across both runtimes: case 1 on an FD virtual bus (simulated clock) with
    agents 2 and 4 on firmware_c (sim.cbind CAgent) beside firmware_py's: every λ they
    send is 32 bytes with a tag per receiver (none: 8 bytes with ``--no-lambda-tags``),
    each side verifies the other's tags, nothing is rejected, case 1 converges."""
    from firmware_py.config import agent_configs_from_scenario as configs

    sc = replace(load_case(1), duration=8.0, fd=True, lambda_tags=lambda_tags)
    m = busrun.run_in_process(sc, tmp_path, duration=8.0, channel=f"test-fd-c-{lambda_tags}",
                              c_agents=(2, 4))
    assert m["final_error"] < 1e-3 and m["frames_undecodable"] == {}
    diag = m["node_diagnostics"]
    assert all(a["RejectedAuth"] == 0 and a["RejectedDlc"] == 0 for a in diag.values()), diag
    frames = list(can.LogReader(str(tmp_path / "run.log")))
    for i in (2, 4):   # C agents' MC, then a Python agent's for the same form
        mc = [f for f in frames if f.arbitration_id == 0x100 + i]
        want = sorted(n.id for n in configs(sc)[i - 1].neighbours) + [0xFE, 0xFF]
        assert mc and all(f.is_fd and f.bitrate_switch for f in mc)
        if lambda_tags:
            assert all(len(f.data) == 32 and f.data[:3] == bytes(3)
                       and list(f.data[8::4]) == want + [0] * (6 - len(want)) for f in mc)
        else:
            assert all(len(f.data) == 8 for f in mc)


@pytest.mark.slow
def test_c_agents_refuse_an_insiders_forged_lambda_on_fd(tmp_path: Path) -> None:
    """AUTH-34 at the C agent in a fleet: case 1 on FD with agents 2 and 4 in C; an insider
    holding agent 3's keys forges agent 1's λ (the hub's) at 1.2 cu/kWh every tick from
    t = 1 s, with a sync one boot ahead every second, each tag towards agents 2 and 4, the
    plant and the router under the best key it holds (agent 1's pair key with agent 3).
    Both C agents count every forged frame and sync `auth` and take none: case 1 still
    converges."""
    from firmware_py import fixedpoint
    from firmware_py import secoc as sec

    master = bytes(range(16))
    sc = replace(load_case(1), duration=6.0, fd=True)
    others = ["agent_2", "agent_4", "plant", "router"]
    best = sec.derive_lambda_tag_key(master, "agent_1", "agent_3")
    sender = FleetSender(FD, keys={sec.pair_label("agent_1", r): best for r in others},
                         boot=2, tag_receivers={1: others})
    sent: list[can.Message] = []
    counters: dict[str, dict[str, int]] = {}

    def inject(t: float) -> list[can.Message]:
        k = round(t / sc.ts)
        if t < 1.0:
            return []
        out = [sender.sync(mc_name(1))] if k % 100 == 0 else []
        out.append(sender.frame(mc_name(1), {"State": 1, "Resets": 0,
                                             "Lambda": fixedpoint.to_fixed(1.2)}))
        sent.extend(out)
        return out

    def observe(_t: float, nodes: dict[str, object]) -> None:
        for n in ("agent_2", "agent_4"):
            if (node := nodes.get(n)) is not None:
                counters[n] = dict(node.counters)  # type: ignore[attr-defined]

    m = busrun.run_in_process(sc, tmp_path, duration=6.0, channel="test-fd-c-forged",
                              inject=inject, observe=observe, c_agents=(2, 4),
                              keyrings=sec.Keyring.fleet(master, sec.fleet_nodes(sc.n)))
    assert len(sent) > 400
    for n in ("agent_2", "agent_4"):  # (the last tick's frames come after the last look)
        assert len(sent) - 1 <= counters[n].get("auth", 0) <= len(sent), (n, counters[n])
    assert m["final_error"] < 1e-3


def test_crafted_frames_on_an_fd_bus_are_counted_by_their_own_cause() -> None:
    """`bess-ded inject --fd`: the crafted frames are FD frames, so an FD agent counts
    each under its cause (dlc, range, unknown_id, impersonation), not as malformed."""
    from sim.nodes.inject import frames

    cfg = agent_configs_from_scenario(load_case(1))[1]
    for kind, cause in (("dlc", "dlc"), ("range", "range"), ("unknown", "unknown_id"),
                        ("impersonate", "impersonation")):
        agent = AgentRuntime(cfg, FD)
        crafted = list(frames(kind, 4, target=2, codec=FD))
        assert all(m.is_fd and m.bitrate_switch for m in crafted)
        for m in crafted:
            agent.on_frame(m, 0.0)
        assert agent.counters[cause] == 4 and agent.counters["malformed"] == 0
