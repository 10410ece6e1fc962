#!/usr/bin/env python3
"""Generate ``tests/vectors/controller/*.json``, golden vectors of the controller core.

Each vector pins ``firmware_py.controllers`` (``fixed=True``: Q24 words, Q1.30
constants, an int64 Q54 state) bit for bit:
a controller configuration with the integer constants the controller derives from it,
an initial λ and a sequence of consensus errors ξ, and after every step the exact step
output and controller state. A port (the C firmware, a third-party node) that
reproduces every vector runs the same control law to the last bit; the format is in
tests/vectors/README.md, and tests/test_vectors.py replays every vector through
firmware_py.

The inputs are fixed by this script (hand-made edge cases, seeded random walks, and ξ
of one agent of a case-1 lockstep run); the outputs are whatever firmware_py computes
now. The generated files are committed; a test checks that they are what this script
produces, so a change of the control core that moves one bit shows up as stale vectors
(and must be a deliberate regeneration).

Usage::

    python tools/gen_vectors.py            # (re)write tests/vectors/controller/ and node/
    python tools/gen_vectors.py --check    # exit 1 if the committed vectors are stale
    python tools/gen_vectors.py -o DIR     # write the controller vectors elsewhere
    python tools/gen_vectors.py --node-output DIR  # the node vectors (gen_node_vectors.py)
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this worktree's firmware_py, not an installed copy

from firmware_py import fixedpoint as fx  # noqa: E402
from firmware_py.controllers import (  # noqa: E402
    Controller,
    ControllerConfig,
    ControllerState,
    FixedArithmetic,
    StepOutput,
    make_controller,
)

DEFAULT_OUTPUT = ROOT / "tests" / "vectors" / "controller"
NODE_OUTPUT = ROOT / "tests" / "vectors" / "node"  # tools/gen_node_vectors.py
FORMAT = "bess-ded controller vector 2"

# One row per step: the input ξ, then StepOutput, then ControllerState after the step,
# then the wire λ. Booleans are 0/1; every value is an int: xi and lam_q24 Q24 raw
# (int32), dlam, lam and nu Q54 raw (int64). The state's xi_prev after a step is always
# that step's ξ, so the row does not repeat it (the replay checks it against "xi").
FIELDS = ("xi", "dlam", "reset", "lam", "nu", "lam_q24", "armed", "since_reset", "resets",
          "saturations")
STATE_FIELDS = ("lam", "nu", "lam_q24", "xi_prev", "armed", "since_reset", "resets",
                "saturations")

MAX, MIN = fx.INT32_MAX, fx.INT32_MIN
ONE = fx.ONE


@dataclass(frozen=True)
class Spec:
    """A vector before it is run: what to feed the controller."""

    name: str
    description: str
    config: ControllerConfig
    lambda0: int          # Q24 raw
    xis: tuple[int, ...]  # Q24 raw, each in int32
    source: str | None = None


# --------------------------------------------------------------------------- running


def _int(v: float | int, what: str) -> int:
    if not isinstance(v, int) or isinstance(v, bool):
        raise TypeError(f"{what}: expected an int from the fixed-point controller, got {v!r}")
    return v


def fixed_constants(c: Controller) -> dict[str, int]:
    """The integers the controller actually computes with, read from the object."""
    ar = c.ar
    if not isinstance(ar, FixedArithmetic):
        raise TypeError("golden vectors are for the fixed-point controller (fixed=True)")
    return {
        "q": ar.q,
        "qc": fx.QC,
        "guard": fx.GUARD,
        "kts": _int(c.kts, "kts"),
        "hts": _int(c.hts, "hts"),
        "ts": _int(c.ts_q, "ts"),
        "band": _int(c.band, "band"),
        "dwell_samples": c.dwell_samples,
        "pow_num": ar.pow_num,
        "pow_sqrts": ar.pow_sqrts,
    }


def state_row(c: Controller, s: ControllerState) -> list[int]:
    return [_int(s.lam, "lam"), _int(s.nu, "nu"), _int(c.wire_lambda(s), "lam_q24"),
            _int(s.xi_prev, "xi_prev"), int(s.armed), s.since_reset, s.resets, s.saturations]


def step_row(c: Controller, xi: int, o: StepOutput, s: ControllerState) -> list[int]:
    if s.xi_prev != xi:
        raise AssertionError(f"xi_prev after a step is {s.xi_prev}, not the step's ξ {xi}")
    return [xi, _int(o.dlam, "dlam"), int(o.reset), _int(s.lam, "lam"), _int(s.nu, "nu"),
            _int(c.wire_lambda(s), "lam_q24"), int(s.armed), s.since_reset, s.resets,
            s.saturations]


def initial(c: Controller, lambda0: int) -> ControllerState:
    """``initial_state`` from the Q24 raw λ(0) (raw / 2**24 is exact in binary64)."""
    s = c.initial_state(lambda0 / ONE)
    if s.lam != lambda0 << fx.GUARD or c.wire_lambda(s) != lambda0:
        raise AssertionError(f"initial_state did not reproduce λ(0) = {lambda0}: {s.lam}")
    return s


def run(spec: Spec) -> dict[str, Any]:
    c = make_controller(spec.config, fixed=True)
    s = initial(c, spec.lambda0)
    init = state_row(c, s)
    rows = []
    for xi in spec.xis:
        if not MIN <= xi <= MAX:
            raise ValueError(f"{spec.name}: ξ = {xi} is not an int32")
        s, o = c.step(s, xi)
        rows.append(step_row(c, xi, o, s))
    vec: dict[str, Any] = {"format": FORMAT, "name": spec.name,
                           "description": spec.description}
    if spec.source is not None:
        vec["source"] = spec.source
    vec.update({
        "config": asdict(spec.config),
        "fixed": fixed_constants(c),
        "lambda0": spec.lambda0,
        "initial": dict(zip(STATE_FIELDS, init, strict=True)),
        "fields": list(FIELDS),
        "steps": rows,
    })
    return vec


def to_json(vec: dict[str, Any]) -> str:
    """Compact JSON, one header key and one step per line (diffable, ASCII)."""
    parts = []
    for key, value in vec.items():
        if key == "steps":
            body = ",\n".join(json.dumps(r, separators=(",", ":")) for r in value)
            parts.append(f'"steps":[\n{body}\n]')
        else:
            parts.append(f"{json.dumps(key)}:{json.dumps(value, separators=(',', ':'))}")
    return "{\n" + ",\n".join(parts) + "\n}\n"


# --------------------------------------------------------------------------- inputs


def q24(x: float) -> int:
    return fx.to_fixed(x)


def splitmix64(seed: int) -> Iterator[int]:
    """A tiny, fully specified PRNG (so the inputs never depend on Python's ``random``)."""
    state = seed & 0xFFFFFFFFFFFFFFFF
    while True:
        state = (state + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
        z = state
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
        yield z ^ (z >> 31)


def random_walk(seed: int, steps: int, stride: int, bound: int) -> tuple[int, ...]:
    """ξ(t) = ξ(t−1) + (r(t) mod (2·stride + 1)) − stride, ξ(−1) = 0, reflected at ±bound;
    r is the splitmix64 sequence of ``seed``."""
    rng = splitmix64(seed)
    x, out = 0, []
    for _ in range(steps):
        x += next(rng) % (2 * stride + 1) - stride
        if x > bound:
            x = 2 * bound - x
        elif x < -bound:
            x = -2 * bound - x
        out.append(x)
    return tuple(out)


def cfg(kind: str, **kw: Any) -> ControllerConfig:
    return ControllerConfig(kind=kind, **kw)


LAM0 = q24(0.8)  # case 1's price: a realistic λ
BAND = q24(1e-4)  # the default band, 1678 LSB


def edge_specs() -> list[Spec]:
    specs: list[Spec] = []
    add = specs.append
    b = BAND
    t21 = 1 << 21  # half-way products in the former Q24 core (kept: now exact)

    add(Spec("pc_steps", "Proportional consensus: zero, +/-1 LSB (k*Ts*xi is exact in Q54: "
             "a 1-LSB xi moves lambda by k*Ts LSB of Q24, far below one wire LSB), +/-2**21, "
             "+/-3*2**21, the band values and the int32 extremes.", cfg("pc"), LAM0,
             (0, 1, -1, t21, -t21, 3 * t21, -3 * t21, 1 << 23, -(1 << 23), 100, -100, 12345,
              -12345, b, -b, MAX, MIN, 0)))

    # Rounding of the state to Q24 (lam_q24, and ν in h·Ts·ν): Ts = 2**-7 makes
    # k·Ts = Ts = 2**23 and h·Ts = 2**24 in Q1.30, so ξ = ±64 moves λ and ν by exactly
    # half a Q24 LSB (2**29 in Q54): the roundings hit exact ties of both signs
    add(Spec("pi_rounding", "PI without reset, k = 1, h = 2, Ts = 2**-7 (k*Ts = Ts = 2**23, "
             "h*Ts = 2**24 in Q1.30), lambda(0) = 0: xi = +/-64 moves lambda and nu by half a "
             "Q24 LSB, so lam_q24 = (lam + 2**29) >> 30 and the nu of h*Ts*nu round exact ties "
             "(toward +inf, also when negative: -0.5 LSB -> 0, -1.5 LSB -> -1); zero crossings "
             "never reset.", cfg("pi", ts=2.0 ** -7), 0,
             (64, 0, -64, -64, 0, -128, 0, 128, 64, 0, 192, -64, 0, 1, -1, 0, -192, 0, 64,
              -64, 2, -2, 0, 40000, -80000, 0)))

    add(Spec("reset_band", "Reset-PI, band 1678 LSB: a reset disarms; |xi| exactly at the band "
             "and just below never re-arm, just above (1679) does, on either side; sign changes "
             "inside the band while disarmed never reset; a crossing that leaves the band while "
             "disarmed re-arms but does not reset (the next crossing does); crossings to and "
             "from exactly 0 (+ -> 0 and - -> 0 are crossings, 0 -> +/- is not).",
             cfg("reset"), LAM0,
             (5000, 5000, -5000,            # crossing while armed: reset, disarmed
              b, -b, b, b - 1, -(b - 1), 0, -(b - 1),  # at / below the band: no re-arm
              b + 1,                        # crossing, disarmed: no reset; re-arms
              -(b + 1),                     # crossing, armed: reset
              3, -3, 0, 5, -7, 1,           # chatter inside the band: nothing
              -(b + 1),                     # crossing while disarmed: re-arms (negative side)
              -10,                          # no crossing; stays armed
              0,                            # - -> 0: crossing, reset
              0,                            # 0 -> 0: nothing
              2000,                         # 0 -> +: no crossing; re-arms
              0,                            # + -> 0: crossing, reset
              -2000,                        # 0 -> -: no crossing; re-arms
              2000,                         # crossing: reset
              -1, 1, -1, b,                 # disarmed: nothing
              -b - 1, -b - 1, 1)))          # re-arm, then a crossing: reset

    add(Spec("reset_band_zero", "Reset-PI with band 0: after a reset any nonzero |xi| re-arms, "
             "xi = 0 does not; 1-LSB sign changes.", cfg("reset", band=0.0), LAM0,
             (1000, -1, 1, -1, 0, 0, 1, -1, 0, 1, 0, -1, 2, -2)))

    add(Spec("reset_first_step", "Reset-PI: the start counts as a reset but leaves the band "
             "armed; xi_prev starts at 0, so the first step can never be a crossing; a crossing "
             "at step 1 (the earliest possible) resets.", cfg("reset"), LAM0,
             (-3000, 3000, 3000, -3000)))

    add(Spec("reset_first_zero", "Reset-PI starting with xi = 0: 0 -> 0 and 0 -> - are not "
             "crossings, - -> 0 is.", cfg("reset"), LAM0, (0, -5000, 0, 0, 5000, -5000)))

    add(Spec("dwell_first_step", "Dwell reset-PI, dwell = Ts (1 sample): a crossing at step 1 "
             "resets (since_reset = 1 >= 1).", cfg("dwell", dwell=0.01), LAM0,
             (-3000, 3000, -3000, -3000, 3000)))

    add(Spec("dwell_first_blocked", "Dwell reset-PI, dwell = 5 samples: a crossing at step 1 "
             "is blocked (since_reset = 1 < 5); the band stays armed, nu keeps integrating.",
             cfg("dwell", dwell=0.05), LAM0, (-3000, 3000, 3000, 3000, -3000, 3000)))

    e = 5000
    add(Spec("dwell_edges", "Dwell reset-PI, dwell = 5 samples (0.05 s / 0.01 s): a crossing "
             "one sample before the dwell time (since_reset = 4) is blocked, at the dwell time "
             "(since_reset = 5) it resets; after a reset the band still applies (a crossing "
             "after the dwell inside the band does not reset).",
             cfg("dwell", dwell=0.05), LAM0,
             (e, e, e, e, -e,                # step 4: since_reset = 4, blocked
              e,                             # step 5: since_reset = 5, reset
              e, e, e, -e,                   # since_reset = 4 again: blocked
              e,                             # since_reset = 5: reset
              e, e, e, e, e, -e,             # since_reset = 6: reset
              1, -1, 1, -1, 1, -1, 1,        # inside the band, past the dwell: no reset
              -e, e)))                       # re-armed: reset

    add(Spec("dwell_ceil", "Dwell reset-PI, dwell = 0.045 s at Ts = 0.01 s: rounded up to 5 "
             "samples (never shorter than asked); blocked at since_reset = 4, reset at 5.",
             cfg("dwell", dwell=0.045), LAM0, (e, e, e, e, -e, e, -e, -e, -e, -e, e)))

    # ---- saturation: gains at the top of the range make every term overflow
    big = {"k": 1.5, "h": 1.5, "ts": 1.0}  # k*Ts = h*Ts = 1.5 (Q30 1610612736), Ts = 1
    add(Spec("sat_pc", "Proportional, k*Ts = 1.5: lambda runs into both limits of the state "
             "(the Q54 image of int32), dlam saturates (counted), lambda + dlam saturates "
             "(counted).",
             cfg("pc", **big), 0,
             (ONE, ONE, MAX, MIN, MIN, MIN, 1, -1, MAX, 0, MIN)))

    add(Spec("sat_pc_negation", "Proportional, k*Ts = 1 exactly (2**30): xi = INT32_MIN "
             "gives k*Ts*xi = -2**61 and its negation 2**61 saturates to INT32_MAX*2**30; "
             "lambda starts at INT32_MAX.",
             cfg("pc", k=100.0, ts=0.01), MAX, (MIN, MIN, MAX, MAX, 0, -ONE, 0)))

    add(Spec("sat_pi", "PI, k*Ts = h*Ts = 1.5, Ts = 1: dlam, nu and lambda all saturate, up "
             "to three counts in one step; nu at both limits.",
             cfg("pi", **big), 0,
             (MAX, MAX, MAX, MIN, MIN, MIN, MIN, 0, 1, -1, MAX, MAX, MAX, 0)))

    add(Spec("sat_reset", "Reset-PI, k*Ts = h*Ts = 1.5, Ts = 1: saturated nu is "
             "reset to 0 at a crossing; lambda saturates at both limits.",
             cfg("reset", **big), 0,
             (MAX, MAX, MAX, MIN, MIN, MAX, MAX, MIN, -ONE, ONE, 0, MIN, MIN, MAX)))

    add(Spec("sat_dwell", "Dwell reset-PI, k*Ts = h*Ts = 1.5, Ts = 1, dwell 3 samples: "
             "saturated nu survives a dwell-blocked crossing, is reset by the next one.",
             cfg("dwell", dwell=3.0, **big), MIN,
             (MIN, MIN, MAX, MIN, MIN, MIN, MIN, MAX, MAX, MAX, MIN)))

    add(Spec("sat_ft", "Finite-time, k*Ts = 1.9, a = 15/16: |xi|**a of the int32 extremes "
             "(|INT32_MIN| = 2**31 does not fit an int32: take it in 64 bits), dlam and lambda "
             "saturate.", cfg("ft", k=1.9, h=1.0, ts=1.0, ft_exponent=0.9375), 0,
             (MIN, MIN, MAX, MAX, MAX, 1, -1, ONE, -ONE, 0)))

    add(Spec("sat_lambda0", "Reset-PI at the default gains starting from lambda = INT32_MIN: "
             "lambda stays pinned at the limit while xi pushes down (counted every step).",
             cfg("reset"), MIN, (ONE, ONE, MAX, MAX, -ONE, MIN, MIN, ONE)))

    # ---- finite time: the fractional power |ξ|**(p/2**n) for several exponents
    mags = [1, 2, 3, 4, 5, 15, 16, 17, 255, 256, 1677, 1678, 1679, (1 << 20) - 1, 1 << 20,
            ONE - 1, ONE, ONE + 1, 3 * ONE, 1 << 30, MAX]
    pairs = [v for m in mags for v in (m, -m)] + [MIN, 0, MAX]
    for a in (0.5, 0.75, 0.0625, 0.9375):
        label = f"{a:g}".replace(".", "p")
        add(Spec(f"ft_pow_{label}", f"Finite-time, exponent {a:g} (|xi|**a by "
                 "integer square roots and products), k*Ts = 1 so dlam = -sign(xi)*|xi|**a "
                 "(times 2**30); "
                 "+v, -v pairs bring lambda back.",
                 cfg("ft", k=50.0, ts=0.02, ft_exponent=a), 0, tuple(pairs)))
    add(Spec("ft_default", "Finite-time at the default gains (k = 1, Ts = 0.01, a = 0.5): the "
             "product k*Ts*|xi|**a, exact in Q54.", cfg("ft"), LAM0, tuple(pairs)))
    return specs


WALK_STEPS = 2000
WALK_STRIDE, WALK_BOUND = 600, 3000  # LSB: the walk straddles the default band (1678)

WALKS: tuple[tuple[str, ControllerConfig, int], ...] = (
    ("pc", cfg("pc", k=2.0), 1),
    ("pi", cfg("pi"), 2),
    ("reset", cfg("reset", k=1.5, h=3.0, ts=0.02), 3),
    ("dwell", cfg("dwell", dwell=0.25, band=5e-5), 4),
    ("ft", cfg("ft", ft_exponent=0.75), 5),
)


def walk_specs() -> list[Spec]:
    return [Spec(f"walk_{kind}", f"Seeded random walk of xi ({WALK_STEPS} steps): "
                 f"xi(t) = xi(t-1) + (r(t) mod {2 * WALK_STRIDE + 1}) - {WALK_STRIDE}, "
                 f"xi(-1) = 0, reflected at +/-{WALK_BOUND} LSB; r(t) is the t-th output of "
                 f"splitmix64 seeded with {seed}.",
                 config, 0, random_walk(seed, WALK_STEPS, WALK_STRIDE, WALK_BOUND))
            for kind, config, seed in WALKS]


CASE = 1
CASE_AGENT = 1     # the centre of case 1's star, the only agent that hears the price
CASE_STEPS = 500   # 5 s: the transient and its resets (the tail is a slow creep)
CASE_KINDS: tuple[tuple[str, dict[str, float]], ...] = (
    ("reset", {}), ("pc", {}), ("pi", {}), ("dwell", {"dwell": 0.5}), ("ft", {}))


def case_specs() -> list[Spec]:
    from sim.model.lockstep import run_lockstep
    from sim.model.scenario import load_case

    base = load_case(CASE)
    specs = []
    for kind, extra in CASE_KINDS:
        sc = base.with_controller(kind=kind, **extra)
        args = ", ".join(f"{k}={v!r}" for k, v in {"kind": kind, **extra}.items())
        traj = run_lockstep(sc)
        if traj.xi is None:
            raise AssertionError("run_lockstep recorded no ξ")
        i = CASE_AGENT - 1
        xis = tuple(q24(float(x)) for x in traj.xi[:CASE_STEPS, i])
        lam0 = q24(float(traj.lam[0, i]))
        spec = Spec(f"case{CASE}_{kind}", f"Realistic closed-loop xi: agent {CASE_AGENT} of "
                    f"case {CASE} under the {kind} controller, the first {CASE_STEPS} samples "
                    f"({CASE_STEPS * sc.ts:g} s).", sc.controller, lam0, xis,
                    source=f"sim.model.lockstep.run_lockstep(sim.model.scenario.load_case({CASE})"
                           f".with_controller({args})).xi[:{CASE_STEPS}, {i}]")
        # the replay must be the lockstep run's own agent, bit for bit
        lam = [row[FIELDS.index("lam_q24")] for row in run(spec)["steps"]]
        ref = [q24(float(x)) for x in traj.lam[1:CASE_STEPS + 1, i]]
        if lam != ref:
            raise AssertionError(f"{spec.name}: replay does not match the lockstep λ")
        specs.append(spec)
    return specs


SPEC_SETS: tuple[Callable[[], list[Spec]], ...] = (edge_specs, walk_specs, case_specs)


def render_all() -> dict[str, str]:
    """File name → text of every vector, exactly as committed."""
    out: dict[str, str] = {}
    for make in SPEC_SETS:
        for spec in make():
            name = f"{spec.name}.json"
            if name in out:
                raise ValueError(f"two vectors named {spec.name}")
            out[name] = to_json(run(spec))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("-o", "--output", type=Path, default=DEFAULT_OUTPUT,
                   help="directory of the vectors (default: tests/vectors/controller)")
    p.add_argument("--node-output", type=Path, default=None,
                   help="directory of the node vectors (tools/gen_node_vectors.py; default: "
                        "tests/vectors/node, or none when -o names another directory)")
    p.add_argument("--check", action="store_true",
                   help="do not write; exit 1 if the directory differs from the generator")
    args = p.parse_args(argv)
    node_out = args.node_output
    if node_out is None and args.output.resolve() == DEFAULT_OUTPUT.resolve():
        node_out = NODE_OUTPUT
    rc = _controller_main(args)
    if node_out is not None:
        rc |= _node_main(node_out, args.check)
    if rc:
        sys.stderr.write("run python tools/gen_vectors.py\n")
    return rc


def _node_main(out: Path, check: bool) -> int:
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "gen_node_vectors", Path(__file__).with_name("gen_node_vectors.py"))
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return write_or_check(mod.render_all(), out, check)


def _controller_main(args: argparse.Namespace) -> int:
    return write_or_check(render_all(), args.output, args.check)


def write_or_check(files: dict[str, str], out: Path, check: bool) -> int:
    """Write ``files`` into ``out`` (removing stale *.json), or with ``check`` report
    every file that differs, is missing or extra and return 1 (controller and node
    vectors alike)."""
    present = {f.name for f in out.glob("*.json")} if out.is_dir() else set()
    if check:
        stale = sorted(n for n, text in files.items()
                       if n not in present or (out / n).read_bytes() != text.encode("ascii"))
        extra = sorted(present - files.keys())
        for n in stale:
            sys.stderr.write(f"{out / n} is stale or missing\n")
        for n in extra:
            sys.stderr.write(f"{out / n} is not produced by the generator\n")
        return 1 if stale or extra else 0
    out.mkdir(parents=True, exist_ok=True)
    for n in sorted(present - files.keys()):
        (out / n).unlink()
    for n, text in files.items():
        (out / n).write_bytes(text.encode("ascii"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
