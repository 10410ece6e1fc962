"""The test kit (sim/testkit, docs/testing.md): the Tester on the simulated clock (exact,
fast), its refusals, what it rejects and reports, and the pytest plugin's loading and
options. The kit on real processes: tests/test_examples.py runs examples/."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import can
import pytest

from firmware_py.errors import EncodeError
from sim.testkit import ExpectationError, Tester, TesterError
from sim.testkit.fleet import KeySet, SimFleet

ROOT = Path(__file__).parents[1]
NO_GAINS = {"GainK": 0, "GainH": 0}


@pytest.fixture
def keys(tmp_path: Path) -> KeySet:
    return KeySet.fresh(tmp_path / "keys")


def test_a_whole_fleet_on_the_simulated_clock_converges_and_reports(keys: KeySet) -> None:
    """Expected: case 1, every node in-process: agent 3 RUNNING right after its join
    window (firmware-spec AUTH-26: 0.2 s, then the next price and status), λ_3
    within 1e-3 of ρ = 0.8 by 8 s of simulated time (lockstep settles in ~3 s), every
    diagnostics counter of the DBC's pages read back (nothing rejected), the tester
    rejecting nothing (it holds the fleet's keys); bus time is the simulated time."""
    with SimFleet(1, keys=keys) as fleet:
        tester = fleet.tester()
        r = tester.expect("AGENT_3_MC", 1.0, where={"State": "RUNNING"})
        assert 0.2 < r.t <= 0.26 and r.label("State") == "RUNNING"
        tester.sleep(8.0)
        assert tester.now() == pytest.approx(8.0 + r.t, abs=2 * fleet.ts)
        mc = tester.expect("AGENT_3_MC", 0.1)
        assert abs(mc["Lambda"] - 0.8) < 1e-3 and set(mc.signals) == {"State", "Resets",
                                                                         "Lambda"}
        assert {"Mac", "Counter"} <= set(mc.raw)
        diag = tester.assert_diagnostics(3, RejectedAuth=0, RejectedDlc=0, Unsynced=0,
                                         DeadlineMisses=0, Resets=lambda n: n >= 1)
        db_msg = tester.codec.database.get_message_by_name("AGENT_3_Diag")
        assert set(diag) == {s.name for s in db_msg.signals   # every counter of every page
                             if s.name not in ("Mac", "Counter", "Page")}
        assert tester.rejected == {} and tester.received["ER_Price"] > 150


def test_the_tester_as_router_isolates_and_reconnects_an_agent(keys: KeySet) -> None:
    """Expected: without the router, the tester's periodic price (a ramp, then updated)
    drives the fleet; ISOLATE 3 → AGENT_3_MC ISOLATED within 0.1 s of bus time (one
    sample of transport), none RUNNING meanwhile; RECONNECT → RUNNING again; the
    price the agents follow is the one the tester sends."""
    with SimFleet(1, nodes=["plant", 1, 2, 3, 4], keys=keys) as fleet:
        tester = fleet.tester()
        price = tester.send_periodic("ER_Price", Rho=lambda t: 0.6 + 0.01 * min(t, 2.0),
                                     Segment=0, PriceValid=1)
        tester.expect("AGENT_3_MC", 1.0, where={"State": "RUNNING"})
        tester.sleep(8.0)
        assert abs(tester.expect("AGENT_1_MC", 0.1)["Lambda"] - 0.62) < 1e-3
        t0 = tester.now()
        tester.send("ER_Command", Command="ISOLATE", Target=3, **NO_GAINS)
        iso = tester.expect("AGENT_3_MC", 0.1, where={"State": "ISOLATED"})
        assert iso.t - t0 <= 0.03
        tester.expect_none("AGENT_3_MC", 1.0, where={"State": "RUNNING"})
        tester.send("ER_Command", Command="RECONNECT", Target=3, **NO_GAINS)
        tester.expect("AGENT_3_MC", 0.1, where={"State": "RUNNING"})
        watcher = fleet.tester()  # the tester does not hear its own frames; a new one
        # takes the price once it heard its next sync (within sync_s = 1 s)
        watcher.expect("ER_Price", 1.5, where={"Rho": 0.62})  # as encoded: 0.62 ± 2^-25
        assert watcher.rejected.keys() <= {"unsynced"}
        price.update(Rho=0.7)
        tester.sleep(8.0)
        assert abs(tester.expect("AGENT_3_MC", 0.1)["Lambda"] - 0.7) < 1e-3
        price.stop()
        assert price.sent > 300
        assert tester.rejected == {}


def test_forged_frames_are_rejected_by_the_agents_and_by_a_tester(keys: KeySet) -> None:
    """Expected: a price signed with agent 1's key (a forgery: it must be the router's)
    is counted by agent 3 (RejectedAuth: the forged sync and the forged frame), never
    moves λ, and a second tester on the bus rejects it under ``auth``: expect does not
    return it, and its timeout says so."""
    with SimFleet(1, keys=keys) as fleet:
        tester, watcher = fleet.tester(), fleet.tester()
        tester.expect("AGENT_3_MC", 1.0, where={"State": "RUNNING"})
        tester.sleep(2.0)
        watcher.mark()
        tester.send("ER_Price", Rho=3.0, Segment=0, PriceValid=1, as_node="agent_1")
        tester.expect("AGENT_3_Diag", 2.0, where={"RejectedAuth": 2})
        tester.expect_none("AGENT_3_MC", 1.0, where={"Lambda": lambda lam: lam > 1.0})
        assert watcher.rejected["auth"] == 2
        with pytest.raises(ExpectationError, match=r"0x010 \(ER_Price\) rejected \(auth: 1\)"):
            watcher.expect("ER_Price", 0.5, where={"Rho": 3.0}, since="mark")


def test_corrupt_and_unsynced_frames_are_counted_not_returned(keys: KeySet) -> None:
    """Expected: a Diag frame of 7 bytes is rejected under ``dlc``; a secured frame of a
    sender whose sync the tester never heard under ``unsynced`` (a Diag page too, now
    that it is signed); none is returned."""
    with SimFleet(1, nodes=[], keys=keys) as fleet:
        tester = fleet.tester()
        raw = fleet.open_bus()
        diag = {"Page": 0, "DeadlineMisses": 0, "Resets": 0}
        unsigned = tester.codec.encode_phys("AGENT_2_Diag", diag, 0)
        short = can.Message(arbitration_id=unsigned.arbitration_id, is_extended_id=False,
                            data=bytes(unsigned.data[:7]))
        raw.send(short)
        mc = tester.codec.encode("AGENT_2_MC", {"State": 1, "Resets": 0, "Lambda": 0}, 0)
        raw.send(mc)
        raw.send(unsigned)
        with pytest.raises(ExpectationError, match="rejected"):
            tester.expect("AGENT_2_Diag", 0.1)
        assert tester.rejected["dlc"] == 1 and tester.rejected["unsynced"] == 2
        assert tester.received["AGENT_2_MC"] == tester.received["AGENT_2_Diag"] == 0


@pytest.mark.parametrize("call, message", [
    (lambda t: t.send("ER_Prize", Rho=1.0), "message: expected a message name defined "
     "in the DBC"),
    (lambda t: t.send("ER_Price", Rho=1.0, Segment=0, PriceValid=1, Foo=2),
     "ER_Price signals: expected signals among PriceValid, Segment, Rho, but got ['Foo']"),
    (lambda t: t.send("ER_Price", Rho=1.0, Segment=0, PriceValid=1, Counter=3),
     "(Counter: filled in by the tester), but got ['Counter']"),
    (lambda t: t.send("ER_Price", Rho=1.0), "missing PriceValid, Segment"),
    (lambda t: t.send("ER_Price", Rho=500.0, Segment=0, PriceValid=1),
     "ER_Price: expected physical values inside the DBC ranges"),
    (lambda t: t.send("ER_Command", Command="EXPLODE", Target=3, **NO_GAINS),
     "ER_Command: expected physical values inside the DBC ranges"),
    (lambda t: t.send("ER_Price", Rho=1.0, Segment=0, PriceValid=1, as_node="agent_x"),
     "node: expected an agent number, 'agent_<i>', 'plant' or 'router', but got 'agent_x'"),
    (lambda t: t.expect("ER_Price", 0.1, where={"Price": 1}),
     "ER_Price where: expected signals among"),
    (lambda t: t.send_periodic("ER_Command", Command="ISOLATE", Target=3, **NO_GAINS),
     "period_s: expected a period for ER_Command (an event message"),
    (lambda t: t.send_periodic("ER_Price", {"Rho": 1, "Segment": 0, "PriceValid": 1}, 0),
     "period_s: expected a period > 0 s, but got 0"),
    (lambda t: t.diagnostics("plant"), "diagnostics node: expected an agent"),
    (lambda t: t.assert_diagnostics(1, Rejected=0), "agent_1 diagnostics: expected "
     "counters among"),
])
def test_bad_calls_name_what_was_expected_and_given(keys: KeySet, call, message: str) -> None:
    with SimFleet(1, nodes=["agent_1", "plant", "router"], keys=keys) as fleet:
        tester = fleet.tester()
        with pytest.raises(ValueError) as e:
            call(tester)
        assert isinstance(e.value, TesterError | EncodeError)  # the codec's: values
        assert message in str(e.value)


def test_expect_waits_for_a_frame_after_the_call_unless_asked_for_the_buffer(
        keys: KeySet) -> None:
    """Expected: as cantools' Tester, ``expect`` returns a frame received after the call
    (never one buffered before it); ``since="mark"`` looks back to the last mark, send
    or sleep; a number to a bus time; a reply to ``send`` counts even when it came before
    the expect (the next expect after that is back to frames after its call)."""
    with SimFleet(1, keys=keys) as fleet:
        tester = fleet.tester()
        tester.expect("AGENT_3_MC", 1.0, where={"State": "RUNNING"})
        tester.mark()
        t_mark = tester.now()
        fleet.run(0.5)   # frames arrive while nobody expects them (bus time passes)
        t_call = tester.now()
        assert tester.expect("AGENT_3_MC", 0.1).t > t_call
        assert t_mark < tester.expect("AGENT_3_Diag", 1.0, since="mark").t < t_call
        assert tester.expect("AGENT_3_MC", 0.1, since=t_mark + 0.1).t < t_mark + 0.2
        tester.send("ER_Command", Command="ISOLATE", Target=3, **NO_GAINS)
        t_sent = tester.now()
        fleet.run(0.3)   # the reply comes before the expect
        isolated = tester.expect("AGENT_3_MC", 0.1, where={"State": "ISOLATED"})
        assert t_sent <= isolated.t < t_sent + 0.3
        t_call = tester.now()
        assert tester.expect("AGENT_3_MC", 0.1).t > t_call
        with pytest.raises(TesterError, match="since: expected 'call', 'mark' or a bus"):
            tester.expect("AGENT_3_MC", 0.1, since="now")  # type: ignore[arg-type]


def test_unmet_expectations_say_what_came_instead(keys: KeySet) -> None:
    with SimFleet(1, keys=keys) as fleet:
        tester = fleet.tester()
        with pytest.raises(ExpectationError) as e:
            tester.expect("AGENT_3_MC", 0.5, where={"State": "SAFE"})
        text = str(e.value)
        assert "expected AGENT_3_MC with State == 'SAFE' within 0.5 s of bus time" in text
        assert ("AGENT_3_MC frame(s) passed the checks in its window (after the call, or "
                "the send before it), the last: {") in text
        with pytest.raises(ExpectationError, match="expected no AGENT_3_MC for 0.2 s"):
            tester.expect_none("AGENT_3_MC", 0.2)
        with pytest.raises(ExpectationError, match="expected Resets == 1000, but got "):
            tester.assert_diagnostics(3, Resets=1000)
        with pytest.raises(ValueError, match="nodes: expected nodes of case1"):
            SimFleet(1, nodes=[7], keys=keys)


def test_the_tester_on_a_real_bus_uses_wall_time_and_a_private_port(
        bess_tester: Tester, bess_bus_options) -> None:
    """Expected (any load): the plugin's default bus is udp_multicast on a port of its own
    (not python-can's shared default); the tester's periodic frames, echoed back by
    udp_multicast, are recognised as its own (neither returned nor rejected), and a
    second tester on the bus verifies them; bus time is the wall clock."""
    kw = bess_bus_options.resolved()
    assert kw["interface"] == "udp_multicast" and kw["port"] != 43113
    with can.Bus(**{**kw, "receive_own_messages": False}) as bus2, \
            Tester(bus2, bess_tester.keys) as other:
        t0, w0 = bess_tester.now(), time.monotonic()
        p = bess_tester.send_periodic("ER_Price", Rho=0.8, Segment=0, PriceValid=1)
        r = other.expect("ER_Price", 30.0, where={"Rho": lambda v: abs(v - 0.8) < 1e-6})
        p.stop()
        assert r.t >= 0 and bess_tester.now() - t0 <= time.monotonic() - w0 + 0.01
        bess_tester.sleep(0.2)
        assert bess_tester.received["ER_Price"] == 0 and bess_tester.rejected == {}
        assert other.rejected == {}


# --------------------------------------------------------------------------- the plugin


def _entry_point_dir(tmp_path: Path) -> Path:
    """A dist-info holding pyproject's pytest11 entry point, as an installed package has
    (the environment's bess-ded may be another checkout's editable install)."""
    eps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]
    lines = "".join(f"{k} = {v}\n" for k, v in eps["pytest11"].items())
    d = tmp_path / "site" / "bess_ded_kit_probe-0.dist-info"
    d.mkdir(parents=True, exist_ok=True)
    (d / "METADATA").write_text("Metadata-Version: 2.1\nName: bess-ded-kit-probe\n"
                                "Version: 0\n")
    (d / "entry_points.txt").write_text(f"[pytest11]\n{lines}")
    return d.parent


def _pytest(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(_entry_point_dir(tmp_path)),
                                                        str(ROOT)])}
    env.pop("PYTEST_ADDOPTS", None)
    return subprocess.run([sys.executable, "-m", "pytest", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)


def test_the_plugin_loads_from_its_entry_point_once_and_documents_its_options(
        tmp_path: Path) -> None:
    """Expected: installed (its pytest11 entry point), the plugin's options are in
    `pytest --help`; beside tests/conftest.py's pytest_plugins it is registered once
    (no error) and collecting the suite's tests with it changes nothing."""
    out = _pytest(tmp_path, "--help")
    assert out.returncode == 0, out.stderr
    for opt in ("--bess-interface", "--bess-channel", "--bess-bus-config", "--bess-keys",
                "--bess-time-scale"):
        assert opt in out.stdout
    col = _pytest(tmp_path, "--co", "-q", "tests/test_testkit.py", "tests/test_keys.py")
    assert col.returncode == 0, col.stdout + col.stderr
    assert "ERROR" not in col.stdout and "already registered" not in col.stderr


@pytest.mark.parametrize("args, message", [
    (["--bess-bus-config", "{oops"],
     "bess-ded test kit: CAN config: expected a JSON object, but got '{oops'"),
    (["--bess-bus-config", '{"prot": 1}'], "bess-ded test kit: CAN config: udp_multicast "
     "accepts"),
    (["--bess-time-scale", "0.5"], "--bess-time-scale: expected a factor ≥ 1, but got 0.5"),
    (["--bess-keys", "/nonexistent"], "--bess-keys: expected a key set directory"),
])
def test_bad_plugin_options_are_one_line_usage_errors(tmp_path: Path, args: list[str],
                                                      message: str) -> None:
    """Expected: checked once at startup (exit code 4, pytest's usage error), before any
    test runs, with what was expected and given."""
    test = tmp_path / "test_probe.py"
    test.write_text("def test_probe(bess_bus):\n    pass\n")
    out = _pytest(tmp_path, "-q", "-p", "no:cacheprovider", *args, str(test))
    assert out.returncode == 4, out.stdout + out.stderr
    assert message in out.stderr


def test_a_process_fleet_refuses_an_in_process_bus(tmp_path: Path, keys: KeySet) -> None:
    from sim.run.busrun import BusOptions
    from sim.testkit.fleet import ProcessFleet

    with pytest.raises(TesterError, match="bus: expected a bus that connects processes"):
        ProcessFleet(1, tmp_path / "f", BusOptions("virtual", "x"), keys)
    with pytest.raises(ValueError, match="nodes: expected nodes of case1"):
        ProcessFleet(1, tmp_path / "f", BusOptions("udp_multicast", None, '{"port": 31999}'),
                     keys).start(["agent_9"])


def test_loading_the_plugin_imports_nothing_heavy() -> None:
    """Expected: installed, the plugin loads in every pytest session of the environment;
    until a test asks for a fixture it imports neither python-can, cantools, numpy nor
    the firmware (nor compiles the DBC)."""
    code = ("import sys, sim.testkit.plugin; print(sorted(m for m in sys.modules if "
            "m.split('.')[0] in ('can', 'cantools', 'numpy', 'firmware_py', 'matplotlib')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.stdout.strip() == "[]"


def test_a_device_model_joins_the_simulated_fleet(keys: KeySet) -> None:
    """Expected: the fleet but agent 3, plus a node of one's own in its place (here our
    own AgentRuntime, built from the fleet's configuration and keyring, as a binding of
    one's firmware would be): it runs and converges to ρ = 0.8 with the rest."""
    from firmware_py.runtime import AgentRuntime

    with SimFleet(1, nodes=["router", "plant", 1, 2, 4], keys=keys) as fleet:
        fleet.add("agent_3", AgentRuntime(fleet.agent_config(3),
                                          keys=fleet.keyring("agent_3")))
        with pytest.raises(TesterError, match="name: expected a node not yet in the fleet"):
            fleet.add("agent_3", object())
        tester = fleet.tester()
        tester.expect("AGENT_3_MC", 1.0, where={"State": "RUNNING"})
        tester.sleep(8.0)
        assert abs(tester.expect("AGENT_3_MC", 0.1)["Lambda"] - 0.8) < 1e-3
        tester.assert_diagnostics(3, RejectedAuth=0, Unsynced=0)
