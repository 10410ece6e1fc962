"""`bess-ded deploy --case N --out DIR`: a scenario's node files, nothing run.

Writes what each node of the fleet needs to run on its own host (docs/deployment.md),
exactly as `bess-ded up` would write it for a run, and starts nothing:

  DIR/scenario.toml          the scenario as it runs (variant chosen, time scale
                             applied): the plant's and the router's --scenario
  DIR/agents/agent_<i>.toml  every agent's configuration (neighbours, gains, limits)
  DIR/keys/<node>.key        a fresh key set (and DIR/keys/master.key), 0600 in a 0700
                             directory, unless --keys DIR (a set from `bess-ded keys`,
                             checked, not copied) or --insecure

It then prints each node's command line. An existing key set in DIR/keys is not
replaced without --force (re-provisioning revokes every node's key).
"""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from firmware_py.cliargs import time_scale
    from firmware_py.nodeargs import add_fd_argument

    from ._common import add_case_option, add_transmit_argument, one_line_errors

    p = one_line_errors(sub.add_parser(
        "deploy", help="write a scenario's node configurations and key files, run nothing",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter))
    add_case_option(p)
    p.add_argument("--variant", metavar="LABEL",
                   help="for a scenario with variants (cases 2, 3, 6): which one "
                   "(default: the first)")
    add_transmit_argument(p)
    add_fd_argument(p)
    p.add_argument("--time-scale", type=time_scale, default=1.0, metavar="F",
                   help="stretch the time axis by F (Ts·F, k/F, h/F²), as `up --time-scale`")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="output directory (default: runs/deploy-<scenario>)")
    k = p.add_mutually_exclusive_group()
    k.add_argument("--keys", type=Path, metavar="DIR",
                   help="the fleet's key set from `bess-ded keys --fleet` (checked, not "
                        "copied); default: a fresh one in DIR/keys")
    k.add_argument("--insecure", action="store_true",
                   help="no keys: every node runs --insecure (the public demo key)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing key set in DIR/keys")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import secrets

    from firmware_py import secoc
    from firmware_py.config import agent_configs_from_scenario
    from firmware_py.nodeargs import fd_argv
    from sim.bench.fleetload import check_bus_load
    from sim.model.scenario import scaled, to_toml
    from sim.model.scenario_select import pick_variant, resolve_scenario, with_fd, with_transmit
    from sim.run.keyset import check_key_set, prepare_key_dir, write_key_set
    from sim.run.nodeprocs import RT_PRIORITY

    sc, chosen = pick_variant(resolve_scenario(args.case), args.variant, "deploy")
    sc = with_transmit(sc, args.transmit)
    sc = with_fd(sc, args.fd, args.no_lambda_tags)
    sc = scaled(sc, args.time_scale)
    out: Path = args.out or Path("runs") / f"deploy-{sc.name}"
    # everything checked before anything is written (a fleet larger than the DBC's frames
    # is refused by agent_configs_from_scenario, one the bus cannot carry by check_bus_load)
    configs = agent_configs_from_scenario(sc)
    check_bus_load(sc)
    if out.exists() and not out.is_dir():
        raise_out(out)
    if args.keys is not None:
        check_key_set(args.keys, sc.n)
        key_dir: Path | None = args.keys
    elif args.insecure:
        key_dir = None
    else:
        key_dir = out / "keys"
        prepare_key_dir(key_dir, args.force)
        write_key_set(sc, key_dir, secrets.token_bytes(secoc.KEY_BYTES))
    (out / "agents").mkdir(parents=True, exist_ok=True)
    (out / "scenario.toml").write_text(to_toml(sc))
    paths = []
    for cfg in configs:
        path = out / "agents" / f"agent_{cfg.id}.toml"
        path.write_text(cfg.to_toml())
        paths.append(path)

    def key(node: str) -> list[str]:
        return ["--insecure"] if key_dir is None else ["--key", str(key_dir / f"{node}.key")]

    rt = ["--rt-priority", str(RT_PRIORITY)]
    scenario = ["--case", str(out / "scenario.toml"), "--period", repr(sc.ts)]
    print(f"bess-ded deploy: {sc.title or sc.name}{chosen}: {sc.n} agents + plant + router"
          + (f", time scale {args.time_scale:g}" if args.time_scale != 1 else ""))
    print(f"  wrote {out / 'scenario.toml'}, {out / 'agents'}/agent_1..{sc.n}.toml"
          + (f", {key_dir}/ (a fresh key set)" if key_dir == out / "keys" else ""))
    print("  run each node on its host, on the fleet's bus (add --interface, --channel):")
    for i, path in enumerate(paths, 1):
        print("    " + shlex.join(["bess-ded", "agent", "--config", str(path),
                                   *key(f"agent_{i}"), *fd_argv(sc.fd, sc.lambda_tags), *rt]))
    for role in ("plant", "router"):  # the router last: its first price frame is t = 0
        print("    " + shlex.join(["bess-ded", role, *scenario, *key(role), *rt]))
    return 0


def raise_out(out: Path) -> None:
    """Refuse --out ``out``: it is a file, not a directory."""
    from firmware_py.errors import ParameterError

    raise ParameterError("--out", "a directory", f"{out} (a file)")
