/*
 * The TOML subset the host-side loaders read (toml.h): the agent configuration
 * (docs/firmware-spec.md section 3, config.c) and the node key file (CFG-8, keyfile.c).
 * Bare keys, [table] and [[neighbour]], integers, floats, booleans and basic strings;
 * the syntax errors in firmware_py's ConfigError wording ("FILE: [file] expected valid
 * TOML ..."). Host side only.
 */
#include "toml.h"

#include <ctype.h>
#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int bd_toml_errorf(toml_doc *d, const char *key, const char *fmt, ...)
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

static int syntax(toml_doc *d, int line, const char *what)
{
    return bd_toml_errorf(d, "file", "expected valid TOML, but got: %s (line %d)", what,
                          line);
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

/* A quoted key ("agent_1>agent_3", AUTH-34's pairs as tomli_w writes them): its text,
 * printable and without quotes or escapes; NULL if key is not one. */
static char *quoted_key(char *key)
{
    size_t n = strlen(key);
    if (n < 3u || n - 2u >= NAME_MAX_ || key[0] != '"' || key[n - 1u] != '"') {
        return NULL;
    }
    key[n - 1u] = '\0';
    for (const char *c = key + 1; *c != '\0'; ++c) {
        if (!isprint((unsigned char)*c) || *c == '"' || *c == '\\') {
            return NULL;
        }
    }
    return key + 1;
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

static int parse_value(toml_doc *d, toml_entry *e, char *v, int line)
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
        e->type = TOML_STRING;
        return 0;
    }
    if (strcmp(v, "true") == 0 || strcmp(v, "false") == 0) {
        e->type = TOML_BOOL;
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
            e->type = TOML_INT;
            e->i = i;
            e->f = (double)i;
            return 0;
        }
    }
    if (strcmp(digits, "inf") == 0 || strcmp(digits, "+inf") == 0 || strcmp(digits, "-inf") == 0
        || strcmp(digits, "nan") == 0 || strcmp(digits, "+nan") == 0 || strcmp(digits, "-nan") == 0) {
        e->type = TOML_FLOAT;   /* TOML's special floats: refused later as not finite */
        e->f = digits[0] == '-' ? -(double)INFINITY : (digits[strlen(digits) - 1u] == 'n'
                                                    ? (double)NAN : (double)INFINITY);
        return 0;
    }
    double f = strtod(digits, &end);
    if (*end != '\0' || end == digits || !(isdigit((unsigned char)digits[0]) || digits[0] == '-'
                                         || digits[0] == '+')) {
        return syntax(d, line, "a value that is not a number, boolean or string");
    }
    e->type = TOML_FLOAT;
    e->f = f;
    return 0;
}

int bd_toml_parse(toml_doc *d, char *text)
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
                    return bd_toml_errorf(d, name, "unknown table; expected agent, "
                                          "controller, neighbour, battery, timeouts or "
                                          "limits");
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
        if (!bare_key(key) && (key = quoted_key(key)) == NULL) {
            return syntax(d, line, "a key that is not a bare key or a plain quoted one");
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
        toml_entry *e = &d->e[d->n];
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

toml_entry *bd_toml_find(toml_doc *d, const char *table, int index, const char *key)
{
    for (int k = 0; k < d->n; ++k) {
        toml_entry *e = &d->e[k];
        if (strcmp(e->table, table) == 0 && e->index == index && strcmp(e->key, key) == 0) {
            e->used = 1;
            return e;
        }
    }
    return NULL;
}

int bd_toml_has_table(const toml_doc *d, const char *name)
{
    for (int k = 0; k < d->n_tables; ++k) {
        if (strcmp(d->tables[k], name) == 0) {
            return 1;
        }
    }
    return 0;
}

/* Python's repr of a TOML value, for "but got ..." */
const char *bd_toml_repr(const toml_entry *e, char *buf, size_t n)
{
    switch (e->type) {
    case TOML_INT:
        (void)snprintf(buf, n, "%lld", e->i);
        break;
    case TOML_BOOL:
        (void)snprintf(buf, n, "%s", e->i != 0 ? "True" : "False");
        break;
    case TOML_STRING:
        (void)snprintf(buf, n, "'%s'", e->s);
        break;
    default:
        (void)snprintf(buf, n, "%.17g", e->f);
        break;
    }
    return buf;
}

int bd_toml_read_file(const char *path, char *buf, size_t size, char *err, size_t errlen,
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
