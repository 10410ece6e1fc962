"""Golden vectors of the controller core (tests/vectors/controller, tools/gen_vectors.py).

Every vector is replayed through firmware_py's fixed-point controller and must match to
the last bit: the integer constants, the initial state and, at every step, every field of
the step output and the state. The first difference fails naming the vector, the step
and the field. The set itself is checked too: it is what the generator produces now, it
stays under its size budget, and it still covers the edge cases it was made for (counted
from the vectors, so a regenerated set that loses one fails here).
"""

from __future__ import annotations

import copy
import json
import runpy
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from firmware_py import fixedpoint as fx
from firmware_py.controllers import (
    KINDS,
    Controller,
    ControllerConfig,
    ControllerState,
    FixedArithmetic,
    StepOutput,
    make_controller,
)

ROOT = Path(__file__).resolve().parent.parent
VECTOR_ROOT = ROOT / "tests" / "vectors"
VECTOR_DIR = VECTOR_ROOT / "controller"
GEN_VECTORS = ROOT / "tools" / "gen_vectors.py"
VECTORS = sorted(VECTOR_DIR.glob("*.json"))

FORMAT = "bess-ded controller vector 2"
FIELDS = ["xi", "dlam", "reset", "lam", "nu", "lam_q24", "armed", "since_reset", "resets",
          "saturations"]
STATE_FIELDS = ["lam", "nu", "lam_q24", "xi_prev", "armed", "since_reset", "resets",
                "saturations"]
SIZE_BUDGET = 1024 * 1024  # bytes, tests/vectors/ but node/ (Q54 state: ~19 digits)
LONG = 2000               # steps of a "long" vector (the random walks)


class VectorMismatch(AssertionError):
    pass


def load(path: Path) -> dict[str, Any]:
    vec: dict[str, Any] = json.loads(path.read_text(encoding="ascii"))
    return vec


def constants(c: Controller) -> dict[str, int]:
    assert isinstance(c.ar, FixedArithmetic)
    return {"q": c.ar.q, "qc": fx.QC, "guard": fx.GUARD, "kts": int(c.kts),
            "hts": int(c.hts), "ts": int(c.ts_q), "band": int(c.band),
            "dwell_samples": c.dwell_samples,
            "pow_num": c.ar.pow_num, "pow_sqrts": c.ar.pow_sqrts}


def state_fields(c: Controller, s: ControllerState) -> dict[str, Any]:
    return {"lam": s.lam, "nu": s.nu, "lam_q24": c.wire_lambda(s), "xi_prev": s.xi_prev,
            "armed": s.armed, "since_reset": s.since_reset, "resets": s.resets,
            "saturations": s.saturations}


def step_fields(c: Controller, xi: int, o: StepOutput, s: ControllerState) -> dict[str, Any]:
    return {"xi": xi, "dlam": o.dlam, "reset": o.reset, **state_fields(c, s)}


def _same(want: Any, got: Any) -> bool:
    """Exact integer equality (the controller's booleans are compared as 0/1)."""
    return type(want) is int and type(got) is int and want == got


def replay(vec: dict[str, Any]) -> None:
    """Run one vector through firmware_py; raise VectorMismatch at the first difference."""
    name = vec["name"]

    def check(where: str, field: str, want: Any, got: Any) -> None:
        got = int(got) if isinstance(got, bool) else got
        if not _same(want, got):
            raise VectorMismatch(f"{name}: {where}: field {field}: the vector has {want!r}, "
                                 f"firmware_py computes {got!r}")

    if vec["format"] != FORMAT:
        raise VectorMismatch(f"{name}: format {vec['format']!r}, expected {FORMAT!r}")
    if vec["fields"] != FIELDS:
        raise VectorMismatch(f"{name}: fields {vec['fields']}, expected {FIELDS}")
    c = make_controller(ControllerConfig(**vec["config"]), fixed=True)
    fixed = constants(c)
    if set(vec["fixed"]) != set(fixed):
        raise VectorMismatch(f"{name}: fixed constants {sorted(vec['fixed'])}, "
                             f"expected {sorted(fixed)}")
    for field, got in fixed.items():
        check("fixed", field, vec["fixed"][field], got)
    s = c.initial_state(vec["lambda0"] / fx.ONE)
    check("initial state", "lambda0", vec["lambda0"], c.wire_lambda(s))
    if list(vec["initial"]) != STATE_FIELDS:
        raise VectorMismatch(f"{name}: initial state fields {list(vec['initial'])}, "
                             f"expected {STATE_FIELDS}")
    for field, got in state_fields(c, s).items():
        check("initial state", field, vec["initial"][field], got)
    for t, row in enumerate(vec["steps"]):
        if len(row) != len(FIELDS):
            raise VectorMismatch(f"{name}: step {t}: {len(row)} values, expected {len(FIELDS)}")
        xi = row[0]
        s, o = c.step(s, xi)
        out = step_fields(c, xi, o, s)
        for field, want in zip(FIELDS, row, strict=True):
            check(f"step {t}", field, want, out[field])
        check(f"step {t}", "xi_prev", xi, s.xi_prev)  # not repeated in the row: = xi


# --------------------------------------------------------------------------- replay




@pytest.mark.parametrize("path", VECTORS, ids=[p.stem for p in VECTORS])
def test_vector_replays_bit_for_bit(path: Path) -> None:
    vec = load(path)
    assert vec["name"] == path.stem, f"{path.name} holds the vector {vec['name']!r}"
    replay(vec)


@pytest.mark.parametrize(("step", "field", "delta"), [
    (11, "reset", -1), (11, "nu", 1), (3, "lam", -1), (12, "saturations", 1), (30, "armed", -1),
])
def test_replay_names_vector_step_and_field_of_the_first_difference(
        step: int, field: str, delta: int) -> None:
    vec = copy.deepcopy(load(VECTOR_DIR / "reset_band.json"))
    vec["steps"][step][FIELDS.index(field)] += delta
    vec["steps"][step + 1][FIELDS.index("lam")] += 7  # a later difference is not reported
    with pytest.raises(VectorMismatch, match=rf"^reset_band: step {step}: field {field}: "):
        replay(vec)


def test_replay_checks_the_constants() -> None:
    vec = copy.deepcopy(load(VECTOR_DIR / "pc_steps.json"))
    vec["fixed"]["kts"] += 1
    with pytest.raises(VectorMismatch, match=r"^pc_steps: fixed: field kts: "):
        replay(vec)


# --------------------------------------------------------------------------- generator


@pytest.fixture(scope="module")
def gen() -> dict[str, Any]:
    return runpy.run_path(str(GEN_VECTORS))  # run_name is not __main__: nothing is written


def test_the_vectors_are_exactly_the_generators_list(gen: dict[str, Any]) -> None:
    """One file per vector the generator's spec sets name (edge cases, random walks, case
    runs), no more and no fewer."""
    names = [spec.name for make in gen["SPEC_SETS"] for spec in make()]
    assert len(names) == len(set(names))
    assert [p.stem for p in VECTORS] == sorted(names)


def test_committed_vectors_are_up_to_date_with_generator(gen: dict[str, Any]) -> None:
    assert gen["main"](["--check"]) == 0, \
        "tests/vectors/controller is stale: run python tools/gen_vectors.py"


def test_generator_check_finds_stale_missing_and_extra_files(
        gen: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "controller"
    assert gen["main"](["-o", str(out)]) == 0
    written = sorted(p.name for p in out.glob("*.json"))
    assert written == [p.name for p in VECTORS]
    (out / "pc_steps.json").write_text(
        (out / "pc_steps.json").read_text().replace("[1,-10737418,", "[1,-10737417,", 1))
    (out / "dwell_edges.json").unlink()
    (out / "old_vector.json").write_text("{}")
    capsys.readouterr()
    assert gen["main"](["--check", "-o", str(out)]) == 1
    assert capsys.readouterr().err == (
        f"{out / 'dwell_edges.json'} is stale or missing\n"
        f"{out / 'pc_steps.json'} is stale or missing\n"
        f"{out / 'old_vector.json'} is not produced by the generator\n"
        "run python tools/gen_vectors.py\n")
    assert gen["main"](["-o", str(out)]) == 0  # rewrites, and removes what it no longer makes
    assert sorted(p.name for p in out.glob("*.json")) == written


def test_vector_set_stays_small() -> None:
    size = sum(p.stat().st_size for p in VECTOR_ROOT.rglob("*")
               if p.is_file() and "node" not in p.relative_to(VECTOR_ROOT).parts)
    assert size <= SIZE_BUDGET, f"tests/vectors/ holds {size} bytes (budget {SIZE_BUDGET})"


# --------------------------------------------------------------------------- coverage


def crossed(prev: int, xi: int) -> bool:
    """Discrete zero crossing (controllers.py): > 0 to ≤ 0, or < 0 to ≥ 0."""
    return (prev > 0 and xi <= 0) or (prev < 0 and xi >= 0)


def tie(x: int) -> bool:
    """A state word lies exactly half-way between two Q24 values (its rounding ties)."""
    return x % (1 << fx.GUARD) == 1 << (fx.GUARD - 1)


def features(vec: dict[str, Any]) -> Iterator[str]:
    """The edge cases one vector exercises, computed from its rows alone."""
    kind, f = vec["config"]["kind"], vec["fixed"]
    band, dwell = f["band"], f["dwell_samples"]
    resetting = kind in ("reset", "dwell")
    integrating = kind in ("pi", "reset", "dwell")
    yield f"kind {kind}"
    if len(vec["steps"]) >= LONG:
        yield f"long {kind}"
    if "run_lockstep" in vec.get("source", ""):
        yield f"lockstep {kind}"
    if kind == "ft":
        yield f"ft exponent {f['pow_num']}/{1 << f['pow_sqrts']}"
    prev = dict(vec["initial"])
    for t, row in enumerate(vec["steps"]):
        r = dict(zip(FIELDS, row, strict=True))
        xi, xi_prev = r["xi"], prev["xi_prev"]
        cross = crossed(xi_prev, xi)
        if xi == fx.INT32_MIN:
            yield "xi = INT32_MIN"
        if tie(r["lam"]):
            yield f"{'negative' if r['lam'] < 0 else 'positive'} tie lam_q24"
        nu_used = 0 if r["reset"] else prev["nu"]
        if integrating and tie(nu_used):
            yield f"{'negative' if nu_used < 0 else 'positive'} tie of nu in h*Ts*nu"
        if r["reset"]:
            yield "reset"
            if t == 1:
                yield "reset at the first possible step"
            if xi == 0:
                yield "crossing to exactly 0 resets"
            if kind == "dwell" and prev["since_reset"] == dwell > 1:
                yield "dwell: reset exactly at the dwell time"
        if resetting and xi_prev == 0 and xi != 0 and prev["armed"] and not r["reset"]:
            yield "0 -> nonzero is no crossing"
        if kind == "dwell" and cross and prev["armed"] and not r["reset"]:
            yield "dwell-blocked crossing"
            if prev["since_reset"] == dwell - 1:
                yield "dwell: blocked one sample before the dwell time"
        if resetting and cross and not prev["armed"] and not r["reset"]:
            yield "crossing while disarmed"
        if resetting and not prev["armed"] and not r["reset"]:
            if r["armed"]:
                yield "band re-arm"
                if abs(xi) == band + 1:
                    yield "band: just above re-arms"
            elif abs(xi) == band > 0:
                yield "band: exactly at the band does not re-arm"
            elif abs(xi) == band - 1 > 0:
                yield "band: just below does not re-arm"
        if band == 0 and resetting and xi == 0 and not prev["armed"] and not r["reset"]:
            yield "band 0: xi = 0 does not re-arm"
        grew = r["saturations"] - prev["saturations"]
        if grew:
            yield "saturation"
        if grew >= 3:
            yield "three saturations in one step"
        for field in ("lam", "nu", "dlam"):
            if r[field] == fx.STATE_MAX:
                yield f"{field} = STATE_MAX"
            if r[field] == fx.STATE_MIN:
                yield f"{field} = STATE_MIN"
        prev = {**prev, **{k: r[k] for k in STATE_FIELDS if k in r}, "xi_prev": xi}


REQUIRED = (
    [f"kind {k}" for k in KINDS] + [f"long {k}" for k in KINDS]
    + [f"lockstep {k}" for k in KINDS]
    + [f"ft exponent {e}" for e in ("1/2", "3/4", "1/16", "15/16")]
    + ["reset", "reset at the first possible step", "crossing to exactly 0 resets",
       "0 -> nonzero is no crossing", "crossing while disarmed",
       "dwell-blocked crossing", "dwell: blocked one sample before the dwell time",
       "dwell: reset exactly at the dwell time",
       "band re-arm", "band: just above re-arms", "band: exactly at the band does not re-arm",
       "band: just below does not re-arm", "band 0: xi = 0 does not re-arm",
       "saturation", "three saturations in one step", "xi = INT32_MIN",
       "negative tie lam_q24", "positive tie lam_q24", "negative tie of nu in h*Ts*nu",
       "positive tie of nu in h*Ts*nu"]
    + [f"{f} = {lim}" for f in ("lam", "nu", "dlam") for lim in ("STATE_MAX", "STATE_MIN")]
)


def test_vector_set_covers_every_kind_and_edge_case() -> None:
    found: dict[str, list[str]] = {}
    for path in VECTORS:
        for feature in set(features(load(path))):
            found.setdefault(feature, []).append(path.stem)
    missing = [f for f in REQUIRED if f not in found]
    assert not missing, f"no vector covers: {missing}"
    # the long vectors of the resetting kinds exercise the reset logic many times, not once
    for kind in ("reset", "dwell"):
        for stem in found[f"long {kind}"]:
            resets = load(VECTOR_DIR / f"{stem}.json")["steps"][-1][FIELDS.index("resets")]
            assert resets >= 10, f"{stem}: only {resets} resets"
