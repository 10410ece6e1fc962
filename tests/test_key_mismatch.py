"""A node that signs with another key than the fleet's, and an `analyze` given another
run's keys (issue 20): each is named as what it is, never "CONVERGED with anomalies" or
"the router never spoke"."""

from __future__ import annotations

import json
import secrets
from dataclasses import replace
from pathlib import Path

import pytest

from firmware_py import secoc
from sim.cli import main
from sim.model.scenario import load_case
from sim.run import busrun
from sim.run.keyset import write_key_set

pytestmark = pytest.mark.slow

SC = replace(load_case(1), duration=5.0)


def fleet_with(agent_3: secoc.Keyring | None, master: bytes) -> dict[str, secoc.Keyring]:
    rings = secoc.Keyring.fleet(master, secoc.fleet_nodes(SC.n))
    if agent_3 is not None:
        rings["agent_3"] = agent_3
    return rings


def kinds(m: dict) -> list[tuple[str, str]]:
    return [(a["kind"], a["node"]) for a in m["anomalies"]]


@pytest.mark.parametrize("whole_file", [False, True], ids=["own-key", "other-key-set"])
def test_a_node_with_another_key_is_named(tmp_path: Path, whole_file: bool) -> None:
    """agent_3 signs with keys of another provisioning: only its own signing keys (it
    still verifies the others), or its whole key file (it rejects everyone else's frames too).
    Every receiver rejects its frames; the verdict says so once, naming agent_3 and its
    key file, instead of a MAC failure and an untrusted-source alarm per receiver."""
    master, other = secrets.token_bytes(secoc.KEY_BYTES), secrets.token_bytes(secoc.KEY_BYTES)
    if whole_file:
        ring = secoc.Keyring.fleet(other, ["agent_3"])["agent_3"]
    else:
        # its signing keys (its own, its setpoint's and its Diag's frame keys, AUTH-28,
        # AUTH-29) are another provisioning's; it verifies with the fleet's
        ring = secoc.Keyring("agent_3", secoc.derive_node_key(other, "agent_3"), 0,
                             lambda _b: None, master=master, fleet=secoc.fleet_id(master),
                             frames={f: secoc.derive_frame_key(other, f)
                                     for f in ("AGENT_3_Setpoint", "AGENT_3_Diag")})
    m = busrun.run_in_process(SC, tmp_path, SC.duration, channel=f"keys-{whole_file}",
                              keyrings=fleet_with(ring, master))
    v = m["verdict"]
    assert not v["converged"] and not v["ok"]
    assert v["cause"].startswith("key_mismatch [agent_3]: agent_3's frames fail the MAC at "
                                 "every receiver"), v["cause"]
    assert "check its key file" in v["cause"]
    found = kinds(m)
    assert found.count(("key_mismatch", "agent_3")) == 1
    # the receivers' alarms are these frames: not listed again, one by one
    assert not [k for k in found if k[0] in ("auth_failed", "untrusted_source", "agent_silent")]


def test_a_healthy_fleet_has_no_key_mismatch(tmp_path: Path) -> None:
    master = secrets.token_bytes(secoc.KEY_BYTES)
    m = busrun.run_in_process(SC, tmp_path, SC.duration, channel="keys-healthy",
                              keyrings=fleet_with(None, master))
    assert not [k for k in kinds(m) if k[0] in ("key_mismatch", "wrong_keys")]


def test_analyze_with_keys_that_are_not_the_logs(tmp_path: Path) -> None:
    """A log analysed with another key set: nothing verifies, and the verdict says the
    keys do not belong to the log (it said "the router never spoke")."""
    run = tmp_path / "run"
    busrun.run_in_process(SC, run, SC.duration, channel="keys-analyze")
    others = tmp_path / "other-keys"
    others.mkdir(mode=0o700)
    write_key_set(SC, others, secrets.token_bytes(secoc.KEY_BYTES))
    out = tmp_path / "a"
    rc = main(["analyze", str(run / "run.log"), "--case", "1", "--keys", str(others),
               "--out", str(out), "--no-plot"])
    m = json.loads((out / "metrics.json").read_text())
    assert rc != 0 and not m["verdict"]["converged"]
    assert m["verdict"]["cause"].startswith("wrong_keys [recorder]: "), m["verdict"]["cause"]
    assert "the keys do not belong to this log" in m["verdict"]["cause"]
    assert "never spoke" not in json.dumps(m["anomalies"])
    # and with the run's own keys, the same log is clean (5 s: not yet within 1e-3)
    main(["analyze", str(run / "run.log"), "--case", "1", "--keys", str(run / "keys"),
          "--out", str(tmp_path / "b"), "--no-plot"])
    assert json.loads((tmp_path / "b" / "metrics.json").read_text())["anomalies"] == []
