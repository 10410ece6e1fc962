#!/usr/bin/env python3
"""Generate the C firmware's view of the bus contract from dbc/bess_ded.dbc.

Run by firmware_c/Makefile at build time (``make`` regenerates when the DBC or this
script changes); nothing it writes is committed. Into OUT_DIR:

* ``bd_dbc.h`` / ``bd_dbc.c``: pack/unpack of every message layout the agent uses, by
  ``cantools generate_c_source --no-floating-point-numbers`` from a DBC holding only
  the router's messages and agent 1's (``AGENT_1_MC``, ``PLANT_1_Status``, ...). Every
  agent's messages have the same layout as agent 1's (checked here, signal by signal),
  so the firmware packs ``AGENT_i_*`` with agent 1's functions and the ID from below;
  this keeps the generated code at 11 messages instead of 229.
* ``bd_contract.h`` / ``bd_contract.c``: every constant of the contract the firmware
  needs (IDs and per-agent ID bases, the agent limit, cadences, the E2E counter, the
  SecOC bit widths, State/Command/SafetyCause values, raw ranges, the Diag pages, the
  agent's counters from firmware_py's ``contract.AGENT_COUNTERS``), and
  tables of every DBC ID (kind, cycle) and of the sync IDs. Read from the DBC through
  firmware_py's contract module, which checks the ID plan on load.

Usage: python firmware_c/gen_contract.py OUT_DIR

It sits beside the C sources so that an installed copy (``pip install .`` puts
firmware_c/ beside firmware_py/ and dbc/) builds like the checkout.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import cantools  # noqa: E402
from cantools.database.can import Database  # noqa: E402

from dbc import DBC_PATH, FD_DBC_PATH  # noqa: E402
from firmware_py import contract, frames, pricesig  # noqa: E402
from firmware_py.frames import FrameCodec, diag_name, mc_name, setpoint_name, status_name  # noqa: E402
from firmware_py.runtime import AgentRuntime  # noqa: E402

DB_NAME = "bd_dbc"
# the layouts the agent packs or unpacks: the router's messages and agent 1's templates
# (AGENT_<i>_Diag is packed from the page table below, not by cantools' code)
TEMPLATES = ("ER_Price", "ER_Command", "ER_Price_Sync", "ER_Command_Sync", mc_name(1),
             setpoint_name(1), status_name(1), mc_name(1) + "_Sync",
             setpoint_name(1) + "_Sync", status_name(1) + "_Sync")
# the agent's counters: firmware_py's, then the signed price's (AUTH-32, AUTH-33)
COUNTERS = (*contract.AGENT_COUNTERS, *contract.SIGNED_PRICE_COUNTERS)
# ER_PriceSig's layout as src/agent_sig.c unpacks it: signal -> (start, length, signed),
# little endian, Page the multiplexer (page 0: the segment, pages 1..: Signature)
PRICE_SIG_LAYOUT = {"Page": (0, 4, False), "PriceValid": (4, 1, False),
                    "Segment": (5, 3, False), "Rho": (8, 32, True), "Boot": (40, 16, False),
                    "SegmentHigh": (56, 8, False), "Signature": (8, 56, False)}
PER_AGENT = {"MC": mc_name, "SETPOINT": setpoint_name, "STATUS": status_name,
             "DIAG": diag_name}


def _layout(m):
    return _layout_of(m.signals)


def check_templates(db: Database) -> None:
    """Every agent's message has agent 1's layout (else one packer cannot serve all)."""
    for i in contract.agent_ids():
        for make in (*PER_AGENT.values(), *(lambda j, m=m: m(j) + "_Sync"
                                             for m in PER_AGENT.values())):
            m, t = db.get_message_by_name(make(i)), db.get_message_by_name(make(1))
            if _layout(m) != _layout(t) or m.length != t.length:
                sys.exit(f"gen_contract: {m.name} does not have {t.name}'s layout: the C "
                         "firmware packs every agent's frames with agent 1's code")


def check_price_sig(db: Database) -> None:
    """ER_PriceSig has the layout src/agent_sig.c unpacks by hand (PRICE_SIG_LAYOUT), every
    signal's full raw range but Page's (0..SIG_PAGES) and the segment's widths pricesig's."""
    m = db.get_message_by_name(pricesig.MESSAGE)
    got = {s.name: (s.start, s.length, s.is_signed) for s in m.signals
           if s.byte_order == "little_endian"}
    page = m.get_signal_by_name("Page")
    if (got != PRICE_SIG_LAYOUT or m.length != 8 or (page.minimum, page.maximum)
            != (0, pricesig.SIG_PAGES) or pricesig.SEGMENT_LOW_BITS != 3
            or pricesig.SEGMENT_MOD != 1 << 11 or pricesig.PAGE_BYTES != 7):
        sys.exit(f"gen_contract: {pricesig.MESSAGE} is not the layout src/agent_sig.c "
                 "unpacks (PRICE_SIG_LAYOUT): update both")


def fd_tags(fd: Database) -> list[tuple[str, int, str]]:
    """AUTH-34 from the FD twin (dbc/bess_ded_fd.dbc): AGENT_<i>_MC and its sync are the
    classic 8 bytes (the same layout: one packer serves both) then TagRx<k> (1 byte) and
    Tag<k> (3) per slot, 4 bytes a slot from byte 8; every other message 8 bytes. The
    sizes and receiver codes as src/agent.c and agent_rx.c use them."""
    classic = cantools.database.load_file(str(DBC_PATH), strict=True)
    tagged = {mc_name(i) + s for i in contract.agent_ids() for s in ("", "_Sync")}
    for m in fd.messages:
        if m.name not in tagged:
            if m.length != 8:
                sys.exit(f"gen_contract: the FD DBC's {m.name} is not 8 bytes")
            continue
        rx = sorted((s for s in m.signals if s.name.startswith("TagRx")), key=lambda s: s.start)
        want = [s for s in m.signals if not re.fullmatch(r"Tag(Rx)?[0-9]+", s.name)]
        slots = [(r.start, r.length, m.get_signal_by_name(f"Tag{k}").start,
                  m.get_signal_by_name(f"Tag{k}").length) for k, r in enumerate(rx)]
        if (_layout_of(want) != _layout(classic.get_message_by_name(m.name))
                or slots != [(64 + 32 * k, 8, 72 + 32 * k, 24) for k in range(len(rx))]
                or m.length != 8 + 4 * len(rx) or not rx):
            sys.exit(f"gen_contract: the FD DBC's {m.name} is not the classic layout and its "
                     "tag slots (TagRx<k> 8 bits, Tag<k> 24 bits, 32 bits a slot from bit 64)")
    mc = fd.get_message_by_name(mc_name(1))
    rx0 = mc.get_signal_by_name("TagRx0")
    codes = {str(v): int(k) for k, v in (rx0.choices or {}).items()}
    if not {"PLANT", "ROUTER"} <= codes.keys():
        sys.exit("gen_contract: the FD DBC's TagRx0 has no PLANT and ROUTER choices")
    if min(codes["PLANT"], codes["ROUTER"]) <= contract.N_AGENTS_MAX:
        sys.exit("gen_contract: a TagRx code of the plant or router is an agent's")
    n = sum(1 for s in mc.signals if s.name.startswith("TagRx"))
    return [("BD_FD_MC_BYTES", mc.length, "AGENT_<i>_MC(_Sync) on CAN FD (AUTH-34)"),
            ("BD_TAG_SLOTS", n, "its tag slots"),
            ("BD_TAG_SLOT_BYTE", rx0.start // 8, "byte of slot 0's TagRx; its Tag follows"),
            ("BD_TAG_SLOT_BYTES", 4, "bytes a slot"),
            ("BD_TAG_RX_PLANT", codes["PLANT"], "TagRx of the plant"),
            ("BD_TAG_RX_ROUTER", codes["ROUTER"], "TagRx of the router")]


def _layout_of(signals):
    return [(s.name, s.start, s.length, s.byte_order, s.is_signed, s.scale, s.offset,
             s.minimum, s.maximum, s.multiplexer_ids, s.is_multiplexer)
            for s in sorted(signals, key=lambda s: s.start)]


def generate_codec(db: Database, out: Path) -> None:
    sub = Database(messages=[db.get_message_by_name(n) for n in TEMPLATES], nodes=db.nodes,
                   buses=db.buses, version=db.version, dbc_specifics=db.dbc)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{DB_NAME}.dbc"
        cantools.database.dump_file(sub, str(path))
        subprocess.run([sys.executable, "-m", "cantools", "generate_c_source",
                        "--no-floating-point-numbers", "--database-name", DB_NAME,
                        "-o", str(out), str(path)], check=True, stdout=subprocess.DEVNULL)


def _id_base(make) -> int:
    base = FrameCodec().frame_id(make(1)) - 1
    for i in contract.agent_ids():
        if FrameCodec().frame_id(make(i)) != base + i:
            sys.exit(f"gen_contract: {make(i)} is not at {make(1)}'s base + {i}")
    return base


def contract_header(db: Database) -> tuple[str, str]:
    codec = FrameCodec()
    d: list[tuple[str, int, str]] = []

    def define(name: str, value: int, why: str = "") -> None:
        d.append((name, value, why))

    define("BD_N_AGENTS_MAX", contract.N_AGENTS_MAX, "agents the DBC defines")
    define("BD_DLC", 8, "every frame is a classic 8-byte frame")
    for name in ("ER_Price", "ER_Command", "ER_Balance", "ER_Price_Sync", "ER_Command_Sync",
                 pricesig.MESSAGE):
        define(f"BD_{name.upper()}_ID", codec.frame_id(name), name)
    # signed_price (AUTH-31..33): ER_PriceSig as src/agent_sig.c reads it
    check_price_sig(db)
    define("BD_SIG_PAGES", pricesig.SIG_PAGES, "ER_PriceSig signature pages (1..n)")
    define("BD_SIG_PAGE_BYTES", pricesig.PAGE_BYTES, "signature bytes a page")
    define("BD_SIG_SEGMENT_LOW_BITS", pricesig.SEGMENT_LOW_BITS, "ER_Price.Segment's bits")
    define("BD_SIG_SEGMENT_MOD", pricesig.SEGMENT_MOD, "the signed segment number's modulus")
    for key, make in PER_AGENT.items():
        pattern = make(1).replace("_1_", "_<i>_")
        define(f"BD_{key}_BASE", _id_base(make), f"{pattern} = base + i")
        define(f"BD_{key}_SYNC_BASE", _id_base(lambda j, m=make: m(j) + "_Sync"),
               f"{pattern}_Sync = base + i")
    define("BD_MAC_BITS", contract.MAC_BITS, "truncated CMAC on the wire")
    for name, value, why in fd_tags(cantools.database.load_file(str(FD_DBC_PATH), strict=True)):
        define(name, value, why)
    define("BD_FV_TX_BITS", contract.FV_TX_BITS, "freshness bits on the wire")
    define("BD_FV_COUNT_BITS", contract.FV_COUNT_BITS, "message counter of the FV")
    define("BD_FV_BOOT_BITS", contract.FV_BOOT_BITS, "boot counter of the FV")
    define("BD_TIMEOUT_CYCLES", contract.TIMEOUT_CYCLES, "cycles of a frame before a timeout")
    define("BD_MC_CYCLE_MS", contract.cycle_ms(mc_name(1)), "Ts the cycles are written for")
    for key, name in (("PRICE", "ER_Price"), ("STATUS", status_name(1)),
                      ("SETPOINT", setpoint_name(1)), ("DIAG", diag_name(1)),
                      ("SYNC", "ER_Price_Sync")):
        define(f"BD_{key}_EVERY", contract.every_ticks(name), f"{name}: every n MC cycles")
    for s in contract.State:
        define(f"BD_STATE_{s.name}", int(s), "AGENT_<i>_MC.State")
    for c in contract.Command:
        define(f"BD_CMD_{c.name}", int(c), "ER_Command.Command")
    define("BD_TARGET_OFFSET", frames.TARGET_OFFSET,
           "ER_Command.Target: agent = raw + this (DBC offset)")
    define("BD_PIN_ON", frames.PIN_ON, "ER_Command PIN: GainK to pin (CMD-7)")
    define("BD_PIN_OFF", frames.PIN_OFF, "ER_Command PIN: GainK to unpin (CMD-7)")
    cause = db.get_message_by_name(diag_name(1)).get_signal_by_name("SafetyCause")
    for value, label in sorted(cause.choices.items()):
        define(f"BD_SAFETY_CAUSE_{label}", int(value), "AGENT_<i>_Diag.SafetyCause")
    gk = codec.raw_range("ER_Command", "GainK")
    scale = codec.scale("ER_Command", "GainK")
    div = round(1 / scale)
    if codec.raw_range("ER_Command", "GainH") != gk or abs(div * scale - 1) > 1e-12:
        sys.exit("gen_contract: GainK and GainH must share a range and a 1/n scale")
    define("BD_GAIN_RAW_MAX", gk[1], "GainK/GainH raw maximum")
    define("BD_GAIN_SCALE_DIV", div, "GainK/GainH = raw / this (1/s, 1/s^2)")
    for name, sig in ((mc_name(1), "Resets"), (mc_name(1), "State"), ("ER_Command", "Target"),
                      ("ER_Command", "Command"), (setpoint_name(1), "PowerSetpoint"),
                      (status_name(1), "Soc"), (diag_name(1), "NeighboursAlive"),
                      (diag_name(1), "SafetySender"), (diag_name(1), "SafetyCause"),
                      (diag_name(1), "Resets"), (diag_name(1), "Page")):
        lo, hi = codec.raw_range(name, sig)
        tag = f"{name.replace('_1_', '_')}_{sig}".upper()
        define(f"BD_{tag}_MIN", lo, f"{name}.{sig} raw range")
        define(f"BD_{tag}_MAX", hi, "")
    diag = db.get_message_by_name(diag_name(1))
    pages = codec.pages(diag_name(1))
    if tuple(pages.values()) != AgentRuntime.DIAG_PAGES:
        sys.exit("gen_contract: firmware_py's DIAG_PAGES are not the DBC's pages")
    define("BD_DIAG_PAGES", len(pages), "AGENT_<i>_Diag pages")
    define("BD_DIAG_PAGE_SIGNALS_MAX", max(len(p) for p in pages.values()),
           "signals on the fullest page")
    for sig in ("Counter", "Page"):
        define(f"BD_AGENT_DIAG_{sig.upper()}_START", diag.get_signal_by_name(sig).start,
               f"{diag_name(1)}.{sig} start bit")
    diag_signals = [name for page in pages.values() for name in page]
    # src/agent_diag.c maps each signal to its counter: a DBC signal it does not know would
    # be sent as 0 without a word, so the build stops instead
    diag_c = (Path(__file__).resolve().parent / "src" / "agent_diag.c").read_text()
    unmapped = [n for n in diag_signals if f"case BD_DIAG_SIG_{n.upper()}:" not in diag_c]
    if unmapped:
        sys.exit(f"gen_contract: src/agent_diag.c (diag_value) has no source for the DBC's "
                 f"{diag_name(1)} signals {', '.join(unmapped)}")
    # the reserved slots (contract.DIAG_RESERVED, the DBC's mark) are exactly the cases of
    # diag_value's block that returns 0
    block = re.search(r"/\* reserved slots .*?\*/((?:\s*case BD_DIAG_SIG_\w+:)+)\s*return 0u;",
                      diag_c, re.S)
    zero = set(re.findall(r"BD_DIAG_SIG_(\w+):", block.group(1))) if block else set()
    if zero != {n.upper() for n in contract.DIAG_RESERVED}:
        sys.exit(f"gen_contract: src/agent_diag.c (diag_value) returns 0 for "
                 f"{', '.join(sorted(zero)) or 'nothing'}, but the DBC's reserved "
                 f"{diag_name(1)} signals are {', '.join(sorted(contract.DIAG_RESERVED))}")
    for k, name in enumerate(diag_signals):
        define(f"BD_DIAG_SIG_{name.upper()}", k, "AGENT_<i>_Diag signal")
    define("BD_N_DIAG_SIGNALS", len(diag_signals), "")
    define("BD_LAMBDA_Q", 24, "the wire λ and ρ are Q24 (the DBC's factor 2^-24)")

    ids = sorted(codec.frame_ids())
    syncs = sorted(contract.PEER_SYNCED_BY)  # not the report frames': no node takes them
    define("BD_N_DBC_IDS", len(ids), "messages in the DBC")
    define("BD_N_SYNC_IDS", len(syncs), "<name>_Sync messages a node takes (PEER_SYNCED_BY)")

    h = ["/* Generated by firmware_c/gen_contract.py from dbc/bess_ded.dbc: do not edit. */",
         "#ifndef BD_CONTRACT_H", "#define BD_CONTRACT_H", "", "#include <stdint.h>", ""]
    for name, value, why in d:
        text = f"0x{value:03X}" if name.endswith(("_ID", "_BASE")) else str(value)
        h.append(f"#define {name} {text}" + (f"  /* {why} */" if why else ""))
    h.append(f'#define BD_SIG_LABEL "{pricesig.SIG_LABEL.decode()}"  /* the signed message\'s '
             'label (AUTH-32) */')
    h += ["", "/* One signal of an AGENT_<i>_Diag page: which (BD_DIAG_SIG_*), where, and the",
          " * maximum the agent saturates it at (the DBC's). */",
          "typedef struct { uint8_t signal, start, length; uint32_t max; } bd_diag_field;",
          "extern const bd_diag_field bd_diag_pages[BD_DIAG_PAGES][BD_DIAG_PAGE_SIGNALS_MAX];",
          "extern const uint8_t bd_diag_page_signals[BD_DIAG_PAGES];  /* fields per page */",
          "", "/* Every 11-bit ID the DBC defines: bit (id % 8) of bd_dbc_ids[id / 8]. */",
          "extern const uint8_t bd_dbc_ids[256];",
          "/* The sync IDs a node takes (sorted: every one but the report frames', firmware_py",
          " * contract.PEER_SYNCED_BY) and the secured frame ID each carries the freshness of. */",
          "extern const uint16_t bd_sync_ids[BD_N_SYNC_IDS];",
          "extern const uint16_t bd_synced_by[BD_N_SYNC_IDS];",
          "", "/* An agent's counters (spec section 13), indexed by BD_C_*; the names are",
          " * firmware_py's (contract.AGENT_COUNTERS, then the signed price's",
          " * contract.SIGNED_PRICE_COUNTERS: no Diag slot). */", "enum {",
          *(f"    BD_C_{n.upper()}," for n in COUNTERS), "    BD_C_COUNT", "};",
          "extern const char *const bd_counter_names[BD_C_COUNT];",
          "", "#endif /* BD_CONTRACT_H */", ""]
    bitmap = [0] * 256
    for fid in ids:
        bitmap[fid // 8] |= 1 << (fid % 8)
    rows = [", ".join(f"0x{b:02X}" for b in bitmap[k:k + 16]) + "," for k in range(0, 256, 16)]
    c = ["/* Generated by firmware_c/gen_contract.py from dbc/bess_ded.dbc: do not edit. */",
         '#include "bd_contract.h"', "",
         "const uint8_t bd_dbc_ids[256] = {", *(f"    {r}" for r in rows), "};", "",
         "const uint16_t bd_sync_ids[BD_N_SYNC_IDS] = {",
         *(f"    0x{s:03X},  /* {codec.name_of(s)} */" for s in syncs), "};", "",
         "const uint16_t bd_synced_by[BD_N_SYNC_IDS] = {",
         *(f"    0x{contract.SYNCED_BY[s]:03X}," for s in syncs), "};", ""]
    c += ["/* the pages of AGENT_<i>_Diag as the DBC lays them out */",
          "const bd_diag_field bd_diag_pages[BD_DIAG_PAGES][BD_DIAG_PAGE_SIGNALS_MAX] = {"]
    for page, names in pages.items():
        fields = []
        for name in names:
            sig = diag.get_signal_by_name(name)
            fields.append(f"{{BD_DIAG_SIG_{name.upper()}, {sig.start}u, {sig.length}u, "
                          f"{codec.raw_range(diag_name(1), name)[1]}u}}")
        c.append(f"    {{{', '.join(fields)}}},  /* page {page} */")
    c += ["};", "const uint8_t bd_diag_page_signals[BD_DIAG_PAGES] = {",
          "    " + ", ".join(f"{len(names)}u" for names in pages.values()) + ",", "};", "",
          "const char *const bd_counter_names[BD_C_COUNT] = {",
          *(f'    "{n}",' for n in COUNTERS), "};", ""]
    return "\n".join(h), "\n".join(c)


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print(__doc__, file=sys.stderr)
        return 2
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    db = cantools.database.load_file(str(DBC_PATH), strict=True)
    check_templates(db)
    generate_codec(db, out)
    h, c = contract_header(db)
    (out / "bd_contract.h").write_text(h)
    (out / "bd_contract.c").write_text(c)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
