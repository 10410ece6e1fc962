"""The C controller core (firmware_c/) against firmware_py, bit for bit.

* the build: firmware_c/Makefile with -std=c99 -Wall -Wextra -Werror -pedantic
  -Wconversion …, no compiler output at all;
* every controller vector (tests/vectors/controller) replays through the C core, every
  field of every step, through the step interface and the batch ``bd_ctrl_run``;
* hypothesis: ≥ 100,000 random steps per kind against firmware_py's fixed Controller
  (random integer constants over their whole valid range and at their edges, ξ sequences
  with INT32_MIN/MAX, ±band, ±1, 0 and random walks), and the arithmetic helpers and ξ
  (XI-2, XI-3) against firmware_py's.

* the same vectors through firmware_c/tools/vector_runner.c, natively and cross-built
  for arm-linux-gnueabihf under qemu-arm; the arm-none-eabi (Cortex-M4, -Os) size of the
  core; cppcheck clean.

Needs ``make`` and a C compiler, and for the cross tier gcc-arm-linux-gnueabihf,
qemu-user, gcc-arm-none-eabi and cppcheck (tools/install-c-deps): skipped without them,
except under CI (env ``CI`` set), where that fails.
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import random
import re
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_py import fixedpoint as fx
from firmware_py.controllers import (
    KINDS,
    Controller,
    ControllerConfig,
    ControllerState,
    FixedArithmetic,
    StepOutput,
    consensus_error,
    make_controller,
)
from sim.cbind import cimpl

ROOT = Path(__file__).resolve().parent.parent
SOURCE = ROOT / "firmware_c"   # this checkout's, whichever sim/ is imported
VECTORS = sorted((ROOT / "tests" / "vectors" / "controller").glob("*.json"))
FIELDS = ["xi", "dlam", "reset", "lam", "nu", "lam_q24", "armed", "since_reset", "resets",
          "saturations"]
I32_MIN, I32_MAX = fx.INT32_MIN, fx.INT32_MAX

STEPS_PER_EXAMPLE = 300
EXAMPLES_PER_KIND = 350          # × 300 = 105,000 steps per kind
STEPS_RUN: Counter[str] = Counter()
EVENTS: Counter[tuple[str, str]] = Counter()   # what the random steps exercised


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def _need(*tools: str) -> None:
    """Skip (fail under CI) unless every tool is on PATH."""
    missing = [t for t in tools if shutil.which(t) is None]
    if missing:
        reason = f"{', '.join(missing)} missing (tools/install-c-deps)"
        if _in_ci():
            pytest.fail(f"{reason}; CI must run the C tier", pytrace=False)
        pytest.skip(reason)


def _make(build: Path, target: str) -> str:
    proc = subprocess.run(["make", "-s", "-C", str(SOURCE), f"BUILD={build}",
                           f"PYTHON={sys.executable}", target],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 0, f"make {target}:\n{proc.stdout}{proc.stderr}"
    assert proc.stderr.strip() == "", proc.stderr
    return proc.stdout


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A fresh build of firmware_c (not the cache): (library, make's output)."""
    _need("make", os.environ.get("CC", "cc"))
    out = tmp_path_factory.mktemp("firmware_c")
    lib = cimpl.build(out, source_dir=SOURCE)
    log = (out / "build.log")
    proc = subprocess.run(["make", "-C", str(SOURCE), f"BUILD={out}", f"PYTHON={sys.executable}",
                           "-B", "all"],
                          capture_output=True, text=True, check=True)
    log.write_text(proc.stdout + proc.stderr)
    return lib, proc.stderr


@pytest.fixture(scope="module")
def core(built: tuple[Path, str]) -> cimpl.CCore:
    if os.environ.get(cimpl.LIB_DIR_ENV):   # tools/c_coverage.py's instrumented build
        return cimpl.load()
    return cimpl.load(built[0])


# --------------------------------------------------------------------------- the build


def test_build_is_warning_free_under_werror(built: tuple[Path, str]) -> None:
    lib, stderr = built
    assert lib.exists()
    assert stderr.strip() == "", f"the compiler said something:\n{stderr}"
    makefile = (SOURCE / "Makefile").read_text()
    for flag in ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Wconversion"):
        assert flag in makefile, flag


# the firmware proper: no floating point, no heap (the host-side loader toml.c, config.c,
# keyfile.c and the Linux program main_agent.c/linux_socketcan.c are not part of it)
FIRMWARE = ("controller", "agent", "agent_rx", "agent_rules", "agent_diag", "agent_internal",
            "frames", "secoc", "node", "frame", "platform")


def test_core_has_no_floating_point_and_no_heap() -> None:
    files = [p for p in cimpl.sources(SOURCE) if p.suffix in (".c", ".h")
             and p.stem in FIRMWARE]
    assert len(files) >= 15
    text = "".join(p.read_text() for p in files)
    code = re.sub(r"/\*.*?\*/", "", text, flags=re.S)  # comments may say "floating point"
    for word in ("float", "double", "malloc", "calloc", "realloc", "free", "math", "sqrt"):
        assert not re.search(rf"\b{word}\b", code), word


def test_a_warning_fails_the_build(tmp_path: Path, built: tuple[Path, str]) -> None:
    src = tmp_path / "src"
    shutil.copytree(SOURCE / "include", tmp_path / "include")
    src.mkdir()
    shutil.copy(SOURCE / "Makefile", tmp_path / "Makefile")
    text = (SOURCE / "src" / "controller.c").read_text()
    (src / "controller.c").write_text(text + "\nint bd_narrowing(int64_t x);\n"
                                      "int bd_narrowing(int64_t x) { return x; }\n")
    with pytest.raises(cimpl.CBuildError, match="conversion"):
        cimpl.build(tmp_path / "out", source_dir=tmp_path)


def test_the_build_runs_the_generator_with_this_interpreter(tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch
                                                            ) -> None:
    """gen_contract.py imports cantools: the build runs it with sys.executable, not the
    first `python3` on PATH (an IDE or tox running venv/bin/python without activating the
    venv finds another one): here a python3 on PATH that fails whenever it runs."""
    _need("make")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "python3"
    fake.write_text("#!/bin/sh\necho 'not the interpreter bess-ded runs under' >&2\nexit 97\n")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    assert subprocess.run(["python3", "-c", ""], check=False).returncode == 97
    cimpl.build(tmp_path / "out", source_dir=SOURCE, target="gen")
    assert "generated" in (tmp_path / "out" / "gen" / "bd_contract.h").read_text().lower()
    assert f"PYTHON={sys.executable}" in cimpl.make_argv(SOURCE, tmp_path, "all")


def test_binding_builds_into_its_cache_on_first_use(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch,
                                                    built: tuple[Path, str]) -> None:
    if cimpl.SOURCE_DIR.resolve() != SOURCE.resolve():
        pytest.skip("sim/ is imported from an installed copy, not this checkout")
    monkeypatch.setenv("BESSDED_C_CACHE", str(tmp_path))
    monkeypatch.delenv(cimpl.LIB_DIR_ENV, raising=False)   # tools/c_coverage.py sets it
    monkeypatch.setattr(cimpl, "_CORE", None)
    core = cimpl.load()
    assert core.path.parent.parent == tmp_path and core.path.exists()
    assert cimpl.load() is core
    assert [p.name for p in tmp_path.iterdir()] == [core.path.parent.name]  # no leftovers
    c = cimpl.CController.from_config(ControllerConfig(kind="pi"))
    assert c.step(c.initial_state(0.5), 1000)[0].nu == 1000 * c.ts_q


def test_an_installed_copy_builds_the_c_agent(installed_site: Path) -> None:
    """`pip install .` carries firmware_c/ (sources, Makefile, generator) beside
    firmware_py/ and dbc/ (pyproject package data), so `bess-ded case N --impl c` and
    `up --agent-impl c` build the C agent from site-packages too: the wheel holds every
    file the cache key hashes, and its unpacked copy builds the library and the node
    program under -Werror with no file of this checkout."""
    site = installed_site
    tmp_path = site.parent
    installed = site / "firmware_c"
    shipped = {p.relative_to(site) for p in cimpl.sources(installed)}
    assert shipped == {p.relative_to(ROOT) for p in cimpl.sources(SOURCE)}
    assert all((site / p).is_file() for p in shipped)
    out = tmp_path / "build"
    subprocess.run(["make", "-s", "-C", str(installed), f"BUILD={out}",
                    f"PYTHON={sys.executable}", "all"], check=True,
                   capture_output=True, env={**os.environ, "PYTHONPATH": ""})
    assert (out / "libbessded.so").is_file() and (out / "bessded-agent").is_file()
    assert "generated" in (out / "gen" / "bd_contract.h").read_text().lower()


# --------------------------------------------------------------------------- vectors


def _fields(c: Any, s: ControllerState, o: StepOutput | None = None) -> dict[str, int]:
    out = {"lam": int(s.lam), "nu": int(s.nu), "lam_q24": int(c.wire_lambda(s)),
           "xi_prev": int(s.xi_prev), "armed": int(s.armed), "since_reset": s.since_reset,
           "resets": s.resets, "saturations": s.saturations}
    if o is not None:
        out |= {"dlam": int(o.dlam), "reset": int(o.reset)}
    return out


def _from_vector(vec: dict[str, Any], core: cimpl.CCore) -> cimpl.CController:
    f = vec["fixed"]
    assert (f["q"], f["qc"], f["guard"]) == (24, 30, 30)
    return cimpl.CController(vec["config"]["kind"], f["kts"], f["hts"], f["ts"], f["band"],
                             f["dwell_samples"], f["pow_num"], f["pow_sqrts"], core=core)


def replay(vec: dict[str, Any], core: cimpl.CCore) -> int:
    """Replay one vector through the C core; the steps checked. Fails at the first
    difference naming the vector, the step and the field."""
    name = vec["name"]
    assert vec["format"] == "bess-ded controller vector 2"
    assert vec["fields"] == FIELDS
    c = _from_vector(vec, core)
    s = c.initial_state(vec["lambda0"] / fx.ONE)
    got = _fields(c, s)
    for field, want in vec["initial"].items():
        assert got[field] == want, f"{name}: initial state: field {field}"
    xis = [row[0] for row in vec["steps"]]
    batch = c.run(s, xis)
    for t, row in enumerate(vec["steps"]):
        s, o = c.step(s, row[0])
        got = _fields(c, s, o) | {"xi": row[0]}
        for field, want in zip(FIELDS, row, strict=True):
            assert got[field] == want, (f"{name}: step {t}: field {field}: the vector has "
                                        f"{want}, the C core computes {got[field]}")
        assert s.xi_prev == row[0], f"{name}: step {t}: xi_prev"
        assert batch[t] == (s, o), f"{name}: step {t}: bd_ctrl_run differs from bd_ctrl_step"
    return len(vec["steps"])


def test_there_are_vectors_of_every_kind() -> None:
    kinds = {json.loads(p.read_text())["config"]["kind"] for p in VECTORS}
    assert kinds == set(KINDS)


@pytest.mark.parametrize("path", VECTORS, ids=[p.stem for p in VECTORS])
def test_vector_replays_bit_for_bit_in_c(path: Path, core: cimpl.CCore) -> None:
    assert replay(json.loads(path.read_text(encoding="ascii")), core) > 0


def test_from_config_derives_the_vectors_constants(core: cimpl.CCore) -> None:
    for path in VECTORS:
        vec = json.loads(path.read_text(encoding="ascii"))
        c = cimpl.CController.from_config(ControllerConfig(**vec["config"]), core=core)
        f = vec["fixed"]
        assert (c.kts, c.hts, c.ts_q, c.band, c.dwell_samples) == (
            f["kts"], f["hts"], f["ts"], f["band"], f["dwell_samples"]), path.stem
        if vec["config"]["kind"] == "ft":
            assert cimpl.exponent_parts(vec["config"]["ft_exponent"]) == (
                f["pow_num"], f["pow_sqrts"])


# --------------------------------------------------------------------------- helpers


def test_helpers_by_hand(core: cimpl.CCore) -> None:
    lib = core.lib
    # NUM-2 examples
    assert lib.bd_mulq(3, 1 << 23) == 2 and lib.bd_mulq(-3, 1 << 23) == -1
    assert lib.bd_mulq(167772, 1 << 21) == 20972
    assert lib.bd_mulq(-167772, 1 << 21) == -20971
    # NUM-8 examples and the extremes
    for x, w in ((1 << 29, 1), (-(1 << 29), 0), (3 << 29, 2), (-3 * (1 << 29), -1),
                 ((1 << 29) - 1, 0), (fx.STATE_MAX, I32_MAX), (fx.STATE_MIN, I32_MIN)):
        assert lib.bd_wire(x) == w, x
    assert lib.bd_shr_floor(-(1 << 63), 62) == -2
    assert lib.bd_shr_floor(-1, 62) == -1
    assert lib.bd_isqrt_u64((1 << 64) - 1) == (1 << 32) - 1


@settings(max_examples=2000, deadline=None)
@given(x=st.integers(-(1 << 63), (1 << 63) - 1), n=st.integers(0, 62),
       u=st.one_of(st.integers(0, (1 << 64) - 1), st.integers(0, 1 << 56),
                   st.integers(0, 1 << 20).map(lambda r: r * r - 1).filter(lambda v: v >= 0)))
def test_helpers_match_python(core: cimpl.CCore, x: int, n: int, u: int) -> None:
    lib = core.lib
    assert lib.bd_shr_floor(x, n) == x >> n
    assert lib.bd_isqrt_u64(u) == math.isqrt(u)
    sats = cimpl.ctypes.c_uint32(0)
    want, flag = fx.saturate_state(x)
    assert lib.bd_sat54(x, cimpl.ctypes.byref(sats)) == want and sats.value == flag
    sats.value = 0
    want, flag = fx.saturate(x)
    assert lib.bd_sat32(x, cimpl.ctypes.byref(sats)) == want and sats.value == flag
    s, _ = fx.saturate_state(x)
    assert lib.bd_wire(s) == fx.narrow(s)
    a, b = x >> 32, (x & 0xFFFFFFFF) - (1 << 31)   # two int32s
    assert lib.bd_mulq(a, b) == fx.mul(a, b)


@settings(max_examples=1000, deadline=None)
@given(v=st.one_of(st.integers(I32_MIN, I32_MAX), st.sampled_from([I32_MIN, I32_MAX, 0, 1, -1])),
       n=st.integers(1, 4), data=st.data())
def test_fpow_matches_python(core: cimpl.CCore, v: int, n: int, data: st.DataObject) -> None:
    p = data.draw(st.integers(0, (1 << (n - 1)) - 1)) * 2 + 1
    assert core.lib.bd_fpow(v, p, n) == FixedArithmetic(exponent=p / (1 << n)).frac_pow(v)


NEIGHBOUR = st.tuples(
    st.one_of(st.integers(fx.to_fixed(0.001), fx.to_fixed(100.0)),
              st.sampled_from([fx.to_fixed(0.001), fx.to_fixed(100.0), fx.ONE])),
    st.one_of(st.integers(I32_MIN, I32_MAX), st.sampled_from([I32_MIN, I32_MAX, 0])))


@settings(max_examples=1500, deadline=None)
@given(lam=st.one_of(st.integers(I32_MIN, I32_MAX), st.sampled_from([I32_MIN, I32_MAX, 0])),
       pin=st.sampled_from([0, fx.ONE]), rho=st.integers(I32_MIN, I32_MAX),
       nbrs=st.lists(NEIGHBOUR, max_size=31))
def test_xi_matches_consensus_error(core: cimpl.CCore, lam: int, pin: int, rho: int,
                                    nbrs: list[tuple[int, int]]) -> None:
    want = consensus_error(FixedArithmetic(), lam, nbrs, pin, rho)
    assert core.xi(lam, pin, rho, nbrs) == want


# --------------------------------------------------------------------------- random steps

GAIN = st.one_of(st.sampled_from([0, 1, 2, 1 << 30, I32_MAX, I32_MAX - 1, 10737418]),
                 st.integers(0, I32_MAX), st.integers(0, 1 << 24))
BAND = st.one_of(st.sampled_from([0, 1, 1678, fx.to_fixed(0.999999)]),
                 st.integers(0, fx.to_fixed(0.999999)))
DWELL = st.one_of(st.sampled_from([1, 2, 3, 5, 100]), st.integers(1, 400))
LAM0 = st.one_of(st.sampled_from([I32_MIN, I32_MAX, 0, -1, 1]), st.integers(I32_MIN, I32_MAX))


def xi_sequence(rng: random.Random, band: int, n: int, prefix: list[int]) -> list[int]:
    """n values of ξ: the prefix, then a mix of edge values and walks that straddle the
    band and zero (crossings, ties at the band, long stretches of one sign)."""
    edges = [I32_MIN, I32_MAX, I32_MIN + 1, I32_MAX - 1, 0, 1, -1, band, -band, band + 1,
             -band - 1, max(band - 1, 0), -max(band - 1, 0)]
    out = list(prefix[:n])
    x = 0
    while len(out) < n:
        mode = rng.random()
        if mode < 0.15:
            x = rng.choice(edges)
        elif mode < 0.25:
            x = rng.randint(I32_MIN, I32_MAX)
        elif mode < 0.75:   # small walk around zero, within a few bands
            x = max(I32_MIN, min(I32_MAX, x // 2 + rng.randint(-3 * band - 8, 3 * band + 8)))
        else:               # a stretch of one sign, then a flip
            x = -x if rng.random() < 0.5 else x
        out.append(int(max(I32_MIN, min(I32_MAX, x))))
    return out


def python_reference(kind: str, kts: int, hts: int, ts: int, band: int, dwell: int,
                     p: int, n: int) -> Controller:
    """firmware_py's fixed Controller of ``kind``, with these integer constants."""
    ref = make_controller(ControllerConfig(kind=kind, ft_exponent=p / (1 << n),
                                           dwell=0.01 if kind == "dwell" else 0.0), fixed=True)
    ref.kts, ref.hts, ref.ts_q, ref.band = kts, hts, ts, band
    ref.dwell_samples = dwell if kind == "dwell" else 0
    return ref


def run_both(core: cimpl.CCore, kind: str, kts: int, hts: int, ts: int, band: int,
             dwell: int, p: int, n: int, lam0: int, xis: list[int]) -> None:
    ref = python_reference(kind, kts, hts, ts, band, dwell, p, n)
    c = cimpl.CController(kind, kts, hts, ts, band, dwell if kind == "dwell" else 0, p, n,
                          core=core)
    s = ref.initial_state(lam0 / fx.ONE)
    assert c.initial_state(lam0 / fx.ONE) == s
    got = c.run(s, xis)
    for t, xi in enumerate(xis):
        s, o = ref.step(s, xi)
        if got[t] != (s, o):
            raise AssertionError(f"{kind} step {t} (xi={xi}): firmware_py {s} {o}, "
                                 f"C {got[t][0]} {got[t][1]}")
    STEPS_RUN[kind] += len(xis)
    EVENTS[kind, "resets"] += s.resets
    EVENTS[kind, "saturations"] += s.saturations
    EVENTS[kind, "zero crossings"] += sum((a > 0 >= b) or (a < 0 <= b)
                                          for a, b in zip([0, *xis], xis, strict=False))


@pytest.mark.parametrize("kind", KINDS)
def test_random_steps_match_firmware_py(core: cimpl.CCore, kind: str) -> None:
    @settings(max_examples=EXAMPLES_PER_KIND, deadline=None, database=None,
              suppress_health_check=[HealthCheck.too_slow])
    @given(kts=GAIN, hts=GAIN, ts=GAIN, band=BAND, dwell=DWELL, n=st.integers(1, 4),
           p_half=st.integers(0, 7), lam0=LAM0, seed=st.integers(0, 2**32 - 1),
           prefix=st.lists(st.integers(I32_MIN, I32_MAX), max_size=8))
    def check(kts: int, hts: int, ts: int, band: int, dwell: int, n: int, p_half: int,
              lam0: int, seed: int, prefix: list[int]) -> None:
        p = (p_half % (1 << (n - 1))) * 2 + 1
        xis = xi_sequence(random.Random(seed), band, STEPS_PER_EXAMPLE, prefix)
        run_both(core, kind, kts, hts, ts, band, dwell, p, n, lam0, xis)

    check()


def test_random_step_budget() -> None:
    """Runs after the random-step tests (file order): each kind got ≥ 100,000 steps."""
    if not STEPS_RUN:
        pytest.skip("the random-step tests did not run in this session")
    print(f"random steps per kind: {dict(STEPS_RUN)}; events: {dict(EVENTS)}")
    for kind, steps in STEPS_RUN.items():
        assert steps >= 100_000, (kind, steps)
        assert EVENTS[kind, "saturations"] > 0 and EVENTS[kind, "zero crossings"] > 0, kind
        if kind in ("reset", "dwell"):
            assert EVENTS[kind, "resets"] > 0, kind


def test_from_config_steps_match_firmware_py(core: cimpl.CCore) -> None:
    """Float configurations through the quantisation seam (firmware_py derives the
    constants, CController.from_config passes them on): same steps as firmware_py."""
    rng = random.Random(11)
    for kind in KINDS:
        for _ in range(20):
            ts = rng.choice([0.001, 0.01, 0.05, 2.0 ** -7, 1.0])
            cfg = ControllerConfig(kind=kind, k=rng.choice([0.5, 1.0, 1.9 / ts]),
                                   h=rng.choice([0.1, 1.0, 1.9 / ts]), ts=ts,
                                   dwell=ts * rng.randint(1, 9) if kind == "dwell" else 0.0,
                                   band=rng.choice([0.0, 1e-4, 2e-3]),
                                   ft_exponent=rng.randint(1, 15) / 16)
            ref = make_controller(cfg, fixed=True)
            c = cimpl.CController.from_config(cfg, core=core)
            s = ref.initial_state(rng.uniform(-100, 100))
            xis = xi_sequence(rng, int(ref.band), 200, [])
            got = c.run(s, xis)
            for t, xi in enumerate(xis):
                s, o = ref.step(s, xi)
                assert got[t] == (s, o), (cfg, t)


# --------------------------------------------------------------------------- C runner, cross


def dump_vectors(path: Path) -> tuple[int, int]:
    """The text dump firmware_c/tools/vector_runner.c reads; (vectors, steps)."""
    lines, steps = [], 0
    for p in VECTORS:
        vec = json.loads(p.read_text(encoding="ascii"))
        f = vec["fixed"]
        lines.append(" ".join(map(str, [
            "V", vec["name"], cimpl.KIND_CODES[vec["config"]["kind"]], f["kts"], f["hts"],
            f["ts"], f["band"], f["dwell_samples"], f["pow_num"], f["pow_sqrts"],
            vec["lambda0"], len(vec["steps"])])))
        lines += [" ".join(["S", *map(str, row)]) for row in vec["steps"]]
        steps += len(vec["steps"])
    path.write_text("\n".join(lines) + "\n", encoding="ascii")
    return len(VECTORS), steps


def _run_runner(cmd: list[str], dump: Path) -> subprocess.CompletedProcess[str]:
    with dump.open() as stdin:
        return subprocess.run(cmd, stdin=stdin, capture_output=True, text=True, check=False,
                              timeout=300)


def test_vector_runner_native_and_it_catches_a_wrong_bit(tmp_path: Path,
                                                         built: tuple[Path, str]) -> None:
    _make(tmp_path, "runner")
    dump = tmp_path / "vectors.txt"
    n, steps = dump_vectors(dump)
    proc = _run_runner([str(tmp_path / "vector_runner")], dump)
    assert proc.returncode == 0 and proc.stdout.split() == ["PASS", str(n), str(steps)], proc
    text = dump.read_text().split("\n")
    i = next(k for k, line in enumerate(text) if line.startswith("S "))
    row = text[i].split()
    row[4] = str(int(row[4]) + 1)                     # one LSB of λ after step 0
    dump.write_text("\n".join(text[:i] + [" ".join(row)] + text[i + 1:]))
    proc = _run_runner([str(tmp_path / "vector_runner")], dump)
    assert proc.returncode == 1 and "step 0 field lam" in proc.stdout, proc.stdout


def test_vectors_replay_cross_built_for_arm_under_qemu(tmp_path: Path) -> None:
    _need("make", "arm-linux-gnueabihf-gcc", "qemu-arm")
    _make(tmp_path, "arm-runner")
    dump = tmp_path / "vectors.txt"
    n, steps = dump_vectors(dump)
    proc = _run_runner(["qemu-arm", str(tmp_path / "vector_runner.arm")], dump)
    assert proc.returncode == 0 and proc.stdout.split() == ["PASS", str(n), str(steps)], proc


def _sizes(make_output: str) -> dict[str, tuple[int, int, int]]:
    """arm-none-eabi-size's rows in ``make``'s output: file name → (text, data, bss)."""
    rows = {}
    for line in make_output.splitlines():
        parts = line.split()
        if len(parts) == 6 and parts[0].isdigit():
            rows[Path(parts[5]).name] = (int(parts[0]), int(parts[1]), int(parts[2]))
    return rows


def test_cortex_m4_size_of_the_core_and_the_agent(tmp_path: Path) -> None:
    """arm-none-eabi -Os, soft float: the core has no static data and stays small; the
    whole agent with 63 neighbours (tools/cm4_image.c: core, runtime, codec, SecOC; the
    board's CAN driver and AES engine stubbed) fits 20 KiB of flash and 8 KiB of RAM (16
    and 4 when the DBC stopped at 32 agents: its tables, sized by the DBC's agents, cost
    ~90 B of flash and ~88 B of RAM per agent), and links no floating-point routine (the
    make target fails if it does)."""
    _need("make", "arm-none-eabi-gcc", "arm-none-eabi-size")
    sizes = _sizes(_make(tmp_path, "arm-size"))
    text, data, bss = sizes["controller.cm4.o"]
    print(f"Cortex-M4 -Os core: text {text} data {data} bss {bss}")
    assert data == 0 and bss == 0
    assert 0 < text < 2048
    text, data, bss = sizes["agent.cm4.elf"]
    print(f"Cortex-M4 -Os agent: text {text} data {data} bss {bss}")
    assert text + data < 20 * 1024 and data + bss < 8 * 1024


def test_cppcheck_clean(tmp_path: Path) -> None:
    _need("make", "cppcheck")
    _make(tmp_path, "cppcheck")


def test_config_check_names_each_refusal(core: cimpl.CCore) -> None:
    """bd_ctrl_config_check: a bad kind, a negative gain, a negative band, an exponent
    that is not p/2^n with p odd each get their own error."""
    good = dict(kind=2, kts=10737418, hts=21474836, tsq=10737418, band=1678, dwell=0,
                pow_num=1, pow_sqrts=1)

    def check(**over: int) -> int:
        cfg = cimpl.CtrlConfig(**{**good, **over})
        return int(core.lib.bd_ctrl_config_check(ctypes.byref(cfg)))

    assert check() == 0
    assert check(kind=9) == 1
    assert check(kts=-1) == 2 and check(hts=-1) == 2 and check(tsq=-1) == 2
    assert check(band=-1) == 3
    assert check(kind=4, pow_num=2, pow_sqrts=2) == 4 and check(kind=4, pow_sqrts=5) == 4
