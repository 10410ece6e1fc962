/*
 * One CAN frame as python-can's udp_multicast bus carries it (src/udp_msgpack.c): a
 * datagram holding one msgpack map of 11 entries, in can/interfaces/udp_multicast/utils.py
 * pack_message's order and encodings (python-can 4.6). Portable (no sockets): the Linux
 * platform src/linux_udp_multicast.c sends and receives with it, libbessded.so exports it
 * for the tests (tests/test_c_udp_multicast.py against python-can's packer).
 */
#ifndef BESSDED_UDP_MSGPACK_H
#define BESSDED_UDP_MSGPACK_H

#include <stddef.h>
#include <stdint.h>

#include "bessded/frame.h"

#ifdef __cplusplus
extern "C" {
#endif

/* The longest datagram taken: a 64-byte FD frame's map is 218 bytes (python-can's,
 * channel None); a channel name of up to ~290 bytes still fits. Longer: not a frame. */
#define BD_UDP_DATAGRAM_MAX 512u

/* What bd_udp_decode found (the node counts the last two as firmware_py does on
 * udp_multicast: firmware_py.node.RX_CAUSES). */
#define BD_UDP_FRAME 0            /* a frame, *f filled */
#define BD_UDP_NOT_A_FRAME 1      /* not the map: truncated, trailing bytes, not msgpack, a
                                     key missing, repeated or unknown, too long */
#define BD_UDP_INVALID_FRAME 2    /* the map, but a value no CAN frame has: a wrong type,
                                     an ID beyond 11/29 bits, DLC and data disagreeing, more
                                     than 8 bytes classic, an FD length that is none, flags
                                     no frame combines (remote FD, BRS on classic, ...) */

/* python-can's map of *f (data: its first min(len, BD_FRAME_DATA) bytes; flags BD_FRAME_*; channel
 * None; error_state_indicator false) with `timestamp` (firmware_py's frames: 0.0) into
 * out[0..cap-1]. Returns the datagram's length, 0 if cap is too small. */
size_t bd_udp_encode(const bd_frame *f, double timestamp, uint8_t *out, size_t cap);

/* The frame in the datagram buf[0..n-1] (BD_UDP_*). Reads nothing beyond buf[n-1],
 * whatever the bytes. On BD_UDP_FRAME: *f as the SocketCAN platform fills it (len the
 * true length, up to 64 on FD; data its first BD_FRAME_DATA bytes) and, if data64 is not NULL, all
 * len data bytes into data64[0..63]. */
int bd_udp_decode(const uint8_t *buf, size_t n, bd_frame *f, uint8_t *data64);

#ifdef __cplusplus
}
#endif

#endif /* BESSDED_UDP_MSGPACK_H */
