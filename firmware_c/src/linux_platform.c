/*
 * The platform seam on Linux (platform.h), common to both buses of bessded-agent: the
 * monotonic clock, ppoll for the deadline on the bus's socket, SIGINT/SIGTERM to stop;
 * the frame itself is read and sent by the bus's platform (linux_socketcan.c,
 * linux_udp_multicast.c).
 */
#define _GNU_SOURCE
#include "linux_platform.h"

#include <errno.h>
#include <poll.h>
#include <signal.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

static volatile sig_atomic_t stop_requested;

static void on_signal(int sig)
{
    (void)sig;
    stop_requested = 1;
}

void bd_linux_install_signal_handlers(void)
{
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    (void)sigaction(SIGINT, &sa, NULL);
    (void)sigaction(SIGTERM, &sa, NULL);
}

void bd_linux_close(bd_platform *plat)
{
    if (plat->fd >= 0) {
        (void)close(plat->fd);
        plat->fd = -1;
    }
}

int64_t bd_platform_now_ns(bd_platform *plat)
{
    struct timespec ts;
    (void)plat;
    (void)clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

int bd_platform_recv(bd_platform *plat, bd_frame *f, int64_t deadline_ns)
{
    struct pollfd p = {plat->fd, POLLIN, 0};
    int64_t wait = deadline_ns - bd_platform_now_ns(plat);
    struct timespec ts = {0, 0};
    if (wait > 0) {
        ts.tv_sec = (time_t)(wait / 1000000000);
        ts.tv_nsec = (long)(wait % 1000000000);
    }
    int r = ppoll(&p, 1u, &ts, NULL);
    if (r <= 0) {
        return (r < 0 && errno != EINTR) ? -1 : 0;
    }
    return plat->kind == BD_LINUX_UDP_MULTICAST ? bd_udp_recv(plat, f)
                                                : bd_socketcan_recv(plat, f);
}

int bd_platform_send(bd_platform *plat, const bd_frame *f)
{
    return plat->kind == BD_LINUX_UDP_MULTICAST ? bd_udp_send(plat, f)
                                                : bd_socketcan_send(plat, f);
}

int bd_platform_should_stop(bd_platform *plat)
{
    (void)plat;
    return stop_requested != 0;
}
