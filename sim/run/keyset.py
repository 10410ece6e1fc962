"""SecOC key sets of a fleet: provisioning, loading, checking (docs/security.md).

A key set is a directory (0700) with one key file per node of a scenario's fleet
(agent_1..agent_N, plant, router: ``<node>.key``, 0600), each holding that node's key,
derived from a fleet master key with NIST SP 800-108 (CMAC-AES-128), the keys of the
peers it receives from, and its freshness state; and usually the master key
(``master.key``). ``provision_fleet_keys`` is what ``bess-ded keys --fleet`` runs (docs/api.md).
"""

from __future__ import annotations

import os
import secrets
import shutil
import stat
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from firmware_py.errors import BessDedError, ParameterError


def key_files(directory: Path) -> list[Path]:
    """The ``*.key`` files in ``directory`` (the master key's too), sorted."""
    return sorted(p for p in directory.iterdir() if p.suffix == ".key" and p.is_file())


def prepare_key_dir(out: Path, force: bool) -> None:
    """Create ``out`` owner-only (0700), or check that an existing one is owner-only and,
    unless ``force``, holds no key set yet (a BessDedError naming --out otherwise)."""
    if out.exists() and not out.is_dir():
        raise BessDedError(f"--out: expected a directory, but {out} is a file")
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        os.mkdir(out, 0o700)
        os.chmod(out, 0o700)  # the umask may have removed bits; make it exact
        return
    mode = stat.S_IMODE(os.stat(out).st_mode)
    if mode & 0o077:
        raise BessDedError(f"--out: {out} is accessible by group or others (mode {mode:04o}): "
                           "give a new directory, or chmod 700 it first")
    existing = key_files(out)
    if existing and not force:
        raise BessDedError(f"--out: {out} already holds a key set ({len(existing)} .key "
                           "files, e.g. " + existing[0].name + "): not overwriting it "
                           "without --force")


def peers_of(sc: Any) -> dict[str, list[str]]:
    """Need to know: the senders whose broadcast frames each node receives, i.e. whose
    node keys its key file holds (agent i: the router and its neighbours; the plant:
    every agent and the router; the router: every agent). The router and the plant use
    the keys of the nodes whose frames they do not take only to notice a restart from
    its sync and re-announce their own at once. No node holds the plant's node key: the
    plant sends link frames only (``frames_of``, AUTH-28)."""
    from firmware_py import secoc
    from firmware_py.config import agent_configs_from_scenario

    fd = tagged_lambda(sc)  # AUTH-34: on CAN FD, λ is tagged per receiver
    out = {f"agent_{c.id}": ["router", *([] if fd else (f"agent_{n.id}" for n in c.neighbours))]
           for c in agent_configs_from_scenario(sc)}
    agents = [] if fd else [n for n in secoc.fleet_nodes(sc.n) if n.startswith("agent_")]
    out["plant"] = [*agents, "router"]
    out["router"] = list(agents)
    return out


def tagged_lambda(sc: Any) -> bool:
    """λ tagged per receiver in ``sc``'s fleet: CAN FD unless ``lambda_tags = false``."""
    return bool(getattr(sc, "fd", False) and getattr(sc, "lambda_tags", True))


def tags_of(sc: Any) -> dict[str, list[str]]:
    """AUTH-34, a CAN FD fleet only: the λ tag keys each node's key file holds, the pairs
    it is one of (agent i: its own to each receiver of its λ, each neighbour's to it; the
    plant and the router: every agent's to them). A classic fleet's: none."""
    from firmware_py import contract, secoc
    from firmware_py.config import agent_configs_from_scenario

    out: dict[str, list[str]] = {node: [] for node in secoc.fleet_nodes(sc.n)}
    if not tagged_lambda(sc):
        return out
    for c in agent_configs_from_scenario(sc):
        me = f"agent_{c.id}"
        for r in contract.lambda_receivers([n.id for n in c.neighbours]):
            out[me].append(secoc.pair_label(me, r))
            out.setdefault(r, []).append(secoc.pair_label(me, r))
    return out


def frames_of(sc: Any) -> dict[str, list[str]]:
    """AUTH-28, AUTH-29: the link frames and reports whose keys each node's key file
    holds, those it sends or receives (agent i: AGENT_<i>_Setpoint, PLANT_<i>_Status and
    AGENT_<i>_Diag; the plant: every agent's setpoint and status, and PLANT_Totals; the
    router: every AGENT_<i>_Diag, PLANT_Totals and ER_Balance)."""
    from firmware_py import contract, secoc

    return {node: [f for f in contract.keyed_frames(sc.n) if node in contract.parties_of(f)]
            for node in secoc.fleet_nodes(sc.n)}


def commands_of(sc: Any) -> dict[str, list[str]]:
    """AUTH-30: the targets whose ER_Command keys each node's key file holds (agent i: its
    own; the router: every agent's; the plant: none)."""
    from firmware_py import secoc

    agents = [n for n in secoc.fleet_nodes(sc.n) if n.startswith("agent_")]
    return {node: agents if node == "router" else [node] if node in agents else []
            for node in secoc.fleet_nodes(sc.n)}


def node_document(sc: Any, master: bytes, node: str, boot: int = 0,
                  floors: Mapping[str, int] | None = None) -> dict:
    """``node``'s key file (a TOML document) from the fleet master key: its own key, the
    node keys of its peers (``peers_of``), its link frame and report keys (``frames_of``)
    and its command keys (``commands_of``)."""
    from firmware_py import pricesig, secoc

    sign = verify = None
    if getattr(sc, "signed_price", False):  # AUTH-31: only the router can sign a price
        seed = secoc.derive_price_sign_key(master)
        if node == "router":
            sign = seed
        else:
            verify = pricesig.public_key(seed)
    return secoc.node_key_document(
        node, secoc.derive_node_key(master, node), secoc.fleet_id(master), boot,
        {p: secoc.derive_node_key(master, p) for p in peers_of(sc)[node]}, floors,
        {f: secoc.derive_frame_key(master, f) for f in frames_of(sc)[node]},
        {t: secoc.derive_command_key(master, t) for t in commands_of(sc)[node]},
        price_sign=sign, price_verify=verify,
        tags={t: secoc.derive_lambda_tag_key(master, *t.split(">"))
              for t in tags_of(sc)[node]})


def write_key_set(sc: Any, out: Path, master: bytes, with_master: bool = True) -> None:
    """Write DIR/<node>.key for every node of ``sc`` (and DIR/master.key), 0600."""
    import tomli_w

    from firmware_py import secoc

    if with_master:
        secoc.write_private(out / "master.key", secoc.MASTER_FILE_HEADER
                            + tomli_w.dumps(secoc.master_key_document(master)))
    for node in peers_of(sc):
        doc = node_document(sc, master, node)
        secoc.write_private(out / f"{node}.key", secoc.KEY_FILE_HEADER + tomli_w.dumps(doc))


def derived_keys(master: bytes, n: int) -> dict[str, bytes]:
    """Every key a fleet of ``n`` agents derives from ``master``: each node's (label ->
    key) and each link frame's (message name -> key, AUTH-28), as ``load_key_set`` gives
    them from files: a monitor's keys for a run without a key set (--insecure)."""
    from firmware_py import contract, secoc

    out = {node: secoc.derive_node_key(master, node) for node in secoc.fleet_nodes(n)}
    out.update({f: secoc.derive_frame_key(master, f) for f in contract.keyed_frames(n)})
    out.update({contract.command_key_name(i): secoc.derive_command_key(master, f"agent_{i}")
                for i in contract.agent_ids(n)})
    agents = [f"agent_{i}" for i in contract.agent_ids(n)]  # AUTH-34: every λ tag pair
    out.update({secoc.pair_label(a, r): secoc.derive_lambda_tag_key(master, a, r)
                for a in agents for r in (*agents, "plant", "router") if r != a})
    return out


def load_key_set(keys_dir: Path) -> dict[str, bytes]:
    """Every node's own key from a key set (label -> key), and every link frame key its
    files list (message name -> key, AUTH-28): what a monitor of the run (the
    recorder's analysis) needs to tell forged frames from the fleet's."""
    from firmware_py import secoc

    files = [secoc.load_node_key(p) for p in key_files(keys_dir) if p.name != "master.key"]
    from firmware_py import contract

    out: dict[str, bytes] = {}
    for k in files:
        for name, key in k.frames.items():
            out.setdefault(name, key)
        for target, key in k.commands.items():  # AUTH-30
            out.setdefault(contract.command_key_name(int(target.removeprefix("agent_"))), key)
        for pair, key in k.tags.items():  # AUTH-34
            out.setdefault(pair, key)
    out.update({k.node: k.key for k in files})
    from firmware_py import pricesig  # signed_price: the recorder checks the price too

    for k in files:
        out.update(pricesig.monitor_entries(k.price_verify, k.fleet_id))
    return out


def load_boot_floors(keys_dir: Path) -> dict[str, int]:
    """Every node's lowest boot counter at its next start (label -> the key file's
    counter + 1: a start uses a new one, AUTH-3). Read before a run, it tells the
    run's monitor that a sync of a lower boot is from an earlier start: a replay."""
    from firmware_py import secoc

    return {k.node: k.boot_counter + 1
            for k in (secoc.load_node_key(p) for p in key_files(keys_dir)
                      if p.name != "master.key")}


def write_boot_floors(keys_dir: Path, nodes: Iterable[str], floors: Mapping[str, int]) -> None:
    """Before a fleet starts: raise the boot floors (AUTH-21) in the key files of
    ``nodes`` to ``floors`` (label -> that node's boot at this start, from
    ``load_boot_floors``), so that no node takes a sync of an earlier run or boot, not
    even before a peer's first genuine sync, nor after its own restart."""
    from firmware_py import secoc

    for node in nodes:
        secoc.save_floors(keys_dir / f"{node}.key", floors)


@dataclass
class ProvisionedKeys:
    """What ``provision_fleet_keys`` wrote."""

    directory: Path
    nodes: list[str]          # the fleet's node labels, one <node>.key each
    fleet_id: str
    removed: list[Path]       # a previous set's key files of nodes this fleet has not
    master_written: bool      # DIR/master.key written (no master key given)


def provision_fleet_keys(sc: Any, out: Path, master_key: Path | None = None,
                         force: bool = False) -> ProvisionedKeys:
    """Provision a key set for the fleet of scenario ``sc`` in ``out`` (created 0700):
    from the master key file ``master_key`` (not copied), else from a new random master
    key written to ``out/master.key``. An existing key set is replaced only with
    ``force``; a previous set's files of nodes this fleet lacks are removed."""
    from firmware_py import secoc

    master = (secoc.load_master_key(master_key) if master_key is not None
              else secrets.token_bytes(secoc.KEY_BYTES))
    prepare_key_dir(out, force)
    nodes = secoc.fleet_nodes(sc.n)
    keep = {f"{n}.key" for n in nodes} | {"master.key"}
    if master_key is not None and master_key.resolve().parent == out.resolve():
        keep.add(master_key.name)
    stale = [p for p in key_files(out) if p.name not in keep]
    for p in stale:  # --force only: a smaller fleet's leftovers would be confusing
        p.unlink()
    write_key_set(sc, out, master, with_master=master_key is None)
    return ProvisionedKeys(out, list(nodes), secoc.fleet_id(master), stale,
                           master_key is None)


def check_key_set(keys: Path, n: int, sc: Any | None = None) -> str:
    """Load every key file a fleet of ``n`` agents needs from ``keys`` before anything
    starts, and check what a node would refuse at its start: permissions (the directory's
    too), format, one fleet, a boot counter left to start with, and the keys of the peers
    it receives from (with ``sc``, whose graph says who that is), so a bad set is a
    ParameterError (--keys) here, never a node refusing its file mid-start; the fleet id."""
    from firmware_py import pricesig, secoc

    if not keys.is_dir():
        raise ParameterError("--keys", "a key set directory (bess-ded keys --fleet ... --out "
                             "DIR)", str(keys))
    mode = stat.S_IMODE(keys.stat().st_mode)
    if mode & 0o077:
        raise ParameterError("--keys", f"a directory only its owner may access (chmod 700 "
                             f"{keys})", f"{keys} with mode {mode:04o}")
    fleets = set()
    loaded = {}
    for node in secoc.fleet_nodes(n):
        path = keys / f"{node}.key"
        if not path.exists() and not path.is_symlink():
            raise ParameterError("--keys", f"a key set with {node}.key (bess-ded keys --fleet "
                                 f"... --out {keys})", str(keys))
        k = loaded[node] = secoc.load_node_key(path)
        if k.node != node:
            raise ParameterError("--keys", f"{node}.key to hold the key of {node}",
                                 f"the key of {k.node}")
        if k.boot_counter >= secoc.DEFAULT_LAYOUT.max_boot:
            raise ParameterError("--keys", f"{node}.key with a boot counter below "
                                 f"{secoc.DEFAULT_LAYOUT.max_boot} (each start uses the next; "
                                 "re-provision with bess-ded keys --fleet ... --force)",
                                 f"{k.boot_counter}, exhausted")
        fleets.add(k.fleet_id)
    if len(fleets) != 1:
        raise ParameterError("--keys", "key files of one fleet", f"fleet ids {sorted(fleets)}")
    sc_peers = peers_of(sc) if sc is not None else {}
    sc_frames = frames_of(sc) if sc is not None else {}
    sc_commands = commands_of(sc) if sc is not None else {}
    for node, k in loaded.items():
        if missing := [p for p in sc_peers.get(node, []) if p not in k.peers]:
            raise ParameterError("--keys", f"{node}.key with the keys of the nodes it receives "
                                 f"from ({', '.join(sc_peers[node])})",
                                 f"none for {', '.join(missing)}")
        if missing := [f for f in sc_frames.get(node, []) if f not in k.frames]:
            raise ParameterError("--keys", f"{node}.key with the keys of its link frames "
                                 f"and reports (AUTH-28, AUTH-29: "
                                 f"{', '.join(sc_frames[node])})",
                                 f"none for {', '.join(missing)}")
        if missing := [t for t in sc_commands.get(node, []) if t not in k.commands]:
            raise ParameterError("--keys", f"{node}.key with the ER_Command keys of "
                                 f"{', '.join(sc_commands[node])} (AUTH-30)",
                                 f"none for {', '.join(missing)}")
    if getattr(sc, "signed_price", False):  # AUTH-31: the router signs, the others verify
        router = loaded["router"]
        if router.price_sign is None:
            raise ParameterError("--keys", "router.key with the price signing key of a "
                                 "signed_price scenario ([price_signature] sign_key; bess-ded "
                                 "keys --fleet SCENARIO)", "none")
        public = pricesig.public_key(router.price_sign)
        if wrong := [node for node, k in loaded.items()
                     if node != "router" and k.price_verify != public]:
            raise ParameterError("--keys", "every other key file with the router's public "
                                 "price key ([price_signature] verify_key, AUTH-31)",
                                 f"none or another one in {', '.join(wrong)}")
    return fleets.pop()


@dataclass
class RotatedKeys:
    """What ``rotate_node_keys`` did."""

    node: str
    rewritten: list[str]      # the nodes whose key files now hold the new keys
    untouched: list[str]      # the fleet's other nodes: their files are as they were


def rotate_node_keys(sc: Any, keys_dir: Path, node: str) -> RotatedKeys:
    """Rotate ``node``'s keys in the key set ``keys_dir`` (issue 25, item 5): a new own key
    and new keys of every link frame and report it is a party of (AUTH-28, AUTH-29) and
    of every command key it holds (AUTH-30: an agent's own, the router's all), all
    fresh from the OS's CSPRNG (not derived from the master key: re-provisioning from the
    master undoes a rotation). Rewrites ``node``'s file and the files of the nodes that
    hold one of those keys (its peers that verify its broadcasts, the other parties of its
    link frames, reports and commands), keeping every boot counter and floor; no other
    file is touched. An interrupted rotation is finished by running it again (all
    affected files get newer keys)."""
    import tomli_w

    from firmware_py import contract, secoc

    fleet = secoc.fleet_nodes(sc.n)
    if node not in fleet:
        raise ParameterError("--rotate", f"a node of the fleet ({', '.join(fleet)})", node)
    check_key_set(keys_dir, sc.n, sc)
    own = secrets.token_bytes(secoc.KEY_BYTES)
    links = {f: secrets.token_bytes(secoc.KEY_BYTES) for f in contract.keyed_frames(sc.n)
             if node in contract.parties_of(f)}
    cmds = {t: secrets.token_bytes(secoc.KEY_BYTES) for t in commands_of(sc)[node]}
    rewritten, untouched = [], []
    for label in fleet:
        path = keys_dir / f"{label}.key"
        k = secoc.load_node_key(path)
        key = own if label == node else k.key
        peers = {p: own if p == node else pk for p, pk in k.peers.items()}
        frames = {f: links.get(f, fk) for f, fk in k.frames.items()}
        commands = {t: cmds.get(t, ck) for t, ck in k.commands.items()}
        if (key == k.key and peers == dict(k.peers) and frames == dict(k.frames)
                and commands == dict(k.commands)):
            untouched.append(label)
            continue
        doc = secoc.node_key_document(label, key, k.fleet_id, k.boot_counter, peers,
                                      k.floors, frames, commands, k.price_sign,
                                      k.price_verify)
        secoc.write_private(path, secoc.KEY_FILE_HEADER + tomli_w.dumps(doc))
        rewritten.append(label)
    return RotatedKeys(node, rewritten, untouched)


def provision_keys(sc: Any, key_dir: Path) -> Path:
    """A fresh key set for one run in ``key_dir`` (0700; a previous run's is replaced):
    every run signs with keys no other run holds, so nothing recorded elsewhere replays."""
    from firmware_py import secoc

    if key_dir.exists():
        shutil.rmtree(key_dir)
    key_dir.mkdir(mode=0o700, parents=True)
    write_key_set(sc, key_dir, secrets.token_bytes(secoc.KEY_BYTES))
    return key_dir
