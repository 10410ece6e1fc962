"""`bess-ded keys --fleet (--case N | --scenario FILE) --out DIR`: provision SecOC keys.

Writes one key file per node of the scenario's fleet (agent_1..agent_N, plant,
router), each holding only that node's key, derived from a fleet master key with
NIST SP 800-108 (CMAC-AES-128), and its freshness state (boot counter 0). The master
key is drawn from the OS's random source and written to DIR/master.key, unless
--master-key FILE gives one (then it is not copied). Every file is created 0600 and
DIR 0700. An existing key set is not overwritten without --force; re-provisioning
from a new master key is how a fleet is re-keyed (docs/security.md). Each file holds
only what its node needs: its own key, the node keys of the broadcasts it takes, the
keys of its own link frames and reports (setpoint, status, Diag: AUTH-28, AUTH-29) and
of the commands to it (AUTH-30; the router: every agent's).

--rotate NODE replaces one node's keys in the key set DIR (a compromised or lost
node): a new random key for NODE, for each link frame or report it sends or receives
and for each command key it holds,
written into NODE's file and the files of the nodes that hold one of them, every
boot counter kept; no other file changes. Restart the nodes named.
Every node signs and verifies its secured frames with its key file:
`bess-ded up --keys DIR`, `bess-ded deploy --keys DIR`, or one node per host with
`bess-ded agent ... --key DIR/agent_3.key` (docs/security.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path


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
    p.add_argument("--rotate", metavar="NODE",
                   help="rotate NODE's keys in the key set DIR (agent_3, plant, router): "
                        "rewrites its file and those of the nodes sharing its keys only")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from sim.model.scenario_select import resolve_scenario
    from sim.run.keyset import provision_fleet_keys

    sc = resolve_scenario(args.case)
    out: Path = args.out
    if args.rotate is not None:
        return _rotate(sc, out, args)
    ks = provision_fleet_keys(sc, out, args.master_key, args.force)
    nodes, stale = ks.nodes, ks.removed

    print(f"bess-ded keys: {len(nodes)} node keys for {sc.name} ({sc.n} agents, plant, "
          f"router), fleet id {ks.fleet_id}, in {out}/")
    print(f"  {', '.join(f'{n}.key' for n in nodes)} (0600, directory 0700)")
    if getattr(sc, "signed_price", False):  # AUTH-31
        print("  signed_price: router.key holds the Ed25519 price signing key, every other "
              "file only its public key")
    if stale:
        print(f"  removed {len(stale)} key file(s) of the previous set: "
              + ", ".join(p.name for p in stale))
    if args.master_key is None:
        print(f"  master.key: the fleet master key; every node key derives from it. Move it "
              f"off the nodes (keep it offline); re-derive with --master-key {out}/master.key")
    else:
        print(f"  master key from {args.master_key} (not copied)")
    return 0


def _rotate(sc: object, out: Path, args: argparse.Namespace) -> int:
    from firmware_py.errors import ParameterError
    from sim.run.keyset import rotate_node_keys

    if args.master_key is not None or args.force:
        raise ParameterError("--rotate", "no --master-key or --force (a rotation keeps the "
                             "key set and draws new random keys)",
                             "--master-key" if args.master_key is not None else "--force")
    r = rotate_node_keys(sc, out, args.rotate)
    print(f"bess-ded keys: rotated {r.node}'s keys in {out}/ (new random keys, boot "
          "counters kept)")
    print(f"  rewrote {', '.join(f'{n}.key' for n in r.rewritten)}: restart these nodes with "
          "their new files")
    if r.untouched:
        print(f"  untouched: {', '.join(f'{n}.key' for n in r.untouched)}")
    print(f"  an old copy of {r.node}.key no longer signs as {r.node} nor its link frames; "
          "the other nodes' keys it held stay valid until those nodes are rotated too")
    return 0
