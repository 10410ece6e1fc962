/*
 * The platform seam on python-can's udp_multicast bus (linux_udp_multicast.h): a UDP
 * socket in the bus's multicast group, every frame one datagram holding python-can's
 * msgpack map (udp_msgpack.c), so the node shares the bus with firmware_py's nodes, the
 * recorder and any python-can program. What a datagram holds instead of a frame is
 * handed up as BD_RECV_NOT_A_FRAME / BD_RECV_INVALID_FRAME (the loop counts it, as
 * firmware_py.node's GuardedBus does). No acceptance filter by default: the interface has
 * none below the process (firmware_py installs none on it either), the agent sees every
 * frame; asked for one, it drops in user space what the kernel's would have.
 * The clock, the wait and the stop flag are linux_platform.c's.
 */
#define _GNU_SOURCE
#include "linux_udp_multicast.h"

#include <arpa/inet.h>
#include <errno.h>
#include <netdb.h>
#include <netinet/in.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

#include "udp_msgpack.h"

static int fail(int fd, char *err, size_t errlen, const char *what, const char *group)
{
    (void)snprintf(err, errlen, "cannot %s of the udp_multicast group %s: %s", what, group,
                   strerror(errno));
    if (fd >= 0) {
        (void)close(fd);
    }
    return -1;
}

/* the acceptance filter (bd_udp_open): 1 if f passes */
static int accepted(const bd_platform *plat, const bd_frame *f)
{
    if (plat->n_ids == 0u || (f->flags & BD_FRAME_ERR) != 0u) {
        return 1;
    }
    if ((f->flags & BD_FRAME_EXT) != 0u) {
        return 0;
    }
    size_t lo = 0u;
    size_t hi = plat->n_ids;
    while (lo < hi) {
        size_t mid = lo + (hi - lo) / 2u;
        if (plat->ids[mid] == f->id) {
            return 1;
        }
        if (plat->ids[mid] < f->id) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return 0;
}

int bd_udp_open(bd_platform *plat, const char *group, long port, const uint32_t *ids,
                size_t n_ids, char *err, size_t errlen)
{
    struct addrinfo hints;
    struct addrinfo *ai = NULL;
    int one = 1;
    int hops = 1;   /* python-can's hop_limit: the frames stay on this host's links */
    memset(plat, 0, sizeof *plat);
    plat->kind = BD_LINUX_UDP_MULTICAST;
    plat->fd = -1;
    if (port < 1 || port > 65535) {
        (void)snprintf(err, errlen, "--port: expected a UDP port 1..65535, but got %ld", port);
        return -1;
    }
    memset(&hints, 0, sizeof hints);
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_DGRAM;
    hints.ai_flags = AI_NUMERICHOST;
    if (getaddrinfo(group, NULL, &hints, &ai) != 0 || ai == NULL
        || ai->ai_addrlen > sizeof plat->group) {
        if (ai != NULL) {
            freeaddrinfo(ai);
        }
        (void)snprintf(err, errlen, "--channel: expected a multicast group address (IPv6 "
                       "ff00::/8 or IPv4 224.0.0.0/4), but got '%s'", group);
        return -1;
    }
    int family = ai->ai_family;
    memcpy(&plat->group, ai->ai_addr, ai->ai_addrlen);
    plat->group_len = (socklen_t)ai->ai_addrlen;
    freeaddrinfo(ai);
    struct sockaddr_in *g4 = (struct sockaddr_in *)&plat->group;
    struct sockaddr_in6 *g6 = (struct sockaddr_in6 *)&plat->group;
    if (family == AF_INET6 ? !IN6_IS_ADDR_MULTICAST(&g6->sin6_addr)
                           : !IN_MULTICAST(ntohl(g4->sin_addr.s_addr))) {
        (void)snprintf(err, errlen, "--channel: expected a multicast group address (IPv6 "
                       "ff00::/8 or IPv4 224.0.0.0/4), but got '%s'", group);
        return -1;
    }
    int fd = socket(family, SOCK_DGRAM, 0);
    if (fd < 0) {
        return fail(fd, err, errlen, "open a socket", group);
    }
    /* python-can's options (bus.py _create_socket), in its order */
    if ((family == AF_INET6
         ? setsockopt(fd, IPPROTO_IPV6, IPV6_MULTICAST_HOPS, &hops, sizeof hops)
         : setsockopt(fd, IPPROTO_IP, IP_MULTICAST_TTL, &hops, sizeof hops)) < 0
        || setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one) < 0
        || setsockopt(fd, SOL_SOCKET, SO_REUSEPORT, &one, sizeof one) < 0) {
        return fail(fd, err, errlen, "configure the socket", group);
    }
    if (family == AF_INET6) {
        struct sockaddr_in6 any;
        memset(&any, 0, sizeof any);
        any.sin6_family = AF_INET6;
        any.sin6_addr = in6addr_any;
        any.sin6_port = htons((uint16_t)port);
        g6->sin6_port = any.sin6_port;
        if (bind(fd, (struct sockaddr *)&any, sizeof any) < 0) {
            return fail(fd, err, errlen, "bind to the port", group);
        }
        struct ipv6_mreq req;
        memset(&req, 0, sizeof req);
        req.ipv6mr_multiaddr = g6->sin6_addr;
        req.ipv6mr_interface = 0u;
        if (setsockopt(fd, IPPROTO_IPV6, IPV6_JOIN_GROUP, &req, sizeof req) < 0) {
            return fail(fd, err, errlen, "join", group);
        }
    } else {
        struct sockaddr_in any;
        memset(&any, 0, sizeof any);
        any.sin_family = AF_INET;
        any.sin_addr.s_addr = htonl(INADDR_ANY);
        any.sin_port = htons((uint16_t)port);
        g4->sin_port = any.sin_port;
        if (bind(fd, (struct sockaddr *)&any, sizeof any) < 0) {
            return fail(fd, err, errlen, "bind to the port", group);
        }
        struct ip_mreq req;
        memset(&req, 0, sizeof req);
        req.imr_multiaddr = g4->sin_addr;
        req.imr_interface.s_addr = htonl(INADDR_ANY);
        if (setsockopt(fd, IPPROTO_IP, IP_ADD_MEMBERSHIP, &req, sizeof req) < 0) {
            return fail(fd, err, errlen, "join", group);
        }
    }
    plat->n_ids = n_ids < BD_LINUX_FILTERS_MAX ? n_ids : BD_LINUX_FILTERS_MAX;
    // cppcheck-suppress knownConditionTrueFalse ; n_ids may be 1..512 (a false positive)
    if (plat->n_ids > 0u) {
        memcpy(plat->ids, ids, plat->n_ids * sizeof ids[0]);
    }
    plat->fd = fd;
    return 0;
}

int bd_udp_recv(bd_platform *plat, bd_frame *f)
{
    uint8_t buf[BD_UDP_DATAGRAM_MAX + 1u];
    /* MSG_TRUNC: the datagram's true length, so a longer one is refused, never cut */
    ssize_t n = recv(plat->fd, buf, sizeof buf, MSG_DONTWAIT | MSG_TRUNC);
    if (n < 0) {
        return (errno == EAGAIN || errno == EINTR) ? 0 : -1;
    }
    plat->received++;
    if ((size_t)n > BD_UDP_DATAGRAM_MAX) {
        return BD_RECV_NOT_A_FRAME;
    }
    switch (bd_udp_decode(buf, (size_t)n, f, NULL)) {
    case BD_UDP_FRAME:
        return accepted(plat, f) ? 1 : 0;   /* filtered: as if nothing came */
    case BD_UDP_INVALID_FRAME:
        return BD_RECV_INVALID_FRAME;
    default:
        return BD_RECV_NOT_A_FRAME;
    }
}

int bd_udp_send(bd_platform *plat, const bd_frame *f)
{
    uint8_t buf[BD_UDP_DATAGRAM_MAX];
    size_t n = bd_udp_encode(f, 0.0, buf, sizeof buf);   /* firmware_py's frames: 0.0 too */
    if (n == 0u || sendto(plat->fd, buf, n, MSG_DONTWAIT, (struct sockaddr *)&plat->group,
                          plat->group_len) != (ssize_t)n) {
        return -1;   /* a full queue or no route: counted, never fatal */
    }
    plat->sent++;
    return 0;
}
