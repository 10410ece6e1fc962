"""The C agent runtime (firmware_c/src/agent*.c) from Python, through ctypes.

``CAgent`` has the node seam of firmware_py's ``AgentRuntime`` (``on_frame(msg, t)``,
``tick(t) -> frames``, ``note``, ``counters``, ``state``, ``lam``), so tests replay the
node vectors and drive fleets with it exactly as with the Python agent. Times cross
the seam as int64 nanoseconds (``round(t·1e9)``), as the C node's clock gives them.

``params_of(cfg)`` computes the integers the C runtime runs from (bd_agent_params) with
firmware_py's own arithmetic, so a difference between the two runtimes is the runtime's,
not the configuration's; the C configuration loader (src/config.c) is checked against
the same function in tests/test_c_config.py.

Over 500 lines: the ctypes mirror of bd_agent_params, its keys and the node seam are one
ABI; split, a field added on the C side would have to be followed in two modules.
"""

from __future__ import annotations

import ctypes
import os
import shutil
from collections import Counter
from collections.abc import Mapping
from pathlib import Path

import can

from firmware_py import contract
from firmware_py import fixedpoint as fx
from firmware_py.config import AgentConfig
from firmware_py.contract import State, cycle_s, raw_range, scale
from firmware_py.controllers import make_controller
from firmware_py.nodeio import HELLO_FRACTION, JOIN_FRACTION
from firmware_py.runtime import SetpointMap
from firmware_py.secoc import Keyring
from sim.cbind import cimpl

LIB_NAME = "libbessded.so"
N_AGENTS_MAX = contract.N_AGENTS_MAX  # include/bessded/agent.h sizes by the DBC's too
MAX_NEIGHBOURS = N_AGENTS_MAX - 1
MAX_PEERS = N_AGENTS_MAX + 2
LABEL_MAX = 32
TICK_FRAMES_MAX = 6
FRAME_DATA = 32        # BD_FRAME_DATA (include/bessded/frame.h): the FD MC's 32 bytes
TAG_SLOTS = 6          # BD_TAG_SLOTS (the FD DBC's AGENT_i_MC, AUTH-34)
TAG_KEYS_MAX = TAG_SLOTS + TAG_SLOTS - 2   # BD_TAG_KEYS_MAX: its tags, 4 neighbours' to it
TAG_RX_PLANT, TAG_RX_ROUTER = 0xFE, 0xFF   # BD_TAG_RX_* (the FD DBC's TagRx codes)
PRICE_KEY_ERROR = 14   # BD_ERR_PRICE_KEY (include/bessded/agent.h)
FRAME_EXT, FRAME_RTR, FRAME_FD, FRAME_ERR, FRAME_BRS = 0x01, 0x02, 0x04, 0x08, 0x10


class Params(ctypes.Structure):
    """bd_agent_params (include/bessded/agent.h), field for field."""

    _fields_ = [
        ("id", ctypes.c_uint32), ("fleet_size", ctypes.c_uint32), ("pinned", ctypes.c_int32),
        ("resilient_f", ctypes.c_uint32),
        ("lambda0", ctypes.c_int32), ("ctrl", cimpl.CtrlConfig),
        ("n_neighbours", ctypes.c_uint32),
        ("neighbour_id", ctypes.c_uint32 * MAX_NEIGHBOURS),
        ("neighbour_weight", ctypes.c_int32 * MAX_NEIGHBOURS),
        ("sp_gain", ctypes.c_int64), ("sp_offset", ctypes.c_int64),
        ("sp_lo", ctypes.c_int32), ("sp_hi", ctypes.c_int32), ("idle_lambda", ctypes.c_int32),
        ("period_ns", ctypes.c_int64), ("neighbour_timeout_ns", ctypes.c_int64),
        ("price_timeout_ns", ctypes.c_int64), ("status_timeout_ns", ctypes.c_int64),
        ("untrusted_ns", ctypes.c_int64), ("sync_ns", ctypes.c_int64),
        ("hello_ns", ctypes.c_int64), ("join_ns", ctypes.c_int64),
        ("lambda_min", ctypes.c_int32), ("lambda_max", ctypes.c_int32),
        ("rho_min", ctypes.c_int32), ("rho_max", ctypes.c_int32),
        ("price_step_max", ctypes.c_int32), ("lambda_step_max", ctypes.c_int32),
        ("price_persist", ctypes.c_uint32), ("untrusted_after", ctypes.c_uint32),
        ("gain_k_raw_min", ctypes.c_uint32), ("gain_k_raw_max", ctypes.c_uint32),
        ("gain_h_raw_min", ctypes.c_uint32), ("gain_h_raw_max", ctypes.c_uint32),
        ("tx_event", ctypes.c_uint32), ("tx_threshold", ctypes.c_int32),
        ("tx_heartbeat", ctypes.c_uint32), ("fd", ctypes.c_uint32),
        ("no_lambda_tags", ctypes.c_uint32),
        ("signed_price", ctypes.c_uint32),
    ]


PERSIST_FN = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_uint32)
EVENT_FN = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_int, ctypes.c_uint32,
                            ctypes.c_uint32)


class KeyringC(ctypes.Structure):
    """bd_keyring."""

    _fields_ = [
        ("node", ctypes.c_char * (LABEL_MAX + 1)), ("key", ctypes.c_uint8 * 16),
        ("boot", ctypes.c_uint32), ("insecure", ctypes.c_int32),
        ("has_master", ctypes.c_int32), ("master", ctypes.c_uint8 * 16),
        ("n_peers", ctypes.c_uint32),
        ("peer_label", (ctypes.c_char * (LABEL_MAX + 1)) * MAX_PEERS),
        ("peer_key", (ctypes.c_uint8 * 16) * MAX_PEERS),
        ("peer_floor", ctypes.c_uint16 * MAX_PEERS),
        ("has_frame_keys", ctypes.c_int32), ("setpoint_key", ctypes.c_uint8 * 16),
        ("status_key", ctypes.c_uint8 * 16), ("diag_key", ctypes.c_uint8 * 16),
        ("command_key", ctypes.c_uint8 * 16), ("status_floor", ctypes.c_uint16),
        # AUTH-34 (CAN FD): the λ tag pair keys, each pair as TagRx codes
        ("n_tags", ctypes.c_uint32), ("tag_pair", (ctypes.c_uint8 * 2) * TAG_KEYS_MAX),
        ("tag_key", (ctypes.c_uint8 * 16) * TAG_KEYS_MAX),
        ("tag_floor", ctypes.c_uint16 * TAG_KEYS_MAX),
        ("persist_boot", PERSIST_FN), ("persist_ctx", ctypes.c_void_p),
        # signed_price (AUTH-31): the router's Ed25519 public key and the fleet ID
        ("has_price_key", ctypes.c_int32), ("price_key", ctypes.c_uint8 * 32),
        ("fleet_id", ctypes.c_uint8 * 8),
    ]


class Frame(ctypes.Structure):
    """bd_frame."""

    _fields_ = [("id", ctypes.c_uint32), ("len", ctypes.c_uint8), ("flags", ctypes.c_uint8),
                ("data", ctypes.c_uint8 * FRAME_DATA)]


class Runtime:
    """libbessded.so (core, runtime, SecOC, config loader) with its prototypes."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        lib = ctypes.CDLL(str(self.path))
        vp, sz, i64, u32 = ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int64, ctypes.c_uint32
        for name, res, args in (
            ("bd_agent_size", sz, []),
            ("bd_agent_params_size", sz, []),
            ("bd_keyring_size", sz, []),
            ("bd_agent_init", ctypes.c_int, [vp, ctypes.POINTER(Params),
                                             ctypes.POINTER(KeyringC), EVENT_FN, vp]),
            ("bd_agent_rx", None, [vp, ctypes.POINTER(Frame), i64]),
            ("bd_agent_tick", sz, [vp, i64, ctypes.POINTER(Frame), sz]),
            ("bd_agent_note", None, [vp, ctypes.c_int, u32]),
            ("bd_agent_accepted_ids", sz, [vp, ctypes.POINTER(u32), sz]),
            ("bd_agent_lambda", ctypes.c_int32, [vp]),
            ("bd_agent_set_tx_count", None, [vp, u32, u32, u32]),
            ("bd_agent_counter", u32, [vp, ctypes.c_int]),
            ("bd_agent_state", u32, [vp]),
            ("bd_agent_resets", u32, [vp]),
            ("bd_agent_boot", u32, [vp]),
            ("bd_agent_fatal", ctypes.c_int32, [vp]),
            ("bd_agent_sig_verifications", u32, [vp]),
            ("bd_counter_name", ctypes.c_char_p, [ctypes.c_int]),
            ("bd_config_parse", ctypes.c_int, [ctypes.c_char_p, ctypes.c_char_p,
                                               ctypes.POINTER(Params), ctypes.c_char_p, sz]),
            ("bd_keyfile_load", ctypes.c_int, [ctypes.c_char_p, ctypes.c_char_p,
                                               ctypes.POINTER(KeyringC), ctypes.c_char_p, sz]),
            ("bd_keyring_insecure", ctypes.c_int, [ctypes.c_char_p, ctypes.POINTER(KeyringC)]),
            ("bd_derive_node_key", ctypes.c_int, [ctypes.c_char_p, ctypes.c_char_p,
                                                  ctypes.c_char_p]),
            ("bd_derive_frame_key", ctypes.c_int, [ctypes.c_char_p, ctypes.c_char_p,
                                                   ctypes.c_char_p]),
            ("bd_derive_command_key", ctypes.c_int, [ctypes.c_char_p, ctypes.c_char_p,
                                                     ctypes.c_char_p]),
            ("bd_fleet_id", ctypes.c_int, [ctypes.c_char_p, ctypes.c_char_p]),
            ("bd_sign_frame", ctypes.c_int, [ctypes.c_char_p, u32, ctypes.c_char_p,
                                             ctypes.c_uint64]),
            ("bd_frame_verifies", ctypes.c_int, [ctypes.c_char_p, u32, ctypes.c_char_p,
                                                 ctypes.c_uint64]),
            ("bd_fv_candidate", ctypes.c_int, [ctypes.c_uint64, u32, ctypes.c_uint,
                                               ctypes.c_uint64,
                                               ctypes.POINTER(ctypes.c_uint64)]),
            ("bd_fv_past", ctypes.c_int, [ctypes.c_uint64, u32, ctypes.c_uint,
                                          ctypes.POINTER(ctypes.c_uint64)]),
            ("bd_udp_encode", sz, [ctypes.POINTER(Frame), ctypes.c_double, ctypes.c_char_p,
                                   sz]),
            ("bd_udp_decode", ctypes.c_int, [ctypes.c_char_p, sz, ctypes.POINTER(Frame),
                                             ctypes.c_char_p]),
        ):
            fn = getattr(lib, name)
            fn.restype = res
            fn.argtypes = args
        if lib.bd_agent_params_size() != ctypes.sizeof(Params):
            raise cimpl.CBuildError(f"bd_agent_params is {lib.bd_agent_params_size()} bytes "
                                    f"in C but {ctypes.sizeof(Params)} in sim/cbind/cagent.py")
        if lib.bd_keyring_size() != ctypes.sizeof(KeyringC):
            raise cimpl.CBuildError(f"bd_keyring is {lib.bd_keyring_size()} bytes in C but "
                                    f"{ctypes.sizeof(KeyringC)} in sim/cbind/cagent.py")
        self.lib = lib
        names: list[str] = []
        while (name := lib.bd_counter_name(len(names))) is not None:
            names.append(name.decode())
        self.counter_names = tuple(names)


# bd_udp_decode's verdicts (src/udp_msgpack.h BD_UDP_*), as the node counts them
UDP_VERDICTS = ("frame", "not_a_frame", "invalid_frame")
UDP_DATAGRAM_MAX = 512


def udp_datagram(msg: can.Message, timestamp: float = 0.0,
                 runtime: Runtime | None = None) -> bytes:
    """bd_udp_encode: the datagram the C node sends for ``msg`` on udp_multicast (its first
    FRAME_DATA data bytes; the node's frames carry timestamp 0.0, as firmware_py's)."""
    rt = runtime or load()
    f = Frame(msg.arbitration_id, min(len(msg.data), FRAME_DATA),
              (FRAME_EXT if msg.is_extended_id else 0) | (FRAME_RTR if msg.is_remote_frame
                                                          else 0)
              | (FRAME_ERR if msg.is_error_frame else 0) | (FRAME_FD if msg.is_fd else 0)
              | (FRAME_BRS if msg.bitrate_switch else 0))
    f.data[:len(msg.data[:FRAME_DATA])] = list(msg.data[:FRAME_DATA])
    buf = ctypes.create_string_buffer(UDP_DATAGRAM_MAX)
    n = rt.lib.bd_udp_encode(ctypes.byref(f), timestamp, buf, len(buf))
    return buf.raw[:n]


def udp_frame(datagram: bytes, runtime: Runtime | None = None
              ) -> tuple[str, can.Message | None]:
    """bd_udp_decode: what the C node reads in a udp_multicast datagram (UDP_VERDICTS) and
    the frame, every data byte (up to 64 on FD), if it is one."""
    rt = runtime or load()
    f = Frame()
    data = ctypes.create_string_buffer(64)
    verdict = UDP_VERDICTS[rt.lib.bd_udp_decode(datagram, len(datagram), ctypes.byref(f),
                                                data)]
    if verdict != "frame":
        return verdict, None
    rtr = bool(f.flags & FRAME_RTR)
    return verdict, can.Message(arbitration_id=f.id, is_extended_id=bool(f.flags & FRAME_EXT),
                                is_remote_frame=rtr, is_error_frame=bool(f.flags & FRAME_ERR),
                                is_fd=bool(f.flags & FRAME_FD),
                                bitrate_switch=bool(f.flags & FRAME_BRS), dlc=f.len,
                                data=b"" if rtr else data.raw[:f.len])


class CConfigError(ValueError):
    """The C loader refused a configuration or key file (its message, as the node prints)."""


def parse_config(text: str, src: str = "<config>", runtime: Runtime | None = None) -> Params:
    """bd_config_parse: the C loader's bd_agent_params of an agent TOML text."""
    rt = runtime or load()
    p = Params()
    err = ctypes.create_string_buffer(1024)
    if rt.lib.bd_config_parse(text.encode(), src.encode(), ctypes.byref(p), err, len(err)):
        raise CConfigError(err.value.decode())
    return p


def load_keyfile(path: Path | str, node: str, runtime: Runtime | None = None) -> KeyringC:
    """bd_keyfile_load: a node key file as the C node loads it (its persist writes it)."""
    rt = runtime or load()
    k = KeyringC()
    err = ctypes.create_string_buffer(1024)
    if rt.lib.bd_keyfile_load(str(path).encode(), node.encode(), ctypes.byref(k), err,
                              len(err)):
        raise CConfigError(err.value.decode())
    return k


def params_dict(p: Params) -> dict[str, object]:
    """Every field of bd_agent_params, for comparisons (arrays cut to n_neighbours)."""
    out: dict[str, object] = {}
    for name, *_ in Params._fields_:
        v = getattr(p, name)
        if name == "ctrl":
            v = tuple(getattr(v, f) for f, *_ in cimpl.CtrlConfig._fields_)
        elif name in ("neighbour_id", "neighbour_weight"):
            v = tuple(v[:p.n_neighbours])
        out[name] = v
    return out


_RUNTIME: Runtime | None = None


def load() -> Runtime:
    """The runtime library from the cache (built on first use, like sim.cbind.cimpl.load)."""
    global _RUNTIME
    if _RUNTIME is None and os.environ.get(cimpl.LIB_DIR_ENV):
        _RUNTIME = Runtime(Path(os.environ[cimpl.LIB_DIR_ENV]) / LIB_NAME)
    if _RUNTIME is None:
        path = cimpl.cache_dir() / LIB_NAME
        if not path.exists():
            tmp = path.parent.with_name(f"{path.parent.name}.rt{os.getpid()}")
            cimpl.build(tmp, target=str(tmp.resolve() / LIB_NAME))
            path.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp / LIB_NAME, path)
            shutil.rmtree(tmp, ignore_errors=True)
        _RUNTIME = Runtime(path)
    return _RUNTIME


FAULTY_LIB_NAME = "libbessded_faulty.so"


def load_faulty() -> Runtime:
    """libbessded_faulty.so: the runtime whose CMAC primitive fails on demand
    (firmware_c/tools/crypto_faulty.c), for tests of what a failed primitive does:
    ``rt.lib.bd_test_cmac_fail_after(n)`` lets n more calls succeed, then fails every
    one (-1: none fails)."""
    lib_dir = os.environ.get(cimpl.LIB_DIR_ENV)
    rt = Runtime(Path(lib_dir) / FAULTY_LIB_NAME if lib_dir else built(FAULTY_LIB_NAME))
    rt.lib.bd_test_cmac_fail_after.restype = None
    rt.lib.bd_test_cmac_fail_after.argtypes = [ctypes.c_int32]
    rt.lib.bd_test_cmac_calls.restype = ctypes.c_uint32
    rt.lib.bd_test_cmac_calls.argtypes = []
    return rt


NODE_NAME = "bessded-agent"
RUNNER_NAME = "node_runner"


def built(name: str) -> Path:
    """A program of firmware_c's Makefile (``bessded-agent``, ``node_runner``,
    ``udp_fuzz``) from the cache, built on first use."""
    path = cimpl.cache_dir() / name
    if not path.exists():
        tmp = path.parent.with_name(f"{path.parent.name}.{name}{os.getpid()}")
        cimpl.build(tmp, target=str(tmp.resolve() / name))
        path.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp / name, path)
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def node_program() -> Path:
    """firmware_c's node program (Linux: SocketCAN or python-can's udp_multicast)."""
    return built(NODE_NAME)


def ns(t: float) -> int:
    """Seconds (binary64) → int64 ns, as the C node's clock counts."""
    return round(t * 1e9)


def _gain_raw_bounds(lo: float, hi: float) -> tuple[int, int]:
    """The GainK/GainH raw values whose raw·scale lies in [lo, hi] (binary64, as
    DecodedFrame.phys and the runtime's comparison): (min, max), min > max if none."""
    s = scale("ER_Command", "GainK")
    top = raw_range("ER_Command", "GainK")[1]
    inside = [r for r in range(top + 1) if lo <= r * s <= hi]
    return (inside[0], inside[-1]) if inside else (top + 1, 0)


def params_of(cfg: AgentConfig) -> Params:
    """bd_agent_params from firmware_py's arithmetic (NUM-4, NUM-6, CTRL-1..5, SP-1)."""
    c = cfg.controller
    ref = make_controller(c, fixed=True)
    p_num, p_sqrts = cimpl.exponent_parts(c.ft_exponent)
    sp = SetpointMap(cfg.battery)
    b = cfg.battery
    sync_s = cycle_s("ER_Price_Sync", c.ts)
    assert cfg.lambda_step_max is not None and cfg.untrusted_s is not None
    assert cfg.k_min is not None and cfg.k_max is not None
    assert cfg.h_min is not None and cfg.h_max is not None
    p = Params()
    p.id = cfg.id
    p.fleet_size = cfg.fleet_size or 0
    p.pinned = int(cfg.pinned)
    p.resilient_f = cfg.resilient_f
    p.lambda0 = fx.to_fixed(cfg.lambda0)
    p.ctrl = cimpl.CtrlConfig(cimpl.KIND_CODES[c.kind], int(ref.kts), int(ref.hts),
                           int(ref.ts_q), int(ref.band), ref.dwell_samples, p_num, p_sqrts)
    p.n_neighbours = len(cfg.neighbours)
    for j, nb in enumerate(cfg.neighbours):
        p.neighbour_id[j] = nb.id
        p.neighbour_weight[j] = fx.to_fixed(nb.weight)
    p.sp_gain, p.sp_offset, p.sp_lo, p.sp_hi = sp.gain, sp.offset, sp.lo, sp.hi
    p.idle_lambda = fx.to_fixed(b.beta * (1 + b.m), "idle λ β·(1+m)")
    p.period_ns = ns(c.ts)
    p.neighbour_timeout_ns = ns(cfg.neighbour_timeout_periods * c.ts)
    p.price_timeout_ns = ns(cfg.price_timeout_s)
    p.status_timeout_ns = ns(cfg.status_timeout_s)
    p.untrusted_ns = ns(float(cfg.untrusted_s))
    p.sync_ns = ns(sync_s)
    p.hello_ns = ns(HELLO_FRACTION * sync_s)
    p.join_ns = ns(JOIN_FRACTION * sync_s)
    for name in ("lambda_min", "lambda_max", "rho_min", "rho_max", "price_step_max",
                 "lambda_step_max"):
        setattr(p, name, fx.to_fixed(float(getattr(cfg, name)), name))
    p.price_persist = cfg.price_persist
    p.untrusted_after = cfg.untrusted_after
    p.gain_k_raw_min, p.gain_k_raw_max = _gain_raw_bounds(cfg.k_min, cfg.k_max)
    p.gain_h_raw_min, p.gain_h_raw_max = _gain_raw_bounds(cfg.h_min, cfg.h_max)
    p.tx_event = int(cfg.transmit.event)
    p.tx_threshold = cfg.transmit.threshold_q24
    p.tx_heartbeat = cfg.transmit.heartbeat
    p.signed_price = int(cfg.signed_price)
    return p


def keyring_of(node: str, key: bytes, boot: int, peers: Mapping[str, bytes] | None = None,
               insecure: bool = False, floors: Mapping[str, int] | None = None,
               frames: Mapping[str, bytes] | None = None,
               commands: Mapping[str, bytes] | None = None,
               tags: Mapping[str, bytes] | None = None) -> KeyringC:
    """A bd_keyring for the C agent: ``node``'s key and boot, its peers' keys
    (at most MAX_PEERS) with their boot floors, its frame keys (``frames``:
    AGENT_<i>_Setpoint, PLANT_<i>_Status, AGENT_<i>_Diag, AUTH-28, AUTH-29; others
    ignored), its command key (``commands[node]``, AUTH-30) and its λ tag pair keys
    (``tags``: ``"agent_1>agent_3"`` → key, AUTH-34; a floor of a tag sender not in
    ``peers`` goes with its pair to ``node``); not persisted (see keyring_from)."""
    k = KeyringC()
    k.node = node.encode()
    k.key[:] = list(key)
    k.boot = boot
    k.insecure = int(insecure)
    peers = dict(peers or {})
    if len(peers) > MAX_PEERS:
        raise ValueError(f"at most {MAX_PEERS} peer keys, got {len(peers)}")
    k.n_peers = len(peers)
    for i, (label, pk) in enumerate(peers.items()):
        k.peer_label[i].value = label.encode()
        k.peer_key[i][:] = list(pk)
        k.peer_floor[i] = (floors or {}).get(label, 0)
    ix = node.removeprefix("agent_")
    sp = (frames or {}).get(f"AGENT_{ix}_Setpoint")
    st = (frames or {}).get(f"PLANT_{ix}_Status")
    dg = (frames or {}).get(f"AGENT_{ix}_Diag")
    cmd = (commands or {}).get(node)
    if sp is not None and st is not None and dg is not None and cmd is not None:
        k.has_frame_keys = 1
        k.setpoint_key[:] = list(sp)
        k.status_key[:] = list(st)
        k.diag_key[:] = list(dg)
        k.command_key[:] = list(cmd)
    if "plant" not in peers:
        k.status_floor = (floors or {}).get("plant", 0)
    tags = dict(tags or {})
    if len(tags) > TAG_KEYS_MAX:
        raise ValueError(f"at most {TAG_KEYS_MAX} λ tag keys, got {len(tags)}")
    k.n_tags = len(tags)
    for i, (pair, tk) in enumerate(sorted(tags.items())):
        sender, receiver = pair.split(">")
        k.tag_pair[i][:] = [tag_code(sender), tag_code(receiver)]
        k.tag_key[i][:] = list(tk)
        if receiver == node and sender not in peers:
            k.tag_floor[i] = (floors or {}).get(sender, 0)
    return k


def tag_code(node: str) -> int:
    """A node's TagRx code (AUTH-34): agent j → j, the plant, the router."""
    return {"plant": TAG_RX_PLANT, "router": TAG_RX_ROUTER}.get(node) or int(
        node.removeprefix("agent_"))


def _with_price_key(k: KeyringC, ring: Keyring) -> KeyringC:
    """``k`` with ``ring``'s public price key and fleet ID (signed_price, AUTH-31)."""
    if ring.price_verify is not None:
        k.has_price_key = 1
        k.price_key[:] = list(ring.price_verify)
        k.fleet_id[:] = list(bytes.fromhex(ring.fleet_id))
    return k


def keyring_from(ring: Keyring) -> KeyringC:
    """A firmware_py Keyring as bd_keyring (insecure: the public keys, boot 0 → 1). The
    C agent persists its new boots through the Keyring (``new_boot``'s write-ahead)."""
    if ring.insecure:
        return _with_price_key(keyring_of(ring.node, ring.key, ring.boot, insecure=True),
                               ring)
    for peer in ring.floors:   # a floor needs its peer listed (derived, for a fleet's)
        if peer != "plant":    # the agent takes only its link frame from the plant
            ring.key_of(peer)
    i = ring.node.removeprefix("agent_")
    for name in (f"AGENT_{i}_Setpoint", f"PLANT_{i}_Status", f"AGENT_{i}_Diag",
                 "ER_Command"):
        ring.key_for(name)
    # AUTH-34: a key file's λ tag keys (a fleet's master derives them in C)
    tags = ring.listed_tag_keys() if ring.master is None else {}
    k = keyring_of(ring.node, ring.key, ring.boot, ring.listed_keys(), floors=ring.floors,
                   frames=ring.listed_frame_keys(), commands=ring.listed_command_keys(),
                   tags=tags)
    if ring.master is not None:   # a simulated fleet: any sender's key on demand
        k.has_master = 1
        k.master[:] = list(ring.master)
    _with_price_key(k, ring)

    def persist(_ctx: int | None, boot: int) -> int:
        try:
            ring.adopt_boot(boot)
        except Exception:  # noqa: BLE001 - any failure refuses the boot (C: nonzero)
            return 1
        return 0

    k.persist_boot = PERSIST_FN(persist)
    k._persist_ref = k.persist_boot   # type: ignore[attr-defined]  # keep it alive
    return k


class CAgent:
    """An agent on the C runtime, behind firmware_py's node seam (firmware_py.node)."""

    def __init__(self, cfg: AgentConfig, keys: Keyring | KeyringC | None = None,
                 runtime: Runtime | None = None, params: Params | None = None,
                 fd: bool = False, lambda_tags: bool = True) -> None:
        self.rt = runtime or load()
        self.cfg = cfg
        self.period = cfg.controller.ts
        self.params = params if params is not None else params_of(cfg)
        self.params.fd = int(fd)  # GEN-1: a CAN FD bus (the DBC's FD twin)
        self.params.no_lambda_tags = int(not lambda_tags)  # AUTH-34: FD without λ tags
        if keys is None:
            keys = Keyring.insecure_for(f"agent_{cfg.id}")
        self.keys = keys if isinstance(keys, KeyringC) else keyring_from(keys)
        self._buf = ctypes.create_string_buffer(self.rt.lib.bd_agent_size())
        self._events: list[tuple[int, int, int]] = []
        self._on_event = EVENT_FN(self._event)
        err = self.rt.lib.bd_agent_init(self._buf, ctypes.byref(self.params),
                                        ctypes.byref(self.keys), self._on_event, None)
        if err == PRICE_KEY_ERROR:
            raise ValueError(f"bd_agent_init refused agent {cfg.id}: signed_price without "
                             "the router's public price key ([price_signature] verify_key)")
        if err:
            raise ValueError(f"bd_agent_init refused agent {cfg.id}: error {err}")
        self._out = (Frame * TICK_FRAMES_MAX)()
        self.ticks = 0

    def _event(self, _ctx: int | None, event: int, frame_id: int, detail: int) -> None:
        self._events.append((event, frame_id, detail))

    def events(self) -> list[tuple[int, int, int]]:
        """(event, frame ID, detail) since the last call: counter increments and states."""
        ev, self._events = self._events, []
        return ev

    def set_tx_count(self, mc: int, setpoint: int, diag: int = 0) -> None:
        """Set the agent's own message counts of MC, Setpoint and Diag (the node
        vectors' ``setup`` test hook: AUTH-5's wrap in seconds, not 2**24 frames)."""
        self.rt.lib.bd_agent_set_tx_count(self._buf, mc, setpoint, diag)

    # ---------------------------------------------------------------- node seam

    def on_frame(self, msg: can.Message, t: float) -> None:
        """Take one received frame at time ``t`` (bd_agent_rx, its flags from the message)."""
        self.rx(msg.arbitration_id, bytes(msg.data),
                (FRAME_EXT if msg.is_extended_id else 0)
                | (FRAME_RTR if msg.is_remote_frame else 0)
                | (FRAME_FD if msg.is_fd else 0) | (FRAME_ERR if msg.is_error_frame else 0)
                | (FRAME_BRS if msg.is_fd and msg.bitrate_switch else 0),
                ns(t))

    def rx(self, frame_id: int, data: bytes, flags: int, t_ns: int) -> None:
        """Hand a raw frame to bd_agent_rx at ``t_ns`` (data beyond FRAME_DATA bytes is
        cut; its length is the whole frame's)."""
        f = Frame(frame_id, len(data), flags)
        n = min(len(data), FRAME_DATA)
        f.data[:n] = list(data[:n])
        self.rt.lib.bd_agent_rx(self._buf, ctypes.byref(f), t_ns)

    def tick_raw(self, t_ns: int) -> list[tuple[int, bytes]]:
        """One bd_agent_tick at ``t_ns``: the (ID, payload) of every frame to send."""
        n = self.rt.lib.bd_agent_tick(self._buf, t_ns, self._out, TICK_FRAMES_MAX)
        self.ticks += 1
        return [(self._out[k].id, bytes(self._out[k].data)[:self._out[k].len])
                for k in range(n)]

    def tick(self, t: float) -> list[can.Message]:
        """One tick at ``t`` s: the frames to send, as python-can messages (FD with the
        bit-rate switch on an FD bus, as the C agent flags them)."""
        frames = self.tick_raw(ns(t))
        flags = [self._out[k].flags for k in range(len(frames))]
        return [can.Message(arbitration_id=fid, data=data, is_extended_id=False,
                            is_fd=bool(f & FRAME_FD), bitrate_switch=bool(f & FRAME_BRS))
                for (fid, data), f in zip(frames, flags, strict=True)]

    def note(self, event: str, count: int = 1) -> None:
        """Count a runtime event reported by run_node (bd_agent_note)."""
        self.rt.lib.bd_agent_note(self._buf, self.rt.counter_names.index(event), count)

    def accepted_ids(self) -> list[int]:
        """The frame IDs the C agent's acceptance filter must pass."""
        ids = (ctypes.c_uint32 * 512)()
        n = self.rt.lib.bd_agent_accepted_ids(self._buf, ids, 512)
        return list(ids[:n])

    # ---------------------------------------------------------------- reporting

    @property
    def counters(self) -> Counter[str]:
        """The C agent's non-zero counters, by name."""
        lib = self.rt.lib
        return Counter({name: v for i, name in enumerate(self.rt.counter_names)
                        if (v := lib.bd_agent_counter(self._buf, i))})

    @property
    def state(self) -> State:
        """The C agent's state (INIT, RUNNING, ISOLATED, SAFE)."""
        return State(self.rt.lib.bd_agent_state(self._buf))

    @property
    def lambda_q24(self) -> int:
        """The λ the C agent sends, Q24 raw."""
        return int(self.rt.lib.bd_agent_lambda(self._buf))

    @property
    def lam(self) -> float:
        """The λ the C agent sends, as a real value (cu/kWh)."""
        return fx.to_float(self.lambda_q24)

    @property
    def resets(self) -> int:
        """The C controller's reset count."""
        return int(self.rt.lib.bd_agent_resets(self._buf))

    @property
    def fatal(self) -> int:
        """0, or the BD_ERR_* that stopped the agent (no boot left, the CMAC failed)."""
        return int(self.rt.lib.bd_agent_fatal(self._buf))

    @property
    def sig_verifications(self) -> int:
        """The router's price signatures the agent verified (signed_price, AUTH-32)."""
        return int(self.rt.lib.bd_agent_sig_verifications(self._buf))

    @property
    def boot(self) -> int:
        """The boot counter the agent signs under (AUTH-3)."""
        return int(self.rt.lib.bd_agent_boot(self._buf))

    def verdict_counters(self) -> dict[str, object]:
        """As firmware_py's AgentRuntime.verdict_counters: the signed price's counters (no
        Diag slot) and the deadline misses, with the ticks (those not zero)."""
        c = self.counters
        return {"ticks": self.ticks,
                "counters": {k: c[k] for k in (*contract.SIGNED_PRICE_COUNTERS, "deadline_miss")
                             if c.get(k)}}

    def summary(self) -> str:
        """The one-line summary at exit, as firmware_py's agent prints it."""
        c = ", ".join(f"{k}={v}" for k, v in sorted(self.counters.items())) or "none"
        return (f"agent {self.cfg.id} (C): state={self.state.name} λ={self.lam:.6f} "
                f"resets={self.resets} ticks={self.ticks} counters: {c}")
