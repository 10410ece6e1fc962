"""Running the schedule: in process against an agent runtime (``simulate``) or
against a device on a bus (``drive``)."""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable, Sequence
from typing import Any

import can

from firmware_py.config import AgentConfig
from firmware_py.frames import FrameCodec
from firmware_py.runtime import AgentRuntime
from firmware_py.secoc import Keyring
from sim.conformance.oracle import Frame, quiet_firmware
from sim.conformance.schedule import STEPS, Planned


def simulate(cfg: AgentConfig, keyring: Keyring, planned: Sequence[Planned],
             deviation: Callable[[AgentRuntime], None] | None = None,
             codec: FrameCodec | None = None, lead_ticks: int = 12,
             phase: float = 0.37, latency: float = 2e-4, jitter: float = 0.0,
             seed: int = 0, filtered: bool = False,
             make_dut: Callable[[AgentConfig, FrameCodec, Keyring], Any] | None = None,
             exact: bool = False) -> list[Frame]:
    """The schedule played against firmware_py's agent (with ``deviation``), or the
    agent ``make_dut`` builds (any object with the node seam: the C agent, sim.cbind.cagent),
    on a simulated clock: the record a bus run of a DUT would give, without the bus. The DUT
    ticks ``lead_ticks`` times before the schedule starts (as a device already running
    when the tester starts) at the phase ``phase`` of Ts; ``jitter``: each tick and each
    tester frame up to that fraction of Ts late (seeded), as on a loaded host;
    ``filtered``: the DUT's CAN controller passes only its acceptance IDs (GEN-5).
    ``exact``: the device's clock trusted (``check(..., exact=True)``): it ticks every Ts
    on the dot (``jitter`` moves the tester's frames only), frames reach it when sent
    (no ``latency``), and a frame planned with an ``age`` is put exactly that old (in
    binary64, as the device subtracts) at a tick: a timeout's boundary."""
    import random

    rnd = random.Random(seed)
    tick_rnd = random.Random(f"ticks {seed}")  # a stream of its own: the device's ticks
    # keep their lateness when the schedule gains or loses a frame
    codec = codec or FrameCodec()
    ts = cfg.controller.ts
    # the device starts a boot of a copy: the caller's keyring stays the key file as filed
    # (AUTH-3: the check compares the device's boot with it)
    dut: Any = (make_dut or AgentRuntime)(cfg, codec, copy.copy(keyring))
    if deviation is not None:
        deviation(dut)
    t0 = (lead_ticks + 0.5) * ts  # the schedule's start, after the DUT's first Diag
    played = {p.step for p in planned}
    end = t0 + max((s.end for s in STEPS if s.name in played), default=0) * ts + 3 * ts
    ticks: list[float] = []
    if exact:
        latency = 0.0
        ticks = [(k + phase) * ts for k in range(int(end / ts) + 2)]
        ticks = [t for t in ticks if t < end]
    inputs: list[Frame] = []
    last: dict[int, int] = {}  # ID → index in inputs of the tester's latest frame of it
    planned_at = -1.0
    for p in planned:
        fid = p.msg.arbitration_id
        if exact and p.after is not None and fid in last:
            before = inputs[last[fid]]
            t_prev, t = _exactly_after(before.t, p.after, ts)
            inputs[last[fid]] = Frame(t_prev, before.msg, True, before.step, before.note)
        elif exact and p.age:
            t = _exactly_old(t0 + p.at, p.age, ticks)
        else:
            t = t0 + p.at + rnd.uniform(0, jitter * ts)
            if inputs and p.at == planned_at:  # a burst (the pages of a transfer) is sent
                t = inputs[-1].t              # back to back: none overtakes another
        planned_at = p.at
        last[fid] = len(inputs)
        inputs.append(Frame(t, p.msg, True, p.step, p.note))
    inputs.sort(key=lambda f: f.t)
    passed = set(getattr(dut, "io", dut).accepted_ids())
    record: list[Frame] = []
    nxt = 0
    k = 0
    with quiet_firmware():
        while (tick := (ticks[k] if k < len(ticks) else end) if exact else
               (k + phase + tick_rnd.uniform(0, jitter)) * ts) < end:
            while nxt < len(inputs) and inputs[nxt].t + latency < tick:
                msg = inputs[nxt].msg
                if not filtered or (not msg.is_extended_id
                                    and msg.arbitration_id in passed):
                    dut.on_frame(msg, inputs[nxt].t + latency)
                record.append(inputs[nxt])
                nxt += 1
            for msg in dut.tick(tick):
                record.append(Frame(tick + latency, msg, False))
            k += 1
    return record


def _exactly_after(prev: float, gap: float, ts: float) -> tuple[float, float]:
    """Two receive times near ``prev`` and ``prev + gap`` that are exactly ``gap`` apart
    as either device subtracts them: in binary64 (firmware_py: (t − t_prev) / Ts ==
    gap / Ts) and in whole ns (firmware_c: round(t·1e9), its period round(Ts·1e9)). The
    first moves by at most 2 ns."""
    want_ns = round(gap / ts * round(ts * 1e9))
    for m in range(2000):
        a = prev + m * 1e-12
        b = a + gap
        if b - a == gap and (b - a) / ts == gap / ts and round(b * 1e9) - round(a * 1e9) == want_ns:
            return a, b
    raise ValueError(f"no two times {gap!r} s apart near {prev!r} s in binary64 and ns")


def _exactly_old(at: float, age: float, ticks: Sequence[float]) -> float:
    """A receive time near ``at`` that is exactly ``age`` old (``tick − t == age`` in
    binary64) at the first of ``ticks`` at least ``age`` after ``at``."""
    import math

    tick = next((t for t in ticks if t >= at + age), None)
    if tick is None:
        return at
    t = tick - age
    for _ in range(64):
        if tick - t == age:
            break
        t = math.nextafter(t, -math.inf if tick - t < age else math.inf)
    return t


def drive(bus: can.BusABC, planned: Sequence[Planned], dut_ids: set[int], diag_id: int,
          wait_s: float, ts: float, progress: Callable[[str], None] | None = None,
          clock: Callable[[], float] | None = None) -> tuple[list[Frame], float]:
    """Play the schedule on ``bus`` once the DUT is heard (its Diag frame, within
    ``wait_s``), recording the DUT's frames and the tester's own (send times). Also
    returns how late the tester sent its latest frame (s): a loaded tester plays a
    schedule the DUT may time out on, which the oracle then has to explain."""
    import threading
    import time

    clock = clock or time.time
    record: list[Frame] = []
    lock = threading.Lock()
    heard = threading.Event()
    # the tester's own frames on the DUT's IDs (impersonation tests), should the
    # interface echo them
    ours = {(p.msg.arbitration_id, bytes(p.msg.data)) for p in planned}

    class Rec(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            if (msg.arbitration_id in dut_ids and not msg.is_error_frame
                    and not msg.is_extended_id
                    and (msg.arbitration_id, bytes(msg.data)) not in ours):
                with lock:
                    record.append(Frame(msg.timestamp, msg, False))
                if msg.arbitration_id == diag_id:
                    heard.set()

        def on_error(self, exc: Exception) -> None:
            """An input that is no frame (node.RX_CAUSES): not the DUT's, reading goes on."""
            from firmware_py.node import rx_cause

            logging.getLogger(__name__).warning("conformance tester: dropped a bus input "
                                                "(%s): %s", rx_cause(exc), exc)

    notifier = can.Notifier(bus, [Rec()], timeout=0.05)
    try:
        if not heard.wait(wait_s):
            raise TimeoutError(f"no {diag_id:#x} frame of the device under test in "
                               f"{wait_s:g} s")
        with lock:
            record.clear()  # from its Diag on: the oracle starts there
        heard.clear()
        heard.wait(wait_s)  # a fresh Diag: the tick count is aligned from it
        # t0 is the DUT's tick (its Diag just heard): the schedule's frames at k + 0.25,
        # 0.5, 0.75 fall between its ticks, not on them, so a tick a few ms late does not
        # swap a frame with the next one (a one-tick pulse stays one tick for the DUT)
        t0 = clock()
        last_report = -1
        worst = 0.0
        for p in planned:
            delay = t0 + p.at - clock()
            if delay > 0:
                time.sleep(delay)
            before = clock()
            worst = max(worst, before - t0 - p.at)
            bus.send(p.msg)
            with lock:
                record.append(Frame(before, p.msg, True, p.step, p.note, clock()))
            if progress is not None and int(p.at) != last_report:
                last_report = int(p.at)
                progress(f"t = {p.at:5.1f} s  step {p.step}")
        time.sleep(3 * ts)
    finally:
        notifier.stop()
    record.sort(key=lambda f: f.t)
    return record, worst
