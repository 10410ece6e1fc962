/*
 * bessded-agent: one BESS agent on Linux, the C twin of `bess-ded agent`.
 *
 *   bessded-agent --config agent_3.toml (--key agent_3.key | --insecure) --channel can0
 *                 [--fd [--no-lambda-tags]] [--interface socketcan] [--duration S]
 *                 [--rt-priority N]
 *                 [--no-acceptance-filter] [--counters-dir DIR]
 *   bessded-agent --config agent_3.toml (--key ... | --insecure) --interface udp_multicast
 *                 [--channel GROUP] [--port N] [--fd [--no-lambda-tags]] [--duration S]
 *                 [--rt-priority N]
 *                 [--acceptance-filter] [--counters-dir DIR]
 *
 * SocketCAN (the default) on a CAN interface; or python-can's udp_multicast bus (the
 * project's default bus), GROUP an IPv6 or IPv4 multicast address (default python-can's
 * ff15:7079:7468:6f6e:6465:6d6f:6d63:6173), port N (default 43113). The acceptance
 * filter is on by default on SocketCAN (the kernel's), off on udp_multicast (no filter
 * below the process there: --acceptance-filter drops the frames in user space, uncounted,
 * as firmware_py's does).
 *
 * The configuration and key files are the ones firmware_py reads (`bess-ded up` and
 * `bess-ded keys` write them). Bad input: "bessded-agent: error: ..." and exit 2. On
 * SIGTERM/SIGINT it stops, prints a summary line with every non-zero counter, exits 0;
 * --counters-dir DIR: and writes DIR/agent_<id>.counters.json as firmware_py's
 * --counters-dir does (the signed price's counters, no Diag slot, and deadline_miss).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "bessded/config.h"
#include "bessded/platform.h"
#include "linux_socketcan.h"
#include "linux_udp_multicast.h"

#define PROG "bessded-agent"
#define LOG_FIRST 5u   /* rejections logged per cause, then every 1000th (as firmware_py) */

static const char *const state_names[] = {"INIT", "RUNNING", "ISOLATED", "SAFE"};

static int usage(const char *problem)
{
    (void)fprintf(stderr, "usage: " PROG " --config FILE (--key FILE | --insecure) "
                  "[--interface socketcan] --channel IFACE [--fd [--no-lambda-tags]] "
                  "[--duration S] "
                  "[--rt-priority N] [--no-acceptance-filter] [--counters-dir DIR]\n"
                  "       " PROG " --config FILE (--key FILE | --insecure) "
                  "--interface udp_multicast [--channel GROUP] [--port N] "
                  "[--fd [--no-lambda-tags]] "
                  "[--duration S] [--rt-priority N] [--acceptance-filter] "
                  "[--counters-dir DIR]\n" PROG ": error: %s\n", problem);
    return 2;
}

static void on_event(void *ctx, int event, uint32_t frame_id, uint32_t detail)
{
    const uint32_t *id = ctx;
    if (event == BD_EV_STATE) {
        (void)fprintf(stderr, "agent %u: state %s\n", *id,
                      detail < 4u ? state_names[detail] : "?");
        return;
    }
    if (event == BD_C_RESYNCS || event == BD_C_LOST_FRAMES || event == BD_C_SATURATIONS
        || event == BD_C_COMMANDS || event == BD_C_DEADLINE_MISS) {
        return;   /* counted, not rejections */
    }
    if (detail <= LOG_FIRST || detail % 1000u == 0u) {
        (void)fprintf(stderr, "agent %u: %s #%u (0x%03X)\n", *id, bd_counter_name(event),
                      detail, frame_id);
    }
}

static int parse_seconds(const char *s, double *out)
{
    char *end = NULL;
    errno = 0;
    double v = strtod(s, &end);
    if (end == s || *end != '\0' || errno != 0 || !(v > 0.0) || v > 1e9) {
        return -1;
    }
    *out = v;
    return 0;
}

/* firmware_py's --counters-dir file (AgentRuntime.verdict_counters, json.dumps' layout):
 * the ticks and the non-zero counters the verdict cannot read from AGENT_<i>_Diag. */
static int write_counters(const char *dir, uint32_t id, const bd_agent *agent)
{
    static const int which[] = {BD_C_UNSIGNED_PRICE, BD_C_BAD_SIGNATURE, BD_C_SIG_MALFORMED,
                                BD_C_DEADLINE_MISS};
    char path[4200];
    (void)snprintf(path, sizeof path, "%s/agent_%u.counters.json", dir, id);
    FILE *f = fopen(path, "w");
    if (f == NULL) {
        (void)fprintf(stderr, PROG ": error: %s: %s\n", path, strerror(errno));
        return -1;
    }
    int ok = fprintf(f, "{\"ticks\": %u, \"counters\": {", agent->ticks) > 0;
    int any = 0;
    for (size_t k = 0u; k < sizeof which / sizeof which[0]; ++k) {
        uint32_t v = bd_agent_counter(agent, which[k]);
        if (v != 0u) {
            ok = ok && fprintf(f, "%s\"%s\": %u", any ? ", " : "", bd_counter_name(which[k]),
                               v) > 0;
            any = 1;
        }
    }
    ok = ok && fprintf(f, "}}\n") > 0;
    ok = (fclose(f) == 0) && ok;
    if (!ok) {
        (void)fprintf(stderr, PROG ": error: %s: cannot write the counters\n", path);
    }
    return ok ? 0 : -1;
}

int main(int argc, char **argv)
{
    const char *config = NULL;
    const char *key = NULL;
    const char *channel = NULL;
    const char *counters_dir = NULL;
    int insecure = 0;
    int udp = 0;
    long port = -1;
    int filter = -1;   /* the bus's default: on for socketcan, off for udp_multicast */
    int fd = 0;
    int no_tags = 0;
    long rt = 0;
    double duration = 0.0;
    char err[1024];
    static bd_agent agent;
    static bd_keyring keys;
    bd_agent_params params;
    bd_platform plat;

    for (int i = 1; i < argc; ++i) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (strcmp(a, "--insecure") == 0) {
            insecure = 1;
        } else if (strcmp(a, "--fd") == 0) {   /* GEN-1: a CAN FD bus */
            fd = 1;
        } else if (strcmp(a, "--no-lambda-tags") == 0) {   /* AUTH-34: FD without λ tags */
            no_tags = 1;
        } else if (strcmp(a, "--no-acceptance-filter") == 0) {
            filter = 0;
        } else if (strcmp(a, "--acceptance-filter") == 0) {
            filter = 1;
        } else if (strcmp(a, "-h") == 0 || strcmp(a, "--help") == 0) {
            (void)usage("(help)");
            return 0;
        } else if (v == NULL) {
            (void)snprintf(err, sizeof err, "%s: expected a value, but got nothing", a);
            return usage(err);
        } else if (strcmp(a, "--config") == 0) {
            config = v;
            ++i;
        } else if (strcmp(a, "--key") == 0) {
            key = v;
            ++i;
        } else if (strcmp(a, "--channel") == 0) {
            channel = v;
            ++i;
        } else if (strcmp(a, "--counters-dir") == 0) {   /* as firmware_py's */
            counters_dir = v;
            ++i;
        } else if (strcmp(a, "--interface") == 0) {   /* bess-ded agent's bus flags */
            if (strcmp(v, "socketcan") != 0 && strcmp(v, "udp_multicast") != 0) {
                (void)snprintf(err, sizeof err, "--interface: expected socketcan or "
                               "udp_multicast (the buses this node runs on), but got '%s'", v);
                return usage(err);
            }
            udp = strcmp(v, "udp_multicast") == 0;
            ++i;
        } else if (strcmp(a, "--port") == 0) {
            char *end = NULL;
            errno = 0;
            port = strtol(v, &end, 10);
            if (end == v || *end != '\0' || errno != 0 || port < 1 || port > 65535) {
                (void)snprintf(err, sizeof err, "--port: expected a UDP port 1..65535, but "
                               "got '%s'", v);
                return usage(err);
            }
            ++i;
        } else if (strcmp(a, "--duration") == 0) {
            if (parse_seconds(v, &duration) != 0) {
                (void)snprintf(err, sizeof err, "--duration: expected a number of seconds "
                               "> 0, but got '%s'", v);
                return usage(err);
            }
            ++i;
        } else if (strcmp(a, "--rt-priority") == 0) {
            char *end = NULL;
            rt = strtol(v, &end, 10);
            if (*end != '\0' || rt < 0 || rt > 99) {
                (void)snprintf(err, sizeof err, "--rt-priority: expected 0..99, but got '%s'",
                               v);
                return usage(err);
            }
            ++i;
        } else {
            (void)snprintf(err, sizeof err, "expected one of --config, --key, --insecure, "
                           "--fd, --no-lambda-tags, --channel, --interface socketcan|udp_multicast, --port, "
                           "--duration, --rt-priority, --[no-]acceptance-filter, "
                           "--counters-dir, but got '%s'", a);
            return usage(err);
        }
    }
    if (udp && channel == NULL) {
        channel = BD_UDP_DEFAULT_GROUP;   /* python-can's default group */
    }
    if (config == NULL || channel == NULL || (key == NULL) == (insecure == 0)) {
        return usage("expected --config, --channel and exactly one of --key or --insecure");
    }
    if (no_tags && !fd) {
        return usage("--no-lambda-tags: expected it only with --fd (classic CAN has no room "
                     "for the tags)");
    }
    if (!udp && port >= 0) {
        return usage("--port: expected only with --interface udp_multicast (a SocketCAN "
                     "interface has no port)");
    }
    if (bd_config_load(config, &params, err, sizeof err) != 0) {
        (void)fprintf(stderr, PROG ": error: %s\n", err);
        return 2;
    }
    params.fd = (uint32_t)fd;
    params.no_lambda_tags = (uint32_t)no_tags;
    if (fd && !no_tags && params.n_neighbours > BD_FD_NEIGHBOURS_MAX) {
        (void)fprintf(stderr, PROG ": error: %s: [[neighbour]] expected at most %d neighbours "
                      "on a CAN FD bus (--fd: AUTH-34's λ tag slots, %d with the plant's and "
                      "the router's), but got %u\n", config, BD_FD_NEIGHBOURS_MAX,
                      BD_TAG_SLOTS, (unsigned)params.n_neighbours);
        return 2;
    }
    char node[BD_LABEL_MAX + 1];
    (void)snprintf(node, sizeof node, "agent_%u", params.id);
    if (insecure) {
        (void)fprintf(stderr, PROG ": warning: %s runs --insecure: its frames are signed with "
                      "the public demo key and anyone on the bus can forge them "
                      "(docs/security.md)\n", node);
        (void)bd_keyring_insecure(node, &keys);
    } else if (bd_keyfile_load(key, node, &keys, err, sizeof err) != 0) {
        (void)fprintf(stderr, PROG ": error: %s\n", err);
        return 2;
    }
    int rc = bd_agent_init(&agent, &params, &keys, on_event, &params.id);
    if (rc != BD_OK) {
        (void)fprintf(stderr, PROG ": error: %s: %s\n", insecure ? node : key,
                      rc == BD_ERR_MISSING_KEY ? "expected the verification key of every "
                      "sender of this agent's inputs (the router, the plant and each "
                      "neighbour), but the key file lacks one: re-provision with bess-ded keys"
                      : rc == BD_ERR_BOOT ? "cannot advance the boot counter (exhausted, or "
                      "the key file cannot be rewritten)"
                      : rc == BD_ERR_PRICE_KEY ? "[security.signed_price] expected a key file "
                      "with the router's public price key ([price_signature] verify_key), but "
                      "it has none: re-provision with bess-ded keys for a signed_price "
                      "scenario" : "the agent refused its parameters");
        return 2;
    }
    uint32_t ids[BD_LINUX_FILTERS_MAX];
    if (filter < 0) {
        filter = !udp;
    }
    size_t n_ids = filter ? bd_agent_accepted_ids(&agent, ids, BD_LINUX_FILTERS_MAX) : 0u;
    if ((udp ? bd_udp_open(&plat, channel, port >= 0 ? port : BD_UDP_DEFAULT_PORT, ids, n_ids,
                           err, sizeof err)
             : bd_linux_open(&plat, channel, ids, n_ids, err, sizeof err)) != 0) {
        (void)fprintf(stderr, PROG ": error: %s\n", err);
        return 2;
    }
    if (rt > 0) {
        struct sched_param sp;
        memset(&sp, 0, sizeof sp);
        sp.sched_priority = (int)rt;
        if (sched_setscheduler(0, SCHED_FIFO, &sp) != 0) {
            (void)fprintf(stderr, PROG ": warning: --rt-priority %ld not applied (%s): running "
                          "with normal priority\n", rt, strerror(errno));
        }
    }
    bd_linux_install_signal_handlers();
    int fatal = bd_node_run(&agent, &plat, (int64_t)(duration * 1e9));
    bd_linux_close(&plat);

    int32_t lam = bd_agent_lambda(&agent);
    (void)fprintf(stderr, "agent %u (C): state=%s λ=%.6f resets=%u ticks=%u counters: ",
                  params.id, state_names[bd_agent_state(&agent) & 3u],
                  (double)lam / 16777216.0, bd_agent_resets(&agent), agent.ticks);
    int any = 0;
    for (int c = 0; c < BD_C_COUNT; ++c) {
        uint32_t v = bd_agent_counter(&agent, c);
        if (v != 0u) {
            (void)fprintf(stderr, "%s%s=%u", any ? ", " : "", bd_counter_name(c), v);
            any = 1;
        }
    }
    (void)fprintf(stderr, "%s\n", any ? "" : "none");
    if (counters_dir != NULL && write_counters(counters_dir, params.id, &agent) != 0) {
        return 1;
    }
    if (fatal != 0) {
        (void)fprintf(stderr, PROG ": error: stopped: %s\n", fatal == BD_ERR_BOOT
                      ? "no boot counter left at a message-count wrap (re-provision the keys)"
                      : "the CMAC primitive failed");
        return 1;
    }
    return 0;
}
