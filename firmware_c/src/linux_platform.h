/*
 * The Linux platforms of bessded-agent (src/linux_platform.c): the one struct bd_platform
 * of platform.h, on SocketCAN (src/linux_socketcan.c) or on python-can's udp_multicast
 * (src/linux_udp_multicast.c), chosen when it is opened (--interface); the clock, the
 * stop flag and the dispatch of receive and send are common.
 */
#ifndef BESSDED_LINUX_PLATFORM_H
#define BESSDED_LINUX_PLATFORM_H

#include <stddef.h>
#include <stdint.h>
#include <sys/socket.h>

#include "bessded/platform.h"

#define BD_LINUX_FILTERS_MAX 512

enum { BD_LINUX_SOCKETCAN, BD_LINUX_UDP_MULTICAST };

struct bd_platform {
    int kind;                        /* BD_LINUX_* */
    int fd;
    uint64_t received;
    uint64_t sent;
    struct sockaddr_storage group;   /* udp_multicast: where every frame is sent */
    socklen_t group_len;
    uint32_t ids[BD_LINUX_FILTERS_MAX];   /* udp_multicast: its acceptance filter in user */
    size_t n_ids;                         /* space, sorted (0: none) */
};

void bd_linux_close(bd_platform *plat);
/* SIGINT and SIGTERM end bd_node_run (bd_platform_should_stop). */
void bd_linux_install_signal_handlers(void);

/* each platform's receive and send (bd_platform_recv/send's contract) */
int bd_socketcan_recv(bd_platform *plat, bd_frame *f);
int bd_socketcan_send(bd_platform *plat, const bd_frame *f);
int bd_udp_recv(bd_platform *plat, bd_frame *f);
int bd_udp_send(bd_platform *plat, const bd_frame *f);

#endif /* BESSDED_LINUX_PLATFORM_H */
