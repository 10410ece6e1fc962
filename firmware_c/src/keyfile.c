/*
 * The node key file (config.h; docs/firmware-spec.md CFG-8, section 12): an owner-only
 * TOML file (toml.c) of format bess-ded-secoc-node-key/1 into a bd_keyring, with
 * firmware_py's checks and wording; the boot counter rewritten before it is used
 * (AUTH-3's write-ahead, keeping the peers' boot floors, AUTH-21); and the public
 * --insecure keyring (AUTH-20). Host side only (POSIX).
 */
#define _POSIX_C_SOURCE 200809L
#include "bessded/config.h"

#include <ctype.h>
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "toml.h"

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
    /* AUTH-31: [price_signature] as the file has it (sign_key or verify_key), rewritten
     * with the boot counter ("" if none) */
    char price_name[NAME_MAX_];
    char price_hex[2 * BD_ED25519_PUBLIC_BYTES + 1];
    bd_keyring *ring;
} key_file;

static key_file key_file_state;   /* the persist callback's context (one node per process) */

static void hex_of(const uint8_t *b, size_t n, char *out);

/* n bytes of hex (either case) into out; -1 if s is not exactly that */
static int hex_bytes(const char *s, uint8_t *out, size_t n)
{
    if (strlen(s) != 2u * n) {
        return -1;
    }
    for (size_t k = 0u; k < n; ++k) {
        unsigned v = 0u;
        for (int j = 0; j < 2; ++j) {
            char c = (char)tolower((unsigned char)s[2u * k + (size_t)j]);
            if (!isxdigit((unsigned char)c)) {
                return -1;
            }
            v = v * 16u + (unsigned)(isdigit((unsigned char)c) ? c - '0' : c - 'a' + 10);
        }
        out[k] = (uint8_t)v;
    }
    return 0;
}

static int hex_key(const char *s, uint8_t out[BD_KEY_BYTES])
{
    return hex_bytes(s, out, BD_KEY_BYTES);
}

/* AUTH-31: [price_signature] (firmware_py secoc._price_keys): exactly one of sign_key
 * (the router's Ed25519 seed: its public key is derived) or verify_key (the public key),
 * 32 bytes hex; none: not a signed fleet. 0, or -1 with err written. */
static int price_keys(toml_doc *d, const char *path, key_file *kf, bd_keyring *k,
                      char *err, size_t errlen)
{
    int n = 0;
    const toml_entry *one = NULL;
    for (int q = 0; q < d->n; ++q) {
        if (strcmp(d->e[q].table, "price_signature") == 0) {
            one = &d->e[q];
            n++;
        }
    }
    int table = bd_toml_has_table(d, "price_signature");
    if (!table && n == 0 && bd_toml_find(d, "", -1, "price_signature") == NULL) {
        return 0;
    }
    if (n != 1 || one == NULL || (strcmp(one->key, "sign_key") != 0
                                  && strcmp(one->key, "verify_key") != 0)) {
        (void)snprintf(err, errlen, "%s: [price_signature] expected exactly one of sign_key, "
                       "verify_key", path);
        return -1;
    }
    uint8_t raw[BD_ED25519_PUBLIC_BYTES];
    if (one->type != TOML_STRING || hex_bytes(one->s, raw, sizeof raw) != 0) {
        (void)snprintf(err, errlen, "%s: [price_signature.%s] expected %d bytes as hex", path,
                       one->key, BD_ED25519_PUBLIC_BYTES);
        return -1;
    }
    if (strcmp(one->key, "sign_key") == 0) {
#if BD_SIGNED_PRICE
        if (bd_ed25519_public(raw, k->price_key) != 0) {
            (void)snprintf(err, errlen, "%s: [price_signature.sign_key] cannot derive its "
                           "public key", path);
            return -1;
        }
#else
        (void)snprintf(err, errlen, "%s: [price_signature.sign_key] expected verify_key: "
                       "this build has no signed price (BD_SIGNED_PRICE 0)", path);
        return -1;
#endif
    } else {
        memcpy(k->price_key, raw, sizeof raw);
    }
    k->has_price_key = 1;
    memcpy(kf->price_name, one->key, strlen(one->key) + 1u);   /* sign_key or verify_key */
    hex_of(raw, sizeof raw, kf->price_hex);
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

/* AUTH-34: a node label's TagRx code (agent_<i>: i, plant, router); 0 if none */
static uint32_t tag_code(const char *s, size_t n)
{
    if (n == 5u && strncmp(s, "plant", 5) == 0) {
        return BD_TAG_RX_PLANT;
    }
    if (n == 6u && strncmp(s, "router", 6) == 0) {
        return BD_TAG_RX_ROUTER;
    }
    if (n < 7u || n > 8u || strncmp(s, "agent_", 6) != 0 || s[6] < '1' || s[6] > '9'
        || (n == 8u && !isdigit((unsigned char)s[7]))) {
        return 0u;
    }
    uint32_t i = (uint32_t)(s[6] - '0');
    if (n == 8u) {
        i = i * 10u + (uint32_t)(s[7] - '0');
    }
    return i <= BD_N_AGENTS_MAX ? i : 0u;
}

static void tag_label(uint32_t code, char out[BD_LABEL_MAX + 1])
{
    (void)snprintf(out, BD_LABEL_MAX + 1, code == BD_TAG_RX_PLANT ? "plant"
                   : code == BD_TAG_RX_ROUTER ? "router" : "agent_%u", (unsigned)code);
}

/* AUTH-34: [lambda_tag_keys], "agent_i>receiver" = key for the pairs `node` is one of
 * (firmware_py secoc's check), into k->tag_*. 0, or -1 with err written. */
static int tag_keys(const toml_doc *d, const char *path, const char *node, bd_keyring *k,
                    char *err, size_t errlen)
{
    uint32_t own = tag_code(node, strlen(node));
    for (int q = 0; q < d->n; ++q) {
        const toml_entry *pe = &d->e[q];
        if (strcmp(pe->table, "lambda_tag_keys") != 0) {
            continue;
        }
        const char *gt = strchr(pe->key, '>');
        uint32_t from = gt != NULL ? tag_code(pe->key, (size_t)(gt - pe->key)) : 0u;
        uint32_t to = gt != NULL ? tag_code(gt + 1, strlen(gt + 1)) : 0u;
        if (from == 0u || from > BD_N_AGENTS_MAX || to == 0u || from == to) {
            (void)snprintf(err, errlen, "%s: [lambda_tag_keys] expected 'agent_i>RECEIVER' (an "
                           "agent other than agent_i, plant or router), but got '%s'", path,
                           pe->key);
            return -1;
        }
        if (own != from && own != to) {
            (void)snprintf(err, errlen, "%s: [lambda_tag_keys] expected the pairs %s is one "
                           "of only, but got %s (re-provision with bess-ded keys)", path, node,
                           pe->key);
            return -1;
        }
        if (k->n_tags >= BD_TAG_KEYS_MAX) {
            (void)snprintf(err, errlen, "%s: [lambda_tag_keys] expected at most %d keys (an "
                           "agent on CAN FD has at most %d neighbours)", path, BD_TAG_KEYS_MAX,
                           BD_FD_NEIGHBOURS_MAX);
            return -1;
        }
        if (pe->type != TOML_STRING || hex_key(pe->s, k->tag_key[k->n_tags]) != 0) {
            (void)snprintf(err, errlen, "%s: [lambda_tag_keys.%s] expected %d hex digits", path,
                           pe->key, 2 * BD_KEY_BYTES);
            return -1;
        }
        k->tag_pair[k->n_tags][0] = (uint8_t)from;
        k->tag_pair[k->n_tags][1] = (uint8_t)to;
        k->n_tags++;
    }
    return 0;
}

/* AUTH-21, AUTH-34: the [lambda_tag_keys] entry of a floor's peer not in [peers]: a
 * sender of a pair to this node; -1 if none */
static int tag_sender(const bd_keyring *k, const char *peer)
{
    uint32_t code = tag_code(peer, strlen(peer));
    uint32_t own = tag_code(k->node, strlen(k->node));
    for (uint32_t t = 0u; t < k->n_tags && code != 0u; ++t) {
        if (k->tag_pair[t][0] == code && k->tag_pair[t][1] == own) {
            return (int)t;
        }
    }
    return -1;
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
    if (k->has_frame_keys && ok) {   /* AUTH-28, AUTH-29: by name, as firmware_py writes */
        char dg[BD_LABEL_MAX + 1];
        char sp[BD_LABEL_MAX + 1];
        char st[BD_LABEL_MAX + 1];
        char hex2[2 * BD_KEY_BYTES + 1];
        char hex3[2 * BD_KEY_BYTES + 1];
        (void)snprintf(dg, sizeof dg, "AGENT_%s_Diag", k->node + 6);
        (void)snprintf(sp, sizeof sp, "AGENT_%s_Setpoint", k->node + 6);
        (void)snprintf(st, sizeof st, "PLANT_%s_Status", k->node + 6);
        hex_of(k->diag_key, BD_KEY_BYTES, hex);
        hex_of(k->setpoint_key, BD_KEY_BYTES, hex2);
        hex_of(k->status_key, BD_KEY_BYTES, hex3);
        ok = fprintf(f, "\n[frame_keys]\n%s = \"%s\"\n%s = \"%s\"\n%s = \"%s\"\n", dg, hex,
                     sp, hex2, st, hex3) > 0;
        hex_of(k->command_key, BD_KEY_BYTES, hex);   /* AUTH-30 */
        ok = ok && fprintf(f, "\n[command_keys]\n%s = \"%s\"\n", k->node, hex) > 0;
    }
    if (k->n_tags > 0u && ok) {   /* AUTH-34, as tomli_w writes them: sorted, quoted */
        ok = fprintf(f, "\n[lambda_tag_keys]\n") > 0;
        for (uint32_t t = 0u; t < k->n_tags && ok; ++t) {
            char from[BD_LABEL_MAX + 1];
            char to[BD_LABEL_MAX + 1];
            tag_label(k->tag_pair[t][0], from);
            tag_label(k->tag_pair[t][1], to);
            hex_of(k->tag_key[t], BD_KEY_BYTES, hex);
            ok = fprintf(f, "\"%s>%s\" = \"%s\"\n", from, to, hex) > 0;
        }
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
    if (k->status_floor != 0u && ok) {   /* the plant's, a sender of [frame_keys] only */
        ok = fprintf(f, "%splant = %u\n", floors == 0 ? "\n[floors]\n" : "",
                     (unsigned)k->status_floor) > 0;
        floors = 1;
    }
    for (uint32_t t = 0u; t < k->n_tags && ok; ++t) {   /* AUTH-34: a tag sender's */
        if (k->tag_floor[t] != 0u) {
            char from[BD_LABEL_MAX + 1];
            tag_label(k->tag_pair[t][0], from);
            ok = fprintf(f, "%s%s = %u\n", floors == 0 ? "\n[floors]\n" : "", from,
                         (unsigned)k->tag_floor[t]) > 0;
            floors = 1;
        }
    }
    if (kf->price_name[0] != '\0' && ok) {   /* AUTH-31: kept as the file had it */
        ok = fprintf(f, "\n[price_signature]\n%s = \"%s\"\n", kf->price_name,
                     kf->price_hex) > 0;
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
    static toml_doc d;
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
    if (bd_toml_read_file(path, text, sizeof text, err, errlen, "node key file") != 0) {
        return -1;
    }
    memset(&d, 0, sizeof d);
    d.src = path;
    d.err = err;
    d.errlen = errlen;
    if (bd_toml_parse(&d, text) != 0) {
        (void)snprintf(err, errlen, "%s: not a readable TOML node key file", path);
        return -1;
    }
    const toml_entry *e = bd_toml_find(&d, "", -1, "format");
    if (e == NULL || e->type != TOML_STRING || strcmp(e->s, KEY_FILE_FORMAT) != 0) {
        (void)snprintf(err, errlen, "%s: [format] expected '%s'", path, KEY_FILE_FORMAT);
        return -1;
    }
    e = bd_toml_find(&d, "", -1, "node");
    if (e == NULL || e->type != TOML_STRING || !node_label_ok(e->s)) {
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
    e = bd_toml_find(&d, "", -1, "fleet_id");
    if (e == NULL || e->type != TOML_STRING || strlen(e->s) != 16u) {
        (void)snprintf(err, errlen, "%s: [fleet_id] expected 16 hex digits", path);
        return -1;
    }
    for (int q = 0; q < 16; ++q) {   /* lowercase hex, as firmware_py's check */
        if (!isdigit((unsigned char)e->s[q]) && !(e->s[q] >= 'a' && e->s[q] <= 'f')) {
            (void)snprintf(err, errlen, "%s: [fleet_id] expected 16 hex digits", path);
            return -1;
        }
    }
    (void)hex_bytes(e->s, k->fleet_id, sizeof k->fleet_id);
    memcpy(kf->fleet_id, e->s, 17u);
    e = bd_toml_find(&d, "", -1, "kdf");
    (void)snprintf(kf->kdf, sizeof kf->kdf, "%s", e != NULL && e->type == TOML_STRING ? e->s
                   : "NIST SP 800-108 counter mode, CMAC-AES-128");
    e = bd_toml_find(&d, "", -1, "mac");
    (void)snprintf(kf->mac, sizeof kf->mac, "%s", e != NULL && e->type == TOML_STRING ? e->s
                   : "CMAC-AES-128");
    e = bd_toml_find(&d, "", -1, "key");
    if (e == NULL || e->type != TOML_STRING || hex_key(e->s, k->key) != 0) {
        (void)snprintf(err, errlen, "%s: [key] expected %d hex digits", path, 2 * BD_KEY_BYTES);
        return -1;
    }
    e = bd_toml_find(&d, "freshness", -1, "boot_counter");
    if (e == NULL || e->type != TOML_INT || e->i < 0 || e->i > 65535) {
        (void)snprintf(err, errlen, "%s: [freshness.boot_counter] expected an integer "
                       "0..65535", path);
        return -1;
    }
    k->boot = (uint32_t)e->i;
    for (int q = 0; q < d.n; ++q) {
        const toml_entry *pe = &d.e[q];
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
        if (pe->type != TOML_STRING || hex_key(pe->s, k->peer_key[k->n_peers]) != 0) {
            (void)snprintf(err, errlen, "%s: [%s] expected %d hex digits", path, pe->key,
                           2 * BD_KEY_BYTES);
            return -1;
        }
        memcpy(k->peer_label[k->n_peers], pe->key, strlen(pe->key) + 1u);
        k->n_peers++;
    }
    char sp[BD_LABEL_MAX + 1];   /* AUTH-28, AUTH-29: the agent's three frame keys */
    char stn[BD_LABEL_MAX + 1];
    char dg[BD_LABEL_MAX + 1];
    (void)snprintf(sp, sizeof sp, "AGENT_%s_Setpoint", k->node + 6);
    (void)snprintf(stn, sizeof stn, "PLANT_%s_Status", k->node + 6);
    (void)snprintf(dg, sizeof dg, "AGENT_%s_Diag", k->node + 6);
    int got = 0;
    for (int q = 0; q < d.n; ++q) {
        const toml_entry *pe = &d.e[q];
        if (strcmp(pe->table, "frame_keys") != 0) {
            continue;
        }
        int which = strcmp(pe->key, sp) == 0 ? 1 : strcmp(pe->key, stn) == 0 ? 2
                    : strcmp(pe->key, dg) == 0 ? 4 : 0;
        if (which == 0) {
            (void)snprintf(err, errlen, "%s: [frame_keys] expected the keys of %s, %s and %s "
                           "only, but got '%s'", path, sp, stn, dg, pe->key);
            return -1;
        }
        uint8_t *out = which == 1 ? k->setpoint_key : which == 2 ? k->status_key : k->diag_key;
        if (pe->type != TOML_STRING || hex_key(pe->s, out) != 0) {
            (void)snprintf(err, errlen, "%s: [%s] expected %d hex digits", path, pe->key,
                           2 * BD_KEY_BYTES);
            return -1;
        }
        got |= which;
    }
    for (int q = 0; q < d.n; ++q) {   /* AUTH-30: the key of the commands to this agent */
        const toml_entry *pe = &d.e[q];
        if (strcmp(pe->table, "command_keys") != 0) {
            continue;
        }
        if (strcmp(pe->key, node) != 0) {
            (void)snprintf(err, errlen, "%s: [command_keys] expected the key of %s only, but "
                           "got '%s'", path, node, pe->key);
            return -1;
        }
        if (pe->type != TOML_STRING || hex_key(pe->s, k->command_key) != 0) {
            (void)snprintf(err, errlen, "%s: [command_keys.%s] expected %d hex digits", path,
                           pe->key, 2 * BD_KEY_BYTES);
            return -1;
        }
        got |= 8;
    }
    if (got != 0 && (got & 7) != 7) {
        (void)snprintf(err, errlen, "%s: [frame_keys] expected the keys of %s, %s and %s, "
                       "but one is missing (re-provision with bess-ded keys)", path, sp, stn,
                       dg);
        return -1;
    }
    if (got != 0 && got != 15) {
        (void)snprintf(err, errlen, "%s: [command_keys] expected the key of %s, but got none "
                       "(re-provision with bess-ded keys)", path, node);
        return -1;
    }
    k->has_frame_keys = got == 15;
    if (tag_keys(&d, path, node, k, err, errlen) != 0) {
        return -1;
    }
    for (int q = 0; q < d.n; ++q) {   /* AUTH-21: each peer's lowest boot accepted */
        const toml_entry *pe = &d.e[q];
        if (strcmp(pe->table, "floors") != 0) {
            continue;
        }
        uint32_t p = 0u;
        while (p < k->n_peers && strcmp(k->peer_label[p], pe->key) != 0) {
            p++;
        }
        if (p == k->n_peers && k->has_frame_keys && strcmp(pe->key, "plant") == 0
            && pe->type == TOML_INT && pe->i >= 0 && pe->i <= 65535) {
            k->status_floor = (uint16_t)pe->i;   /* the sender of PLANT_<id>_Status */
            continue;
        }
        int t = p == k->n_peers ? tag_sender(k, pe->key) : -1;
        if (t >= 0 && pe->type == TOML_INT && pe->i >= 0 && pe->i <= 65535) {
            k->tag_floor[t] = (uint16_t)pe->i;   /* AUTH-34: a neighbour on CAN FD */
            continue;
        }
        if (p == k->n_peers && k->has_frame_keys && strcmp(pe->key, node) == 0
            && pe->type == TOML_INT && pe->i >= 0 && pe->i <= 65535) {
            continue;   /* its own (the sender of its setpoint): its boot is [freshness] */
        }
        if (p == k->n_peers || pe->type != TOML_INT || pe->i < 0 || pe->i > 65535) {
            (void)snprintf(err, errlen, "%s: [floors] expected a table of peer = lowest boot "
                           "counter (0..65535), for peers listed in [peers] or senders of "
                           "[frame_keys], but got '%s'", path, pe->key);
            return -1;
        }
        k->peer_floor[p] = (uint16_t)pe->i;
    }
    kf->price_name[0] = '\0';
    if (price_keys(&d, path, kf, k, err, errlen) != 0) {
        return -1;
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
