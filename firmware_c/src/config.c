/*
 * Host-side provisioning (config.h): the agent's TOML configuration and its key file
 * into bd_agent_params and bd_keyring, with firmware_py/config.py's checks, key names
 * and wording. The binary64 arithmetic of the spec's formulas (q24, q30, rne, the
 * default timeouts) happens here, written as the reference writes it, operation for
 * operation; nothing of it reaches the runtime.
 */
#define _POSIX_C_SOURCE 200809L
#include "bessded/config.h"

#include <ctype.h>
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#define TEXT_MAX 65536
#define ENTRIES_MAX 256
#define NAME_MAX_ 40
#define STR_MAX 128

/* ------------------------------------------------------------------ a TOML subset */

enum { V_INT, V_FLOAT, V_BOOL, V_STRING };

typedef struct {
    char table[NAME_MAX_];   /* "" for the root; "neighbour" for every [[neighbour]] */
    int index;               /* which [[neighbour]] (-1 elsewhere) */
    char key[NAME_MAX_];
    int type;
    long long i;
    double f;
    char s[STR_MAX];
    int line;
    int used;
} entry;

typedef struct {
    entry e[ENTRIES_MAX];
    int n;
    int n_neighbours;
    char tables[16][NAME_MAX_];
    int n_tables;
    const char *src;
    char *err;
    size_t errlen;
} doc;

static int errorf(doc *d, const char *key, const char *fmt, ...)
{
    va_list ap;
    int n = snprintf(d->err, d->errlen, "%s: [%s] ", d->src, key);
    va_start(ap, fmt);
    if (n >= 0 && (size_t)n < d->errlen) {
        (void)vsnprintf(d->err + n, d->errlen - (size_t)n, fmt, ap);
    }
    va_end(ap);
    return -1;
}

static int syntax(doc *d, int line, const char *what)
{
    return errorf(d, "file", "expected valid TOML, but got: %s (line %d)", what, line);
}

static char *trim(char *s)
{
    while (*s == ' ' || *s == '\t') {
        s++;
    }
    size_t n = strlen(s);
    while (n > 0u && (s[n - 1u] == ' ' || s[n - 1u] == '\t' || s[n - 1u] == '\r')) {
        s[--n] = '\0';
    }
    return s;
}

static int bare_key(const char *s)
{
    if (*s == '\0' || strlen(s) >= NAME_MAX_) {
        return 0;
    }
    for (; *s != '\0'; ++s) {
        if (!isalnum((unsigned char)*s) && *s != '_' && *s != '-') {
            return 0;
        }
    }
    return 1;
}

static void strip_comment(char *s)
{
    int in_string = 0;
    for (; *s != '\0'; ++s) {
        if (*s == '"' ) {
            in_string = !in_string;
        } else if (*s == '\\' && in_string && s[1] != '\0') {
            ++s;
        } else if (*s == '#' && !in_string) {
            *s = '\0';
            return;
        }
    }
}

static int parse_value(doc *d, entry *e, char *v, int line)
{
    size_t n = strlen(v);
    if (n >= 2u && v[0] == '"' && v[n - 1u] == '"') {
        size_t k = 0u;
        for (size_t j = 1u; j + 1u < n; ++j) {
            char c = v[j];
            if (c == '\\') {
                c = v[++j];
                c = c == 'n' ? '\n' : c == 't' ? '\t' : c;
            } else if (c == '"') {
                return syntax(d, line, "a quote inside a string");
            }
            if (k + 1u >= STR_MAX) {
                return syntax(d, line, "a string too long");
            }
            e->s[k++] = c;
        }
        e->s[k] = '\0';
        e->type = V_STRING;
        return 0;
    }
    if (strcmp(v, "true") == 0 || strcmp(v, "false") == 0) {
        e->type = V_BOOL;
        e->i = v[0] == 't';
        return 0;
    }
    char digits[64];
    size_t k = 0u;
    int is_float = 0;
    for (size_t j = 0u; j < n; ++j) {   /* TOML allows '_' between digits */
        if (v[j] == '_') {
            continue;
        }
        if (k + 1u >= sizeof digits) {
            return syntax(d, line, "a number too long");
        }
        if (strchr(".eEnN", v[j]) != NULL) {
            is_float = 1;
        }
        digits[k++] = v[j];
    }
    digits[k] = '\0';
    if (k == 0u) {
        return syntax(d, line, "a key without a value");
    }
    char *end = NULL;
    errno = 0;
    if (!is_float) {
        long long i = strtoll(digits, &end, 10);
        if (*end == '\0' && errno == 0 && (isdigit((unsigned char)digits[0]) || digits[0] == '-'
                                           || digits[0] == '+')) {
            e->type = V_INT;
            e->i = i;
            e->f = (double)i;
            return 0;
        }
    }
    if (strcmp(digits, "inf") == 0 || strcmp(digits, "+inf") == 0 || strcmp(digits, "-inf") == 0
        || strcmp(digits, "nan") == 0 || strcmp(digits, "+nan") == 0 || strcmp(digits, "-nan") == 0) {
        e->type = V_FLOAT;   /* TOML's special floats: refused later as not finite */
        e->f = digits[0] == '-' ? -(double)INFINITY : (digits[strlen(digits) - 1u] == 'n'
                                                    ? (double)NAN : (double)INFINITY);
        return 0;
    }
    double f = strtod(digits, &end);
    if (*end != '\0' || end == digits || !(isdigit((unsigned char)digits[0]) || digits[0] == '-'
                                         || digits[0] == '+')) {
        return syntax(d, line, "a value that is not a number, boolean or string");
    }
    e->type = V_FLOAT;
    e->f = f;
    return 0;
}

static int parse(doc *d, char *text)
{
    char table[NAME_MAX_] = "";
    int index = -1;
    int line = 0;
    for (char *next = text; next != NULL;) {
        char *s = next;
        char *nl = strchr(s, '\n');
        next = nl != NULL ? nl + 1 : NULL;
        if (nl != NULL) {
            *nl = '\0';
        }
        line++;
        strip_comment(s);
        s = trim(s);
        if (*s == '\0') {
            continue;
        }
        size_t n = strlen(s);
        if (s[0] == '[') {
            int array = n >= 4u && s[1] == '[' && s[n - 1u] == ']' && s[n - 2u] == ']';
            if (s[n - 1u] != ']') {
                return syntax(d, line, "an unterminated table header");
            }
            s[n - (array ? 2u : 1u)] = '\0';
            char *name = trim(s + (array ? 2 : 1));
            if (!bare_key(name)) {
                return syntax(d, line, "a table name that is not a bare key");
            }
            if (array) {
                if (strcmp(name, "neighbour") != 0) {
                    return errorf(d, name, "unknown table; expected agent, controller, "
                                  "neighbour, battery, timeouts or limits");
                }
                index = d->n_neighbours++;
            } else {
                index = -1;
                for (int k = 0; k < d->n_tables; ++k) {
                    if (strcmp(d->tables[k], name) == 0) {
                        return syntax(d, line, "a table defined twice");
                    }
                }
                if (d->n_tables >= 16) {
                    return syntax(d, line, "too many tables");
                }
                memcpy(d->tables[d->n_tables++], name, strlen(name) + 1u);
            }
            memcpy(table, name, strlen(name) + 1u);
            continue;
        }
        char *eq = strchr(s, '=');
        if (eq == NULL) {
            return syntax(d, line, "a line that is neither a table nor key = value");
        }
        *eq = '\0';
        char *key = trim(s);
        char *value = trim(eq + 1);
        if (!bare_key(key)) {
            return syntax(d, line, "a key that is not a bare key");
        }
        if (d->n >= ENTRIES_MAX) {
            return syntax(d, line, "too many keys");
        }
        for (int k = 0; k < d->n; ++k) {
            if (strcmp(d->e[k].table, table) == 0 && d->e[k].index == index
                && strcmp(d->e[k].key, key) == 0) {
                return syntax(d, line, "a key defined twice");
            }
        }
        entry *e = &d->e[d->n];
        memset(e, 0, sizeof *e);
        memcpy(e->table, table, strlen(table) + 1u);
        memcpy(e->key, key, strlen(key) + 1u);
        e->index = index;
        e->line = line;
        if (parse_value(d, e, value, line) != 0) {
            return -1;
        }
        d->n++;
    }
    return 0;
}

static entry *find(doc *d, const char *table, int index, const char *key)
{
    for (int k = 0; k < d->n; ++k) {
        entry *e = &d->e[k];
        if (strcmp(e->table, table) == 0 && e->index == index && strcmp(e->key, key) == 0) {
            e->used = 1;
            return e;
        }
    }
    return NULL;
}

static int has_table(const doc *d, const char *name)
{
    for (int k = 0; k < d->n_tables; ++k) {
        if (strcmp(d->tables[k], name) == 0) {
            return 1;
        }
    }
    return 0;
}

/* Python's repr of a TOML value, for "but got ..." */
static const char *repr(const entry *e, char *buf, size_t n)
{
    switch (e->type) {
    case V_INT:
        (void)snprintf(buf, n, "%lld", e->i);
        break;
    case V_BOOL:
        (void)snprintf(buf, n, "%s", e->i != 0 ? "True" : "False");
        break;
    case V_STRING:
        (void)snprintf(buf, n, "'%s'", e->s);
        break;
    default:
        (void)snprintf(buf, n, "%.17g", e->f);
        break;
    }
    return buf;
}

/* Unknown keys of a table (CFG-1): "[table.key] unknown key; expected one of ..." */
static int check_keys(doc *d, const char *table, const char *const *allowed, const char *list)
{
    for (int k = 0; k < d->n; ++k) {
        const entry *e = &d->e[k];
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
            return errorf(d, key, "unknown key; expected one of %s", list);
        }
    }
    return 0;
}

/* num() of firmware_py/config.py: a finite number in [lo, hi], or the default */
static int num(doc *d, const char *table, int index, const char *name, double lo, double hi,
               const double *def, double *out)
{
    char key[2 * NAME_MAX_ + 16];
    char got[160];
    if (index >= 0) {
        (void)snprintf(key, sizeof key, "%s[%d].%s", table, index + 1, name); /* numbered from 1 */
    } else {
        (void)snprintf(key, sizeof key, "%s.%s", table, name);
    }
    entry *e = find(d, table, index, name);
    if (e == NULL) {
        if (def == NULL) {
            return errorf(d, key, "is required");
        }
        *out = *def;
        return 0;
    }
    if ((e->type != V_INT && e->type != V_FLOAT) || !isfinite(e->f)) {
        return errorf(d, key, "expected a number, but got %s", repr(e, got, sizeof got));
    }
    if (!(lo <= e->f && e->f <= hi)) {
        return errorf(d, key, "expected a value in [%g, %g], but got %s", lo, hi,
                      repr(e, got, sizeof got));
    }
    *out = e->f;
    return 0;
}

/* count() of firmware_py/config.py: an integer in lo..hi */
static int count(doc *d, const char *name, long long lo, long long hi, long long def,
                 uint32_t *out)
{
    char key[NAME_MAX_ + 8];
    entry *e = find(d, "limits", -1, name);
    long long v = def;
    (void)snprintf(key, sizeof key, "limits.%s", name);
    if (e != NULL) {
        if (e->type != V_INT || e->i < lo || e->i > hi) {
            char got[160];
            return errorf(d, key, "expected an integer in %lld..%lld, but got %s", lo, hi,
                          repr(e, got, sizeof got));
        }
        v = e->i;
    }
    *out = (uint32_t)v;
    return 0;
}

static int agent_id(doc *d, entry *e, const char *key, uint32_t *out)
{
    if (e == NULL) {
        return errorf(d, key, "expected an agent id in 1..%d, but got None", BD_N_AGENTS_MAX);
    }
    if (e->type != V_INT || e->i < 1 || e->i > BD_N_AGENTS_MAX) {
        char got[160];
        return errorf(d, key, "expected an agent id in 1..%d, but got %s", BD_N_AGENTS_MAX,
                      repr(e, got, sizeof got));
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

static int positive(doc *d, const entry *e, const char *name, double upper, double *out,
                    double def)
{
    char key[NAME_MAX_ + 16];
    (void)snprintf(key, sizeof key, "controller.%s", name);
    if (e == NULL) {
        *out = def;
        return 0;
    }
    if ((e->type != V_INT && e->type != V_FLOAT) || !isfinite(e->f) || !(e->f > 0.0)
        || e->f > upper) {
        char got[160];
        return errorf(d, key, "expected a finite number in (0, %g], but got %s", upper,
                      repr(e, got, sizeof got));
    }
    *out = e->f;
    return 0;
}

static int finite_entry(const entry *e)
{
    return (e->type == V_INT || e->type == V_FLOAT) && isfinite(e->f);
}

/* ControllerConfig (CFG-3, CTRL-1..3) */
static int controller(doc *d, bd_ctrl_config *c, double *k_out, double *h_out, double *ts_out)
{
    static const char *const kinds[] = {"pc", "pi", "reset", "dwell", "ft"};
    char got[160];
    double k, h, ts, dwell = 0.0, band = 1e-4, a = 0.5;
    entry *e = find(d, "controller", -1, "kind");
    int kind = BD_KIND_RESET;
    if (e != NULL) {
        kind = -1;
        for (int j = 0; j < 5; ++j) {
            if (e->type == V_STRING && strcmp(e->s, kinds[j]) == 0) {
                kind = j;
            }
        }
        if (kind < 0) {
            return errorf(d, "controller.kind", "expected one of pc, pi, reset, dwell, ft, "
                          "but got %s", repr(e, got, sizeof got));
        }
    }
    if (positive(d, find(d, "controller", -1, "ts"), "ts", 1.0, &ts, 0.01) != 0
        || positive(d, find(d, "controller", -1, "k"), "k", 1e4, &k, 1.0) != 0) {
        return -1;
    }
    int integrates = kind == BD_KIND_PI || kind == BD_KIND_RESET || kind == BD_KIND_DWELL;
    e = find(d, "controller", -1, "h");
    if (integrates) {
        if (positive(d, e, "h", 1e4, &h, 2.0) != 0) {
            return -1;
        }
    } else {
        h = 2.0;
        if (e != NULL) {
            if (!finite_entry(e) || !(e->f >= 0.0)) {
                return errorf(d, "controller.h", "expected a finite number ≥ 0, but got %s",
                              repr(e, got, sizeof got));
            }
            h = e->f;
        }
    }
    e = find(d, "controller", -1, "dwell");
    if (e != NULL) {
        /* ≤ 1e5 s: D = ceil(dwell/ts) fits the uint32 below for any ts ≥ 1e-4 (CTRL-2) */
        if (!finite_entry(e) || !(e->f >= 0.0 && e->f <= 1e5)) {
            return errorf(d, "controller.dwell", "expected a finite number of seconds in "
                          "[0, 100000], but got %s", repr(e, got, sizeof got));
        }
        dwell = e->f;
    }
    if (kind == BD_KIND_DWELL && dwell < ts) {
        return errorf(d, "controller.dwell", "expected Δ ≥ Ts = %.17g s for the dwell "
                      "controller, but got %.17g", ts, dwell);
    }
    if (kind == BD_KIND_DWELL && ceil(dwell / ts - 1e-9) > 4294967295.0) {
        return errorf(d, "controller.dwell", "expected Δ/Ts < 2^32 (D = ceil(Δ/Ts) is a "
                      "uint32, CTRL-2), but got Δ = %.17g s at Ts = %.17g s", dwell, ts);
    }
    e = find(d, "controller", -1, "band");
    if (e != NULL) {
        if (!finite_entry(e) || !(e->f >= 0.0 && e->f < 1.0)) {
            return errorf(d, "controller.band", "expected a reset band in [0, 1) cu/kWh, but "
                          "got %s", repr(e, got, sizeof got));
        }
        band = e->f;
    }
    e = find(d, "controller", -1, "ft_exponent");
    if (e != NULL) {
        if (!finite_entry(e) || !(e->f > 0.0 && e->f < 1.0)
            || nearbyint(e->f * 16.0) < e->f * 16.0 || nearbyint(e->f * 16.0) > e->f * 16.0) {
            return errorf(d, "controller.ft_exponent", "expected a in (0, 1) that is a "
                          "multiple of 1/16, but got %s", repr(e, got, sizeof got));
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
            return errorf(d, key, "expected a value in [0, 2) (int32 Q1.30, at most "
                          "(2**31 − 1)·2**-30), but got %.17g", values[j]);
        }
        if (r == -2) {
            return errorf(d, key, "expected 0 or ≥ 2**-30 (one LSB of Q1.30), but got %.17g",
                          values[j]);
        }
    }
    int32_t band_q;
    if (q24(band, &band_q) != 0) {
        return errorf(d, "controller.band", "expected a value that fits int32 Q24");
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
    static doc d;   /* large: kept off the stack (host side only) */
    static char buf[TEXT_MAX];
    char got[160];
    size_t len = strlen(text);
    memset(&d, 0, sizeof d);
    d.src = src;
    d.err = err;
    d.errlen = errlen;
    if (len >= sizeof buf) {
        return errorf(&d, "file", "expected at most %d bytes, but got %zu", TEXT_MAX - 1, len);
    }
    memcpy(buf, text, len + 1u);
    if (parse(&d, buf) != 0) {
        return -1;
    }
    memset(p, 0, sizeof *p);
    /* CFG-1: the tables */
    static const char *const tables[] = {"agent", "controller", "neighbour", "battery",
                                         "timeouts", "limits", NULL};
    for (int k = 0; k < d.n; ++k) {
        int ok = 0;
        for (const char *const *t = tables; *t != NULL; ++t) {
            ok |= strcmp(*t, d.e[k].table) == 0;
        }
        if (!ok) {
            return errorf(&d, d.e[k].table[0] != '\0' ? d.e[k].table : d.e[k].key,
                          "unknown table; expected agent, controller, neighbour, battery, "
                          "timeouts or limits");
        }
    }
    for (int k = 0; k < d.n_tables; ++k) {
        int ok = 0;
        for (const char *const *t = tables; *t != NULL; ++t) {
            ok |= strcmp(*t, d.tables[k]) == 0;
        }
        if (!ok) {
            return errorf(&d, d.tables[k], "unknown table; expected agent, controller, "
                          "neighbour, battery, timeouts or limits");
        }
    }
    /* CFG-2 */
    if (!has_table(&d, "agent")) {
        return errorf(&d, "agent", "expected a table, but got None");
    }
    static const char *const agent_keys[] = {"id", "lambda0", "pinned", "fleet_size", NULL};
    if (check_keys(&d, "agent", agent_keys, "fleet_size, id, lambda0, pinned") != 0
        || agent_id(&d, find(&d, "agent", -1, "id"), "agent.id", &p->id) != 0) {
        return -1;
    }
    entry *e = find(&d, "agent", -1, "pinned");
    if (e != NULL && e->type != V_BOOL) {
        return errorf(&d, "agent.pinned", "expected true or false, but got %s",
                      repr(e, got, sizeof got));
    }
    p->pinned = e != NULL ? (int32_t)e->i : 0;
    e = find(&d, "agent", -1, "fleet_size");
    if (e != NULL) {
        if (e->type != V_INT || e->i < (long long)p->id || e->i > BD_N_AGENTS_MAX) {
            return errorf(&d, "agent.fleet_size", "expected an agent count in %u..%d (at "
                          "least this agent's id), but got %s", p->id, BD_N_AGENTS_MAX,
                          repr(e, got, sizeof got));
        }
        p->fleet_size = (uint32_t)e->i;
    }
    /* CFG-3 */
    if (!has_table(&d, "controller")) {
        return errorf(&d, "controller", "expected a table, but got None");
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
        return errorf(&d, "neighbour", "expected at most %d neighbours, but got %d",
                      BD_MAX_NEIGHBOURS, d.n_neighbours);
    }
    for (int j = 0; j < d.n_neighbours; ++j) {
        char key[32];
        (void)snprintf(key, sizeof key, "neighbour[%d]", j + 1); /* from 1, as agents */
        for (int q = 0; q < d.n; ++q) {
            if (d.e[q].index == j && strcmp(d.e[q].key, "id") != 0
                && strcmp(d.e[q].key, "weight") != 0) {
                return errorf(&d, key, "expected a table with id and weight, but got a key "
                              "'%s'", d.e[q].key);
            }
        }
        char id_key[40];
        double w;
        const double one = 1.0;
        uint32_t nid;
        (void)snprintf(id_key, sizeof id_key, "%s.id", key);
        if (agent_id(&d, find(&d, "neighbour", j, "id"), id_key, &nid) != 0) {
            return -1;
        }
        if (nid == p->id) {
            return errorf(&d, id_key, "expected another agent than this one (%u)", p->id);
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
                return errorf(&d, "neighbour", "expected each neighbour once, but got "
                              "duplicates");
            }
        }
    }
    /* CFG-5 */
    if (!has_table(&d, "battery")) {
        return errorf(&d, "battery", "expected a table, but got None");
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
        return errorf(&d, "battery.p_max", "expected p_min < p_max, but got %.17g ≥ %.17g",
                      p_min, p_max);
    }
    if (!(p_min >= -327.67 && p_min <= 327.67)) {
        return errorf(&d, "battery.p_min", "expected a limit within ±327.67 kW (the setpoint "
                      "frame's range), but got %.17g", p_min);
    }
    if (!(p_max >= -327.67 && p_max <= 327.67)) {
        return errorf(&d, "battery.p_max", "expected a limit within ±327.67 kW (the setpoint "
                      "frame's range), but got %.17g", p_max);
    }
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
    const double d_periods = 3.0, d_price = cycles * (every_price * ts),
                 d_status = cycles * (every_status * ts);
    const double d_lmin = -10.0, d_lmax = 10.0, d_rmin = -5.0, d_rmax = 5.0, d_step = 0.5;
    const double gain_max = BD_GAIN_RAW_MAX * (1.0 / BD_GAIN_SCALE_DIV);
    double lambda0, periods, price_s, status_s, lmin, lmax, rmin, rmax, step;
    double lstep = (10.0 * k) * ts, kmin = 0.5 * k, kmax = 2.0 * k, hmin = 0.5 * h,
           hmax = 2.0 * h, untrusted = (1.0 * ts) / (BD_MC_CYCLE_MS / 1000.0);
    int given_kmax = find(&d, "limits", -1, "k_max") != NULL;
    int given_hmax = find(&d, "limits", -1, "h_max") != NULL;
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
    if (!(lmin < lambda0 && lambda0 < lmax)) {
        return errorf(&d, "agent.lambda0", "expected a value inside limits [%.17g, %.17g], "
                      "but got %.17g", lmin, lmax, lambda0);
    }
    if (!(rmin < rmax)) {
        return errorf(&d, "limits.rho_max", "expected rho_min < rho_max, but got %.17g ≥ "
                      "%.17g", rmin, rmax);
    }
    if (!(kmin <= kmax)) {
        return errorf(&d, "limits.k_max", "expected k_min ≤ k_max, but got %.17g > %.17g",
                      kmin, kmax);
    }
    if (!(hmin <= hmax)) {
        return errorf(&d, "limits.h_max", "expected h_min ≤ h_max, but got %.17g > %.17g",
                      hmin, hmax);
    }
    int32_t unused;
    if (q30(kmax * ts, &unused) != 0) {
        return errorf(&d, "limits.k_max", "expected k_max·ts < 2 (SET_GAINS may set the gain "
                      "to k_max; int32 Q1.30), but got k_max = %g (%s), k_max·ts = %g", kmax,
                      given_kmax ? "set" : "the default 2·k", kmax * ts);
    }
    if (q30(hmax * ts, &unused) != 0) {
        return errorf(&d, "limits.h_max", "expected h_max·ts < 2 (SET_GAINS may set the gain "
                      "to h_max; int32 Q1.30), but got h_max = %g (%s), h_max·ts = %g", hmax,
                      given_hmax ? "set" : "the default 2·h", hmax * ts);
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
        return errorf(&d, "battery.beta", "expected an idle marginal cost β·(1+m) that fits "
                      "int32 Q24 (|β·(1+m)| < 128, CMD-3), but got %.17g", beta * (1.0 + m));
    }
    double gain = nearbyint(6553600.0 / (((1.0 + m) * 2.0) * alpha));
    if (!(gain < 9.2e18)) {
        return errorf(&d, "battery.alpha", "expected a setpoint gain that fits int64, but "
                      "alpha = %g gives %g", alpha, gain);
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

static int read_file(const char *path, char *buf, size_t size, char *err, size_t errlen,
                     const char *what)
{
    FILE *f = fopen(path, "rb");
    if (f == NULL) {
        (void)snprintf(err, errlen, "%s: [file] expected an existing %s, but it %s", path,
                       what, errno == ENOENT ? "does not exist" : strerror(errno));
        return -1;
    }
    size_t n = fread(buf, 1u, size - 1u, f);
    int big = n == size - 1u && fgetc(f) != EOF;
    (void)fclose(f);
    if (big) {
        (void)snprintf(err, errlen, "%s: [file] expected at most %zu bytes", path, size - 1u);
        return -1;
    }
    buf[n] = '\0';
    if (strlen(buf) != n) {
        (void)snprintf(err, errlen, "%s: [file] expected a text file, but it has a NUL byte",
                       path);
        return -1;
    }
    return 0;
}

int bd_config_load(const char *path, bd_agent_params *p, char *err, size_t errlen)
{
    static char text[TEXT_MAX];
    if (read_file(path, text, sizeof text, err, errlen, "TOML file") != 0) {
        return -1;
    }
    return bd_config_parse(text, path, p, err, errlen);
}

/* ------------------------------------------------------------------ key files */

#define KEY_FILE_FORMAT "bess-ded-secoc-node-key/1"
#define KEY_FILE_HEADER \
    "# bess-ded SecOC node key (docs/security.md). Secret: keep it owner-only (0600).\n" \
    "# freshness.boot_counter is rewritten at every start; losing it means " \
    "re-provisioning.\n"

typedef struct {
    char path[4096];
    char fleet_id[17];
    char kdf[STR_MAX];
    char mac[STR_MAX];
    bd_keyring *ring;
} key_file;

static key_file key_file_state;   /* the persist callback's context (one node per process) */

static int hex_key(const char *s, uint8_t out[BD_KEY_BYTES])
{
    if (strlen(s) != 2u * BD_KEY_BYTES) {
        return -1;
    }
    for (int k = 0; k < BD_KEY_BYTES; ++k) {
        unsigned v = 0u;
        for (int j = 0; j < 2; ++j) {
            char c = (char)tolower((unsigned char)s[2 * k + j]);
            if (!isxdigit((unsigned char)c)) {
                return -1;
            }
            v = v * 16u + (unsigned)(isdigit((unsigned char)c) ? c - '0' : c - 'a' + 10);
        }
        out[k] = (uint8_t)v;
    }
    return 0;
}

static int node_label_ok(const char *s)
{
    size_t n = strlen(s);
    if (n < 1u || n > BD_LABEL_MAX || !(s[0] >= 'a' && s[0] <= 'z')) {
        return 0;
    }
    for (size_t k = 0u; k < n; ++k) {
        if (!((s[k] >= 'a' && s[k] <= 'z') || isdigit((unsigned char)s[k]) || s[k] == '_')) {
            return 0;
        }
    }
    return 1;
}

static void hex_of(const uint8_t *b, size_t n, char *out)
{
    static const char digits[] = "0123456789abcdef";
    for (size_t k = 0u; k < n; ++k) {
        out[2u * k] = digits[b[k] >> 4];
        out[2u * k + 1u] = digits[b[k] & 15u];
    }
    out[2u * n] = '\0';
}

/* Rewrite the key file with a new boot counter: a 0600 temporary file (O_EXCL,
 * O_NOFOLLOW), fsynced, renamed over, the directory fsynced (AUTH-3's write-ahead). */
static int persist_boot(void *ctx, uint32_t boot)
{
    const key_file *kf = ctx;
    const bd_keyring *k = kf->ring;
    char tmp[4200];
    char hex[2 * BD_KEY_BYTES + 1];
    (void)snprintf(tmp, sizeof tmp, "%s.%ld.tmp", kf->path, (long)getpid());
    int fd = open(tmp, O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW, 0600);
    if (fd < 0) {
        return -1;
    }
    FILE *f = fdopen(fd, "w");
    if (f == NULL) {
        (void)close(fd);
        (void)unlink(tmp);
        return -1;
    }
    hex_of(k->key, BD_KEY_BYTES, hex);
    int ok = fprintf(f, "%sformat = \"%s\"\nnode = \"%s\"\nfleet_id = \"%s\"\nkdf = \"%s\"\n"
                     "mac = \"%s\"\nkey = \"%s\"\n\n[freshness]\nboot_counter = %u\n\n[peers]\n",
                     KEY_FILE_HEADER, KEY_FILE_FORMAT, k->node, kf->fleet_id, kf->kdf, kf->mac,
                     hex, boot) > 0;
    for (uint32_t p = 0u; p < k->n_peers && ok; ++p) {
        hex_of(k->peer_key[p], BD_KEY_BYTES, hex);
        ok = fprintf(f, "%s = \"%s\"\n", k->peer_label[p], hex) > 0;
    }
    int floors = 0;   /* AUTH-21: the peers' boot floors are kept */
    for (uint32_t p = 0u; p < k->n_peers && ok; ++p) {
        if (k->peer_floor[p] != 0u) {
            if (floors == 0) {
                ok = fprintf(f, "\n[floors]\n") > 0;
                floors = 1;
            }
            ok = ok && fprintf(f, "%s = %u\n", k->peer_label[p],
                               (unsigned)k->peer_floor[p]) > 0;
        }
    }
    ok = ok && fflush(f) == 0 && fsync(fileno(f)) == 0;
    ok = (fclose(f) == 0) && ok;
    if (!ok || rename(tmp, kf->path) != 0) {
        (void)unlink(tmp);
        return -1;
    }
    char dir[4096];
    memcpy(dir, kf->path, strlen(kf->path) + 1u);
    char *slash = strrchr(dir, '/');
    if (slash != NULL) {
        *slash = '\0';
    } else {
        memcpy(dir, ".", 2u);
    }
    int dfd = open(dir[0] != '\0' ? dir : "/", O_RDONLY);
    if (dfd >= 0) {
        (void)fsync(dfd);
        (void)close(dfd);
    }
    return 0;
}

int bd_keyfile_load(const char *path, const char *node, bd_keyring *k, char *err,
                    size_t errlen)
{
    static doc d;
    static char text[TEXT_MAX];
    struct stat st;
    key_file *kf = &key_file_state;
    memset(k, 0, sizeof *k);
    if (lstat(path, &st) != 0) {
        (void)snprintf(err, errlen, "%s: cannot read the node key file: %s", path,
                       strerror(errno));
        return -1;
    }
    /* a symbolic link is refused, not followed, as firmware_py does: a boot counter saved
     * through it would replace the link by a copy and leave the target's behind */
    if (S_ISLNK(st.st_mode)) {
        (void)snprintf(err, errlen, "%s: expected the node key file itself, but got a "
                       "symbolic link: give the file's own path", path);
        return -1;
    }
    if (!S_ISREG(st.st_mode)) {
        (void)snprintf(err, errlen, "%s: expected a regular file for the node key file", path);
        return -1;
    }
    if ((st.st_mode & 077) != 0u) {
        (void)snprintf(err, errlen, "%s: permissions %04o are too open: the node key file "
                       "must not be accessible by group or others (chmod 600 %s)", path,
                       (unsigned)(st.st_mode & 07777), path);
        return -1;
    }
    if (st.st_uid != getuid()) {
        (void)snprintf(err, errlen, "%s: the node key file is owned by uid %u, not by this "
                       "user (%u)", path, (unsigned)st.st_uid, (unsigned)getuid());
        return -1;
    }
    if (read_file(path, text, sizeof text, err, errlen, "node key file") != 0) {
        return -1;
    }
    memset(&d, 0, sizeof d);
    d.src = path;
    d.err = err;
    d.errlen = errlen;
    if (parse(&d, text) != 0) {
        (void)snprintf(err, errlen, "%s: not a readable TOML node key file", path);
        return -1;
    }
    const entry *e = find(&d, "", -1, "format");
    if (e == NULL || e->type != V_STRING || strcmp(e->s, KEY_FILE_FORMAT) != 0) {
        (void)snprintf(err, errlen, "%s: [format] expected '%s'", path, KEY_FILE_FORMAT);
        return -1;
    }
    e = find(&d, "", -1, "node");
    if (e == NULL || e->type != V_STRING || !node_label_ok(e->s)) {
        (void)snprintf(err, errlen, "%s: [node] expected a name like 'agent_3', 'plant' or "
                       "'router'", path);
        return -1;
    }
    if (strcmp(e->s, node) != 0) {
        (void)snprintf(err, errlen, "--key %s: expected the key file of %s, but got the one "
                       "of %s", path, node, e->s);
        return -1;
    }
    memcpy(k->node, e->s, strlen(e->s) + 1u);
    e = find(&d, "", -1, "fleet_id");
    if (e == NULL || e->type != V_STRING || strlen(e->s) != 16u) {
        (void)snprintf(err, errlen, "%s: [fleet_id] expected 16 hex digits", path);
        return -1;
    }
    memcpy(kf->fleet_id, e->s, 17u);
    e = find(&d, "", -1, "kdf");
    (void)snprintf(kf->kdf, sizeof kf->kdf, "%s", e != NULL && e->type == V_STRING ? e->s
                   : "NIST SP 800-108 counter mode, CMAC-AES-128");
    e = find(&d, "", -1, "mac");
    (void)snprintf(kf->mac, sizeof kf->mac, "%s", e != NULL && e->type == V_STRING ? e->s
                   : "CMAC-AES-128");
    e = find(&d, "", -1, "key");
    if (e == NULL || e->type != V_STRING || hex_key(e->s, k->key) != 0) {
        (void)snprintf(err, errlen, "%s: [key] expected %d hex digits", path, 2 * BD_KEY_BYTES);
        return -1;
    }
    e = find(&d, "freshness", -1, "boot_counter");
    if (e == NULL || e->type != V_INT || e->i < 0 || e->i > 65535) {
        (void)snprintf(err, errlen, "%s: [freshness.boot_counter] expected an integer "
                       "0..65535", path);
        return -1;
    }
    k->boot = (uint32_t)e->i;
    for (int q = 0; q < d.n; ++q) {
        const entry *pe = &d.e[q];
        if (strcmp(pe->table, "peers") != 0) {
            continue;
        }
        if (!node_label_ok(pe->key)) {
            (void)snprintf(err, errlen, "%s: [peers] expected a name like 'agent_3', 'plant' "
                           "or 'router', but got '%s'", path, pe->key);
            return -1;
        }
        if (k->n_peers >= BD_MAX_PEERS) {
            (void)snprintf(err, errlen, "%s: [peers] expected at most %d keys", path,
                           BD_MAX_PEERS);
            return -1;
        }
        if (pe->type != V_STRING || hex_key(pe->s, k->peer_key[k->n_peers]) != 0) {
            (void)snprintf(err, errlen, "%s: [%s] expected %d hex digits", path, pe->key,
                           2 * BD_KEY_BYTES);
            return -1;
        }
        memcpy(k->peer_label[k->n_peers], pe->key, strlen(pe->key) + 1u);
        k->n_peers++;
    }
    for (int q = 0; q < d.n; ++q) {   /* AUTH-21: each peer's lowest boot accepted */
        const entry *pe = &d.e[q];
        if (strcmp(pe->table, "floors") != 0) {
            continue;
        }
        uint32_t p = 0u;
        while (p < k->n_peers && strcmp(k->peer_label[p], pe->key) != 0) {
            p++;
        }
        if (p == k->n_peers || pe->type != V_INT || pe->i < 0 || pe->i > 65535) {
            (void)snprintf(err, errlen, "%s: [floors] expected a table of peer = lowest boot "
                           "counter (0..65535), for peers listed in [peers], but got '%s'",
                           path, pe->key);
            return -1;
        }
        k->peer_floor[p] = (uint16_t)pe->i;
    }
    (void)snprintf(kf->path, sizeof kf->path, "%s", path);
    kf->ring = k;
    k->persist_boot = persist_boot;
    k->persist_ctx = kf;
    return 0;
}

int bd_keyring_insecure(const char *node, bd_keyring *k)
{
    static const uint8_t zero[BD_KEY_BYTES] = {0};
    memset(k, 0, sizeof *k);
    if (!node_label_ok(node)) {
        return -1;
    }
    memcpy(k->node, node, strlen(node) + 1u);
    k->insecure = 1;
    k->boot = 0u;   /* the runtime starts at boot 1 (AUTH-20) */
    return bd_derive_node_key(zero, node, k->key);
}
