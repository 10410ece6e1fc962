/*
 * SecOC-style authentication (secoc.h): the KDF, the truncated frame MAC and the
 * freshness candidate, over the one primitive bd_cmac_aes128 (the crypto seam).
 */
#include "bessded/secoc.h"

#include <string.h>

#define NODE_KEY_LABEL "bess-ded/secoc/node-key/v1"
#define FLEET_ID_LABEL "bess-ded/secoc/fleet-id/v1"
#define FRAME_KEY_LABEL "bess-ded/secoc/frame-key/v1"   /* AUTH-28 */
#define COMMAND_KEY_LABEL "bess-ded/secoc/command-key/v1"   /* AUTH-30 */
#define TAG_KEY_LABEL "bess-ded/secoc/lambda-tag-key/v1"   /* AUTH-34: the longest label */
#define KDF_MAX (4u + sizeof TAG_KEY_LABEL + BD_LABEL_MAX + 4u)

static void put_be32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v >> 24);
    p[1] = (uint8_t)(v >> 16);
    p[2] = (uint8_t)(v >> 8);
    p[3] = (uint8_t)v;
}

/* NIST SP 800-108 counter mode, one block: CMAC(K, [1]_32 || label || 00 || context ||
 * [L]_32), the first out_len bytes. */
static int kdf(const uint8_t master[BD_KEY_BYTES], const char *label, const char *context,
               uint32_t l_bits, uint8_t *out, size_t out_len)
{
    uint8_t m[KDF_MAX];
    uint8_t tag[16];
    size_t nl = strlen(label);
    size_t nc = strlen(context);
    size_t k = 0u;
    if (nl + 1u > sizeof TAG_KEY_LABEL || nc > BD_LABEL_MAX || out_len > sizeof tag) {
        return -1;   /* the message would not fit m (a node label over BD_LABEL_MAX) */
    }
    put_be32(&m[k], 1u);
    k += 4u;
    memcpy(&m[k], label, nl);
    k += nl;
    m[k++] = 0u;
    memcpy(&m[k], context, nc);
    k += nc;
    put_be32(&m[k], l_bits);
    k += 4u;
    if (bd_cmac_aes128(master, m, k, tag) != 0) {
        return -1;
    }
    memcpy(out, tag, out_len);
    return 0;
}

int bd_derive_node_key(const uint8_t master[BD_KEY_BYTES], const char *label,
                       uint8_t out[BD_KEY_BYTES])
{
    if (label[0] == '\0') {
        return -1;
    }
    return kdf(master, NODE_KEY_LABEL, label, 8u * BD_KEY_BYTES, out, BD_KEY_BYTES);
}

int bd_derive_frame_key(const uint8_t master[BD_KEY_BYTES], const char *name,
                        uint8_t out[BD_KEY_BYTES])
{
    if (name[0] == '\0') {
        return -1;
    }
    return kdf(master, FRAME_KEY_LABEL, name, 8u * BD_KEY_BYTES, out, BD_KEY_BYTES);
}

int bd_derive_command_key(const uint8_t master[BD_KEY_BYTES], const char *target,
                          uint8_t out[BD_KEY_BYTES])
{
    if (strncmp(target, "agent_", 6) != 0 || target[6] == '\0') {
        return -1;
    }
    return kdf(master, COMMAND_KEY_LABEL, target, 8u * BD_KEY_BYTES, out, BD_KEY_BYTES);
}

int bd_derive_lambda_tag_key(const uint8_t master[BD_KEY_BYTES], const char *sender,
                             const char *receiver, uint8_t out[BD_KEY_BYTES])
{
    char pair[BD_LABEL_MAX + 1];
    size_t ns = strlen(sender);
    size_t nr = strlen(receiver);
    if (strncmp(sender, "agent_", 6) != 0 || ns == 6u || nr == 0u
        || ns + 1u + nr > BD_LABEL_MAX) {
        return -1;
    }
    memcpy(pair, sender, ns);   /* the pair's label, "agent_1>agent_3" */
    pair[ns] = '>';
    memcpy(&pair[ns + 1u], receiver, nr + 1u);
    return kdf(master, TAG_KEY_LABEL, pair, 8u * BD_KEY_BYTES, out, BD_KEY_BYTES);
}

int bd_fleet_id(const uint8_t master[BD_KEY_BYTES], uint8_t out[8])
{
    return kdf(master, FLEET_ID_LABEL, "", 64u, out, 8u);
}

/* AUTH-6: CMAC(key, id (2 bytes BE) || d[3] & 0xF0 || d[4..7] || fv (8 bytes BE)) */
static int frame_tag(const uint8_t key[BD_KEY_BYTES], uint32_t frame_id, const uint8_t d[8],
                     uint64_t fv, uint8_t tag[16])
{
    uint8_t m[2u + 5u + 8u];
    m[0] = (uint8_t)(frame_id >> 8);
    m[1] = (uint8_t)frame_id;
    m[2] = (uint8_t)(d[3] & 0xF0u);
    memcpy(&m[3], &d[4], 4u);
    for (unsigned k = 0u; k < 8u; ++k) {
        m[7u + k] = (uint8_t)(fv >> (56u - 8u * k));
    }
    return bd_cmac_aes128(key, m, sizeof m, tag);
}

int bd_tag_frame(const uint8_t key[BD_KEY_BYTES], uint32_t frame_id, const uint8_t data[8],
                 uint64_t fv, uint8_t tag[3])
{
    uint8_t full[16];
    if (frame_tag(key, frame_id, data, fv, full) != 0) {
        return -1;
    }
    memcpy(tag, full, 3u);   /* the leading 24 bits, MSB first (AUTH-7) */
    return 0;
}

int bd_tag_verifies(const uint8_t key[BD_KEY_BYTES], uint32_t frame_id, const uint8_t data[8],
                    uint64_t fv, const uint8_t tag[3])
{
    uint8_t full[16];
    if (frame_tag(key, frame_id, data, fv, full) != 0) {
        return -1;
    }
    unsigned diff = 0u;   /* no early exit: the time does not tell where they differ */
    for (unsigned k = 0u; k < 3u; ++k) {
        diff |= (unsigned)(full[k] ^ tag[k]);
    }
    return diff == 0u;
}

int bd_sign_frame(const uint8_t key[BD_KEY_BYTES], uint32_t frame_id, uint8_t data[8],
                  uint64_t fv)
{
    return bd_tag_frame(key, frame_id, data, fv, data);
}

int bd_frame_verifies(const uint8_t key[BD_KEY_BYTES], uint32_t frame_id,
                      const uint8_t data[8], uint64_t fv)
{
    return bd_tag_verifies(key, frame_id, data, fv, data);
}

int bd_fv_candidate(uint64_t last, uint32_t truncated, unsigned tx_bits, uint64_t max_value,
                    uint64_t *out)
{
    uint64_t mask = (UINT64_C(1) << tx_bits) - 1u;
    if (tx_bits < 1u || tx_bits > 63u || truncated > mask) {
        return -1;
    }
    uint64_t high = last >> tx_bits;
    if (truncated <= (last & mask)) {
        high++;
    }
    uint64_t value = (high << tx_bits) | truncated;
    if (value > max_value) {
        return -1;
    }
    *out = value;
    return 0;
}

int bd_fv_past(uint64_t last, uint32_t truncated, unsigned tx_bits, uint64_t *out)
{
    uint64_t mask = (UINT64_C(1) << tx_bits) - 1u;
    if (tx_bits < 1u || tx_bits > 63u || truncated > mask) {
        return -1;
    }
    uint64_t back = (last - truncated) & mask;   /* mod 2^tx_bits, last >= back below */
    if (back > last) {
        return -1;
    }
    *out = last - back;
    return 0;
}
