/*
 * The Linux SocketCAN platform (src/linux_socketcan.c): what main_agent.c needs beyond
 * the seam of platform.h.
 */
#ifndef BESSDED_LINUX_SOCKETCAN_H
#define BESSDED_LINUX_SOCKETCAN_H

#include <stddef.h>
#include <stdint.h>

#include "linux_platform.h"

/* Open a raw CAN socket on ifname with an acceptance filter passing ids (n_ids = 0: every
 * frame). 0, or -1 with a message in err. */
int bd_linux_open(bd_platform *plat, const char *ifname, const uint32_t *ids, size_t n_ids,
                  char *err, size_t errlen);

#endif /* BESSDED_LINUX_SOCKETCAN_H */
