/*
 * python-can's udp_multicast datagram (udp_msgpack.h): the writer of its one map, and a
 * strict reader of exactly that map. The reader never trusts a length: every read is
 * checked against the datagram's end (struct reader), the structure is walked in full
 * before any value is used (so what msgpack itself would refuse, as python-can's
 * msgpack.unpackb does, is BD_UDP_NOT_A_FRAME whatever it holds), nesting is bounded,
 * and each container's count is bounded by the bytes left (an item is at least a byte).
 */
#include "udp_msgpack.h"

#include <string.h>

/* pack_message's keys, in its order */
enum {
    K_TIMESTAMP, K_ID, K_EXTENDED, K_REMOTE, K_ERROR, K_CHANNEL, K_DLC, K_DATA, K_FD, K_BRS,
    K_ESI, K_COUNT
};
static const char *const keys[K_COUNT] = {
    "timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame",
    "channel", "dlc", "data", "is_fd", "bitrate_switch", "error_state_indicator"
};

#define DEPTH_MAX 8   /* nesting walked in a value no key takes (channel: an array, ...) */

/* ------------------------------------------------------------------ writer */

typedef struct {
    uint8_t *p;
    size_t cap;
    size_t n;
} writer;

static void put(writer *w, uint8_t b)
{
    if (w->n < w->cap) {
        w->p[w->n] = b;
    }
    w->n++;   /* counts on past cap: the caller sees it did not fit */
}

static void put_be(writer *w, uint64_t v, unsigned width)
{
    for (unsigned k = width; k > 0u; --k) {
        put(w, (uint8_t)(v >> (8u * (k - 1u))));
    }
}

static void put_bytes(writer *w, const uint8_t *b, size_t len)
{
    for (size_t i = 0u; i < len; ++i) {
        put(w, b[i]);
    }
}

static void put_key(writer *w, int k)   /* every key is a fixstr (< 32 bytes) */
{
    size_t len = strlen(keys[k]);
    put(w, (uint8_t)(0xa0u | len));
    put_bytes(w, (const uint8_t *)keys[k], len);
}

static void put_bool(writer *w, int k, uint32_t set)
{
    put_key(w, k);
    put(w, set != 0u ? 0xc3u : 0xc2u);
}

static void put_uint(writer *w, uint32_t v)   /* msgpack's smallest form, as msgpack-python */
{
    if (v <= 0x7fu) {
        put(w, (uint8_t)v);
    } else if (v <= 0xffu) {
        put(w, 0xccu);
        put_be(w, v, 1u);
    } else if (v <= 0xffffu) {
        put(w, 0xcdu);
        put_be(w, v, 2u);
    } else {
        put(w, 0xceu);
        put_be(w, v, 4u);
    }
}

size_t bd_udp_encode(const bd_frame *f, double timestamp, uint8_t *out, size_t cap)
{
    writer w = {out, cap, 0u};
    uint64_t bits;
    uint8_t len = f->len <= BD_FRAME_DATA ? f->len : BD_FRAME_DATA;
    memcpy(&bits, &timestamp, sizeof bits);
    put(&w, (uint8_t)(0x80u | K_COUNT));
    put_key(&w, K_TIMESTAMP);
    put(&w, 0xcbu);   /* a Python float: binary64 */
    put_be(&w, bits, 8u);
    put_key(&w, K_ID);
    put_uint(&w, f->id);
    put_bool(&w, K_EXTENDED, f->flags & BD_FRAME_EXT);
    put_bool(&w, K_REMOTE, f->flags & BD_FRAME_RTR);
    put_bool(&w, K_ERROR, f->flags & BD_FRAME_ERR);
    put_key(&w, K_CHANNEL);
    put(&w, 0xc0u);   /* None */
    put_key(&w, K_DLC);
    put_uint(&w, len);
    put_key(&w, K_DATA);
    put(&w, 0xc4u);   /* bytes (use_bin_type=True): bin 8 */
    put(&w, len);
    put_bytes(&w, f->data, len);
    put_bool(&w, K_FD, f->flags & BD_FRAME_FD);
    put_bool(&w, K_BRS, f->flags & BD_FRAME_BRS);
    put_bool(&w, K_ESI, 0u);
    return w.n <= cap ? w.n : 0u;
}

/* ------------------------------------------------------------------ reader */

typedef struct {
    const uint8_t *b;
    size_t n;
    size_t pos;
} reader;

static int get_u8(reader *r, uint8_t *v)
{
    if (r->pos >= r->n) {
        return -1;
    }
    *v = r->b[r->pos++];
    return 0;
}

static int get_be(reader *r, unsigned width, uint64_t *v)
{
    if (r->n - r->pos < width) {
        return -1;
    }
    uint64_t x = 0u;
    for (unsigned k = 0u; k < width; ++k) {
        x = (x << 8u) | r->b[r->pos++];
    }
    *v = x;
    return 0;
}

static int skip(reader *r, uint64_t len)
{
    if ((uint64_t)(r->n - r->pos) < len) {
        return -1;
    }
    r->pos += (size_t)len;
    return 0;
}

/* the width of the length or count field after tag t (str/bin/array/map/ext 8/16/32) */
static unsigned width_of(uint8_t t)
{
    switch (t) {
    case 0xd9u: case 0xc4u: case 0xc7u:
        return 1u;
    case 0xdau: case 0xc5u: case 0xc8u: case 0xdcu: case 0xdeu:
        return 2u;
    default:   /* 0xdb, 0xc6, 0xc9, 0xdd, 0xdf */
        return 4u;
    }
}

static int skip_value(reader *r, int depth);

static int skip_items(reader *r, uint64_t count, int depth)
{
    if (depth >= DEPTH_MAX) {
        return -1;
    }
    for (uint64_t k = 0u; k < count; ++k) {   /* ends by n - pos: each item takes a byte */
        if (skip_value(r, depth + 1) != 0) {
            return -1;
        }
    }
    return 0;
}

/* One msgpack object of any type, walked to its end; -1 if it is none (truncated, the
 * never-used tag 0xc1, nested deeper than DEPTH_MAX). */
static int skip_value(reader *r, int depth)
{
    uint8_t t;
    uint64_t len;
    if (get_u8(r, &t) != 0) {
        return -1;
    }
    if (t <= 0x7fu || t >= 0xe0u || t == 0xc0u || t == 0xc2u || t == 0xc3u) {
        return 0;   /* fixint, nil, bool */
    }
    if (t >= 0xa0u && t <= 0xbfu) {
        return skip(r, t & 0x1fu);
    }
    if (t >= 0x90u && t <= 0x9fu) {
        return skip_items(r, t & 0x0fu, depth);
    }
    if (t >= 0x80u && t <= 0x8fu) {
        return skip_items(r, 2u * (t & 0x0fu), depth);
    }
    switch (t) {
    case 0xccu: case 0xd0u:
        return skip(r, 1u);
    case 0xcdu: case 0xd1u:
        return skip(r, 2u);
    case 0xceu: case 0xd2u: case 0xcau:
        return skip(r, 4u);
    case 0xcfu: case 0xd3u: case 0xcbu:
        return skip(r, 8u);
    case 0xd4u: case 0xd5u: case 0xd6u: case 0xd7u: case 0xd8u:   /* fixext 1..16 + type */
        return skip(r, 1u + (1u << (t - 0xd4u)));
    case 0xd9u: case 0xdau: case 0xdbu: case 0xc4u: case 0xc5u: case 0xc6u:
        return get_be(r, width_of(t), &len) != 0 ? -1 : skip(r, len);
    case 0xc7u: case 0xc8u: case 0xc9u:
        return get_be(r, width_of(t), &len) != 0 ? -1 : skip(r, len + 1u);
    case 0xdcu: case 0xddu:
        return get_be(r, width_of(t), &len) != 0 ? -1 : skip_items(r, len, depth);
    case 0xdeu: case 0xdfu:
        return get_be(r, width_of(t), &len) != 0 ? -1 : skip_items(r, 2u * len, depth);
    default:   /* 0xc1: never used */
        return -1;
    }
}

enum { V_UINT, V_NEG, V_FLOAT, V_NIL, V_BOOL, V_STR, V_BIN, V_OTHER };

typedef struct {
    int kind;
    uint64_t u;           /* V_UINT: the value; V_BOOL: 0/1; V_STR, V_BIN: the length */
    const uint8_t *p;     /* V_STR, V_BIN: the bytes (within the datagram) */
} value;

/* One value of a datagram whose structure skip_value has checked (the reads are
 * checked all the same). -1: truncated. */
static int read_value(reader *r, value *v)
{
    uint8_t t;
    uint64_t x;
    size_t start = r->pos;
    memset(v, 0, sizeof *v);
    if (get_u8(r, &t) != 0) {
        return -1;
    }
    if (t <= 0x7fu) {
        v->kind = V_UINT;
        v->u = t;
        return 0;
    }
    if (t >= 0xe0u) {
        v->kind = V_NEG;
        return 0;
    }
    if ((t >= 0xa0u && t <= 0xbfu) || t == 0xd9u || t == 0xdau || t == 0xdbu
        || t == 0xc4u || t == 0xc5u || t == 0xc6u) {
        if (t >= 0xa0u && t <= 0xbfu) {
            x = t & 0x1fu;
        } else if (get_be(r, width_of(t), &x) != 0) {
            return -1;
        }
        v->kind = (t >= 0xc4u && t <= 0xc6u) ? V_BIN : V_STR;
        v->u = x;
        v->p = r->b + r->pos;
        return skip(r, x);
    }
    switch (t) {
    case 0xc0u:
        v->kind = V_NIL;
        return 0;
    case 0xc2u: case 0xc3u:
        v->kind = V_BOOL;
        v->u = t == 0xc3u ? 1u : 0u;
        return 0;
    case 0xccu: case 0xcdu: case 0xceu: case 0xcfu:
        v->kind = V_UINT;
        return get_be(r, 1u << (t - 0xccu), &v->u);
    case 0xd0u: case 0xd1u: case 0xd2u: case 0xd3u: {   /* signed: an int if >= 0 */
        unsigned width = 1u << (t - 0xd0u);
        if (get_be(r, width, &x) != 0) {
            return -1;
        }
        uint64_t sign = (uint64_t)1u << (8u * width - 1u);
        v->kind = (x & sign) != 0u ? V_NEG : V_UINT;
        v->u = x;
        return 0;
    }
    case 0xcau: case 0xcbu:
        v->kind = V_FLOAT;
        return skip(r, t == 0xcau ? 4u : 8u);
    default:   /* an array, a map, an ext: no key of the map takes one */
        r->pos = start;
        v->kind = V_OTHER;
        return skip_value(r, 0);
    }
}

/* the key at r: its index in keys[], -1 if none (or not a string) */
static int read_key(reader *r)
{
    value v;
    if (read_value(r, &v) != 0 || v.kind != V_STR) {
        return -1;
    }
    for (int k = 0; k < K_COUNT; ++k) {
        if (strlen(keys[k]) == v.u && memcmp(keys[k], v.p, (size_t)v.u) == 0) {
            return k;
        }
    }
    return -1;
}

static int fd_length(uint64_t len)
{
    return len <= 8u || len == 12u || len == 16u || len == 20u || len == 24u || len == 32u
           || len == 48u || len == 64u;
}

/* can.Message(check=True)'s rules (its _check) and firmware_py.node.frame_fault's
 * types, plus a length a CAN FD frame can have */
static int check(const value *v)
{
    static const int flags[] = {K_EXTENDED, K_REMOTE, K_ERROR, K_FD, K_BRS, K_ESI};
    for (size_t k = 0u; k < sizeof flags / sizeof flags[0]; ++k) {
        if (v[flags[k]].kind != V_BOOL) {
            return -1;
        }
    }
    int channel = v[K_CHANNEL].kind;
    if ((v[K_TIMESTAMP].kind != V_FLOAT && v[K_TIMESTAMP].kind != V_UINT)
        || v[K_ID].kind != V_UINT || v[K_DLC].kind != V_UINT || v[K_DATA].kind != V_BIN
        || (channel != V_NIL && channel != V_STR && channel != V_UINT && channel != V_NEG)) {
        return -1;
    }
    uint64_t fd = v[K_FD].u;
    uint64_t remote = v[K_REMOTE].u;
    uint64_t dlc = v[K_DLC].u;
    uint64_t len = v[K_DATA].u;
    if ((remote != 0u && (v[K_ERROR].u != 0u || fd != 0u))
        || v[K_ID].u > (v[K_EXTENDED].u != 0u ? 0x1fffffffu : 0x7ffu)
        || dlc > (fd != 0u ? 64u : 8u)
        || (remote != 0u ? len != 0u : len != dlc)
        || (fd == 0u && (v[K_BRS].u != 0u || v[K_ESI].u != 0u))
        || (fd != 0u && !fd_length(len))) {
        return -1;
    }
    return 0;
}

int bd_udp_decode(const uint8_t *buf, size_t n, bd_frame *f, uint8_t *data64)
{
    reader r = {buf, n, 0u};
    value v[K_COUNT];
    uint8_t t = 0u;
    int seen[K_COUNT] = {0};
    memset(f, 0, sizeof *f);
    memset(v, 0, sizeof v);
    if (n > BD_UDP_DATAGRAM_MAX || skip_value(&r, 0) != 0 || r.pos != n) {
        return BD_UDP_NOT_A_FRAME;   /* msgpack.unpackb fails: truncated, extra data, ... */
    }
    r.pos = 0u;
    (void)get_u8(&r, &t);   /* n >= 1: skip_value read it */
    if (t != (uint8_t)(0x80u | K_COUNT)) {   /* the map of 11 entries, as pack_message */
        return BD_UDP_NOT_A_FRAME;
    }
    for (int e = 0; e < K_COUNT; ++e) {
        int k = read_key(&r);
        if (k < 0 || seen[k]) {
            return BD_UDP_NOT_A_FRAME;   /* Message() takes no such argument */
        }
        seen[k] = 1;
        if (read_value(&r, &v[k]) != 0) {
            return BD_UDP_NOT_A_FRAME;
        }
    }
    if (check(v) != 0) {
        return BD_UDP_INVALID_FRAME;
    }
    uint8_t len = (uint8_t)v[K_DLC].u;   /* <= 64 (check) */
    f->id = (uint32_t)v[K_ID].u;
    f->len = len;
    f->flags = (uint8_t)((v[K_EXTENDED].u != 0u ? BD_FRAME_EXT : 0u)
                         | (v[K_REMOTE].u != 0u ? BD_FRAME_RTR : 0u)
                         | (v[K_ERROR].u != 0u ? BD_FRAME_ERR : 0u)
                         | (v[K_FD].u != 0u ? BD_FRAME_FD : 0u)
                         | (v[K_BRS].u != 0u ? BD_FRAME_BRS : 0u));
    size_t have = (size_t)v[K_DATA].u;   /* == len, or 0 for a remote frame */
    memcpy(f->data, v[K_DATA].p, have <= BD_FRAME_DATA ? have : BD_FRAME_DATA);
    if (data64 != NULL) {
        memcpy(data64, v[K_DATA].p, have);
    }
    return BD_UDP_FRAME;
}
