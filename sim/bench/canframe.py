"""How long a frame holds the bus: classic CAN and CAN FD, worst-case bit stuffing.

The one place the bench computes frame lengths (``micro.bus_load``, ``auth``,
``fleetload``).

Classic CAN (ISO 11898-1 classic base/extended data frame), the worst-case length of
Davis, Burns, Bril and Lukkien (Real-Time Systems 35(3), 2007, eq. (1)), the 3-bit
intermission included::

    bits(s) = g + 8 s + 13 + floor((g + 8 s - 1) / 4)

with ``s`` data bytes and g = 34 control bits exposed to stuffing (11-bit ID) or 54
(29-bit ID). An 8-byte frame with an 11-bit ID: 135 bits, 270 µs at 500 kbit/s.

CAN FD (ISO 11898-1:2015 FD base/extended data frame with the bit-rate switch), counted
field by field, worst case:

- nominal rate (arbitration phase): the header up to and including BRS, h = 17 bits
  (SOF, 11-bit ID, RRS, IDE, FDF, res, BRS) or 36 (SOF, 11-bit base ID, SRR, IDE, 18-bit
  ID extension, RRS, FDF, res, BRS), with its worst-case dynamic stuff bits
  floor((h - 1) / 4); and the tail, 13 bits: CRC delimiter (the switch back is at its
  sample point; counted whole at the nominal rate, the longer), ACK slot, ACK
  delimiter, 7 EOF, 3 intermission;
- data rate (data phase): ESI, 4 DLC bits, 8 n data bits, the rest of the dynamic stuff
  bits over SOF..last data bit (floor((h + 5 + 8 n - 1) / 4) in all, less the header's),
  the 4-bit stuff count, the CRC (17 bits for n <= 16, 21 above) and its fixed stuff
  bits, one before the stuff count and one after every 4th bit of stuff count and CRC:
  ceil((4 + crc) / 4).

``n`` is padded up to the next FD payload size (0..8, 12, 16, 20, 24, 32, 48, 64). A
64-byte base frame: 34 nominal + 678 data bits, 407 µs at 500 kbit/s / 2 Mbit/s.
"""

from __future__ import annotations

import math

FD_SIZES = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
"""The payload sizes a CAN FD frame can have (DLC 0..15), bytes."""
CLASSIC_MAX = 8
FD_MAX = FD_SIZES[-1]
FD_TAIL_BITS = 13     # CRC delimiter, ACK, ACK delimiter, EOF (7), intermission (3)


def classic_frame_bits(data_bytes: int, extended: bool = False) -> int:
    """Worst-case bits of a classic CAN data frame on the bus (stuffing and
    intermission included): g + 8 s + 13 + floor((g + 8 s − 1)/4)."""
    if not 0 <= data_bytes <= CLASSIC_MAX:
        raise ValueError(f"data_bytes: expected 0..{CLASSIC_MAX}, but got {data_bytes}")
    g = 54 if extended else 34
    return g + 8 * data_bytes + 13 + (g + 8 * data_bytes - 1) // 4


def classic_frame_time(data_bytes: int, bitrate: float, extended: bool = False) -> float:
    """Seconds a worst-case classic frame holds a bus of ``bitrate`` bit/s."""
    return classic_frame_bits(data_bytes, extended) / bitrate


def fd_payload(data_bytes: int) -> int:
    """The smallest CAN FD payload size that holds ``data_bytes``."""
    for size in FD_SIZES:
        if size >= data_bytes:
            return size
    raise ValueError(f"data_bytes: expected 0..{FD_MAX}, but got {data_bytes}")


def fd_frame_bits(data_bytes: int, extended: bool = False) -> tuple[int, int]:
    """(bits at the nominal rate, bits at the data rate) of a worst-case CAN FD frame
    with the bit-rate switch carrying ``data_bytes`` (padded to an FD size)."""
    n = fd_payload(data_bytes)
    header = 36 if extended else 17
    dynamic = header + 5 + 8 * n             # SOF .. last data bit
    stuff_all = (dynamic - 1) // 4
    stuff_header = (header - 1) // 4
    crc = 17 if n <= 16 else 21
    nominal = header + stuff_header + FD_TAIL_BITS
    data = 5 + 8 * n + (stuff_all - stuff_header) + 4 + crc + math.ceil((4 + crc) / 4)
    return nominal, data


def fd_frame_time(data_bytes: int, nominal_rate: float, data_rate: float,
                  extended: bool = False) -> float:
    """Seconds a worst-case CAN FD frame (bit-rate switch) holds the bus."""
    nominal, data = fd_frame_bits(data_bytes, extended)
    return nominal / nominal_rate + data / data_rate
