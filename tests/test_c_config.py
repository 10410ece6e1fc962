"""The C node's configuration and key-file loader (firmware_c/src/config.c, keyfile.c).

Every paper case's agent configurations and every node vector's, written as `bess-ded up`
writes them, load in C to exactly the integers firmware_py computes (sim.cbind.cagent.params_of:
q24, q30, the setpoint map, the timeouts in ns, the SET_GAINS raw bounds). Bad files are
refused naming the key firmware_py names. Key files written by firmware_py load in C, and
the boot counter C persists loads back in firmware_py.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import tomllib
from pathlib import Path

import pytest
from test_node_vectors import VECTORS

from firmware_py.config import agent_configs_from_scenario, parse_agent_config
from firmware_py.errors import ConfigError
from firmware_py.secoc import (
    KEY_FILE_HEADER,
    KeyFileError,
    derive_command_key,
    derive_frame_key,
    derive_node_key,
    fleet_id,
    load_node_key,
    node_key_document,
    save_floors,
    write_private,
)
from sim.cbind.cagent import (
    CConfigError,
    load_keyfile,
    node_program,
    params_dict,
    params_of,
    parse_config,
)
from sim.model.scenario import load_case

MASTER = bytes(range(16))


def _configs() -> list[tuple[str, str]]:
    out = []
    for n in range(1, 8):
        for cfg in agent_configs_from_scenario(load_case(n)):
            out.append((f"case{n}-agent{cfg.id}", cfg.to_toml()))
    for path in VECTORS:
        out.append((path.stem, json.loads(path.read_text())["config"]))
    return out


CONFIGS = _configs()


@pytest.mark.parametrize("name,text", CONFIGS, ids=[n for n, _ in CONFIGS])
def test_c_loader_computes_firmware_pys_integers(name: str, text: str) -> None:
    cfg = parse_agent_config(tomllib.loads(text), name)
    assert params_dict(parse_config(text, name)) == params_dict(params_of(cfg))


def test_scaled_and_explicit_limits_load_alike() -> None:
    """Every optional key given (a time-scaled agent at Ts = 40 ms with hand limits)."""
    text = """
[agent]
id = 3
lambda0 = -0.25
pinned = false
fleet_size = 7
[controller]
kind = "dwell"
k = 0.25
h = 0.125
ts = 0.04
dwell = 0.1
band = 0.0002
ft_exponent = 0.75
[battery]
alpha = 0.0125
beta = -0.5
m = 0.0
p_min = -327.67
p_max = 12.5
[timeouts]
neighbour_periods = 3.9
price_s = 1.0
status_s = 0.75
[limits]
lambda_min = -3
lambda_max = 4.5
rho_min = -1
rho_max = 2
price_step_max = 0.001
price_persist = 7
lambda_step_max = 0.05
k_min = 0.1
k_max = 1.25
h_min = 0.0
h_max = 0.5
untrusted_after = 9
untrusted_s = 0
[[neighbour]]
id = 7
weight = 0.001
[[neighbour]]
id = 1
weight = 100
"""
    cfg = parse_agent_config(tomllib.loads(text), "x")
    assert params_dict(parse_config(text)) == params_dict(params_of(cfg))


BASE = CONFIGS[0][1]


def _edit(table: str, key: str, value: str) -> str:
    """BASE with ``key = value`` set in ``[table]`` (added if missing)."""
    doc = tomllib.loads(BASE)
    lines = BASE.splitlines()
    out, current, done = [], None, False
    for line in lines:
        s = line.strip()
        if s.startswith("["):
            if current == table and not done:
                out.append(f"{key} = {value}")
                done = True
            current = s.strip("[]")
        if current == table and s.split("=")[0].strip() == key:
            out.append(f"{key} = {value}")
            done = True
            continue
        out.append(line)
    if not done:
        if table not in doc:
            out.append(f"[{table}]")
        out.append(f"{key} = {value}")
    return "\n".join(out) + "\n"


BAD = [
    ("agent", "id", "0"), ("agent", "id", "65"), ("agent", "id", '"2"'),
    ("agent", "pinned", "1"), ("agent", "fleet_size", "0"), ("agent", "lambda0", "101"),
    ("agent", "lambda0", "inf"), ("agent", "lambda0", "nan"), ("agent", "lambda0", "true"),
    ("agent", "lambda0", "11"), ("agent", "colour", "1"),
    ("controller", "kind", '"pid"'), ("controller", "k", "0"), ("controller", "k", "1e5"),
    ("controller", "h", "-1"), ("controller", "ts", "2"), ("controller", "band", "1"),
    ("controller", "ft_exponent", "0.3"), ("controller", "k", "300"),
    ("controller", "dwell", "-1"), ("controller", "dwell", "1e300"), ("controller", "gain", "1"),
    ("battery", "alpha", "0"), ("battery", "m", "-1"), ("battery", "p_min", "200"),
    ("battery", "alpha", "101"), ("battery", "beta", "-101"), ("battery", "m", "101"),
    ("battery", "p_min", "-400"), ("battery", "p_max", "400"), ("battery", "soc", "1"),
    ("timeouts", "price_s", "0"), ("timeouts", "status_s", "61"),
    ("timeouts", "neighbour_periods", "0.5"), ("timeouts", "other", "1"),
    ("limits", "rho_min", "6"), ("limits", "price_persist", "0"),
    ("limits", "price_persist", "1.5"), ("limits", "k_min", "3"), ("limits", "k_max", "17"),
    ("limits", "h_max", "199"), ("limits", "untrusted_after", "1001"),
    ("limits", "untrusted_s", "-1"), ("limits", "lambda_step_max", "0"),
    ("limits", "speed", "1"), ("extra", "x", "1"),
    ("security", "signed_price", "1"), ("security", "signed_price", '"yes"'),
    ("security", "other", "true"),
]


@pytest.mark.parametrize("table,key,value", BAD, ids=[f"{t}.{k}={v}" for t, k, v in BAD])
def test_c_loader_refuses_what_firmware_py_refuses_naming_the_key(table: str, key: str,
                                                                  value: str) -> None:
    text = _edit(table, key, value)
    with pytest.raises(ConfigError) as py:
        parse_agent_config(tomllib.loads(text), "agent.toml")
    with pytest.raises(CConfigError) as c:
        parse_config(text, "agent.toml")
    assert f"[{py.value.key}]" in str(c.value), (str(py.value), str(c.value))
    assert str(c.value).startswith("agent.toml: ")


@pytest.mark.parametrize(("fourth", "key"), [
    ("id = 5\nweight = 1000", "neighbour[4].weight"), ("id = 1\nweight = 1", "neighbour[4].id"),
    ("id = 5\ncolour = 1", "neighbour[4]"), ("weight = 1", "neighbour[4].id"),
])
def test_both_loaders_number_neighbours_from_1(fourth: str, key: str) -> None:
    """BASE's fourth [[neighbour]] table is neighbour[4] in both loaders' messages (it was
    neighbour[3]), as agents and batteries are numbered from 1 wherever a user reads them."""
    text = BASE + "\n[[neighbour]]\n" + fourth + "\n"
    with pytest.raises(ConfigError) as py:
        parse_agent_config(tomllib.loads(text), "agent.toml")
    with pytest.raises(CConfigError) as c:
        parse_config(text, "agent.toml")
    assert py.value.key == key and f"[{key}]" in str(c.value), (str(py.value), str(c.value))


def test_a_dwell_of_2_to_the_32_samples_is_refused_by_both() -> None:
    """CTRL-2: D = ceil(Δ/Ts) is a uint32 in C; Δ = 5e4 s at Ts = 1e-5 s is 5e9 samples
    (the C cast was undefined, firmware_py's D unbounded): both refuse it naming dwell."""
    text = (BASE.replace('kind = "reset"', 'kind = "dwell"').replace("ts = 0.01", "ts = 1e-5")
            .replace("dwell = 0.0", "dwell = 5e4"))
    with pytest.raises(ConfigError, match=r"\[controller\.dwell\] expected Δ/Ts < 2\^32"):
        parse_agent_config(tomllib.loads(text), "agent.toml")
    with pytest.raises(CConfigError, match=r"\[controller\.dwell\] expected Δ/Ts < 2\^32"):
        parse_config(text, "agent.toml")


def test_an_idle_mc_beyond_q24_is_refused_by_both_naming_beta() -> None:
    """CMD-3: β·(1+m) = 100·1.3 = 130 does not fit Q24: neither loader starts with it."""
    text = _edit("battery", "beta", "100.0").replace("m = 0.1\n", "m = 0.3\n")
    with pytest.raises(ConfigError, match=r"\[battery\.beta\] expected an idle marginal"):
        parse_agent_config(tomllib.loads(text), "agent.toml")
    with pytest.raises(CConfigError, match=r"\[battery\.beta\] expected an idle marginal"):
        parse_config(text, "agent.toml")


@pytest.mark.parametrize("text", ["[agent\nid = 1", "[agent]\nid = ", "[agent]\nid = 1\nid = 2",
                                  "[agent]\n= 3", "[agent]\nid 3", '[agent]\nx = "a"b"'])
def test_c_loader_refuses_broken_toml(text: str) -> None:
    with pytest.raises(CConfigError, match=r"^x\.toml: \[file\] expected valid TOML"):
        parse_config(text, "x.toml")


def _key_file(tmp_path: Path, boot: int = 6) -> Path:
    peers = {n: derive_node_key(MASTER, n) for n in ("router", "plant", "agent_1", "agent_3")}
    doc = node_key_document("agent_2", derive_node_key(MASTER, "agent_2"), fleet_id(MASTER),
                            boot, peers)
    import tomli_w

    path = tmp_path / "agent_2.key"
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
    return path


def test_key_file_loads_and_the_persisted_boot_loads_in_firmware_py(tmp_path: Path) -> None:
    path = _key_file(tmp_path)
    k = load_keyfile(path, "agent_2")
    ref = load_node_key(path)
    assert bytes(k.key) == ref.key and k.boot == 6 and k.node == b"agent_2"
    assert {k.peer_label[i].value.decode(): bytes(k.peer_key[i]) for i in range(k.n_peers)} \
        == dict(ref.peers)
    assert k.persist_boot(k.persist_ctx, 7) == 0
    again = load_node_key(path)
    assert again.boot_counter == 7 and again.key == ref.key and dict(again.peers) == \
        dict(ref.peers) and again.fleet_id == ref.fleet_id
    assert os.stat(path).st_mode & 0o777 == 0o600


def test_key_file_boot_floors_load_and_survive_every_boot_rewrite(tmp_path: Path) -> None:
    """AUTH-21: [floors] loads in C as in firmware_py, the C persist keeps it, a floor
    of a peer the file does not list is refused (as firmware_py refuses it)."""
    import tomli_w

    path = _key_file(tmp_path)
    save_floors(path, {"router": 9, "agent_3": 4, "agent_4": 7})  # agent_4: not a peer
    assert dict(load_node_key(path).floors) == {"router": 9, "agent_3": 4}
    k = load_keyfile(path, "agent_2")
    floors = {k.peer_label[i].value.decode(): k.peer_floor[i] for i in range(k.n_peers)}
    assert floors == {"router": 9, "plant": 0, "agent_1": 0, "agent_3": 4}
    assert k.persist_boot(k.persist_ctx, 7) == 0
    again = load_node_key(path)
    assert again.boot_counter == 7 and dict(again.floors) == {"router": 9, "agent_3": 4}
    doc = tomllib.loads(path.read_text())
    doc["floors"]["agent_4"] = 1
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
    with pytest.raises(CConfigError, match=r"\[floors\] expected .* but got 'agent_4'"):
        load_keyfile(path, "agent_2")
    with pytest.raises(KeyFileError, match=r"\[floors\] expected"):
        load_node_key(path)


def test_key_file_frame_keys_load_and_survive_every_boot_rewrite(tmp_path: Path) -> None:
    """AUTH-28, AUTH-29, CFG-8: agent 2's key file as `bess-ded keys` writes it (the
    router's and its neighbours' node keys, its two link frame keys and its Diag's, no
    plant key) loads in C with the setpoint's, the status' and the Diag's keys
    firmware_py reads; the C persist keeps [frame_keys] and the plant's floor; the C
    agent starts with it; a frame key of another agent is refused (by both loaders), a
    missing one too; likewise its command key (AUTH-30)."""
    import tomli_w

    from sim.cbind.cagent import CAgent
    from sim.run.keyset import node_document

    sc = load_case(1)
    path = tmp_path / "agent_2.key"
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(node_document(sc, MASTER, "agent_2", 6)))
    save_floors(path, {"router": 9, "plant": 5})
    ref = load_node_key(path)
    assert "plant" not in ref.peers and sorted(ref.frames) == [
        "AGENT_2_Diag", "AGENT_2_Setpoint", "PLANT_2_Status"]
    assert dict(ref.floors) == {"router": 9, "plant": 5}
    k = load_keyfile(path, "agent_2")
    assert k.has_frame_keys == 1 and k.status_floor == 5
    assert bytes(k.setpoint_key) == derive_frame_key(MASTER, "AGENT_2_Setpoint")
    assert bytes(k.status_key) == derive_frame_key(MASTER, "PLANT_2_Status")
    assert bytes(k.diag_key) == derive_frame_key(MASTER, "AGENT_2_Diag")
    assert bytes(k.command_key) == derive_command_key(MASTER, "agent_2")
    assert k.persist_boot(k.persist_ctx, 7) == 0
    again = load_node_key(path)
    assert again.boot_counter == 7 and again.frames == ref.frames
    assert again.commands == ref.commands == {"agent_2": derive_command_key(MASTER, "agent_2")}
    assert dict(again.floors) == {"router": 9, "plant": 5}
    agent = CAgent(agent_configs_from_scenario(sc)[1], load_keyfile(path, "agent_2"))
    assert agent.boot == 8
    doc = tomllib.loads(path.read_text())
    doc["command_keys"]["agent_1"] = derive_command_key(MASTER, "agent_1").hex()
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
    with pytest.raises(CConfigError, match=r"\[command_keys\] expected the key of agent_2 "
                       r"only, but got 'agent_1'"):
        load_keyfile(path, "agent_2")
    with pytest.raises(KeyFileError, match=r"\[command_keys\] expected the key of agent_2 "
                       r"only, but got agent_1"):   # firmware_py refuses it too
        load_node_key(path)
    del doc["command_keys"]
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
    with pytest.raises(CConfigError, match=r"\[command_keys\] expected the key of agent_2, "
                       r"but got none"):
        load_keyfile(path, "agent_2")
    doc = tomllib.loads(path.read_text())
    doc["command_keys"] = {"agent_2": derive_command_key(MASTER, "agent_2").hex()}
    del doc["frame_keys"]["AGENT_2_Diag"]   # a key file written before AUTH-29
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
    with pytest.raises(CConfigError, match=r"\[frame_keys\] expected the keys of "
                       r"AGENT_2_Setpoint, PLANT_2_Status and AGENT_2_Diag, but one is missing"):
        load_keyfile(path, "agent_2")
    doc["frame_keys"]["PLANT_1_Status"] = derive_frame_key(MASTER, "PLANT_1_Status").hex()
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
    with pytest.raises(CConfigError, match=r"\[frame_keys\] expected the keys of "
                       r"AGENT_2_Setpoint, PLANT_2_Status and AGENT_2_Diag only, but got "
                       r"'PLANT_1_Status'"):
        load_keyfile(path, "agent_2")
    with pytest.raises(KeyFileError, match=r"\[frame_keys\] expected the keys of the frames "
                       r"agent_2 sends or receives only, but got PLANT_1_Status"):
        load_node_key(path)


def test_key_file_lambda_tag_keys_load_and_survive_every_boot_rewrite(tmp_path: Path) -> None:
    """AUTH-34: agent 2's key file of an FD fleet as `bess-ded keys` writes it (no other
    agent's node key; [lambda_tag_keys]: its tags to its neighbours, the plant and the
    router, its neighbours' to it, quoted TOML keys) loads in C with firmware_py's pairs
    and keys; the C persist keeps them (and a neighbour's floor, AUTH-21); the C agent
    starts on FD with it and tags its λ with them; a pair agent 2 is not one of, or a
    malformed pair, is refused by both loaders."""
    import tomli_w

    from sim.cbind.cagent import CAgent, tag_code
    from sim.run.keyset import node_document

    sc = dataclasses.replace(load_case(1), fd=True)
    path = tmp_path / "agent_2.key"
    doc = node_document(sc, MASTER, "agent_2", 6)
    doc["floors"] = {"router": 9, "plant": 5}
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
    ref = load_node_key(path)
    assert set(ref.peers) == {"router"} and ref.tags
    k = load_keyfile(path, "agent_2")
    got = {(k.tag_pair[t][0], k.tag_pair[t][1]): bytes(k.tag_key[t]) for t in range(k.n_tags)}
    assert got == {(tag_code(s), tag_code(r)): key
                   for s, r, key in ((*p.split(">"), key) for p, key in ref.tags.items())}
    assert k.persist_boot(k.persist_ctx, 7) == 0
    again = load_node_key(path)
    assert again.boot_counter == 7 and again.tags == ref.tags and again.peers == ref.peers
    assert dict(again.floors) == {"router": 9, "plant": 5}
    cfg = agent_configs_from_scenario(sc)[1]
    agent = CAgent(cfg, load_keyfile(path, "agent_2"), fd=True)
    mc = next(m for m in agent.tick(0.0) if m.arbitration_id == 0x102)
    assert len(mc.data) == 32 and list(mc.data[8::4]) == [
        *sorted(n.id for n in cfg.neighbours), 0xFE, 0xFF] + [0] * (4 - len(cfg.neighbours))
    # a neighbour's floor (C: the sender of a pair to agent 2) survives the C rewrite
    text = path.read_text().replace("[floors]\n", "[floors]\nagent_1 = 4\n")
    write_private(path, text)
    k = load_keyfile(path, "agent_2")
    assert sorted(k.tag_floor[t] for t in range(k.n_tags))[-1] == 4
    assert k.persist_boot(k.persist_ctx, 9) == 0
    assert "agent_1 = 4" in path.read_text()
    doc = tomllib.loads(path.read_text())
    doc["floors"].pop("agent_1")
    for pair, message in (("agent_1>agent_3", "expected the pairs agent_2 is one of only"),
                          ("plant>agent_2", "expected 'agent_i>RECEIVER'")):
        bad = {**doc, "lambda_tag_keys": {**doc["lambda_tag_keys"], pair: "00" * 16}}
        write_private(path, KEY_FILE_HEADER + tomli_w.dumps(bad))
        with pytest.raises(CConfigError, match=r"\[lambda_tag_keys\] " + message):
            load_keyfile(path, "agent_2")
        with pytest.raises(KeyFileError):
            load_node_key(path)


def test_key_file_refusals(tmp_path: Path) -> None:
    path = _key_file(tmp_path)
    with pytest.raises(CConfigError, match="expected the key file of agent_3"):
        load_keyfile(path, "agent_3")
    os.chmod(path, 0o644)
    with pytest.raises(CConfigError, match="too open"):
        load_keyfile(path, "agent_2")
    with pytest.raises(CConfigError, match="cannot read"):
        load_keyfile(tmp_path / "missing.key", "agent_2")
    os.chmod(path, 0o600)
    link = tmp_path / "link.key"
    link.symlink_to(path)
    with pytest.raises(CConfigError, match="symbolic link"):
        load_keyfile(link, "agent_2")


# --------------------------------------------------------------------------- the node program


def _node(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(node_program()), *argv], capture_output=True, text=True,
                          timeout=60, check=False)


def test_node_program_refuses_bad_input_with_exit_2(tmp_path: Path) -> None:
    cfg = tmp_path / "agent_2.toml"
    cfg.write_text(json.loads(VECTORS[0].read_text())["config"])
    bad = tmp_path / "bad.toml"
    bad.write_text(_edit("agent", "id", "0"))
    key = _key_file(tmp_path)
    agent_1 = tmp_path / "agent_1.toml"
    agent_1.write_text(BASE)
    signed = tmp_path / "signed.toml"
    signed.write_text(cfg.read_text() + "\n[security]\nsigned_price = true\n")
    five = tmp_path / "five.toml"   # AUTH-34: 5 neighbours, one more than FD's tag slots
    five.write_text(cfg.read_text().replace("fleet_size = 4", "fleet_size = 6") + "".join(
        f"\n[[neighbour]]\nid = {j}\nweight = 1.0\n" for j in (4, 5, 6)))
    cases = [
        ((), "expected --config, --channel and exactly one of --key or --insecure"),
        (("--config", str(cfg), "--insecure", "--key", str(key), "--channel", "vcan0"),
         "exactly one of --key or --insecure"),
        (("--config", str(bad), "--insecure", "--channel", "vcan0"), "[agent.id] expected"),
        (("--config", str(tmp_path / "none.toml"), "--insecure", "--channel", "vcan0"),
         "does not exist"),
        (("--config", str(cfg), "--insecure", "--channel", "vcan0", "--interface",
          "virtual"), "--interface: expected socketcan or udp_multicast"),
        (("--config", str(cfg), "--insecure", "--channel", "vcan0", "--interface",
          "udp_multicast"), "--channel: expected a multicast group address"),
        (("--config", str(cfg), "--insecure", "--channel", "10.0.0.1", "--interface",
          "udp_multicast"), "--channel: expected a multicast group address"),
        (("--config", str(cfg), "--insecure", "--interface", "udp_multicast", "--port",
          "70000"), "--port: expected a UDP port 1..65535, but got '70000'"),
        (("--config", str(cfg), "--insecure", "--interface", "udp_multicast", "--port", "x"),
         "--port: expected a UDP port"),
        (("--config", str(cfg), "--insecure", "--channel", "vcan0", "--port", "43200"),
         "--port: expected only with --interface udp_multicast"),
        (("--config", str(cfg), "--insecure", "--channel", "vcan0", "--duration", "-1"),
         "--duration: expected a number of seconds"),
        (("--config", str(cfg), "--insecure", "--channel", "vcan0", "--speed", "2"),
         "but got '--speed'"),
        (("--config", str(agent_1), "--key", str(key), "--channel", "no-such-can9"),
         "expected the key file of agent_1"),
        (("--config", str(cfg), "--insecure", "--channel", "no-such-can9"), "error: "),
        # AUTH-31: a signed_price agent needs the router's public key: never run unsigned
        (("--config", str(signed), "--insecure", "--channel", "vcan0"),
         "[security.signed_price] expected a key file with the router's public price key"),
        # AUTH-34: an FD agent's λ has a tag slot per neighbour beside the plant's and the
        # router's: at most 4 neighbours (without the tags, any number)
        (("--config", str(five), "--insecure", "--channel", "vcan0", "--fd"),
         "[[neighbour]] expected at most 4 neighbours on a CAN FD bus"),
        (("--config", str(cfg), "--insecure", "--channel", "vcan0", "--no-lambda-tags"),
         "--no-lambda-tags: expected it only with --fd"),
    ]
    for argv, message in cases:
        res = _node(*argv)
        assert res.returncode == 2, (argv, res.stderr)
        assert "bessded-agent: error: " in res.stderr and message in res.stderr, \
            (argv, res.stderr)


# --------------------------------------------------------------------------- signed_price


@pytest.mark.parametrize("value", ["true", "false"])
def test_c_loader_takes_signed_price_as_firmware_py_does(value: str) -> None:
    """AUTH-31: [security] signed_price loads in C to firmware_py's flag (no refusal)."""
    text = _edit("security", "signed_price", value)
    cfg = parse_agent_config(tomllib.loads(text), "agent.toml")
    p = parse_config(text, "agent.toml")
    assert p.signed_price == int(value == "true") == int(cfg.signed_price)
    assert params_dict(p) == params_dict(params_of(cfg))


def test_key_file_price_key_loads_and_survives_every_boot_rewrite(tmp_path: Path) -> None:
    """AUTH-31, CFG-8: a signed_price fleet's agent key file (`bess-ded keys`: the
    router's public price key in [price_signature] verify_key) loads in C with the key and
    the fleet ID firmware_py reads; the C persist keeps the table; the C agent starts with
    it; a malformed table is refused by both loaders; a router's sign_key loads as its
    public key."""
    import tomli_w

    from firmware_py import pricesig
    from firmware_py.secoc import derive_price_sign_key
    from sim.cbind.cagent import CAgent
    from sim.run.keyset import node_document

    sc = dataclasses.replace(load_case(1), signed_price=True)
    path = tmp_path / "agent_2.key"
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(node_document(sc, MASTER, "agent_2", 6)))
    ref = load_node_key(path)
    public = pricesig.public_key(derive_price_sign_key(MASTER))
    assert ref.price_verify == public and ref.price_sign is None
    k = load_keyfile(path, "agent_2")
    assert k.has_price_key == 1 and bytes(k.price_key) == public
    assert bytes(k.fleet_id) == bytes.fromhex(ref.fleet_id)
    assert k.persist_boot(k.persist_ctx, 7) == 0
    again = load_node_key(path)
    assert again.boot_counter == 7 and again.price_verify == public
    cfg = agent_configs_from_scenario(sc)[1]
    assert cfg.signed_price
    agent = CAgent(cfg, load_keyfile(path, "agent_2"))
    assert agent.boot == 8 and agent.sig_verifications == 0
    assert load_node_key(path).price_verify == public   # kept by the C agent's new boot
    doc = tomllib.loads(path.read_text())
    for bad, message in (({"verify_key": public.hex(), "sign_key": public.hex()},
                          r"\[price_signature\] expected exactly one of sign_key, verify_key"),
                         ({}, r"\[price_signature\] expected exactly one of"),
                         ({"public": public.hex()}, r"\[price_signature\] expected exactly one"),
                         ({"verify_key": public.hex()[:-2]},
                          r"\[price_signature.verify_key\] expected 32 bytes as hex"),
                         ({"verify_key": "zz" * 32},
                          r"\[price_signature.verify_key\] expected 32 bytes as hex")):
        doc["price_signature"] = bad
        write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
        with pytest.raises(CConfigError, match=message):
            load_keyfile(path, "agent_2")
        with pytest.raises(KeyFileError, match=message):
            load_node_key(path)
    seed = derive_price_sign_key(MASTER)
    doc["price_signature"] = {"sign_key": seed.hex()}
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
    k = load_keyfile(path, "agent_2")
    assert k.has_price_key == 1 and bytes(k.price_key) == public
    assert k.persist_boot(k.persist_ctx, 9) == 0
    assert load_node_key(path).price_sign == seed
    del doc["price_signature"]
    write_private(path, KEY_FILE_HEADER + tomli_w.dumps(doc))
    with pytest.raises(ValueError, match="signed_price without the router's public price key"):
        CAgent(cfg, load_keyfile(path, "agent_2"))


def test_a_build_without_the_signed_price_refuses_it(tmp_path: Path) -> None:
    """`make SIGNED_PRICE=0` (what the Cortex-M4 image is: no libsodium): the node links
    no libsodium, and refuses [security] signed_price = true naming the key (exit 2),
    never running unsigned; signed_price = false still starts as before."""
    from sim.cbind.cimpl import SOURCE_DIR, make_argv

    build = tmp_path / "build"
    proc = subprocess.run(make_argv(SOURCE_DIR, build, str(build / "bessded-agent"))
                          + ["SIGNED_PRICE=0"], capture_output=True, text=True, timeout=300,
                          check=False)
    assert proc.returncode == 0, proc.stderr
    assert "-DBD_SIGNED_PRICE=0" in proc.stdout and "-lsodium" not in proc.stdout
    cfg = tmp_path / "agent_2.toml"
    base = json.loads(VECTORS[0].read_text())["config"]
    for value, rc, message in (("true", 2, "[security.signed_price] expected false: this "
                                           "firmware_c build has no signed price"),
                               ("false", 2, "runs --insecure")):   # past the loader
        cfg.write_text(base + f"\n[security]\nsigned_price = {value}\n")
        res = subprocess.run([str(build / "bessded-agent"), "--config", str(cfg), "--insecure",
                              "--channel", "no-such-can9"], capture_output=True, text=True,
                             timeout=60, check=False)
        assert res.returncode == rc and message in res.stderr, (value, res.stderr)
