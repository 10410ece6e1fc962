"""`bess-ded keys --fleet (--case N | --scenario FILE) --out DIR`: provision SecOC keys.

Writes one key file per node of the scenario's fleet (agent_1..agent_N, plant,
router), each holding only that node's key, derived from a fleet master key with
NIST SP 800-108 (CMAC-AES-128), and its freshness state (boot counter 0). The master
key is drawn from the OS's random source and written to DIR/master.key, unless
--master-key FILE gives one (then it is not copied). Every file is created 0600 and
DIR 0700. An existing key set is not overwritten without --force; re-provisioning
from a new master key is how a compromised node is revoked (docs/security.md).
Every node signs and verifies its secured frames with its key file:
`bess-ded up --keys DIR`, `bess-ded deploy --keys DIR`, or one node per host with
`bess-ded agent ... --key DIR/agent_3.key` (docs/security.md).
"""

from __future__ import annotations

import argparse
import os
import secrets
import stat
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from firmware_py.errors import BessDedError


def register(sub: argparse._SubParsersAction) -> None:
    from ._common import add_case_option, one_line_errors

    p = one_line_errors(sub.add_parser(
        "keys", help="provision SecOC keys for a fleet (one key file per node)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter))
    p.add_argument("--fleet", action="store_true", required=True,
                   help="provision every node of a fleet (the only mode so far)")
    add_case_option(p)
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="the directory for the key files (created 0700)")
    p.add_argument("--master-key", type=Path, metavar="FILE",
                   help="derive from this master key (a master.key, or 32 hex digits in "
                        "an owner-only file) instead of a new random one")
    p.add_argument("--force", action="store_true",
                   help="replace an existing key set in DIR")
    p.set_defaults(func=run)


def _key_files(out: Path) -> list[Path]:
    return sorted(p for p in out.iterdir() if p.suffix == ".key" and p.is_file())


def _prepare_dir(out: Path, force: bool) -> None:
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
    existing = _key_files(out)
    if existing and not force:
        raise BessDedError(f"--out: {out} already holds a key set ({len(existing)} .key "
                           "files, e.g. " + existing[0].name + "): not overwriting it "
                           "without --force")


def peers_of(sc: Any) -> dict[str, list[str]]:
    """Need to know: the senders whose secured frames each node receives, i.e. whose
    verification keys its key file holds (agent i: the router, the plant and its
    neighbours; the plant: every agent and the router; the router: the plant and every
    agent). The router and the plant use the keys of the nodes whose frames they do not
    take only to notice a restart from its sync and re-announce their own at once."""
    from firmware_py import secoc
    from firmware_py.config import agent_configs_from_scenario

    out = {f"agent_{c.id}": ["router", "plant", *(f"agent_{n.id}" for n in c.neighbours)]
           for c in agent_configs_from_scenario(sc)}
    agents = [n for n in secoc.fleet_nodes(sc.n) if n.startswith("agent_")]
    out["plant"] = [*agents, "router"]
    out["router"] = ["plant", *agents]
    return out


def write_key_set(sc: Any, out: Path, master: bytes, with_master: bool = True) -> None:
    """Write DIR/<node>.key for every node of ``sc`` (and DIR/master.key), 0600."""
    import tomli_w

    from firmware_py import secoc

    if with_master:
        secoc.write_private(out / "master.key", secoc.MASTER_FILE_HEADER
                            + tomli_w.dumps(secoc.master_key_document(master)))
    fleet = secoc.fleet_id(master)
    for node, peers in peers_of(sc).items():
        doc = secoc.node_key_document(node, secoc.derive_node_key(master, node), fleet, 0,
                                      {p: secoc.derive_node_key(master, p) for p in peers})
        secoc.write_private(out / f"{node}.key", secoc.KEY_FILE_HEADER + tomli_w.dumps(doc))


def load_key_set(keys_dir: Path) -> dict[str, bytes]:
    """Every node's own key from a key set (label -> key): what a monitor of the run
    (the recorder's analysis) needs to tell forged frames from the fleet's."""
    from firmware_py import secoc

    return {k.node: k.key for k in (secoc.load_node_key(p) for p in _key_files(keys_dir)
                                    if p.name != "master.key")}


def load_boot_floors(keys_dir: Path) -> dict[str, int]:
    """Every node's lowest boot counter at its next start (label -> the key file's
    counter + 1: a start uses a new one, AUTH-3). Read before a run, it tells the
    run's monitor that a sync of a lower boot is from an earlier start: a replay."""
    from firmware_py import secoc

    return {k.node: k.boot_counter + 1
            for k in (secoc.load_node_key(p) for p in _key_files(keys_dir)
                      if p.name != "master.key")}


def write_boot_floors(keys_dir: Path, nodes: Iterable[str], floors: Mapping[str, int]) -> None:
    """Before a fleet starts: raise the boot floors (AUTH-21) in the key files of
    ``nodes`` to ``floors`` (label -> that node's boot at this start, from
    ``load_boot_floors``), so that no node takes a sync of an earlier run or boot, not
    even before a peer's first genuine sync, nor after its own restart."""
    from firmware_py import secoc

    for node in nodes:
        secoc.save_floors(keys_dir / f"{node}.key", floors)


def run(args: argparse.Namespace) -> int:
    from firmware_py import secoc

    from ._common import resolve_scenario

    sc = resolve_scenario(args.case)
    master = (secoc.load_master_key(args.master_key) if args.master_key is not None
              else secrets.token_bytes(secoc.KEY_BYTES))
    out: Path = args.out
    _prepare_dir(out, args.force)

    nodes = secoc.fleet_nodes(sc.n)
    fleet = secoc.fleet_id(master)
    keep = {f"{n}.key" for n in nodes} | {"master.key"}
    if args.master_key is not None and args.master_key.resolve().parent == out.resolve():
        keep.add(args.master_key.name)
    stale = [p for p in _key_files(out) if p.name not in keep]
    for p in stale:  # --force only: a smaller fleet's leftovers would be confusing
        p.unlink()
    write_key_set(sc, out, master, with_master=args.master_key is None)

    print(f"bess-ded keys: {len(nodes)} node keys for {sc.name} ({sc.n} agents, plant, "
          f"router), fleet id {fleet}, in {out}/")
    print(f"  {', '.join(f'{n}.key' for n in nodes)} (0600, directory 0700)")
    if stale:
        print(f"  removed {len(stale)} key file(s) of the previous set: "
              + ", ".join(p.name for p in stale))
    if args.master_key is None:
        print(f"  master.key: the fleet master key; every node key derives from it. Move it "
              f"off the nodes (keep it offline); re-derive with --master-key {out}/master.key")
    else:
        print(f"  master key from {args.master_key} (not copied)")
    return 0
