/*
 * The agent configuration (config.h; docs/firmware-spec.md section 3, CFG-1..7): the
 * parsed TOML (toml.c) checked with firmware_py/config.py's rules, key names and wording,
 * and turned into bd_agent_params. The binary64 arithmetic of the spec's formulas (q24,
 * q30, rne, the default timeouts) happens here, written as the reference writes it,
 * operation for operation; nothing of it reaches the runtime. The key file is keyfile.c.
 */
#include "bessded/config.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

#include "toml.h"

/* [transmit] defaults (firmware_py/config.py: EVENT_THRESHOLD, EVENT_HEARTBEAT, ...): a
 * neighbour timeout of heartbeat + margin periods stays within the 4-bit counter window,
 * so at most 15 frames of a live neighbour can be lost in a row (CFG-9, AUTH-12) */
#define BD_EVENT_THRESHOLD 3e-4
#define BD_EVENT_HEARTBEAT 13
#define BD_HEARTBEAT_MARGIN 2
#define BD_EVENT_HEARTBEAT_MAX ((1 << BD_FV_TX_BITS) - 1 - BD_HEARTBEAT_MARGIN)

/* Unknown keys of a table (CFG-1): "[table.key] unknown key; expected one of ..." */
static int check_keys(toml_doc *d, const char *table, const char *const *allowed,
                      const char *list)
{
    for (int k = 0; k < d->n; ++k) {
        const toml_entry *e = &d->e[k];
        if (strcmp(e->table, table) != 0) {
            continue;
        }
        int ok = 0;
        for (const char *const *a = allowed; *a != NULL; ++a) {
            ok |= strcmp(*a, e->key) == 0;
        }
        if (!ok) {
            char key[2 * NAME_MAX_ + 1];
            (void)snprintf(key, sizeof key, "%s.%s", table, e->key);
            return bd_toml_errorf(d, key, "unknown key; expected one of %s", list);
        }
    }
    return 0;
}

/* num() of firmware_py/config.py: a finite number in [lo, hi], or the default */
static int num(toml_doc *d, const char *table, int index, const char *name, double lo,
               double hi, const double *def, double *out)
{
    char key[2 * NAME_MAX_ + 16];
    char got[160];
    if (index >= 0) {
        (void)snprintf(key, sizeof key, "%s[%d].%s", table, index + 1, name); /* numbered from 1 */
    } else {
        (void)snprintf(key, sizeof key, "%s.%s", table, name);
    }
    toml_entry *e = bd_toml_find(d, table, index, name);
    if (e == NULL) {
        if (def == NULL) {
            return bd_toml_errorf(d, key, "is required");
        }
        *out = *def;
        return 0;
    }
    if ((e->type != TOML_INT && e->type != TOML_FLOAT) || !isfinite(e->f)) {
        return bd_toml_errorf(d, key, "expected a number, but got %s",
                              bd_toml_repr(e, got, sizeof got));
    }
    if (!(lo <= e->f && e->f <= hi)) {
        return bd_toml_errorf(d, key, "expected a value in [%g, %g], but got %s", lo, hi,
                              bd_toml_repr(e, got, sizeof got));
    }
    *out = e->f;
    return 0;
}

/* count() of firmware_py/config.py: an integer in lo..hi */
static int count(toml_doc *d, const char *name, long long lo, long long hi, long long def,
                 uint32_t *out)
{
    char key[NAME_MAX_ + 8];
    toml_entry *e = bd_toml_find(d, "limits", -1, name);
    long long v = def;
    (void)snprintf(key, sizeof key, "limits.%s", name);
    if (e != NULL) {
        if (e->type != TOML_INT || e->i < lo || e->i > hi) {
            char got[160];
            return bd_toml_errorf(d, key, "expected an integer in %lld..%lld, but got %s", lo,
                                  hi, bd_toml_repr(e, got, sizeof got));
        }
        v = e->i;
    }
    *out = (uint32_t)v;
    return 0;
}

static int agent_id(toml_doc *d, toml_entry *e, const char *key, uint32_t *out)
{
    if (e == NULL) {
        return bd_toml_errorf(d, key, "expected an agent id in 1..%d, but got None",
                              BD_N_AGENTS_MAX);
    }
    if (e->type != TOML_INT || e->i < 1 || e->i > BD_N_AGENTS_MAX) {
        char got[160];
        return bd_toml_errorf(d, key, "expected an agent id in 1..%d, but got %s",
                              BD_N_AGENTS_MAX, bd_toml_repr(e, got, sizeof got));
    }
    *out = (uint32_t)e->i;
    return 0;
}

/* ------------------------------------------------------------------ the spec's arithmetic */

/* q24 / NUM-4: rne(x * 2^24), which must fit an int32 */
static int q24(double x, int32_t *out)
{
    double r = nearbyint(x * 16777216.0);
    if (!(r >= -2147483648.0 && r <= 2147483647.0)) {
        return -1;
    }
    *out = (int32_t)r;
    return 0;
}

/* q30 / NUM-6: rne(x * 2^30) in [0, 2^31 - 1], and x = 0 or x >= 2^-30 */
static int q30(double x, int32_t *out)
{
    double r = isfinite(x) ? nearbyint(x * 1073741824.0) : -1.0;
    if (!(r >= 0.0 && r <= 2147483647.0)) {
        return -1;
    }
    if ((x < 0.0 || x > 0.0) && x < 1.0 / 1073741824.0) {
        return -2;
    }
    *out = (int32_t)r;
    return 0;
}

static int64_t to_ns(double s)
{
    return (int64_t)nearbyint(s * 1e9);
}

static int positive(toml_doc *d, const toml_entry *e, const char *name, double upper,
                    double *out, double def)
{
    char key[NAME_MAX_ + 16];
    (void)snprintf(key, sizeof key, "controller.%s", name);
    if (e == NULL) {
        *out = def;
        return 0;
    }
    if ((e->type != TOML_INT && e->type != TOML_FLOAT) || !isfinite(e->f) || !(e->f > 0.0)
        || e->f > upper) {
        char got[160];
        return bd_toml_errorf(d, key, "expected a finite number in (0, %g], but got %s", upper,
                              bd_toml_repr(e, got, sizeof got));
    }
    *out = e->f;
    return 0;
}

static int finite_entry(const toml_entry *e)
{
    return (e->type == TOML_INT || e->type == TOML_FLOAT) && isfinite(e->f);
}

/* ControllerConfig (CFG-3, CTRL-1..3) */
static int controller(toml_doc *d, bd_ctrl_config *c, double *k_out, double *h_out,
                      double *ts_out)
{
    static const char *const kinds[] = {"pc", "pi", "reset", "dwell", "ft"};
    char got[160];
    double k, h, ts, dwell = 0.0, band = 1e-4, a = 0.5;
    toml_entry *e = bd_toml_find(d, "controller", -1, "kind");
    int kind = BD_KIND_RESET;
    if (e != NULL) {
        kind = -1;
        for (int j = 0; j < 5; ++j) {
            if (e->type == TOML_STRING && strcmp(e->s, kinds[j]) == 0) {
                kind = j;
            }
        }
        if (kind < 0) {
            return bd_toml_errorf(d, "controller.kind", "expected one of pc, pi, reset, "
                                  "dwell, ft, but got %s", bd_toml_repr(e, got, sizeof got));
        }
    }
    if (positive(d, bd_toml_find(d, "controller", -1, "ts"), "ts", 1.0, &ts, 0.01) != 0
        || positive(d, bd_toml_find(d, "controller", -1, "k"), "k", 1e4, &k, 1.0) != 0) {
        return -1;
    }
    int integrates = kind == BD_KIND_PI || kind == BD_KIND_RESET || kind == BD_KIND_DWELL;
    e = bd_toml_find(d, "controller", -1, "h");
    if (integrates) {
        if (positive(d, e, "h", 1e4, &h, 2.0) != 0) {
            return -1;
        }
    } else {
        h = 2.0;
        if (e != NULL) {
            if (!finite_entry(e) || !(e->f >= 0.0)) {
                return bd_toml_errorf(d, "controller.h", "expected a finite number ≥ 0, but "
                                      "got %s", bd_toml_repr(e, got, sizeof got));
            }
            h = e->f;
        }
    }
    e = bd_toml_find(d, "controller", -1, "dwell");
    if (e != NULL) {
        /* ≤ 1e5 s: D = ceil(dwell/ts) fits the uint32 below for any ts ≥ 1e-4 (CTRL-2) */
        if (!finite_entry(e) || !(e->f >= 0.0 && e->f <= 1e5)) {
            return bd_toml_errorf(d, "controller.dwell", "expected a finite number of "
                                  "seconds in [0, 100000], but got %s",
                                  bd_toml_repr(e, got, sizeof got));
        }
        dwell = e->f;
    }
    if (kind == BD_KIND_DWELL && dwell < ts) {
        return bd_toml_errorf(d, "controller.dwell", "expected Δ ≥ Ts = %.17g s for the "
                              "dwell controller, but got %.17g", ts, dwell);
    }
    if (kind == BD_KIND_DWELL && ceil(dwell / ts - 1e-9) > 4294967295.0) {
        return bd_toml_errorf(d, "controller.dwell", "expected Δ/Ts < 2^32 (D = ceil(Δ/Ts) "
                              "is a uint32, CTRL-2), but got Δ = %.17g s at Ts = %.17g s",
                              dwell, ts);
    }
    e = bd_toml_find(d, "controller", -1, "band");
    if (e != NULL) {
        if (!finite_entry(e) || !(e->f >= 0.0 && e->f < 1.0)) {
            return bd_toml_errorf(d, "controller.band", "expected a reset band in [0, 1) "
                                  "cu/kWh, but got %s", bd_toml_repr(e, got, sizeof got));
        }
        band = e->f;
    }
    e = bd_toml_find(d, "controller", -1, "ft_exponent");
    if (e != NULL) {
        if (!finite_entry(e) || !(e->f > 0.0 && e->f < 1.0)
            || nearbyint(e->f * 16.0) < e->f * 16.0 || nearbyint(e->f * 16.0) > e->f * 16.0) {
            return bd_toml_errorf(d, "controller.ft_exponent", "expected a in (0, 1) that "
                                  "is a multiple of 1/16, but got %s",
                                  bd_toml_repr(e, got, sizeof got));
        }
        a = e->f;
    }
    const char *names[3] = {"k·ts", "h·ts", "ts"};
    double values[3] = {k * ts, h * ts, ts};
    int32_t q[3];
    for (int j = 0; j < 3; ++j) {
        char key[32];
        (void)snprintf(key, sizeof key, "controller.%s", names[j]);
        int r = q30(values[j], &q[j]);
        if (r == -1) {
            return bd_toml_errorf(d, key, "expected a value in [0, 2) (int32 Q1.30, at most "
                                  "(2**31 − 1)·2**-30), but got %.17g", values[j]);
        }
        if (r == -2) {
            return bd_toml_errorf(d, key, "expected 0 or ≥ 2**-30 (one LSB of Q1.30), but "
                                  "got %.17g", values[j]);
        }
    }
    int32_t band_q;
    if (q24(band, &band_q) != 0) {
        return bd_toml_errorf(d, "controller.band", "expected a value that fits int32 Q24");
    }
    memset(c, 0, sizeof *c);
    c->kind = kind;
    c->kts = q[0];
    c->hts = q[1];
    c->tsq = q[2];
    c->band = band_q;
    c->dwell = kind == BD_KIND_DWELL ? (uint32_t)ceil(dwell / ts - 1e-9) : 0u;
    /* CTRL-3: a = p / 2^n in lowest terms (a is a multiple of 1/16) */
    uint32_t p = (uint32_t)nearbyint(a * 16.0);
    uint32_t n = 4u;
    while (n > 0u && (p & 1u) == 0u) {
        p >>= 1;
        n--;
    }
    c->pow_num = p;
    c->pow_sqrts = n;
    *k_out = k;
    *h_out = h;
    *ts_out = ts;
    return 0;
}

/* the raw GainK/GainH values r with lo <= r * scale <= hi (binary64, as the reference
 * compares), as [min, max]; min > max if there is none */
static void gain_raw_bounds(double lo, double hi, uint32_t *min, uint32_t *max)
{
    const double scale = 1.0 / BD_GAIN_SCALE_DIV;   /* the DBC's factor 0.001 */
    *min = BD_GAIN_RAW_MAX + 1u;
    *max = 0u;
    for (uint32_t r = 0u; r <= BD_GAIN_RAW_MAX; ++r) {
        double g = r * scale;
        if (lo <= g && g <= hi) {
            if (*min > BD_GAIN_RAW_MAX) {
                *min = r;
            }
            *max = r;
        }
    }
}

int bd_config_parse(const char *text, const char *src, bd_agent_params *p, char *err,
                    size_t errlen)
{
    static toml_doc d;   /* large: kept off the stack (host side only) */
    static char buf[TEXT_MAX];
    char got[160];
    size_t len = strlen(text);
    memset(&d, 0, sizeof d);
    d.src = src;
    d.err = err;
    d.errlen = errlen;
    if (len >= sizeof buf) {
        return bd_toml_errorf(&d, "file", "expected at most %d bytes, but got %zu",
                              TEXT_MAX - 1, len);
    }
    memcpy(buf, text, len + 1u);
    if (bd_toml_parse(&d, buf) != 0) {
        return -1;
    }
    memset(p, 0, sizeof *p);
    /* CFG-1: the tables */
    static const char *const tables[] = {"agent", "controller", "neighbour", "battery",
                                         "timeouts", "limits", "transmit", "security",
                                         NULL};
    for (int k = 0; k < d.n; ++k) {
        int ok = 0;
        for (const char *const *t = tables; *t != NULL; ++t) {
            ok |= strcmp(*t, d.e[k].table) == 0;
        }
        if (!ok) {
            return bd_toml_errorf(&d, d.e[k].table[0] != '\0' ? d.e[k].table : d.e[k].key,
                                  "unknown table; expected agent, controller, neighbour, "
                                  "battery, timeouts, limits, transmit or security");
        }
    }
    for (int k = 0; k < d.n_tables; ++k) {
        int ok = 0;
        for (const char *const *t = tables; *t != NULL; ++t) {
            ok |= strcmp(*t, d.tables[k]) == 0;
        }
        if (!ok) {
            return bd_toml_errorf(&d, d.tables[k], "unknown table; expected agent, "
                                  "controller, neighbour, battery, timeouts, limits, "
                                  "transmit or security");
        }
    }
    /* CFG-2 */
    if (!bd_toml_has_table(&d, "agent")) {
        return bd_toml_errorf(&d, "agent", "expected a table, but got None");
    }
    static const char *const agent_keys[] = {"id", "lambda0", "pinned", "fleet_size",
                                             "resilient_f", NULL};
    if (check_keys(&d, "agent", agent_keys, "fleet_size, id, lambda0, pinned, resilient_f")
        != 0
        || agent_id(&d, bd_toml_find(&d, "agent", -1, "id"), "agent.id", &p->id) != 0) {
        return -1;
    }
    toml_entry *e = bd_toml_find(&d, "agent", -1, "pinned");
    if (e != NULL && e->type != TOML_BOOL) {
        return bd_toml_errorf(&d, "agent.pinned", "expected true or false, but got %s",
                              bd_toml_repr(e, got, sizeof got));
    }
    p->pinned = e != NULL ? (int32_t)e->i : 0;
    e = bd_toml_find(&d, "agent", -1, "fleet_size");
    if (e != NULL) {
        if (e->type != TOML_INT || e->i < (long long)p->id || e->i > BD_N_AGENTS_MAX) {
            return bd_toml_errorf(&d, "agent.fleet_size", "expected an agent count in "
                                  "%u..%d (at least this agent's id), but got %s", p->id,
                                  BD_N_AGENTS_MAX, bd_toml_repr(e, got, sizeof got));
        }
        p->fleet_size = (uint32_t)e->i;
    }
    /* WMSR-1: F of the resilient update, 0 (off) unless given */
    e = bd_toml_find(&d, "agent", -1, "resilient_f");
    if (e != NULL) {
        if (e->type != TOML_INT || e->i < 0 || e->i > BD_RESILIENT_F_MAX) {
            return bd_toml_errorf(&d, "agent.resilient_f", "expected an integer in 0..%d, but "
                                  "got %s", BD_RESILIENT_F_MAX, bd_toml_repr(e, got, sizeof got));
        }
        p->resilient_f = (uint32_t)e->i;
    }
    /* CFG-3 */
    if (!bd_toml_has_table(&d, "controller")) {
        return bd_toml_errorf(&d, "controller", "expected a table, but got None");
    }
    static const char *const controller_keys[] = {"kind", "k", "h", "ts", "dwell", "band",
                                                  "ft_exponent", NULL};
    double k = 0.0, h = 0.0, ts = 0.0;
    if (check_keys(&d, "controller", controller_keys,
                   "band, dwell, ft_exponent, h, k, kind, ts") != 0
        || controller(&d, &p->ctrl, &k, &h, &ts) != 0) {
        return -1;
    }
    /* CFG-4 */
    static const char *const neighbour_keys[] = {"id", "weight", NULL};
    if (d.n_neighbours > BD_MAX_NEIGHBOURS) {
        return bd_toml_errorf(&d, "neighbour", "expected at most %d neighbours, but got %d",
                              BD_MAX_NEIGHBOURS, d.n_neighbours);
    }
    for (int j = 0; j < d.n_neighbours; ++j) {
        char key[32];
        (void)snprintf(key, sizeof key, "neighbour[%d]", j + 1); /* from 1, as agents */
        for (int q = 0; q < d.n; ++q) {
            if (d.e[q].index == j && strcmp(d.e[q].key, "id") != 0
                && strcmp(d.e[q].key, "weight") != 0) {
                return bd_toml_errorf(&d, key, "expected a table with id and weight, but got "
                                      "a key '%s'", d.e[q].key);
            }
        }
        char id_key[40];
        double w;
        const double one = 1.0;
        uint32_t nid;
        (void)snprintf(id_key, sizeof id_key, "%s.id", key);
        if (agent_id(&d, bd_toml_find(&d, "neighbour", j, "id"), id_key, &nid) != 0) {
            return -1;
        }
        if (nid == p->id) {
            return bd_toml_errorf(&d, id_key, "expected another agent than this one (%u)",
                                  p->id);
        }
        if (num(&d, "neighbour", j, "weight", 1e-3, 100.0, &one, &w) != 0) {
            return -1;
        }
        (void)snprintf(key, sizeof key, "neighbour[%d]", j + 1);
        p->neighbour_id[j] = nid;
        (void)q24(w, &p->neighbour_weight[j]);
        (void)neighbour_keys;
    }
    p->n_neighbours = (uint32_t)d.n_neighbours;
    for (uint32_t a = 0u; a < p->n_neighbours; ++a) {
        for (uint32_t b = a + 1u; b < p->n_neighbours; ++b) {
            if (p->neighbour_id[a] == p->neighbour_id[b]) {
                return bd_toml_errorf(&d, "neighbour", "expected each neighbour once, but got "
                                      "duplicates");
            }
        }
    }
    /* CFG-5 */
    if (!bd_toml_has_table(&d, "battery")) {
        return bd_toml_errorf(&d, "battery", "expected a table, but got None");
    }
    static const char *const battery_keys[] = {"alpha", "beta", "m", "p_min", "p_max", NULL};
    double alpha, beta, m, p_min, p_max;
    if (check_keys(&d, "battery", battery_keys, "alpha, beta, m, p_max, p_min") != 0
        || num(&d, "battery", -1, "alpha", 1e-9, 100.0, NULL, &alpha) != 0
        || num(&d, "battery", -1, "beta", -100.0, 100.0, NULL, &beta) != 0
        || num(&d, "battery", -1, "m", 0.0, 100.0, NULL, &m) != 0
        || num(&d, "battery", -1, "p_min", -INFINITY, INFINITY, NULL, &p_min) != 0
        || num(&d, "battery", -1, "p_max", -INFINITY, INFINITY, NULL, &p_max) != 0) {
        return -1;
    }
    if (!(p_min < p_max)) {
        return bd_toml_errorf(&d, "battery.p_max", "expected p_min < p_max, but got %.17g ≥ "
                              "%.17g", p_min, p_max);
    }
    if (!(p_min >= -327.67 && p_min <= 327.67)) {
        return bd_toml_errorf(&d, "battery.p_min", "expected a limit within ±327.67 kW (the "
                              "setpoint frame's range), but got %.17g", p_min);
    }
    if (!(p_max >= -327.67 && p_max <= 327.67)) {
        return bd_toml_errorf(&d, "battery.p_max", "expected a limit within ±327.67 kW (the "
                              "setpoint frame's range), but got %.17g", p_max);
    }
    /* CFG-9: [transmit] (firmware_py.config.Transmit) */
    static const char *const transmit_keys[] = {"mode", "threshold", "heartbeat", NULL};
    double threshold = BD_EVENT_THRESHOLD;
    long long heartbeat = BD_EVENT_HEARTBEAT;
    if (check_keys(&d, "transmit", transmit_keys, "heartbeat, mode, threshold") != 0) {
        return -1;
    }
    e = bd_toml_find(&d, "transmit", -1, "mode");
    p->tx_event = 0u;
    if (e != NULL) {
        if (e->type != TOML_STRING || (strcmp(e->s, "periodic") != 0
                                       && strcmp(e->s, "event") != 0)) {
            return bd_toml_errorf(&d, "transmit.mode", "expected one of periodic, event, but "
                                  "got %s", bd_toml_repr(e, got, sizeof got));
        }
        p->tx_event = strcmp(e->s, "event") == 0 ? 1u : 0u;
    }
    e = bd_toml_find(&d, "transmit", -1, "threshold");
    if (e != NULL) {
        if (!finite_entry(e) || !(e->f >= 0.0 && e->f < 1.0)) {
            return bd_toml_errorf(&d, "transmit.threshold", "expected a number in [0, 1) "
                                  "cu/kWh, but got %s", bd_toml_repr(e, got, sizeof got));
        }
        threshold = e->f;
    }
    e = bd_toml_find(&d, "transmit", -1, "heartbeat");
    if (e != NULL) {
        if (e->type != TOML_INT || e->i < 1 || e->i > BD_EVENT_HEARTBEAT_MAX) {
            return bd_toml_errorf(&d, "transmit.heartbeat", "expected an integer number of "
                                  "ticks in 1..%d, but got %s", BD_EVENT_HEARTBEAT_MAX,
                                  bd_toml_repr(e, got, sizeof got));
        }
        heartbeat = e->i;
    }
    (void)q24(threshold, &p->tx_threshold);
    p->tx_heartbeat = (uint32_t)heartbeat;
    /* AUTH-31: [security] signed_price, only the router's signed price taken */
    static const char *const security_keys[] = {"signed_price", NULL};
    if (check_keys(&d, "security", security_keys, "signed_price") != 0) {
        return -1;
    }
    e = bd_toml_find(&d, "security", -1, "signed_price");
    if (e != NULL && e->type != TOML_BOOL) {
        return bd_toml_errorf(&d, "security.signed_price", "expected true or false, but got "
                              "%s", bd_toml_repr(e, got, sizeof got));
    }
    p->signed_price = (e != NULL && e->i != 0) ? 1u : 0u;
#if !BD_SIGNED_PRICE
    if (p->signed_price != 0u) {   /* compiled out: refused, never run unsigned */
        return bd_toml_errorf(&d, "security.signed_price", "expected false: this firmware_c "
                              "build has no signed price (BD_SIGNED_PRICE 0, no Ed25519 "
                              "verification; build it with libsodium: make SIGNED_PRICE=1)");
    }
#endif
    /* CFG-6, CFG-7 */
    static const char *const timeout_keys[] = {"neighbour_periods", "price_s", "status_s", NULL};
    static const char *const limit_keys[] = {
        "lambda_min", "lambda_max", "rho_min", "rho_max", "price_step_max", "price_persist",
        "lambda_step_max", "k_min", "k_max", "h_min", "h_max", "untrusted_after",
        "untrusted_s", NULL};
    if (check_keys(&d, "timeouts", timeout_keys, "neighbour_periods, price_s, status_s") != 0
        || check_keys(&d, "limits", limit_keys, "h_max, h_min, k_max, k_min, lambda_max, "
                      "lambda_min, lambda_step_max, price_persist, price_step_max, rho_max, "
                      "rho_min, untrusted_after, untrusted_s") != 0) {
        return -1;
    }
    const double every_price = BD_PRICE_EVERY, every_status = BD_STATUS_EVERY;
    const double cycles = BD_TIMEOUT_CYCLES;
    /* in event mode a neighbour may be silent for a heartbeat: the default timeout is
     * heartbeat + 2 periods (TX-7) */
    const double d_periods = p->tx_event != 0u ? (double)(heartbeat + BD_HEARTBEAT_MARGIN) : 3.0,
                 d_price = cycles * (every_price * ts),
                 d_status = cycles * (every_status * ts);
    const double d_lmin = -10.0, d_lmax = 10.0, d_rmin = -5.0, d_rmax = 5.0, d_step = 0.5;
    const double gain_max = BD_GAIN_RAW_MAX * (1.0 / BD_GAIN_SCALE_DIV);
    double lambda0, periods, price_s, status_s, lmin, lmax, rmin, rmax, step;
    double lstep = (10.0 * k) * ts, kmin = 0.5 * k, kmax = 2.0 * k, hmin = 0.5 * h,
           hmax = 2.0 * h, untrusted = (1.0 * ts) / (BD_MC_CYCLE_MS / 1000.0);
    int given_kmax = bd_toml_find(&d, "limits", -1, "k_max") != NULL;
    int given_hmax = bd_toml_find(&d, "limits", -1, "h_max") != NULL;
    if (num(&d, "agent", -1, "lambda0", -100.0, 100.0, NULL, &lambda0) != 0
        || num(&d, "timeouts", -1, "neighbour_periods", 1.0, 100.0, &d_periods, &periods) != 0
        || num(&d, "timeouts", -1, "price_s", 0.01, 60.0, &d_price, &price_s) != 0
        || num(&d, "timeouts", -1, "status_s", 0.01, 60.0, &d_status, &status_s) != 0
        || num(&d, "limits", -1, "lambda_min", -127.0, 127.0, &d_lmin, &lmin) != 0
        || num(&d, "limits", -1, "lambda_max", -127.0, 127.0, &d_lmax, &lmax) != 0
        || num(&d, "limits", -1, "rho_min", -127.0, 127.0, &d_rmin, &rmin) != 0
        || num(&d, "limits", -1, "rho_max", -127.0, 127.0, &d_rmax, &rmax) != 0
        || num(&d, "limits", -1, "price_step_max", 1e-6, 127.0, &d_step, &step) != 0
        || count(&d, "price_persist", 1, 100, 3, &p->price_persist) != 0
        || num(&d, "limits", -1, "lambda_step_max", 1e-6, 127.0, &lstep, &lstep) != 0
        || num(&d, "limits", -1, "k_min", 0.0, gain_max, &kmin, &kmin) != 0
        || num(&d, "limits", -1, "k_max", 0.0, gain_max, &kmax, &kmax) != 0
        || num(&d, "limits", -1, "h_min", 0.0, gain_max, &hmin, &hmin) != 0
        || num(&d, "limits", -1, "h_max", 0.0, gain_max, &hmax, &hmax) != 0
        || count(&d, "untrusted_after", 1, 1000, 5, &p->untrusted_after) != 0
        || num(&d, "limits", -1, "untrusted_s", 0.0, 3600.0, &untrusted, &untrusted) != 0) {
        return -1;
    }
    if (p->tx_event != 0u && trunc(periods) <= (double)heartbeat) {
        return bd_toml_errorf(&d, "timeouts.neighbour_periods", "expected more than "
                              "transmit.heartbeat = %lld periods (a neighbour may be silent "
                              "that long), but got %.0f", heartbeat, trunc(periods));
    }
    if (!(lmin < lambda0 && lambda0 < lmax)) {
        return bd_toml_errorf(&d, "agent.lambda0", "expected a value inside limits [%.17g, "
                              "%.17g], but got %.17g", lmin, lmax, lambda0);
    }
    if (!(rmin < rmax)) {
        return bd_toml_errorf(&d, "limits.rho_max", "expected rho_min < rho_max, but got "
                              "%.17g ≥ %.17g", rmin, rmax);
    }
    if (!(kmin <= kmax)) {
        return bd_toml_errorf(&d, "limits.k_max", "expected k_min ≤ k_max, but got %.17g > "
                              "%.17g", kmin, kmax);
    }
    if (!(hmin <= hmax)) {
        return bd_toml_errorf(&d, "limits.h_max", "expected h_min ≤ h_max, but got %.17g > "
                              "%.17g", hmin, hmax);
    }
    int32_t unused;
    if (q30(kmax * ts, &unused) != 0) {
        return bd_toml_errorf(&d, "limits.k_max", "expected k_max·ts < 2 (SET_GAINS may set "
                              "the gain to k_max; int32 Q1.30), but got k_max = %g (%s), "
                              "k_max·ts = %g", kmax, given_kmax ? "set" : "the default 2·k",
                              kmax * ts);
    }
    if (q30(hmax * ts, &unused) != 0) {
        return bd_toml_errorf(&d, "limits.h_max", "expected h_max·ts < 2 (SET_GAINS may set "
                              "the gain to h_max; int32 Q1.30), but got h_max = %g (%s), "
                              "h_max·ts = %g", hmax, given_hmax ? "set" : "the default 2·h",
                              hmax * ts);
    }
    /* the integers the runtime uses */
    (void)q24(lambda0, &p->lambda0);
    (void)q24(lmin, &p->lambda_min);
    (void)q24(lmax, &p->lambda_max);
    (void)q24(rmin, &p->rho_min);
    (void)q24(rmax, &p->rho_max);
    (void)q24(step, &p->price_step_max);
    (void)q24(lstep, &p->lambda_step_max);
    if (q24(beta * (1.0 + m), &p->idle_lambda) != 0) {
        return bd_toml_errorf(&d, "battery.beta", "expected an idle marginal cost β·(1+m) "
                              "that fits int32 Q24 (|β·(1+m)| < 128, CMD-3), but got %.17g",
                              beta * (1.0 + m));
    }
    double gain = nearbyint(6553600.0 / (((1.0 + m) * 2.0) * alpha));
    if (!(gain < 9.2e18)) {
        return bd_toml_errorf(&d, "battery.alpha", "expected a setpoint gain that fits "
                              "int64, but alpha = %g gives %g", alpha, gain);
    }
    p->sp_gain = (int64_t)gain;
    p->sp_offset = (int64_t)nearbyint((100.0 * beta) / (2.0 * alpha));
    p->sp_lo = (int32_t)nearbyint(100.0 * p_min);
    p->sp_hi = (int32_t)nearbyint(100.0 * p_max);
    double sync_s = BD_SYNC_EVERY * ts;
    p->period_ns = to_ns(ts);
    p->neighbour_timeout_ns = to_ns(trunc(periods) * ts);
    p->price_timeout_ns = to_ns(price_s);
    p->status_timeout_ns = to_ns(status_s);
    p->untrusted_ns = to_ns(untrusted);
    p->sync_ns = to_ns(sync_s);
    p->hello_ns = to_ns(0.1 * sync_s);
    p->join_ns = to_ns(0.2 * sync_s);
    gain_raw_bounds(kmin, kmax, &p->gain_k_raw_min, &p->gain_k_raw_max);
    gain_raw_bounds(hmin, hmax, &p->gain_h_raw_min, &p->gain_h_raw_max);
    return 0;
}

int bd_config_load(const char *path, bd_agent_params *p, char *err, size_t errlen)
{
    static char text[TEXT_MAX];
    if (bd_toml_read_file(path, text, sizeof text, err, errlen, "TOML file") != 0) {
        return -1;
    }
    return bd_config_parse(text, path, p, err, errlen);
}
