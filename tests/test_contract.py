"""firmware_py.contract: every bus constant comes from the DBC, and fails loudly if absent."""

from __future__ import annotations

import re

import pytest

from firmware_py import contract, frames
from firmware_py.errors import ConfigError
from firmware_py.frames import FrameCodec

DB = FrameCodec().database


def test_agent_limit_ids_and_counter_modulus_are_read_from_the_dbc() -> None:
    mc = [m for m in DB.messages if re.fullmatch(r"AGENT_\d+_MC", m.name)]
    assert contract.N_AGENTS_MAX == len(mc) == frames.N_AGENTS_MAX
    counter = DB.get_message_by_name("ER_Price").get_signal_by_name("Counter")
    assert contract.COUNTER_MODULO == 2**counter.length
    for base, pattern in zip(contract.AGENT_BASES, ("AGENT_{}_MC", "AGENT_{}_Setpoint",
                                                   "PLANT_{}_Status", "AGENT_{}_Diag",
                                                   "AGENT_{}_MC_Sync", "AGENT_{}_Setpoint_Sync",
                                                   "PLANT_{}_Status_Sync",
                                                   "AGENT_{}_Diag_Sync"),
                             strict=True):
        for i in contract.agent_ids():
            assert DB.get_message_by_name(pattern.format(i)).frame_id == base + i
            assert frames.agent_of(base + i) == i
    assert contract.ER_PRICE_ID == DB.get_message_by_name("ER_Price").frame_id


def test_cycles_ticks_and_time_scale() -> None:
    assert contract.MC_CYCLE_S == DB.get_message_by_name("AGENT_1_MC").cycle_time / 1000
    for name in ("AGENT_1_Setpoint", "PLANT_1_Status", "ER_Price", "AGENT_1_Diag",
                 "ER_Balance"):
        ms = DB.get_message_by_name(name).cycle_time
        assert contract.every_ticks(name) * contract.MC_CYCLE_S == pytest.approx(ms / 1000)
        assert contract.cycle_s(name) == pytest.approx(ms / 1000)
        assert contract.cycle_s(name, 0.04) == pytest.approx(4 * ms / 1000)   # F = 4
        assert contract.timeout_s(name) == pytest.approx(5 * ms / 1000)
    assert not contract.is_cyclic("ER_Command")
    with pytest.raises(ConfigError, match="expected a cyclic message"):
        contract.cycle_ms("ER_Command")
    with pytest.raises(ConfigError, match="expected this message in the DBC"):
        contract.cycle_ms("AGENT_99_MC")


def test_enums_are_the_dbc_choice_tables() -> None:
    state = DB.get_message_by_name("AGENT_1_MC").get_signal_by_name("State").choices
    assert {int(k): str(v) for k, v in state.items()} == {s.value: s.name for s in
                                                          contract.State}
    cmd = DB.get_message_by_name("ER_Command").get_signal_by_name("Command").choices
    assert {int(k): str(v) for k, v in cmd.items()} == {c.value: c.name for c in
                                                        contract.Command}
    with pytest.raises(ConfigError, match="expected a choice named BOGUS, but got INIT"):
        contract._choice("AGENT_1_MC", "State", "BOGUS")


def test_is_active_is_running_only() -> None:
    assert [s.name for s in contract.State if contract.is_active(s)] == ["RUNNING"]


def test_scales_and_ranges() -> None:
    assert contract.scale("PLANT_1_Status", "Power") == 0.01
    assert contract.raw_range("PLANT_1_Status", "Soc") == (0, 200)


def test_secoc_constants_are_read_from_the_dbc() -> None:
    """The secured frames are those with a Mac; each has its <name>_Sync at ID + 0x400
    from the same sender; the MAC and freshness widths are the signals' lengths."""
    secured = {m.frame_id for m in DB.messages
               if any(s.name == "Mac" for s in m.signals) and not m.name.endswith("_Sync")}
    assert contract.SECURED_IDS == secured
    # every frame but the syncs: ER_Price, ER_Command, ER_Balance, PLANT_Totals, 4 per agent
    assert len(secured) == 4 + 4 * contract.N_AGENTS_MAX
    for fid in secured:
        m, sync = DB.get_message_by_frame_id(fid), DB.get_message_by_frame_id(
            contract.SYNC_OF[fid])
        assert sync.name == f"{m.name}_Sync" and sync.senders == m.senders
        assert contract.SYNCED_BY[sync.frame_id] == fid
    price = DB.get_message_by_name("ER_Price")
    assert contract.MAC_BITS == price.get_signal_by_name("Mac").length == 24
    assert contract.FV_TX_BITS == price.get_signal_by_name("Counter").length == 4
    sync = DB.get_message_by_name("ER_Price_Sync")
    assert (contract.FV_BOOT_BITS, contract.FV_COUNT_BITS) == (
        sync.get_signal_by_name("Boot").length, sync.get_signal_by_name("Count").length)
    assert [contract.sender_of(n) for n in ("ER_Command", "PLANT_3_Status",
                                            "AGENT_7_Setpoint")] == ["router", "plant",
                                                                     "agent_7"]


def test_every_counter_the_python_agent_counts_is_in_the_one_list() -> None:
    """The counter names firmware_py's agent uses (``counters["…"]``, ``reject("…")``,
    ``fail(id, "…")``) are contract.AGENT_COUNTERS', the list firmware_c's BD_C_* are
    generated from: a name typed differently in one place fails here."""
    import ast
    from pathlib import Path

    from firmware_py import contract

    root = Path(contract.__file__).parent
    used: set[str] = set()
    for name in ("nodeio.py", "runtime.py", "node.py"):
        for n in ast.walk(ast.parse((root / name).read_text(encoding="utf-8"))):
            if isinstance(n, ast.Subscript) and isinstance(n.value, ast.Attribute) \
                    and n.value.attr == "counters" and isinstance(n.slice, ast.Constant):
                used.add(n.slice.value)
            elif isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute):
                pos = {"reject": 0, "fail": 1}.get(n.func.attr)
                if pos is not None and len(n.args) > pos \
                        and isinstance(n.args[pos], ast.Constant):
                    used.add(n.args[pos].value)
    assert len(used) >= 15  # the walk found the agent's counting
    # the signed price's causes (AUTH-32, AUTH-33): BD_C_* after AGENT_COUNTERS' in firmware_c
    assert used - set(contract.AGENT_COUNTERS) - set(contract.SIGNED_PRICE_COUNTERS) == set()
