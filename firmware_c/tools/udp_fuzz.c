/*
 * A fuzz loop over the udp_multicast datagram reader (src/udp_msgpack.c), built with
 * AddressSanitizer and UBSan (`make udp-fuzz`): random datagrams and mutations (flips,
 * insertions, deletions) of a frame's datagram, each in a heap buffer of exactly its
 * length, so a read past its end or any undefined behaviour aborts the run.
 *
 *   build/udp_fuzz [ITERATIONS [SEED]]   prints the verdicts' counts, exit 0; 1 on a bad
 *                                        verdict or a datagram the writer's reader refuses
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "udp_msgpack.h"

static uint64_t state;

static uint32_t next(void)   /* xorshift64 */
{
    state ^= state << 13u;
    state ^= state >> 7u;
    state ^= state << 17u;
    return (uint32_t)(state >> 32u);
}

static size_t mutate(uint8_t *b, size_t n, size_t cap)
{
    uint32_t edits = 1u + next() % 4u;
    for (uint32_t e = 0u; e < edits; ++e) {
        size_t at = next() % (n + 1u);
        uint32_t op = next() % 3u;
        if (op == 0u && at < n) {
            b[at] = (uint8_t)next();
        } else if (op == 1u && n < cap) {
            memmove(b + at + 1u, b + at, n - at);
            b[at] = (uint8_t)next();
            n++;
        } else if (at < n) {
            memmove(b + at, b + at + 1u, n - at - 1u);
            n--;
        }
    }
    return n;
}

int main(int argc, char **argv)
{
    long iterations = argc > 1 ? strtol(argv[1], NULL, 10) : 1000000L;
    state = argc > 2 ? strtoull(argv[2], NULL, 10) | 1u : 20261127u;
    bd_frame seeds[3] = {{0x123u, 8u, 0u, {1, 2, 3, 4, 5, 6, 7, 8}},
                         {0x1abcdefu, 8u, BD_FRAME_EXT | BD_FRAME_FD | BD_FRAME_BRS, {0}},
                         {0x7ffu, 0u, BD_FRAME_RTR, {0}}};
    uint8_t good[3][BD_UDP_DATAGRAM_MAX];
    size_t good_n[3];
    unsigned long verdicts[3] = {0u, 0u, 0u};
    bd_frame f;
    uint8_t data[64];
    for (int k = 0; k < 3; ++k) {
        good_n[k] = bd_udp_encode(&seeds[k], 0.5, good[k], sizeof good[k]);
        if (good_n[k] == 0u || bd_udp_decode(good[k], good_n[k], &f, data) != BD_UDP_FRAME) {
            (void)printf("udp_fuzz: seed %d does not read back\n", k);
            return 1;
        }
    }
    for (long it = 0; it < iterations; ++it) {
        uint8_t tmp[2u * BD_UDP_DATAGRAM_MAX];
        size_t n;
        if (it % 3 == 0) {
            n = next() % sizeof tmp;
            for (size_t k = 0u; k < n; ++k) {
                tmp[k] = (uint8_t)next();
            }
        } else {
            uint32_t s = next() % 3u;
            memcpy(tmp, good[s], good_n[s]);
            n = mutate(tmp, good_n[s], sizeof tmp);
        }
        uint8_t *buf = malloc(n > 0u ? n : 1u);
        if (buf == NULL) {
            return 1;
        }
        memcpy(buf, tmp, n);
        int r = bd_udp_decode(buf, n, &f, data);
        free(buf);
        if (r < BD_UDP_FRAME || r > BD_UDP_INVALID_FRAME) {
            (void)printf("udp_fuzz: verdict %d\n", r);
            return 1;
        }
        verdicts[r]++;
    }
    (void)printf("frame %lu not_a_frame %lu invalid_frame %lu\n", verdicts[0], verdicts[1],
                 verdicts[2]);
    return 0;
}
