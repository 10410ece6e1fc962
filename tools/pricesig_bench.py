#!/usr/bin/env python3
"""What the opt-in signed price costs (``signed_price``, docs/security.md, AUTH-31..33):
µs to sign a price segment and to verify it on this machine (firmware_py.pricesig, Ed25519
from `cryptography`), a receiver's whole transfer (11 ER_PriceSig pages decoded,
reassembled, verified once) and its once-a-second repeat (no verify), the C agent's
verify (firmware_c's seam bd_ed25519_verify: libsodium, called through ctypes from
libbessded.so, built on first use like sim.cbind), and the bus time the transfers take
(sim.bench.canframe, worst-case stuffing).

Usage: ``PYTHONPATH=. python3 tools/pricesig_bench.py [-n N]``
"""

from __future__ import annotations

import argparse
import ctypes
import sys
import timeit
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from firmware_py import pricesig, secoc  # noqa: E402
from firmware_py.frames import FrameCodec  # noqa: E402
from firmware_py.pricesig import PriceSigReceiver, SignedSegment  # noqa: E402
from sim.bench.canframe import classic_frame_time, fd_frame_time  # noqa: E402

BITRATE, FD_RATE = 500_000, 2_000_000


def c_verify_s(n: int, public: bytes, message: bytes, signature: bytes) -> float | None:
    """Seconds per bd_ed25519_verify (firmware_c/src/crypto_sodium.c) of a genuine
    signature, through ctypes (its call overhead, ~1 µs, included); None without a C
    build."""
    from sim.cbind.cagent import load
    from sim.cbind.cimpl import CBuildError

    try:
        lib = load().lib
    except (CBuildError, OSError) as e:
        print(f"(no C figure: {e})")
        return None
    fn = lib.bd_ed25519_verify
    fn.restype = ctypes.c_int
    fn.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_size_t, ctypes.c_char_p]
    if fn(signature, message, len(message), public) != 1 \
            or fn(bytes([signature[0] ^ 1]) + signature[1:], message, len(message), public):
        raise SystemExit("bd_ed25519_verify disagrees with firmware_py.pricesig")
    return timeit.timeit(lambda: fn(signature, message, len(message), public), number=n) / n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=500, help="repetitions per figure (500)")
    n = ap.parse_args(argv).n
    codec = FrameCodec()
    master = bytes(range(16))
    seed = secoc.derive_price_sign_key(master)
    public, fleet = pricesig.public_key(seed), secoc.fleet_id(master)
    segs = [SignedSegment(1, k % pricesig.SEGMENT_MOD, 1, k * 1000) for k in range(2 * n + 1)]
    it = iter(segs)
    sign = timeit.timeit(lambda: pricesig.sign(seed, fleet, next(it)), number=n) / n
    sig0 = pricesig.sign(seed, fleet, segs[0])
    verify = timeit.timeit(lambda: pricesig.verifies(public, fleet, segs[0], sig0),
                           number=n) / n
    transfers = iter([[codec.encode(pricesig.MESSAGE, raw, 0)
                       for raw in pricesig.pages(s, pricesig.sign(seed, fleet, s))]
                      for s in segs[1:n + 1]])
    rx = PriceSigReceiver(public, fleet)

    def take(msgs: list) -> None:
        for m in msgs:
            if rx.take(codec.decode(m).raw) is not None:
                raise SystemExit("a genuine transfer was refused")

    transfer = timeit.timeit(lambda: take(next(transfers)), number=n) / n
    assert rx.current is not None and rx.verifications == n
    held = pricesig.sign(seed, fleet, rx.current)
    repeat_msgs = [codec.encode(pricesig.MESSAGE, raw, 0) for raw in pricesig.pages(rx.current,
                                                                                   held)]
    repeat = timeit.timeit(lambda: take(repeat_msgs), number=n) / n
    frame = classic_frame_time(8, BITRATE)
    fd = fd_frame_time(8, BITRATE, FD_RATE)
    burst = pricesig.PAGES * frame
    c_verify = c_verify_s(n, public, segs[0].message(fleet), sig0)
    print(f"sign a segment: {sign * 1e6:.0f} µs; verify: {verify * 1e6:.0f} µs")
    if c_verify is not None:
        print(f"C agent (libsodium, bd_ed25519_verify): verify {c_verify * 1e6:.0f} µs")
    print(f"a receiver's transfer (11 pages decoded, reassembled, one verify): "
          f"{transfer * 1e6:.0f} µs; its repeat (no verify): {repeat * 1e6:.0f} µs")
    print(f"bus: {pricesig.PAGES} frames a transfer, {burst * 1e3:.2f} ms on classic CAN at "
          f"{BITRATE // 1000} kbit/s ({pricesig.PAGES * fd * 1e3:.2f} ms as FD frames); "
          f"once a second: +{pricesig.PAGES} frames/s, {100 * burst:.2f} % of the bus, plus "
          f"one transfer per price segment change")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
