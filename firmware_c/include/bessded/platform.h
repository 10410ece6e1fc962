/*
 * The platform seam: the few functions a board provides so that the portable node loop
 * (src/node.c, bd_node_run) can drive an agent. src/linux_platform.c implements them
 * on Linux, over SocketCAN (src/linux_socketcan.c) or python-can's udp_multicast
 * (src/linux_udp_multicast.c); an MCU port implements the same four on its CAN controller and a
 * hardware timer (README: porting to an MCU), plus bd_cmac_aes128 (secoc.h).
 */
#ifndef BESSDED_PLATFORM_H
#define BESSDED_PLATFORM_H

#include <stdint.h>

#include "bessded/agent.h"
#include "bessded/frame.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef struct bd_platform bd_platform;   /* defined by each platform */

/* A monotonic clock in nanoseconds. */
int64_t bd_platform_now_ns(bd_platform *plat);

/* What bd_platform_recv read that was no frame, on a bus that hands up bytes (python-can's
 * udp_multicast: a datagram per frame); the loop counts them as not_a_frame and
 * invalid_frame (firmware_py.node.RX_CAUSES) and reads on. */
#define BD_RECV_NOT_A_FRAME (-2)     /* bytes that are no frame's encoding */
#define BD_RECV_INVALID_FRAME (-3)   /* a frame's encoding, of a frame no CAN bus carries */

/* Wait for one received frame until the absolute time deadline_ns at the latest
 * (deadline_ns <= now: do not wait). Returns 1 with *f filled, 0 if none came, -1 on a
 * receive error, or BD_RECV_NOT_A_FRAME / BD_RECV_INVALID_FRAME for what was read
 * instead of a frame (the loop counts error frames the platform reports as frames with
 * BD_FRAME_ERR). */
int bd_platform_recv(bd_platform *plat, bd_frame *f, int64_t deadline_ns);

/* Queue one frame for transmission; 0 on success, nonzero if it could not be sent
 * (counted as send_failure, never fatal). */
int bd_platform_send(bd_platform *plat, const bd_frame *f);

/* Nonzero once the node should stop (SIGTERM/SIGINT on Linux). */
int bd_platform_should_stop(bd_platform *plat);

#define BD_DRAIN_MAX 256   /* frames read before a late tick (LOOP-3) */

/* The super-loop of firmware_py.node.run_node (spec section 15): receive until the
 * next release, then tick with the clock's time; a tick released more than Ts/2 late is
 * a deadline miss, skipped whole periods count too and the loop re-aligns. Runs until
 * bd_platform_should_stop or, if duration_ns > 0, that long. Returns 0. */
int bd_node_run(bd_agent *a, bd_platform *plat, int64_t duration_ns);

#ifdef __cplusplus
}
#endif

#endif /* BESSDED_PLATFORM_H */
