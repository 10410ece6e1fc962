/*
 * The Linux platform on python-can's udp_multicast bus (src/linux_udp_multicast.c): what
 * main_agent.c needs beyond the seam of platform.h.
 */
#ifndef BESSDED_LINUX_UDP_MULTICAST_H
#define BESSDED_LINUX_UDP_MULTICAST_H

#include <stddef.h>
#include <stdint.h>

#include "linux_platform.h"

/* python-can's UdpMulticastBus defaults (can/interfaces/udp_multicast/bus.py) */
#define BD_UDP_DEFAULT_GROUP "ff15:7079:7468:6f6e:6465:6d6f:6d63:6173"
#define BD_UDP_DEFAULT_PORT 43113

/* Join the multicast group (an IPv6 ff00::/8 or IPv4 224.0.0.0/4 address) on port, as
 * python-can does: hop limit (TTL) 1, SO_REUSEADDR and SO_REUSEPORT, bound to the port
 * on every interface, loopback on (every frame sent comes back: the agent tells its own
 * echo, BD_ECHO_DEPTH). ids[0..n_ids-1] (sorted; n_ids = 0: none): an acceptance filter
 * in user space, passing 11-bit data frames of these IDs and error frames, dropping the
 * rest uncounted (firmware_py.node.AcceptanceBus). 0, or -1 with a message in err. */
int bd_udp_open(bd_platform *plat, const char *group, long port, const uint32_t *ids,
                size_t n_ids, char *err, size_t errlen);

#endif /* BESSDED_LINUX_UDP_MULTICAST_H */
