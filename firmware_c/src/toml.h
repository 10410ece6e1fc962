/*
 * The TOML subset of the host-side loaders (toml.c): a parsed file as a flat list of
 * entries, and the error message every loader writes ("SRC: [key] ...", firmware_py's
 * ConfigError wording). Shared by config.c (docs/firmware-spec.md section 3) and
 * keyfile.c (CFG-8); internal to the library, not part of include/bessded.
 */
#ifndef BESSDED_TOML_H
#define BESSDED_TOML_H

#include <stddef.h>

#define TEXT_MAX 65536      /* the largest file read, with its NUL */
#define ENTRIES_MAX 256
#define NAME_MAX_ 40
#define STR_MAX 128

enum { TOML_INT, TOML_FLOAT, TOML_BOOL, TOML_STRING };

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
} toml_entry;

typedef struct {
    toml_entry e[ENTRIES_MAX];
    int n;
    int n_neighbours;
    char tables[16][NAME_MAX_];
    int n_tables;
    const char *src;
    char *err;
    size_t errlen;
} toml_doc;

/* Parse text (modified in place) into d; on a syntax error -1, with d->err written. */
int bd_toml_parse(toml_doc *d, char *text);

/* The entry table.key (index: which [[neighbour]], else -1); NULL if absent. */
toml_entry *bd_toml_find(toml_doc *d, const char *table, int index, const char *key);

int bd_toml_has_table(const toml_doc *d, const char *name);

/* Python's repr of a value into buf, for "but got ..."; returns buf. */
const char *bd_toml_repr(const toml_entry *e, char *buf, size_t n);

/* "SRC: [key] " and the formatted rest into d->err; returns -1. */
int bd_toml_errorf(toml_doc *d, const char *key, const char *fmt, ...);

/* A text file (no NUL byte) of at most size - 1 bytes into buf; -1 with err written
 * ("PATH: [file] expected an existing WHAT ..."). */
int bd_toml_read_file(const char *path, char *buf, size_t size, char *err, size_t errlen,
                      const char *what);

#endif /* BESSDED_TOML_H */
