"""The C controller core (firmware_c/) from Python, through ctypes.

``CController`` has the step interface of firmware_py's fixed ``Controller``
(``initial_state``, ``wire_lambda``, ``step(state, xi) -> (state, StepOutput)``), so a
test can run both side by side and compare state by state. The core takes integers
only: the binary64 → Q1.30/Q24 quantisation of the configuration (NUM-4, NUM-6) is done
here, by firmware_py's own ``Controller`` (the seam the C runtime will own later).

The library is built by firmware_c/Makefile (``make BUILD=DIR``): on first use into a
cache directory keyed by the sources' hash (``$BESSDED_C_CACHE``, else
``~/.cache/bess-ded/cimpl``), or wherever ``build()`` is told.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any

from firmware_py import fixedpoint as fx
from firmware_py.controllers import (
    KINDS,
    ControllerConfig,
    ControllerState,
    StepOutput,
    make_controller,
)


def _source_dir() -> Path:
    """firmware_c/: $BESSDED_FIRMWARE_C, else beside sim/ (a checkout, an editable
    install), else in the working directory (`pip install .` run from the checkout)."""
    env = os.environ.get("BESSDED_FIRMWARE_C")
    if env:
        return Path(env)
    for base in (Path(__file__).resolve().parents[2], Path.cwd()):
        if (base / "firmware_c" / "Makefile").is_file():
            return base / "firmware_c"
    return Path(__file__).resolve().parents[2] / "firmware_c"


SOURCE_DIR = _source_dir()
LIB_NAME = "libbessded_core.so"
KIND_CODES = {kind: code for code, kind in enumerate(KINDS)}  # BD_KIND_* in controller.h
UINT32_MAX = (1 << 32) - 1
# a directory of libraries built elsewhere (tools/c_coverage.py: an instrumented build)
LIB_DIR_ENV = "BESSDED_C_LIB_DIR"


class CBuildError(RuntimeError):
    """The C core did not build (the compiler's output is the message)."""


class CtrlConfig(ctypes.Structure):
    """firmware_c's bd_ctrl_config (the controller's parameters), as ctypes lays it out."""

    _fields_ = [("kind", ctypes.c_int32), ("kts", ctypes.c_int32), ("hts", ctypes.c_int32),
                ("tsq", ctypes.c_int32), ("band", ctypes.c_int32), ("dwell", ctypes.c_uint32),
                ("pow_num", ctypes.c_uint32), ("pow_sqrts", ctypes.c_uint32)]


class _State(ctypes.Structure):
    _fields_ = [("lam", ctypes.c_int64), ("nu", ctypes.c_int64), ("xi_prev", ctypes.c_int32),
                ("armed", ctypes.c_int32), ("since_reset", ctypes.c_uint32),
                ("resets", ctypes.c_uint32), ("saturations", ctypes.c_uint32)]


class _Out(ctypes.Structure):
    _fields_ = [("dlam", ctypes.c_int64), ("reset", ctypes.c_int32)]


class _Record(ctypes.Structure):
    _fields_ = [("state", _State), ("out", _Out)]


def sources(source_dir: Path = SOURCE_DIR) -> list[Path]:
    """The files the library is built from (what the cache key hashes)."""
    root = source_dir.parent
    return [source_dir / "Makefile", *sorted((source_dir / "include").rglob("*.h")),
            *sorted((source_dir / "src").glob("*.[ch]")),
            *sorted((source_dir / "tools").glob("*.c")), source_dir / "gen_contract.py",
            root / "dbc" / "bess_ded.dbc", root / "dbc" / "bess_ded_fd.dbc"]


def make_argv(source_dir: Path, build_dir: Path, target: str) -> list[str]:
    """make's command line: the Makefile runs gen_contract.py (which imports cantools)
    with PYTHON, so pass this interpreter, not whatever `python3` is first on PATH."""
    return ["make", "-C", str(source_dir), f"BUILD={build_dir}", f"PYTHON={sys.executable}",
            target]


def build(build_dir: Path, source_dir: Path = SOURCE_DIR, target: str = "all") -> Path:
    """``make -C firmware_c BUILD=build_dir target``; the library's path. Raises
    ``CBuildError`` with the compiler's output (any warning is an error: -Werror)."""
    build_dir = Path(build_dir).resolve()
    proc = subprocess.run(make_argv(source_dir, build_dir, target),
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise CBuildError(f"make {target} failed ({proc.returncode}):\n"
                          f"{proc.stdout}{proc.stderr}")
    return build_dir / LIB_NAME


def cache_dir(source_dir: Path = SOURCE_DIR) -> Path:
    """Where the library built from ``source_dir`` is cached: BESSDED_C_CACHE (or
    ~/.cache/bess-ded/cimpl) / a hash of the sources, so an edit rebuilds."""
    digest = hashlib.sha256()
    for path in sources(source_dir):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    root = Path(os.environ.get("BESSDED_C_CACHE",
                               Path.home() / ".cache" / "bess-ded" / "cimpl"))
    return root / digest.hexdigest()[:16]


class CCore:
    """The loaded library, with its prototypes declared."""

    def __init__(self, lib_path: Path) -> None:
        self.path = Path(lib_path)
        lib = ctypes.CDLL(str(self.path))
        i32, i64, u32, u64 = ctypes.c_int32, ctypes.c_int64, ctypes.c_uint32, ctypes.c_uint64
        p_u32 = ctypes.POINTER(u32)
        for name, res, args in (
            ("bd_shr_floor", i64, [i64, ctypes.c_uint]),
            ("bd_mulq", i64, [i64, i64]),
            ("bd_sat54", i64, [i64, p_u32]),
            ("bd_sat32", i32, [i64, p_u32]),
            ("bd_wire", i32, [i64]),
            ("bd_isqrt_u64", u64, [u64]),
            ("bd_fpow", i64, [i32, u32, u32]),
            ("bd_ctrl_config_check", ctypes.c_int, [ctypes.POINTER(CtrlConfig)]),
            ("bd_ctrl_init", None, [ctypes.POINTER(_State), i32]),
            ("bd_ctrl_wire_lambda", i32, [ctypes.POINTER(_State)]),
            ("bd_ctrl_step", None, [ctypes.POINTER(CtrlConfig), ctypes.POINTER(_State), i32,
                                    ctypes.POINTER(_Out)]),
            ("bd_ctrl_run", None, [ctypes.POINTER(CtrlConfig), ctypes.POINTER(_State),
                                   ctypes.POINTER(i32), ctypes.c_size_t,
                                   ctypes.POINTER(_Record)]),
            ("bd_xi", i32, [i32, i32, i32, ctypes.POINTER(i32), ctypes.POINTER(i32),
                            ctypes.c_size_t, p_u32]),
            ("bd_wmsr_trim", ctypes.c_size_t, [i32, ctypes.c_uint32, ctypes.POINTER(i32),
                                               ctypes.POINTER(i32), ctypes.c_size_t]),
        ):
            fn = getattr(lib, name)
            fn.restype = res
            fn.argtypes = args
        self.lib = lib

    def xi(self, lam_wire: int, pin: int, rho: int,
           neighbours: Sequence[tuple[int, int]], trim: int = 0) -> tuple[int, bool]:
        """XI-2/XI-3 in C: (ξ, saturated?), as ``consensus_error`` on FixedArithmetic;
        ``trim`` > 0: after bd_wmsr_trim (WMSR-1, WMSR-2), as the agent steps."""
        n = len(neighbours)
        weights = (ctypes.c_int32 * max(n, 1))(*(w for w, _ in neighbours))
        lams = (ctypes.c_int32 * max(n, 1))(*(lam for _, lam in neighbours))
        sats = ctypes.c_uint32(0)
        if trim:
            n = self.lib.bd_wmsr_trim(lam_wire, trim, weights, lams, n)
        out = self.lib.bd_xi(lam_wire, pin, rho, weights, lams, n, ctypes.byref(sats))
        return int(out), sats.value > 0


_CORE: CCore | None = None


def load(lib_path: Path | None = None) -> CCore:
    """The C core: ``lib_path`` if given, else the cached build (built on first use)."""
    global _CORE
    if lib_path is not None:
        return CCore(lib_path)
    if _CORE is None and os.environ.get(LIB_DIR_ENV):
        # the whole firmware's library holds the core too: one instrumented build
        _CORE = CCore(Path(os.environ[LIB_DIR_ENV]) / "libbessded.so")
    if _CORE is None:
        path = cache_dir() / LIB_NAME
        if not path.exists():
            # build beside it, then rename: two processes on first use never load a
            # half-written library
            tmp = path.parent.with_name(f"{path.parent.name}.tmp{os.getpid()}")
            built = build(tmp, target=str(tmp.resolve() / LIB_NAME))
            path.parent.mkdir(parents=True, exist_ok=True)
            os.replace(built, path)
            shutil.rmtree(tmp, ignore_errors=True)
        _CORE = CCore(path)
    return _CORE


def exponent_parts(a: float) -> tuple[int, int]:
    """ft exponent a = p / 2**n → (p, n) (CTRL-3), as firmware_py's FixedArithmetic."""
    f = Fraction(a).limit_denominator(16)
    return f.numerator, f.denominator.bit_length() - 1


class CController:
    """firmware_py's fixed ``Controller`` interface over the C core."""

    def __init__(self, kind: str, kts: int, hts: int, ts: int, band: int,
                 dwell_samples: int = 0, pow_num: int = 1, pow_sqrts: int = 1,
                 core: CCore | None = None) -> None:
        self.core = core or load()
        self.kind = kind
        self.kts, self.hts, self.ts_q, self.band = kts, hts, ts, band
        self.dwell_samples = dwell_samples
        self._cfg = CtrlConfig(KIND_CODES[kind], kts, hts, ts, band, dwell_samples, pow_num,
                            pow_sqrts)
        err = self.core.lib.bd_ctrl_config_check(ctypes.byref(self._cfg))
        if err:
            raise ValueError(f"bd_ctrl_config_check refused the constants: error {err}")

    @classmethod
    def from_config(cls, config: ControllerConfig, core: CCore | None = None
                    ) -> CController:
        """The constants firmware_py derives from ``config`` (CTRL-1..3), in C."""
        if config.q != fx.Q:
            raise ValueError(f"the C core runs Q{fx.Q} words only, not Q{config.q}")
        ref = make_controller(config, fixed=True)
        p, n = exponent_parts(config.ft_exponent)
        return cls(config.kind, int(ref.kts), int(ref.hts), int(ref.ts_q), int(ref.band),
                   ref.dwell_samples, p, n, core)

    # ---------------------------------------------------------------- Controller interface

    def initial_state(self, lam0: float) -> ControllerState:
        """bd_ctrl_init: the state at λ = q24(lam0), as firmware_py's ControllerState."""
        s = _State()
        self.core.lib.bd_ctrl_init(ctypes.byref(s), fx.to_fixed(lam0, "lambda0"))
        return _to_py(s)

    def wire_lambda(self, s: ControllerState) -> int:
        """bd_ctrl_wire_lambda: the state's λ rounded to Q24."""
        return int(self.core.lib.bd_ctrl_wire_lambda(ctypes.byref(_to_c(s))))

    def step(self, s: ControllerState, xi: float | int) -> tuple[ControllerState, StepOutput]:
        """bd_ctrl_step: one sample with consensus error ``xi``."""
        cs, out = _to_c(s), _Out()
        self.core.lib.bd_ctrl_step(ctypes.byref(self._cfg), ctypes.byref(cs), int(xi),
                                   ctypes.byref(out))
        return _to_py(cs), StepOutput(dlam=out.dlam, reset=bool(out.reset))

    def run(self, s: ControllerState, xis: Sequence[int]
            ) -> list[tuple[ControllerState, StepOutput]]:
        """len(xis) steps in one C call (bd_ctrl_run): the state and output after each."""
        n = len(xis)
        cs = _to_c(s)
        arr = (ctypes.c_int32 * max(n, 1))(*xis)
        rec = (_Record * max(n, 1))()
        self.core.lib.bd_ctrl_run(ctypes.byref(self._cfg), ctypes.byref(cs), arr, n, rec)
        return [(_to_py(r.state), StepOutput(dlam=r.out.dlam, reset=bool(r.out.reset)))
                for r in rec[:n]]

    def run_into(self, s: ControllerState, xis: ctypes.Array[ctypes.c_int32],
                 records: ctypes.Array[Any]) -> None:
        """len(xis) steps in one bd_ctrl_run call into ``records`` (``record_buffer``),
        nothing converted per step: the C core's own speed, for benchmarks."""
        self.core.lib.bd_ctrl_run(ctypes.byref(self._cfg), ctypes.byref(_to_c(s)), xis,
                                  len(xis), records)


def record_buffer(n: int) -> ctypes.Array[Any]:
    """A buffer for ``n`` steps' records of ``CController.run_into``."""
    return (_Record * max(n, 1))()


def _to_c(s: ControllerState) -> _State:
    for name in ("since_reset", "resets", "saturations"):
        if not 0 <= getattr(s, name) <= UINT32_MAX:
            raise ValueError(f"{name} = {getattr(s, name)} does not fit the C state (uint32)")
    return _State(int(s.lam), int(s.nu), int(s.xi_prev), int(s.armed), s.since_reset,
                  s.resets, s.saturations)


def _to_py(s: _State) -> ControllerState:
    return ControllerState(lam=s.lam, nu=s.nu, xi_prev=s.xi_prev, armed=bool(s.armed),
                           since_reset=s.since_reset, resets=s.resets,
                           saturations=s.saturations)
