/*
 * The node's super-loop (platform.h): firmware_py/node.py's run_node over the platform
 * seam, integers only. Single-threaded like an MCU main loop: receive until the next
 * release, then tick; a late tick first drains what is queued (at most BD_DRAIN_MAX), so
 * an overrunning node still reads its inputs.
 */
#include "bessded/platform.h"

static void deliver(bd_agent *a, bd_platform *plat, const bd_frame *f)
{
    if ((f->flags & BD_FRAME_ERR) != 0u) {   /* a bus event, not data (LOOP-4) */
        bd_agent_note(a, BD_C_ERROR_FRAME, 1u);
    } else {
        bd_agent_rx(a, f, bd_platform_now_ns(plat));
    }
}

/* One receive: 1 if a frame was delivered, -1 after a receive error (counted as rx_error,
 * LOOP-6: the loop goes on), 0 if nothing came; what the bus handed up instead of a frame
 * is counted (not_a_frame, invalid_frame) and returns 1 too: something was read. */
static int receive(bd_agent *a, bd_platform *plat, bd_frame *f, int64_t deadline_ns)
{
    int r = bd_platform_recv(plat, f, deadline_ns);
    if (r == 1) {
        deliver(a, plat, f);
    } else if (r == BD_RECV_NOT_A_FRAME) {
        bd_agent_note(a, BD_C_NOT_A_FRAME, 1u);
        r = 1;
    } else if (r == BD_RECV_INVALID_FRAME) {
        bd_agent_note(a, BD_C_INVALID_FRAME, 1u);
        r = 1;
    } else if (r < 0) {
        bd_agent_note(a, BD_C_RX_ERROR, 1u);
    }
    return r;
}

int bd_node_run(bd_agent *a, bd_platform *plat, int64_t duration_ns)
{
    const int64_t period = a->p.period_ns;
    const int64_t start = bd_platform_now_ns(plat);
    int64_t release = start;
    bd_frame f;
    bd_frame out[BD_TICK_FRAMES_MAX];

    while (!bd_platform_should_stop(plat) && a->fatal == 0) {
        int64_t now = bd_platform_now_ns(plat);
        if (duration_ns > 0 && now - start >= duration_ns) {
            break;
        }
        if (now < release) {
            /* wake at least every 50 ms to notice a stop request */
            int64_t until = release - now > 50000000 ? now + 50000000 : release;
            receive(a, plat, &f, until);
            continue;
        }
        for (int k = 0; k < BD_DRAIN_MAX; ++k) {   /* LOOP-3: what is already queued */
            if (receive(a, plat, &f, now) != 1) {
                break;
            }
        }
        int64_t late = now - release;
        if (late > period / 2) {   /* LOOP-2: a miss, and every whole period skipped */
            int64_t skipped = late / period;
            bd_agent_note(a, BD_C_DEADLINE_MISS, (uint32_t)(1 + skipped));
            release += skipped * period;
        }
        size_t n = bd_agent_tick(a, now, out, BD_TICK_FRAMES_MAX);
        for (size_t k = 0u; k < n; ++k) {
            if (bd_platform_send(plat, &out[k]) != 0) {
                bd_agent_note(a, BD_C_SEND_FAILURE, 1u);
            }
        }
        release += period;
    }
    return a->fatal;
}
