/*
 * The platform seam on Linux SocketCAN (platform.h): a raw CAN socket with the agent's
 * acceptance filter installed before it is bound (no gap for foreign frames, GEN-5),
 * error frames and CAN FD frames on (to count them); the clock, the wait and the stop
 * flag are linux_platform.c's.
 */
#define _GNU_SOURCE
#include "linux_socketcan.h"

#include <errno.h>
#include <net/if.h>
#include <stdio.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <unistd.h>

#include <linux/can.h>
#include <linux/can/error.h>
#include <linux/can/raw.h>

int bd_linux_open(bd_platform *plat, const char *ifname, const uint32_t *ids, size_t n_ids,
                  char *err, size_t errlen)
{
    struct ifreq ifr;
    struct sockaddr_can addr;
    int fd = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    memset(plat, 0, sizeof *plat);
    plat->kind = BD_LINUX_SOCKETCAN;
    plat->fd = -1;
    if (fd < 0) {
        (void)snprintf(err, errlen, "cannot open a CAN_RAW socket: %s", strerror(errno));
        return -1;
    }
    if (strlen(ifname) >= sizeof ifr.ifr_name) {
        (void)snprintf(err, errlen, "--channel: expected a network interface name, but "
                       "got '%s' (too long)", ifname);
        (void)close(fd);
        return -1;
    }
    memset(&ifr, 0, sizeof ifr);
    memcpy(ifr.ifr_name, ifname, strlen(ifname) + 1u);
    if (ioctl(fd, SIOCGIFINDEX, &ifr) < 0) {
        (void)snprintf(err, errlen, "--channel: expected a CAN interface (e.g. vcan0, can0), "
                       "but got '%s': %s", ifname, strerror(errno));
        (void)close(fd);
        return -1;
    }
    if (n_ids > 0u) {   /* the acceptance filter: 11-bit data frames of these IDs only */
        struct can_filter filters[BD_LINUX_FILTERS_MAX];
        size_t n = n_ids < BD_LINUX_FILTERS_MAX ? n_ids : BD_LINUX_FILTERS_MAX;
        // cppcheck-suppress knownConditionTrueFalse ; n >= 1 here (n_ids > 0)
        for (size_t k = 0u; k < n; ++k) {
            filters[k].can_id = ids[k];
            filters[k].can_mask = CAN_SFF_MASK | CAN_EFF_FLAG;
        }
        if (setsockopt(fd, SOL_CAN_RAW, CAN_RAW_FILTER, filters,
                       (socklen_t)(n * sizeof filters[0])) < 0) {
            (void)snprintf(err, errlen, "cannot install the acceptance filter: %s",
                           strerror(errno));
            (void)close(fd);
            return -1;
        }
    }
    can_err_mask_t errors = CAN_ERR_MASK;   /* error frames are counted (LOOP-4) */
    (void)setsockopt(fd, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, &errors, sizeof errors);
    /* CAN FD frames are read too, so that a classic node counts them (malformed, RX-2)
     * instead of the kernel dropping them unseen; an FD node (--fd) sends them, which
     * needs an FD interface (vcan: mtu 72): else every send fails, counted */
    int fd_frames = 1;
    (void)setsockopt(fd, SOL_CAN_RAW, CAN_RAW_FD_FRAMES, &fd_frames, sizeof fd_frames);
    memset(&addr, 0, sizeof addr);
    addr.can_family = AF_CAN;
    addr.can_ifindex = ifr.ifr_ifindex;
    if (bind(fd, (struct sockaddr *)&addr, sizeof addr) < 0) {
        (void)snprintf(err, errlen, "cannot bind to %s: %s", ifname, strerror(errno));
        (void)close(fd);
        return -1;
    }
    plat->fd = fd;
    return 0;
}

int bd_socketcan_recv(bd_platform *plat, bd_frame *f)
{
    struct canfd_frame cf;   /* a classic frame fills its first CAN_MTU bytes */
    ssize_t n = recv(plat->fd, &cf, sizeof cf, MSG_DONTWAIT);
    if (n != (ssize_t)CAN_MTU && n != (ssize_t)CANFD_MTU) {
        return (n < 0 && (errno == EAGAIN || errno == EINTR)) ? 0 : -1;
    }
    memset(f, 0, sizeof *f);
    f->flags = (uint8_t)(((cf.can_id & CAN_EFF_FLAG) != 0u ? BD_FRAME_EXT : 0u)
                         | ((cf.can_id & CAN_RTR_FLAG) != 0u ? BD_FRAME_RTR : 0u)
                         | ((cf.can_id & CAN_ERR_FLAG) != 0u ? BD_FRAME_ERR : 0u)
                         | (n == (ssize_t)CANFD_MTU ? BD_FRAME_FD : 0u)
                         | (n == (ssize_t)CANFD_MTU && (cf.flags & CANFD_BRS) != 0u
                            ? BD_FRAME_BRS : 0u));
    f->id = cf.can_id & ((cf.can_id & CAN_EFF_FLAG) != 0u ? CAN_EFF_MASK : CAN_SFF_MASK);
    f->len = cf.len;   /* up to 64 on FD: its DLC check (RX-7) sees the true length */
    memcpy(f->data, cf.data, cf.len <= BD_FRAME_DATA ? cf.len : BD_FRAME_DATA);
    plat->received++;
    return 1;
}

int bd_socketcan_send(bd_platform *plat, const bd_frame *f)
{
    struct canfd_frame cf;   /* a classic frame is its first CAN_MTU bytes */
    size_t size = (f->flags & BD_FRAME_FD) != 0u ? CANFD_MTU : CAN_MTU;
    uint8_t len = f->len <= BD_FRAME_DATA ? f->len : BD_FRAME_DATA;
    memset(&cf, 0, sizeof cf);
    cf.can_id = f->id;
    cf.len = len;
    cf.flags = (f->flags & BD_FRAME_BRS) != 0u ? (uint8_t)CANFD_BRS : 0u;
    memcpy(cf.data, f->data, len);
    if (send(plat->fd, &cf, size, MSG_DONTWAIT) != (ssize_t)size) {
        return -1;   /* a full queue or a down interface: counted, never fatal */
    }
    plat->sent++;
    return 0;
}
