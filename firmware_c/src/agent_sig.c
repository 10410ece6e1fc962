/*
 * The signed price (docs/firmware-spec.md AUTH-31..33, docs/security.md): the router's
 * ER_PriceSig pages reassembled, the Ed25519 signature verified once per transfer
 * through the crypto seam (bd_ed25519_verify, src/crypto_sodium.c), and the check that
 * an ER_Price carries the signed segment. Bit-exact C99 port of firmware_py/pricesig.py
 * (PriceSigReceiver) and its use in firmware_py/runtime.py: the same pages, the same
 * signed bytes, the same acceptance rule and counters (unsigned_price, bad_signature,
 * sig_malformed). Compiled out with BD_SIGNED_PRICE 0 (agent.h).
 */
#include "bessded/agent.h"

#include <string.h>

#include "agent_internal.h"

#if BD_SIGNED_PRICE

#define LABEL_BYTES (sizeof BD_SIG_LABEL - 1u)
/* label ‖ fleet ID (8) ‖ Boot (2, BE) ‖ segment number (2, BE) ‖ PriceValid (1) ‖ Rho (4) */
#define MESSAGE_BYTES (LABEL_BYTES + 8u + 2u + 2u + 1u + 4u)
/* the last page's signature bytes (the rest of its Signature must be 0) */
#define LAST_PAGE_BYTES \
    (BD_ED25519_SIG_BYTES - (BD_SIG_PAGES - 1) * BD_SIG_PAGE_BYTES)
#define PAGE_MASK 0x0Fu   /* ER_PriceSig.Page: bits 0..3 (gen_contract.py checks the layout) */

/* the two's-complement int32 of a 32-bit raw value, without an implementation-defined
 * conversion */
static int32_t s32(uint32_t u)
{
    return u >= 0x80000000u ? -(int32_t)(~u) - 1 : (int32_t)u;
}

static int same_segment(const bd_signed_segment *x, const bd_signed_segment *y)
{
    return x->boot == y->boot && x->number == y->number && x->valid == y->valid
           && x->rho == y->rho;
}

/* pricesig.SignedSegment.after: a later boot, or a segment number at or after other's
 * (mod BD_SIG_SEGMENT_MOD, within half the range) in the same boot */
static int after(const bd_signed_segment *x, const bd_signed_segment *other)
{
    if (x->boot != other->boot) {
        return x->boot > other->boot;
    }
    uint32_t d = ((uint32_t)x->number + BD_SIG_SEGMENT_MOD - other->number)
                 % BD_SIG_SEGMENT_MOD;
    return d < BD_SIG_SEGMENT_MOD / 2u;
}

/* pricesig.SignedSegment.message: the bytes the router signs */
static void message(const bd_price_sig *g, const bd_signed_segment *seg,
                    uint8_t m[MESSAGE_BYTES])
{
    size_t n = 0u;
    memcpy(m, BD_SIG_LABEL, LABEL_BYTES);
    n += LABEL_BYTES;
    memcpy(m + n, g->fleet, 8u);
    n += 8u;
    m[n++] = (uint8_t)(seg->boot >> 8);
    m[n++] = (uint8_t)(seg->boot & 0xFFu);
    m[n++] = (uint8_t)(seg->number >> 8);
    m[n++] = (uint8_t)(seg->number & 0xFFu);
    m[n++] = (uint8_t)(seg->valid & 1u);
    uint32_t r = (uint32_t)seg->rho;
    for (int k = 3; k >= 0; --k) {
        m[n++] = (uint8_t)((r >> (8 * k)) & 0xFFu);
    }
}

static void reject(bd_agent *a, int cause)
{
    bd_count_add(a, cause, 1u, BD_ER_PRICESIG_ID);
}

void bd_sig_page(bd_agent *a, const bd_frame *f)
{
    bd_price_sig *g = &a->sig;
    if (f->len != 8u) {   /* the codec's DLC check: a transfer's fault is sig_malformed */
        reject(a, BD_C_SIG_MALFORMED);
        return;
    }
    uint64_t x = 0u;
    for (unsigned k = 0u; k < 8u; ++k) {
        x |= (uint64_t)f->data[k] << (8u * k);
    }
    uint32_t page = (uint32_t)(x & PAGE_MASK);
    if (page > BD_SIG_PAGES) {   /* outside Page's DBC range */
        reject(a, BD_C_SIG_MALFORMED);
        return;
    }
    if (page == 0u) {   /* the signed segment: a new transfer */
        g->header.valid = (uint8_t)((x >> 4) & 1u);
        g->header.number = (uint16_t)(((x >> 5) & 7u)
                                      | (((x >> 56) & 0xFFu) << BD_SIG_SEGMENT_LOW_BITS));
        g->header.rho = s32((uint32_t)((x >> 8) & 0xFFFFFFFFu));
        g->header.boot = (uint16_t)((x >> 40) & 0xFFFFu);
        g->has_header = 1u;
        g->have = 0u;
        return;
    }
    if (!g->has_header) {   /* a page without its page 0 */
        reject(a, BD_C_SIG_MALFORMED);
        return;
    }
    uint64_t value = x >> 8;   /* Signature: bytes 1..7 */
    if (page == BD_SIG_PAGES && (value >> (8u * LAST_PAGE_BYTES)) != 0u) {
        g->has_header = 0u;   /* bytes beyond the signature */
        reject(a, BD_C_SIG_MALFORMED);
        return;
    }
    uint16_t bit = (uint16_t)(1u << (page - 1u));
    if ((g->have & bit) != 0u && g->part[page - 1u] != value) {
        g->has_header = 0u;   /* a page repeated with other bytes */
        reject(a, BD_C_SIG_MALFORMED);
        return;
    }
    g->part[page - 1u] = value;
    g->have = (uint16_t)(g->have | bit);
    if (g->have != (uint16_t)((1u << BD_SIG_PAGES) - 1u)) {
        return;
    }
    bd_signed_segment seg = g->header;
    g->has_header = 0u;
    g->have = 0u;
    uint8_t sig[BD_ED25519_SIG_BYTES];
    for (unsigned k = 0u; k < BD_ED25519_SIG_BYTES; ++k) {
        unsigned p = k / BD_SIG_PAGE_BYTES;
        sig[k] = (uint8_t)((g->part[p] >> (8u * (k - p * BD_SIG_PAGE_BYTES))) & 0xFFu);
    }
    if (g->has_current && same_segment(&seg, &g->current)
        && memcmp(sig, g->signature, sizeof sig) == 0) {
        return;   /* the once-a-second repeat of what is held: no verify */
    }
    uint8_t m[MESSAGE_BYTES];
    message(g, &seg, m);
    if (g->verifications < UINT32_MAX) {
        g->verifications++;
    }
    if (bd_ed25519_verify(sig, m, sizeof m, g->key) != 1) {
        reject(a, BD_C_BAD_SIGNATURE);
        return;
    }
    /* the router's boot as its freshness says (a signature of an earlier boot: a replay) */
    const bd_rx_slot *price = &a->rx[BD_RX_PRICE];
    uint32_t min_boot = (price->flags & BD_RX_HAS_FV) != 0u ? fv_boot(price->fv) : 0u;
    if (seg.boot < min_boot || (g->has_current && !after(&seg, &g->current))) {
        reject(a, BD_C_BAD_SIGNATURE);   /* genuine but older than the one held */
        return;
    }
    g->current = seg;
    g->has_current = 1u;
    memcpy(g->signature, sig, sizeof sig);
}

int bd_sig_vouches(const bd_agent *a, uint32_t boot)
{
    const bd_price_sig *g = &a->sig;
    return g->has_current && g->current.boot >= boot;
}

int bd_sig_price_ok(const bd_agent *a, const bd_price_msg *m)
{
    const bd_price_sig *g = &a->sig;
    return g->has_current && m->price_valid == g->current.valid && m->rho == g->current.rho
           && m->segment == ((uint32_t)g->current.number & ((1u << BD_SIG_SEGMENT_LOW_BITS) - 1u));
}

#endif /* BD_SIGNED_PRICE */

uint32_t bd_agent_sig_verifications(const bd_agent *a)
{
#if BD_SIGNED_PRICE
    return a->sig.verifications;
#else
    (void)a;
    return 0u;
#endif
}
