"""Golden vectors of one agent node (tests/vectors/node, tools/gen_node_vectors.py).

Each vector is replayed through ``firmware_py.runtime.AgentRuntime`` as a port would
replay it (tests/vectors/README.md, "Node-level vectors"): the agent is built from the
vector's configuration and keys alone, every received frame is handed to ``on_frame`` at
its time, every tick to ``tick``, and each frame the agent sends must equal the vector's,
byte for byte and in order. Further tests: the committed files are what the generator
writes; together they cover every requirement of the spec's sections 7, 8, 11 and 12;
and each mutated agent fails exactly the vectors listed for it (the vectors can fail).
"""

from __future__ import annotations

import contextlib
import copy
import json
import re
import runpy
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import pytest

from firmware_py import controllers, nodeio, pricesig
from firmware_py.config import parse_agent_config
from firmware_py.frames import FrameCodec, target_agent
from firmware_py.runtime import AgentRuntime
from firmware_py.secoc import (
    INSECURE_MASTER,
    Keyring,
    derive_command_key,
    derive_frame_key,
    derive_node_key,
    derive_price_sign_key,
)

ROOT = Path(__file__).resolve().parent.parent
VECTOR_DIR = ROOT / "tests" / "vectors" / "node"
SPEC = ROOT / "docs" / "firmware-spec.md"
GEN_VECTORS = ROOT / "tools" / "gen_vectors.py"
GEN_NODE_VECTORS = ROOT / "tools" / "gen_node_vectors.py"
FORMAT = "bess-ded node vector 1"
SIZE_LIMIT = 1_500_000  # bytes, the whole set
CODEC = FrameCodec()

VECTORS = sorted(VECTOR_DIR.glob("*.json"))


class NodeVectorMismatch(AssertionError):
    pass


def load(path: Path) -> dict[str, Any]:
    vec: dict[str, Any] = json.loads(path.read_text(encoding="ascii"))
    if vec.get("format") != FORMAT:
        raise ValueError(f"{path.name}: format {vec.get('format')!r}, expected {FORMAT!r}")
    return vec


def keyring(vec: dict[str, Any]) -> Keyring | None:
    """The agent's keys, derived from the vector's master key (and checked against the
    keys the vector lists, so that a port can take either)."""
    k = vec["keys"]
    master = bytes.fromhex(k["master_key"])
    if k["insecure"]:
        assert master == INSECURE_MASTER
        return None
    key = derive_node_key(master, k["node"])
    assert key.hex() == k["key"], f"{vec['name']}: the listed key is not the derived one"
    peers = {}
    for label, hexkey in k["peers"].items():
        peers[label] = derive_node_key(master, label)
        assert peers[label].hex() == hexkey, f"{vec['name']}: peer {label}'s key"
    frames = {}
    for name, hexkey in k["frame_keys"].items():  # AUTH-28: the link frames' own keys
        frames[name] = derive_frame_key(master, name)
        assert frames[name].hex() == hexkey, f"{vec['name']}: {name}'s key"
    commands = {}
    for target, hexkey in k["command_keys"].items():  # AUTH-30: its commands' key
        commands[target] = derive_command_key(master, target)
        assert commands[target].hex() == hexkey, f"{vec['name']}: {target}'s command key"
    price = None
    if "price_verify_key" in k:  # signed_price (AUTH-31): the router's public price key
        price = pricesig.public_key(derive_price_sign_key(master))
        assert price.hex() == k["price_verify_key"], f"{vec['name']}: the price key"
    return Keyring(k["node"], key, k["boot_counter"], lambda _b: None, peers=peers,
                   floors=k.get("floors"), frames=frames, commands=commands,
                   fleet=k["fleet_id"], price_verify=price)


def agent_of(vec: dict[str, Any]) -> AgentRuntime:
    cfg = parse_agent_config(tomllib.loads(vec["config"]), f"{vec['name']}.json")
    agent = AgentRuntime(cfg, CODEC, keys=keyring(vec))
    tx_count = vec.get("setup", {}).get("tx_count")
    if tx_count is not None:  # the test hook: own message counts start here
        agent.io.start_tx_counts(tx_count)
    return agent


def message(row: list[Any]) -> can.Message:
    _, _t, fid, data, *extra = row
    flags = extra[0].get("flags", "") if extra else ""
    payload = bytes.fromhex(data)
    return can.Message(arbitration_id=fid, data=payload, dlc=len(payload),
                       is_extended_id="ext" in flags, is_remote_frame="rtr" in flags,
                       is_fd="fd" in flags, check=False)


def describe(fid: int, data: str) -> str:
    msg = can.Message(arbitration_id=fid, data=bytes.fromhex(data), is_extended_id=False)
    try:
        f = CODEC.decode(msg)
    except Exception as e:  # noqa: BLE001 - a description, whatever the frame
        return f"(does not decode: {e})"
    return f"{f.name} {f.raw}"


def replay(vec: dict[str, Any], make: Callable[[dict[str, Any]], Any] = agent_of) -> int:
    """Run the vector on the agent ``make(vec)`` builds (firmware_py's by default; any
    object with ``on_frame`` and ``tick``); raise NodeVectorMismatch at the first
    difference. The number of frames compared."""
    name = vec["name"]
    agent = make(vec)
    expected = vec["output"]
    i = 0
    for row in vec["input"]:
        t = row[1]
        if row[0] == "tick":
            for frame in agent.tick(t):
                got = [t, frame.arbitration_id, bytes(frame.data).hex()]
                if (frame.is_extended_id or frame.is_remote_frame or frame.is_fd
                        or frame.dlc != 8):
                    raise NodeVectorMismatch(f"{name}: t = {t}: a non-classic frame {frame}")
                if i >= len(expected):
                    raise NodeVectorMismatch(
                        f"{name}: t = {t}: an extra frame 0x{got[1]:03X} {got[2]} "
                        f"({describe(got[1], got[2])}) after the {len(expected)} expected")
                if got != expected[i]:
                    et, eid, edata = expected[i]
                    raise NodeVectorMismatch(
                        f"{name}: frame #{i}: expected t = {et} 0x{eid:03X} {edata} "
                        f"({describe(eid, edata)}), got t = {t} 0x{got[1]:03X} {got[2]} "
                        f"({describe(got[1], got[2])})")
                i += 1
        elif row[0] == "rx":
            agent.on_frame(message(row), t)
        else:
            raise ValueError(f"{name}: unknown event {row[0]!r}")
    if i != len(expected):
        et, eid, edata = expected[i]
        raise NodeVectorMismatch(f"{name}: frame #{i} missing: expected t = {et} 0x{eid:03X} "
                                 f"{edata} ({describe(eid, edata)})")
    # signed_price (AUTH-32, AUTH-33): its counters have no Diag slot; the vector states them
    got = {k: agent.counters.get(k, 0) for k in vec.get("counters", {})}
    if got != vec.get("counters", {}):
        raise NodeVectorMismatch(f"{name}: counters at the end: expected {vec['counters']}, "
                                 f"got {got}")
    return i


@pytest.fixture(scope="module")
def vectors() -> dict[str, dict[str, Any]]:
    return {p.stem: load(p) for p in VECTORS}


def test_the_set_is_the_generators_and_is_compact() -> None:
    """One file per scenario of tools/gen_node_vectors.py (their names are checked with
    the contents by test_committed_node_vectors_are_what_the_generator_writes), and the
    whole set stays under SIZE_LIMIT."""
    scenarios = runpy.run_path(str(GEN_NODE_VECTORS))["SCENARIOS"]
    assert len(VECTORS) == len(scenarios)
    assert sum(p.stat().st_size for p in VECTORS) < SIZE_LIMIT


@pytest.mark.parametrize("path", VECTORS, ids=[p.stem for p in VECTORS])
def test_vector_replays_byte_exact(path: Path) -> None:
    vec = load(path)
    assert vec["name"] == path.stem
    assert replay(vec) == len(vec["output"]) > 0


def test_a_changed_byte_is_reported_with_time_id_and_signals(
        vectors: dict[str, dict[str, Any]]) -> None:
    vec = copy.deepcopy(vectors["start_steady"])
    row = vec["output"][7]
    row[2] = f"{int(row[2][:2], 16) ^ 1:02x}" + row[2][2:]
    with pytest.raises(NodeVectorMismatch, match=r"^start_steady: frame #7: expected t = .* "
                       r"0x\w{3} \w{16} \(AGENT_2_\w+ \{.*\}\), got t = "):
        replay(vec)


# --------------------------------------------------------------------------- coverage


def spec_requirements(sections: tuple[int, ...]) -> set[str]:
    """The requirement IDs (``- **STATE-3**``) defined in the spec's numbered sections."""
    text = SPEC.read_text(encoding="utf-8")
    parts = re.split(r"^## (\d+)\. ", text, flags=re.M)
    found: set[str] = set()
    for number, body in zip(parts[1::2], parts[2::2], strict=True):
        if int(number) in sections:
            found |= set(re.findall(r"^- \*\*([A-Z]+-\d+)\*\*", body, flags=re.M))
    return found


# The node vectors are classic CAN frames; what only a CAN FD bus has is compared C against
# Python elsewhere, bit for bit
NOT_IN_NODE_VECTORS = {
    "AUTH-34": "λ tags exist on CAN FD only: tests/test_c_agent.py "
               "test_c_and_python_agents_agree_on_an_fd_bus replays random FD traffic, "
               "tagged λ included, into both and compares every frame",
}


def test_vectors_cover_every_state_transition_command_and_auth_requirement(
        vectors: dict[str, dict[str, Any]]) -> None:
    required = spec_requirements((7, 8, 11, 12)) - set(NOT_IN_NODE_VECTORS)
    assert len(required) >= 40  # STATE-*, LIVE-*, TMO-*, PRICE-*, LAM-*, CMD-*, AUTH-*
    covered = set().union(*(v["covers"] for v in vectors.values()))
    assert not required - covered, f"no node vector covers {sorted(required - covered)}"


def test_covered_ids_exist_in_the_spec(vectors: dict[str, dict[str, Any]]) -> None:
    every = spec_requirements(tuple(range(0, 20)))
    for name, vec in vectors.items():
        unknown = set(vec["covers"]) - every
        assert not unknown, f"{name} names requirements the spec does not define: {unknown}"


def test_every_state_and_command_appears_in_the_frames(
        vectors: dict[str, dict[str, Any]]) -> None:
    """What the covers lists claim, read from the frames: every state on the MC frames,
    every transition between them, every command received."""
    states, transitions, commands = set(), set(), set()
    for vec in vectors.values():
        mc = 0x100 + int(re.search(r"id = (\d+)", vec["config"]).group(1))  # type: ignore
        prev = None
        for _, fid, data in vec["output"]:
            if fid == mc:
                s = CODEC.decode(can.Message(arbitration_id=fid, data=bytes.fromhex(data),
                                             is_extended_id=False)).raw["State"]
                states.add(s)
                if prev is not None and prev != s:
                    transitions.add((prev, s))
                prev = s
        for row in vec["input"]:
            if row[0] == "rx" and row[2] == 0x020:
                with contextlib.suppress(Exception):
                    f = CODEC.decode(message(row))
                    commands.add((f.raw["Command"], target_agent(f.raw["Target"]) == 2))
    assert states == {0, 1, 2, 3}
    # INIT→RUNNING, RUNNING→SAFE, SAFE→RUNNING, RUNNING→ISOLATED, ISOLATED→RUNNING (via the
    # INIT of a RECONNECT, invisible on the MC frames: STATE-8)
    assert {(0, 1), (1, 3), (3, 1), (1, 2), (2, 1)} <= transitions
    assert {(c, mine) for c in (1, 2, 3) for mine in (True, False)} <= commands


# --------------------------------------------------------------------------- the vectors can fail


def _ignore_pin(orig: Callable[..., Any]) -> Callable[..., Any]:
    def on_command(self: Any, f: Any, fid: int) -> None:
        pin = self.pin
        orig(self, f, fid)
        self.pin = pin
    return on_command


def _rearm_at_reset(orig: Callable[..., Any]) -> Callable[..., Any]:
    def step(self: Any, s: Any, xi: Any) -> Any:
        new, out = orig(self, s, xi)
        if out.reset:  # BAND-2 broken: the reset sample re-arms
            new = replace(new, armed=True)
        return new, out
    return step


def _no_diag_mac(orig: Callable[..., Any]) -> Callable[..., Any]:
    def diag(self: Any, page: int) -> can.Message:
        msg = orig(self, page)
        msg.data[0:3] = bytes(3)  # TX-5 broken: the Diag page not signed
        return msg
    return diag


def _no_plausibility(orig: Callable[..., Any]) -> Callable[..., Any]:
    def on_mc(self: Any, slot: Any, f: Any, t: float) -> None:
        slot.alive = False  # LAM-1 broken: never checked
        orig(self, slot, f, t)
        slot.alive = True
    return on_mc


def _restart_at_entry(orig: Callable[..., Any]) -> Callable[..., Any]:
    def update_state(self: Any) -> None:
        before = self.state
        orig(self)
        if self.state != before:  # DWELL-2 broken: a state entry restarts dwell and band
            self.cstate = replace(self.cstate, armed=True, since_reset=0)
    return update_state


def _trim_smaller_weight_first(lam: Any, neighbours: Any, f: int) -> list[Any]:
    """WMSR-2 broken: of equal λ_j, the smaller weight dropped first."""
    if f <= 0:
        return list(neighbours)
    above = sorted((t for t in neighbours if t[1] > lam), key=lambda t: (-t[1], t[0]))
    below = sorted((t for t in neighbours if t[1] < lam), key=lambda t: (t[1], t[0]))
    return above[f:] + below[f:] + [t for t in neighbours if t[1] == lam]


def _command_never_lost(orig: Callable[..., Any]) -> Callable[..., Any]:
    def update_inputs(self: Any) -> None:
        lost = self.io.sender_lost

        def only_the_price(fid: int) -> None:
            if fid != self.command_id:  # AUTH-13 broken: ER_Command kept at a price timeout
                lost(fid)
        self.io.sender_lost = only_the_price
        try:
            orig(self)
        finally:
            del self.io.sender_lost
    return update_inputs


@contextlib.contextmanager
def mutated(kind: str, mp: pytest.MonkeyPatch) -> Iterator[None]:
    if kind == "band_rearms_at_reset":
        mp.setattr(controllers.PIController, "step",
                   _rearm_at_reset(controllers.PIController.step))
    elif kind == "diag_without_mac":
        mp.setattr(AgentRuntime, "_diag_frame", _no_diag_mac(AgentRuntime._diag_frame))
    elif kind == "one_freshness_window_after_a_timeout":
        mp.setattr(nodeio, "LOST_WINDOWS", 1)
    elif kind == "no_boot_bound":  # AUTH-27's bound lifted
        mp.setattr(nodeio, "beyond_boot_bound", lambda *_a: False)
    elif kind == "no_boot_undo":  # AUTH-27's undo left out
        mp.setattr(nodeio.NodeIO, "_revert", lambda *_a: False)
    elif kind == "no_pending_advance":    # AUTH-35 left out: an advance taken at once
        mp.setattr(nodeio.NodeIO, "_holds_advance", lambda *_a: False)
    elif kind == "pending_never_dropped":  # AUTH-35's drop left out
        mp.setattr(nodeio.NodeIO, "_drop_pending", lambda *_a: None)
    elif kind == "no_count_bound":        # AUTH-27's count bound lifted
        mp.setattr(nodeio.NodeIO, "_count_jump", lambda *_a: False)
    elif kind == "command_kept_at_price_timeout":   # ER_Command not lost with the price
        mp.setattr(AgentRuntime, "_update_inputs",
                   _command_never_lost(AgentRuntime._update_inputs))
    elif kind == "no_lambda_plausibility":
        mp.setattr(AgentRuntime, "_on_mc", _no_plausibility(AgentRuntime._on_mc))
    elif kind == "no_dwell":
        mp.setattr(controllers.DwellResetPIController, "_reset_now",
                   controllers.ResetPIController._reset_now)
    elif kind == "mc_every_tick":  # TX-7 ignored: the MC frame every tick in event mode
        mp.setattr(AgentRuntime, "_mc_due", lambda self: True)
    elif kind == "state_entry_restarts_dwell_and_band":
        mp.setattr(AgentRuntime, "_update_state", _restart_at_entry(AgentRuntime._update_state))
    elif kind == "resilient_f_ignored":   # WMSR-1 broken: no trimming
        mp.setattr(controllers, "resilient_trim", lambda lam, nb, f: list(nb))
    elif kind == "trim_ties_by_smaller_weight":
        mp.setattr(controllers, "resilient_trim", _trim_smaller_weight_first)
    elif kind == "unsigned_price_taken":  # AUTH-33 broken: any ER_Price with a valid MAC
        mp.setattr(AgentRuntime, "_signed_price", lambda self, f: None)
    elif kind == "unsigned_boot_taken":   # AUTH-33 broken: a held price advance taken
        mp.setattr(AgentRuntime, "_signed_boot", lambda self, boot: True)  # unsigned
    elif kind == "pin_ignored":           # CMD-7 broken: a PIN counted, nothing else
        mp.setattr(AgentRuntime, "_on_command", _ignore_pin(AgentRuntime._on_command))
    else:
        raise ValueError(kind)
    yield


# every mutation and the vectors that notice it (the replay is deterministic: a vector
# that stops noticing one, or starts to, is a change to look at)
MUTATIONS: dict[str, list[str]] = {
    # the reset-PI vectors but price_steps and tx_count_wrap (insecure_scaled runs the
    # dwell controller)
    "band_rearms_at_reset": [
        "auth_forgery_replay", "boot_floors", "commands", "event_transmit", "init_wait_status",
        "malformed_foreign", "neighbour_timeout", "peer_restart", "pin", "price_timeout_safe",
        "resilient_trim", "signed_price", "start_steady", "status_fault_timeout",
        "sync_boot_jump", "sync_count_jump"],
    # every vector: each sends Diag pages
    "diag_without_mac": [p.stem for p in VECTORS],
    "one_freshness_window_after_a_timeout": ["price_timeout_safe"],
    "no_boot_bound": ["sync_boot_jump"],
    "no_boot_undo": ["sync_boot_jump"],
    "no_pending_advance": ["boot_floors", "peer_restart", "signed_price", "sync_boot_jump"],
    "pending_never_dropped": ["sync_boot_jump"],
    "no_count_bound": ["sync_count_jump"],
    "command_kept_at_price_timeout": ["sync_count_jump"],
    "no_lambda_plausibility": ["neighbour_timeout"],
    "no_dwell": ["insecure_scaled"],
    "state_entry_restarts_dwell_and_band": ["insecure_scaled"],
    "resilient_f_ignored": ["resilient_trim"],
    "trim_ties_by_smaller_weight": ["resilient_trim"],
    "mc_every_tick": ["event_transmit"],
    "pin_ignored": ["pin"],
    "unsigned_price_taken": ["signed_price"],
    "unsigned_boot_taken": ["signed_price"],
}


@pytest.mark.parametrize("kind", MUTATIONS)
def test_a_mutated_agent_fails_exactly_its_vectors(kind: str,
                                                   vectors: dict[str, dict[str, Any]],
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    failed = []
    with mutated(kind, monkeypatch):
        for name, vec in vectors.items():
            try:
                replay(vec)
            except NodeVectorMismatch:
                failed.append(name)
    assert sorted(failed) == MUTATIONS[kind], f"the vectors that notice the mutation {kind}"


# --------------------------------------------------------------------------- generator


@pytest.fixture(scope="module")
def gen_node() -> dict[str, Any]:
    return runpy.run_path(str(GEN_NODE_VECTORS))  # not __main__: nothing is written


def test_committed_node_vectors_are_what_the_generator_writes(gen_node: dict[str, Any]) -> None:
    files = gen_node["render_all"]()
    assert gen_node["write_or_check"](files, VECTOR_DIR, True) == 0, \
        "tests/vectors/node is stale: run python tools/gen_vectors.py"
    assert files == gen_node["render_all"](), "the generator is not deterministic"


def test_gen_vectors_check_names_a_stale_node_vector(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    main = runpy.run_path(str(GEN_VECTORS))["main"]
    out = tmp_path / "node"
    ctrl = tmp_path / "controller"
    assert main(["-o", str(ctrl), "--node-output", str(out)]) == 0
    assert sorted(p.name for p in out.glob("*.json")) == [p.name for p in VECTORS]
    path = out / "commands.json"
    text = path.read_text()
    path.write_text(text.replace('"output":[\n[0.0,1282,"', '"output":[\n[0.0,1282,"0', 1))
    capsys.readouterr()
    assert main(["--check", "-o", str(ctrl), "--node-output", str(out)]) == 1
    assert capsys.readouterr().err == (f"{out / 'commands.json'} is stale or missing\n"
                                       "run python tools/gen_vectors.py\n")
