/*
 * The Linux SocketCAN platform (src/linux_socketcan.c): what main_agent.c needs beyond
 * the seam of platform.h.
 */
#ifndef BESSDED_LINUX_SOCKETCAN_H
#define BESSDED_LINUX_SOCKETCAN_H

#include <stddef.h>
#include <stdint.h>

#include "bessded/platform.h"

#define BD_LINUX_FILTERS_MAX 512

struct bd_platform {
    int fd;
    uint64_t received;
    uint64_t sent;
};

/* Open a raw CAN socket on ifname with an acceptance filter passing ids (n_ids = 0: every
 * frame). 0, or -1 with a message in err. */
int bd_linux_open(bd_platform *plat, const char *ifname, const uint32_t *ids, size_t n_ids,
                  char *err, size_t errlen);
void bd_linux_close(bd_platform *plat);
/* SIGINT and SIGTERM end bd_node_run (bd_platform_should_stop). */
void bd_linux_install_signal_handlers(void);

#endif /* BESSDED_LINUX_SOCKETCAN_H */
