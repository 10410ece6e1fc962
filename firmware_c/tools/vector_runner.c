/*
 * Replays controller vectors through the C core, for a host or a cross target (qemu-arm).
 * Reads on stdin the text dump tests/test_c_core.py writes from
 * the JSON files of tests/vectors/controller (one token list per line):
 *
 *   V <name> <kind> <kts> <hts> <ts> <band> <dwell> <pow_num> <pow_sqrts> <lambda0> <steps>
 *   S <xi> <dlam> <reset> <lam> <nu> <lam_q24> <armed> <since_reset> <resets> <saturations>
 *
 * Prints "FAIL <name> step <t> field <f>: want <w> got <g>" at the first difference of a
 * vector, and at the end "PASS <vectors> <steps>" (exit 0) or "FAILED <n>" (exit 1).
 */
#include <inttypes.h>
#include <stdio.h>
#include <string.h>

#include "bessded/controller.h"

#define NFIELDS 10

static const char *const field_names[NFIELDS] = {
    "xi", "dlam", "reset", "lam", "nu", "lam_q24", "armed", "since_reset", "resets",
    "saturations"};

int main(void)
{
    char name[128];
    char tag[2];
    bd_ctrl_config cfg;
    bd_ctrl_state s;
    bd_step_out o;
    long vectors = 0;
    long steps_total = 0;
    long failed = 0;

    while (scanf("%1s", tag) == 1) {
        int32_t lambda0;
        long n;
        long t;
        int bad = 0;

        if (tag[0] != 'V'
            || scanf("%127s %" SCNd32 " %" SCNd32 " %" SCNd32 " %" SCNd32 " %" SCNd32
                     " %" SCNu32 " %" SCNu32 " %" SCNu32 " %" SCNd32 " %ld",
                     name, &cfg.kind, &cfg.kts, &cfg.hts, &cfg.tsq, &cfg.band, &cfg.dwell,
                     &cfg.pow_num, &cfg.pow_sqrts, &lambda0, &n) != 11) {
            printf("BAD INPUT after %ld vectors\n", vectors);
            return 2;
        }
        if (bd_ctrl_config_check(&cfg) != BD_OK) {
            printf("FAIL %s config refused\n", name);
            ++failed;
            bad = 1;
        }
        bd_ctrl_init(&s, lambda0);
        for (t = 0; t < n; ++t) {
            int64_t want[NFIELDS];
            int64_t got[NFIELDS];
            int f;

            if (scanf("%1s %" SCNd64 " %" SCNd64 " %" SCNd64 " %" SCNd64 " %" SCNd64
                      " %" SCNd64 " %" SCNd64 " %" SCNd64 " %" SCNd64 " %" SCNd64,
                      tag, &want[0], &want[1], &want[2], &want[3], &want[4], &want[5],
                      &want[6], &want[7], &want[8], &want[9]) != 11 || tag[0] != 'S') {
                printf("BAD INPUT in %s step %ld\n", name, t);
                return 2;
            }
            if (bad) {
                continue;
            }
            bd_ctrl_step(&cfg, &s, (int32_t)want[0], &o);
            got[0] = s.xi_prev;
            got[1] = o.dlam;
            got[2] = o.reset;
            got[3] = s.lam;
            got[4] = s.nu;
            got[5] = bd_ctrl_wire_lambda(&s);
            got[6] = s.armed;
            got[7] = s.since_reset;
            got[8] = s.resets;
            got[9] = s.saturations;
            for (f = 0; f < NFIELDS; ++f) {
                if (got[f] != want[f]) {
                    printf("FAIL %s step %ld field %s: want %" PRId64 " got %" PRId64 "\n",
                           name, t, field_names[f], want[f], got[f]);
                    ++failed;
                    bad = 1;
                    break;
                }
            }
            ++steps_total;
        }
        ++vectors;
    }
    if (failed != 0) {
        printf("FAILED %ld\n", failed);
        return 1;
    }
    printf("PASS %ld %ld\n", vectors, steps_total);
    return 0;
}
