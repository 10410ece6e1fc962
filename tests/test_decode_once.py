"""One decode per frame per consumer (issue 21, item 3): a counting spy over the codec.

`up`'s consumers of a frame are the live view (``Progress``), the recording's read-back
(``buslog.read_log``, through ``runreport.report``) and, on the in-process bus, every
node's receive seam (``NodeIO``); the conformance check's is the oracle, which compares
the DUT's frames with every hypothesis of the order of events. Each decodes a frame once.
"""

from __future__ import annotations

import sys
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import pytest

from firmware_py import secoc
from firmware_py.config import agent_configs_from_scenario
from firmware_py.frames import DecodedFrame, FrameCodec
from sim import conformance as conf
from sim.model.scenario import load_case
from sim.run import inprocess
from sim.run.recorder import Progress
from sim.testkit.tester import fleet_keys


def _frame_key(msg: can.Message) -> tuple[float, int, bytes]:
    return (round(msg.timestamp, 6), msg.arbitration_id, bytes(msg.data))


class CountingCodec(FrameCodec):
    """A FrameCodec whose ``decode`` counts each call by consumer (the object whose
    method called it, else the calling function's name) and frame (time, ID, data), and
    by the identity of the message (``by_msg``)."""

    def __init__(self, *dbc: Path) -> None:
        super().__init__(*dbc)
        self.decodes: Counter[tuple[str, tuple[float, int, bytes]]] = Counter()
        self.by_msg: Counter[int] = Counter()

    def decode(self, msg: can.Message) -> DecodedFrame:
        """Count, then decode as FrameCodec does."""
        caller = sys._getframe(1)
        owner = caller.f_locals.get("self")
        who = (f"{type(owner).__name__}@{id(owner):x}" if owner is not None
               else caller.f_code.co_name)
        self.decodes[(who, _frame_key(msg))] += 1
        self.by_msg[id(msg)] += 1
        return super().decode(msg)


@pytest.fixture(scope="module")
def in_process_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, CountingCodec]:
    """Case 1 for 3 s on the in-process bus, every codec of the run a counting one."""
    out = tmp_path_factory.mktemp("decode-once")
    spy: list[CountingCodec] = []

    def codec(*dbc: Path) -> CountingCodec:  # the run's DBC (its frame format)
        spy.append(CountingCodec(*dbc))
        return spy[-1]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(inprocess, "FrameCodec", codec)
        inprocess.run_in_process(replace(load_case(1), duration=3.0), out, duration=3.0,
                                 channel="decode-once")
    assert len(spy) == 1  # the run's one codec: its nodes' and its report's
    return out, spy[0]


def _log(out: Path) -> list[can.Message]:
    return list(can.LogReader(str(out / "run.log")))


def test_the_recording_is_decoded_once_per_frame(in_process_run: tuple[Path, Any]) -> None:
    """``read_log`` (what `up` and `analyze` report from) decodes every frame of run.log
    exactly once: the decodes it made are the log's frames, each once."""
    out, codec = in_process_run
    read_back = Counter({k: n for (who, k), n in codec.decodes.items() if who == "read_log"})
    log = Counter(_frame_key(m) for m in _log(out))
    assert sum(log.values()) > 1000  # 3 s of case 1: ~300 ticks of 8 nodes' frames
    assert read_back == log


def test_each_node_decodes_a_frame_once(in_process_run: tuple[Path, Any]) -> None:
    """On the in-process bus every node's receive seam decodes each frame it reads once."""
    _, codec = in_process_run
    by_node = {(who, k): n for (who, k), n in codec.decodes.items() if who != "read_log"}
    assert {who.split("@")[0] for who, _ in by_node} == {"NodeIO"}
    assert len({who for who, _ in by_node}) == 4  # case 1's four agents
    assert max(by_node.values()) == 1


def test_the_live_view_decodes_a_frame_at_most_once(in_process_run: tuple[Path, Any]
                                                    ) -> None:
    """``Progress`` (`up`'s live view) decodes only ρ's and the λs' frames, each once."""
    out, _ = in_process_run
    codec = CountingCodec()
    view = Progress(codec, 4)
    frames = _log(out)
    for msg in frames:
        view.on_message_received(msg)
    assert view.frames == len(frames) and view.rho is not None and len(view.lam) == 4
    assert sum(codec.by_msg.values()) == sum(
        1 for m in frames if codec.name_of(m.arbitration_id) == "ER_Price"
        or codec.name_of(m.arbitration_id).endswith("_MC"))
    assert max(codec.by_msg.values()) == 1


def test_the_conformance_check_decodes_each_dut_frame_once() -> None:
    """The oracle compares the DUT's frames with every hypothesis (and, on a mismatch,
    a second pass with the other filter): each DUT frame is still decoded once per
    check. The jittered case keeps several hypotheses alive at many ticks."""
    master = bytes(range(16))
    keys = fleet_keys(master, 4)
    sc = load_case(1)
    cfg = agent_configs_from_scenario(sc)[0]

    def ring() -> secoc.Keyring:
        return secoc.Keyring("agent_1", keys["agent_1"], 0, lambda _b: None, master=master,
                             floors={n: 2 for n in keys if n != "agent_1"})

    planned = conf.plan(cfg, keys, sc.prices[0].rho, boot=2)
    frames = conf.simulate(cfg, ring(), planned, jitter=0.95, seed=2)
    dut = {id(f.msg) for f in frames if not f.sent}
    codec = CountingCodec()
    outcome = conf.check(cfg, ring(), keys["agent_1"], frames, codec)
    assert not outcome.mismatches and outcome.ticks > 100
    decoded = {i: n for i, n in codec.by_msg.items() if i in dut}
    assert len(decoded) == len(dut)  # every DUT frame was read (auth check, comparison)
    assert max(decoded.values()) == 1
