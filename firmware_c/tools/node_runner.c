/*
 * Replays node vectors (tests/vectors/node) through the C agent, for a host or a cross
 * target (qemu-arm): the configuration through the C loader (src/config.c), the keys,
 * then every received frame and tick; prints every frame the agent sends. Reads on stdin
 * the text dump tests/test_c_agent.py writes, one vector after the other:
 *
 *   V <name> <config TOML as hex>
 *   P <price key hex> <fleet ID hex>    (optional, before K: signed_price, AUTH-31)
 *   K <node> <insecure 0/1> <key hex> <boot> <n_peers> [<label> <key hex> <floor>]...
 *     <n_frames 0/4> [<setpoint key hex> <status key hex> <Diag key hex>
 *     <command key hex> <the plant's floor>] (AUTH-28..30)
 *   S <tx_count>                        (optional: the vector's setup)
 *   R <t_ns> <id> <flags> <data hex or ->
 *   T <t_ns>
 *   E
 *
 * Prints "F <t_ns> <id> <8 data bytes hex>" per frame sent, "END <name>" per vector, or
 * "FAIL <name>: <why>" (exit 1) when the configuration or the keys are refused.
 *
 * `node_runner --bench` (bess-ded bench): one vector; its R/T events are read into memory
 * first, then replayed with the clock read around each tick's work (the frames received
 * since the last tick and the tick itself); prints "BENCH <ticks> <ns total> <ns worst>"
 * and nothing per frame.
 */
#define _POSIX_C_SOURCE 199309L
#include <inttypes.h>
#include <stdio.h>
#include <string.h>
#include <time.h>

#include "bessded/agent.h"
#include "bessded/config.h"

#define TEXT_MAX 65536
#define BENCH_EVENTS 400000

typedef struct {
    int64_t t;
    bd_frame f;   /* id 0 and len 0xFF: a tick */
} event;

static event events[BENCH_EVENTS];

static int64_t now_ns(void)
{
    struct timespec ts;
    (void)clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static void bench(bd_agent *agent, size_t n)
{
    bd_frame out[BD_TICK_FRAMES_MAX];
    int64_t total = 0;
    int64_t worst = 0;
    long ticks = 0;
    int64_t start = now_ns();
    for (size_t k = 0u; k < n; ++k) {
        if (events[k].f.len != 0xFFu) {
            bd_agent_rx(agent, &events[k].f, events[k].t);
            continue;
        }
        (void)bd_agent_tick(agent, events[k].t, out, BD_TICK_FRAMES_MAX);
        int64_t end = now_ns();
        total += end - start;
        worst = end - start > worst ? end - start : worst;
        ticks++;
        start = now_ns();
    }
    printf("BENCH %ld %" PRId64 " %" PRId64 "\n", ticks, total, worst);
}

static int unhex(const char *s, uint8_t *out, size_t max, size_t *n)
{
    size_t len = strlen(s);
    if (strcmp(s, "-") == 0) {
        *n = 0u;
        return 0;
    }
    if (len % 2u != 0u || len / 2u > max) {
        return -1;
    }
    for (size_t k = 0u; k < len / 2u; ++k) {
        unsigned v;
        if (sscanf(&s[2u * k], "%2x", &v) != 1) {
            return -1;
        }
        out[k] = (uint8_t)v;
    }
    *n = len / 2u;
    return 0;
}

int main(int argc, char **argv)
{
    int bench_mode = argc > 1 && strcmp(argv[1], "--bench") == 0;
    size_t n_events = 0u;
    static char hex[2 * TEXT_MAX + 1];
    static char text[TEXT_MAX];
    static bd_agent agent;
    static bd_keyring keys;
    char tag[2];
    char name[128];
    char err[1024];
    bd_agent_params params;
    int failed = 0;
    int has_price = 0;
    uint8_t price_key[BD_ED25519_PUBLIC_BYTES];
    uint8_t fleet[8];

    while (scanf("%1s", tag) == 1) {
        if (tag[0] == 'V') {
            size_t n;
            if (scanf("%127s %131072s", name, hex) != 2
                || unhex(hex, (uint8_t *)text, TEXT_MAX - 1u, &n) != 0) {
                printf("BAD INPUT at V\n");
                return 2;
            }
            text[n] = '\0';
            if (bd_config_parse(text, name, &params, err, sizeof err) != 0) {
                printf("FAIL %s: %s\n", name, err);
                failed = 1;
            }
        } else if (tag[0] == 'P') {   /* AUTH-31: the router's public key, the fleet ID */
            char phex[2 * BD_ED25519_PUBLIC_BYTES + 2];
            char fhex[20];
            size_t n;
            size_t m;
            if (scanf("%65s %19s", phex, fhex) != 2
                || unhex(phex, price_key, sizeof price_key, &n) != 0 || n != sizeof price_key
                || unhex(fhex, fleet, sizeof fleet, &m) != 0 || m != sizeof fleet) {
                printf("BAD INPUT at P\n");
                return 2;
            }
            has_price = 1;
        } else if (tag[0] == 'K') {
            char khex[64];
            int insecure;
            uint32_t n_peers;
            size_t n;
            memset(&keys, 0, sizeof keys);
            if (scanf("%32s %d %63s %" SCNu32 " %" SCNu32, keys.node, &insecure, khex,
                      &keys.boot, &n_peers) != 5 || n_peers > BD_MAX_PEERS
                || unhex(khex, keys.key, BD_KEY_BYTES, &n) != 0) {
                printf("BAD INPUT at K\n");
                return 2;
            }
            keys.insecure = insecure;
            for (uint32_t p = 0u; p < n_peers; ++p) {
                uint32_t floor;
                if (scanf("%32s %63s %" SCNu32, keys.peer_label[p], khex, &floor) != 3
                    || floor > 65535u || unhex(khex, keys.peer_key[p], BD_KEY_BYTES, &n) != 0) {
                    printf("BAD INPUT at K peers\n");
                    return 2;
                }
                keys.peer_floor[p] = (uint16_t)floor;   /* AUTH-21 */
            }
            keys.n_peers = n_peers;
            /* AUTH-28..30: 0, or the setpoint's, the status', the Diag's and the command
             * keys */
            uint32_t n_frames;
            if (scanf("%" SCNu32, &n_frames) != 1 || (n_frames != 0u && n_frames != 4u)) {
                printf("BAD INPUT at K frames\n");
                return 2;
            }
            if (n_frames == 4u) {
                char shex[64];
                char dhex[64];
                char chex[64];
                uint32_t floor;
                if (scanf("%63s %63s %63s %63s %" SCNu32, khex, shex, dhex, chex, &floor) != 5
                    || floor > 65535u
                    || unhex(khex, keys.setpoint_key, BD_KEY_BYTES, &n) != 0
                    || unhex(shex, keys.status_key, BD_KEY_BYTES, &n) != 0
                    || unhex(dhex, keys.diag_key, BD_KEY_BYTES, &n) != 0
                    || unhex(chex, keys.command_key, BD_KEY_BYTES, &n) != 0) {
                    printf("BAD INPUT at K frames\n");
                    return 2;
                }
                keys.has_frame_keys = 1;
                keys.status_floor = (uint16_t)floor;
            }
            if (has_price) {
                keys.has_price_key = 1;
                memcpy(keys.price_key, price_key, sizeof price_key);
                memcpy(keys.fleet_id, fleet, sizeof fleet);
                has_price = 0;
            }
            int rc = bd_agent_init(&agent, &params, &keys, NULL, NULL);
            if (rc != BD_OK) {
                printf("FAIL %s: bd_agent_init %d\n", name, rc);
                failed = 1;
            }
        } else if (tag[0] == 'S') {
            uint32_t count;
            if (scanf("%" SCNu32, &count) != 1) {
                printf("BAD INPUT at S\n");
                return 2;
            }
            bd_agent_set_tx_count(&agent, count, count, count);
        } else if (tag[0] == 'R') {
            bd_frame f;
            int64_t t;
            uint32_t id;
            unsigned flags;
            size_t n;
            memset(&f, 0, sizeof f);
            if (scanf("%" SCNd64 " %" SCNu32 " %u %31s", &t, &id, &flags, hex) != 4
                || unhex(hex, f.data, 8u, &n) != 0) {
                printf("BAD INPUT at R\n");
                return 2;
            }
            f.id = id;
            f.flags = (uint8_t)flags;
            f.len = (uint8_t)n;
            if (bench_mode && n_events < BENCH_EVENTS) {
                events[n_events].t = t;
                events[n_events++].f = f;
            } else {
                bd_agent_rx(&agent, &f, t);
            }
        } else if (tag[0] == 'T') {
            bd_frame out[BD_TICK_FRAMES_MAX];
            int64_t t;
            if (scanf("%" SCNd64, &t) != 1) {
                printf("BAD INPUT at T\n");
                return 2;
            }
            if (bench_mode && n_events < BENCH_EVENTS) {
                memset(&events[n_events].f, 0, sizeof events[n_events].f);
                events[n_events].f.len = 0xFFu;
                events[n_events++].t = t;
                continue;
            }
            size_t n = bd_agent_tick(&agent, t, out, BD_TICK_FRAMES_MAX);
            for (size_t k = 0u; k < n; ++k) {
                printf("F %" PRId64 " %" PRIu32 " ", t, out[k].id);
                for (size_t b = 0u; b < out[k].len; ++b) {
                    printf("%02x", out[k].data[b]);
                }
                printf("\n");
            }
        } else if (tag[0] == 'E') {
            if (bench_mode) {
                bench(&agent, n_events);
                n_events = 0u;
            } else {
                printf("END %s\n", name);
            }
        } else {
            printf("BAD INPUT: tag %c\n", tag[0]);
            return 2;
        }
    }
    return failed;
}
