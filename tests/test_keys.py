"""`bess-ded keys`: fleet key provisioning."""

from __future__ import annotations

import os
import stat
import tomllib
from pathlib import Path

import pytest

from firmware_py import secoc
from sim.cli import main
from sim.model.scenario import SCENARIO_DIR


def _mode(p: Path) -> int:
    return stat.S_IMODE(os.stat(p).st_mode)


def test_fleet_for_a_case(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "keys"
    assert main(["keys", "--fleet", "--case", "1", "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "fleet id" in stdout
    nodes = ["agent_1", "agent_2", "agent_3", "agent_4", "plant", "router"]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{n}.key" for n in nodes] + ["master.key"])
    assert _mode(out) == 0o700
    assert all(_mode(p) == 0o600 for p in out.iterdir())
    master = secoc.load_master_key(out / "master.key")
    keys = {}
    for n in nodes:
        nk = secoc.load_node_key(out / f"{n}.key")
        assert nk.node == n and nk.boot_counter == 0
        assert nk.key == secoc.derive_node_key(master, n)  # re-derives from the master
        assert nk.fleet_id == secoc.fleet_id(master)
        keys[n] = nk.key
        assert nk.key.hex() not in stdout
    assert len(set(keys.values())) == len(nodes)
    assert master not in keys.values()
    doc = tomllib.loads((out / "agent_1.key").read_text())
    assert doc["format"] == secoc.KEY_FILE_FORMAT and doc["freshness"] == {"boot_counter": 0}


def test_key_files_hold_only_the_link_frame_keys_each_node_needs(tmp_path: Path) -> None:
    """AUTH-28, AUTH-29, issue 25 item 5: each key file lists the node keys of the
    broadcasts it takes and the keys of its own link frames and reports only; agent 3's
    file yields no key that tags agent 1's setpoint, status or Diag, nor the router's
    ledger (nor any frame whose parties exclude it); no file but the plant's, agent 1's
    holds PLANT_1_Status's key (the router's ledger takes PLANT_Totals, the plant's and
    the router's only), none but agent 1's and the router's AGENT_1_Diag's, none but the
    router's ER_Balance's."""
    from firmware_py import contract
    from firmware_py.frames import FrameCodec

    out = tmp_path / "keys"
    assert main(["keys", "--fleet", "--case", "1", "--out", str(out)]) == 0
    master = secoc.load_master_key(out / "master.key")
    files = {n: secoc.load_node_key(out / f"{n}.key")
             for n in ["agent_1", "agent_2", "agent_3", "agent_4", "plant", "router"]}
    assert contract.link_frames(4) == [*(f"AGENT_{i}_Setpoint" for i in range(1, 5)),
                                       *(f"PLANT_{i}_Status" for i in range(1, 5))]
    links = contract.keyed_frames(4)
    assert sorted(links) == sorted([*contract.link_frames(4), "ER_Balance", "PLANT_Totals",
                                    *(f"AGENT_{i}_Diag" for i in range(1, 5))])
    for node, nk in files.items():
        want = [f for f in links if node in contract.parties_of(f)]
        assert sorted(nk.frames) == sorted(want), node
        assert all(k == secoc.derive_frame_key(master, f) for f, k in nk.frames.items())
        assert "plant" not in nk.peers  # the plant sends link frames only
    assert sorted(files["agent_3"].frames) == ["AGENT_3_Diag", "AGENT_3_Setpoint",
                                               "PLANT_3_Status"]
    assert [n for n, nk in files.items() if "AGENT_1_Diag" in nk.frames] == [
        "agent_1", "router"]
    assert [n for n, nk in files.items() if "ER_Balance" in nk.frames] == ["router"]
    assert "router" in files["agent_3"].peers and "plant" not in files["agent_3"].peers
    assert [n for n, nk in files.items() if "PLANT_1_Status" in nk.frames] == [
        "agent_1", "plant"]
    assert [n for n, nk in files.items() if "PLANT_Totals" in nk.frames] == ["plant", "router"]
    # every key agent 3's file holds fails to tag agent 1's status, setpoint and Diag,
    # the ledger, and every frame whose parties exclude agent 3
    codec = FrameCodec()
    ring = secoc.Keyring.from_file(out / "agent_3.key")
    held = [ring.key, *files["agent_3"].peers.values(), *files["agent_3"].frames.values()]
    for name in links:
        if "agent_3" in contract.parties_of(name):
            continue
        assert ring.key_for(name) is None and ring.key_for(name + "_Sync") is None
        fid = codec.frame_id(name)
        genuine = secoc.derive_frame_key(master, name)
        data = bytearray(8)
        data[4:6] = (12000).to_bytes(2, "little")
        fv = contract.FRESHNESS.join(1, 7)
        for key in held:
            forged = bytearray(data)
            secoc.sign_frame(key, fid, forged, fv)
            assert not secoc.frame_verifies(genuine, fid, forged, fv), (name, key.hex())


def test_key_files_hold_only_the_command_keys_each_node_needs(tmp_path: Path) -> None:
    """AUTH-30: agent i's file holds the key of the commands to it only, the router's
    every agent's, the plant's none; no key in agent 3's file tags a command to agent 1
    (ISOLATE) as agent 1 verifies it, and agent 1's keyring from its file verifies the
    router's."""
    from firmware_py import contract

    out = tmp_path / "keys"
    assert main(["keys", "--fleet", "--case", "1", "--out", str(out)]) == 0
    master = secoc.load_master_key(out / "master.key")
    files = {n: secoc.load_node_key(out / f"{n}.key") for n in secoc.fleet_nodes(4)}
    agents = [f"agent_{i}" for i in range(1, 5)]
    for node, nk in files.items():
        want = agents if node == "router" else [node] if node in agents else []
        assert sorted(nk.commands) == want, node
        assert all(k == secoc.derive_command_key(master, t) for t, k in nk.commands.items())
    agent_1 = secoc.Keyring.from_file(out / "agent_1.key")
    genuine = agent_1.key_for(contract.COMMAND)
    assert genuine == files["router"].commands["agent_1"]
    held = [files["agent_3"].key, *files["agent_3"].peers.values(),
            *files["agent_3"].frames.values(), *files["agent_3"].commands.values()]
    fid, fv = contract.ER_COMMAND_ID, contract.FRESHNESS.join(1, 3)
    data = bytearray(8)
    data[3], data[4] = 0x10, 0x01   # an ISOLATE-like payload; any payload would do
    for key in held:
        forged = bytearray(data)
        secoc.sign_frame(key, fid, forged, fv)
        assert genuine is not None and not secoc.frame_verifies(genuine, fid, forged, fv)


def test_rotating_one_node_rewrites_only_the_files_sharing_its_keys(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 25, item 5: `keys --rotate agent_3` gives agent 3 a new own key and new link
    frame, Diag and command keys, written into its file and those of the nodes holding
    one of them (case 1: agent 1, its neighbour; the plant; the router), boot counters and
    floors kept;
    agents 2 and 4's files are untouched byte for byte. The old copy of agent_3.key no
    longer tags agent 3's setpoint or MC as its receivers now verify them; the rotated
    set passes `up`'s check and runs a clean dispatch."""
    from firmware_py import contract
    from firmware_py.frames import FrameCodec
    from sim.model.scenario import load_case
    from sim.run import busrun
    from sim.run.keyset import check_key_set, write_boot_floors

    out = tmp_path / "keys"
    assert main(["keys", "--fleet", "--case", "1", "--out", str(out)]) == 0
    write_boot_floors(out, ["plant"], {"agent_3": 2})
    secoc.save_boot_counter(out / "agent_3.key", 4)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    old = secoc.load_node_key(out / "agent_3.key")
    capsys.readouterr()
    assert main(["keys", "--fleet", "--case", "1", "--out", str(out),
                 "--rotate", "agent_3"]) == 0
    said = capsys.readouterr().out
    assert "rewrote agent_1.key, agent_3.key, plant.key, router.key" in said, said
    changed = {p.name for p in out.iterdir() if p.read_bytes() != before[p.name]}
    assert changed == {"agent_3.key", "agent_1.key", "plant.key", "router.key"}
    new = secoc.load_node_key(out / "agent_3.key")
    assert new.key != old.key and new.boot_counter == 4
    assert all(new.frames[f] != old.frames[f] for f in old.frames)
    assert new.peers == old.peers  # the keys of others it holds are not its to rotate
    plant = secoc.load_node_key(out / "plant.key")
    assert plant.peers["agent_3"] == new.key and plant.floors["agent_3"] == 2
    assert plant.frames["AGENT_3_Setpoint"] == new.frames["AGENT_3_Setpoint"]
    router = secoc.load_node_key(out / "router.key")
    assert "PLANT_3_Status" not in router.frames  # its ledger takes PLANT_Totals
    assert router.frames["AGENT_3_Diag"] == new.frames["AGENT_3_Diag"]  # AUTH-29
    # AUTH-30: the key of the commands to agent 3, in its file and the router's
    assert router.commands["agent_3"] == new.commands["agent_3"] != old.commands["agent_3"]
    assert secoc.load_node_key(out / "agent_1.key").peers["agent_3"] == new.key
    codec = FrameCodec()
    for name, old_key, now in (("AGENT_3_Setpoint", old.frames["AGENT_3_Setpoint"],
                                plant.frames["AGENT_3_Setpoint"]),
                               ("AGENT_3_MC", old.key, plant.peers["agent_3"])):
        data, fid, fv = bytearray(8), codec.frame_id(name), contract.FRESHNESS.join(5, 1)
        secoc.sign_frame(old_key, fid, data, fv)
        assert not secoc.frame_verifies(now, fid, data, fv)
    sc = load_case(1)
    assert check_key_set(out, sc.n, sc)
    m = busrun.run_in_process(sc, tmp_path / "run", sc.duration, channel="rotated",
                              keyrings={n: secoc.Keyring.from_file(out / f"{n}.key")
                                        for n in secoc.fleet_nodes(sc.n)})
    assert m["verdict"]["exit_code"] == 0, m["anomalies"]
    assert main(["keys", "--fleet", "--case", "1", "--out", str(out),
                 "--rotate", "agent_9"]) == 2


def test_files_never_exist_world_readable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                          ) -> None:
    """Every key file is opened with mode 0600 and O_EXCL from the start."""
    opened: list[tuple[str, int, int]] = []
    real_open = os.open

    def spy(path: str | os.PathLike[str], flags: int, mode: int = 0o777, **kw: object) -> int:
        opened.append((str(path), flags, mode))
        return real_open(path, flags, mode)

    monkeypatch.setattr(os, "open", spy)
    out = tmp_path / "k"
    assert main(["keys", "--fleet", "--case", "2", "--out", str(out)]) == 0
    created = [(p, f, m) for p, f, m in opened if f & os.O_CREAT]
    assert len(created) == len(list(out.iterdir()))
    assert all(m == 0o600 and f & os.O_EXCL for _, f, m in created)


def test_scenario_file_and_given_master_key(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    first = tmp_path / "a"
    assert main(["keys", "--fleet", "--case", "3", "--out", str(first)]) == 0
    second = tmp_path / "b"
    assert main(["keys", "--fleet", "--scenario", str(SCENARIO_DIR / "case3.toml"),
                 "--out", str(second), "--master-key", str(first / "master.key")]) == 0
    assert not (second / "master.key").exists()  # a given master key is not copied
    names = sorted(p.name for p in second.iterdir())
    assert names == sorted(p.name for p in first.iterdir() if p.name != "master.key")
    for name in names:
        assert (secoc.load_node_key(first / name).key == secoc.load_node_key(second / name).key)


def test_refuses_to_overwrite_without_force(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "keys"
    assert main(["keys", "--fleet", "--case", "7", "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert main(["keys", "--fleet", "--case", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: error: --out:") and "--force" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    # --force: a new master key, a new (smaller) fleet, no leftovers of the old one
    assert main(["keys", "--fleet", "--case", "1", "--out", str(out), "--force"]) == 0
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(after) == sorted(["agent_1.key", "agent_2.key", "agent_3.key",
                                    "agent_4.key", "plant.key", "router.key", "master.key"])
    assert after["master.key"] != before["master.key"]
    assert after["agent_1.key"] != before["agent_1.key"]
    assert all(_mode(out / n) == 0o600 for n in after)
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("argv", [
    ["keys", "--fleet", "--case", "99"],
    ["keys", "--fleet", "--case", "x"],
    ["keys", "--fleet", "--case", "1", "--scenario", "a.toml"],
    ["keys", "--fleet"],
    ["keys", "--case", "1"],
    ["keys", "--fleet", "--scenario", "missing.toml"],
    ["keys", "--fleet", "--case", "1", "--master-key", "MISSING"],
    ["keys", "--fleet", "--case", "1", "--master-key", "BAD"],
    ["keys", "--fleet", "--case", "1", "--master-key", "OPEN"],
])
def test_bad_input_is_a_one_line_error(argv: list[str], tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    secoc.write_private(tmp_path / "BAD", "not a key\n")
    secoc.write_private(tmp_path / "OPEN", "00" * 16 + "\n")
    os.chmod(tmp_path / "OPEN", 0o644)
    argv = [str(tmp_path / a) if a in ("MISSING", "BAD", "OPEN") else a for a in argv]
    if "--out" not in argv and argv[1:] != ["--fleet"] and argv[1:] != ["--case", "1"]:
        argv += ["--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("bess-ded: error: ") and err.count("\n") == 1
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_out_is_a_file_or_an_open_directory(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "file"
    f.write_text("")
    assert main(["keys", "--fleet", "--case", "1", "--out", str(f)]) == 2
    assert "a directory" in capsys.readouterr().err
    d = tmp_path / "open"
    d.mkdir()
    os.chmod(d, 0o755)
    assert main(["keys", "--fleet", "--case", "1", "--out", str(d)]) == 2
    assert "group or others" in capsys.readouterr().err
    assert not any(d.iterdir())


def test_keys_is_listed_in_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["-h"]) == 0
    listed = [" ".join(ln.split()) for ln in capsys.readouterr().out.splitlines()
              if ln.split()[:1] == ["keys"]]
    assert listed == ["keys provision SecOC keys for a fleet (one key file per node)"]
