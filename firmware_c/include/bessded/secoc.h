/*
 * SecOC-style frame authentication (docs/firmware-spec.md section 12, docs/security.md):
 * the node key derivation (AUTH-1), the 24-bit truncated CMAC of a secured or sync
 * frame (AUTH-6..8) and the receiver's freshness reconstruction (AUTH-9..11).
 *
 * The only cryptographic primitive is CMAC-AES-128, and it is the crypto seam:
 * bd_cmac_aes128 is implemented by src/crypto_mbedtls.c (mbedTLS) on Linux; an MCU
 * port links its own (a hardware AES, an HSM/SHE) instead. The opt-in signed price adds
 * a second seam, Ed25519 verification (bd_ed25519_verify, src/crypto_sodium.c:
 * libsodium). Nothing here is hand-written cryptography.
 */
#ifndef BESSDED_SECOC_H
#define BESSDED_SECOC_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define BD_KEY_BYTES 16
#define BD_LABEL_MAX 32       /* node labels: [a-z][a-z0-9_]{0,31} */

/* The crypto seam: the full 16-byte CMAC-AES-128 tag (NIST SP 800-38B) of msg.
 * Returns 0 on success, nonzero if the platform's primitive failed. */
int bd_cmac_aes128(const uint8_t key[BD_KEY_BYTES], const uint8_t *msg, size_t len,
                   uint8_t tag[16]);

/* The signed price's seam (AUTH-31, AUTH-32; BD_SIGNED_PRICE builds only): Ed25519
 * (RFC 8032) by src/crypto_sodium.c (libsodium) on Linux. bd_ed25519_verify: 1 if sig is
 * the holder of public key pk's signature of msg[0..len-1], 0 if not (a malformed key or
 * signature included). bd_ed25519_public: the public key of a 32-byte private key (its
 * seed), 0 on success. */
#define BD_ED25519_PUBLIC_BYTES 32
#define BD_ED25519_SEED_BYTES 32
#define BD_ED25519_SIG_BYTES 64
int bd_ed25519_verify(const uint8_t sig[BD_ED25519_SIG_BYTES], const uint8_t *msg, size_t len,
                      const uint8_t pk[BD_ED25519_PUBLIC_BYTES]);
int bd_ed25519_public(const uint8_t seed[BD_ED25519_SEED_BYTES],
                      uint8_t pk[BD_ED25519_PUBLIC_BYTES]);

/* AUTH-1: K_node = CMAC(K_master, 00000001 || "bess-ded/secoc/node-key/v1" || 00 ||
 * label || 00000080). label: NUL-terminated, 1..32 characters. 0 on success. */
int bd_derive_node_key(const uint8_t master[BD_KEY_BYTES], const char *label,
                       uint8_t out[BD_KEY_BYTES]);

/* AUTH-28: the key of link frame `name` (a DBC message name, 1..32 characters:
 * AGENT_<i>_Setpoint, PLANT_<i>_Status) and of its sync: CMAC(K_master, 00000001 ||
 * "bess-ded/secoc/frame-key/v1" || 00 || name || 00000080). 0 on success. */
int bd_derive_frame_key(const uint8_t master[BD_KEY_BYTES], const char *name,
                        uint8_t out[BD_KEY_BYTES]);

/* AUTH-30: the key of the ER_Command frames to agent `target` ("agent_<i>"):
 * CMAC(K_master, 00000001 || "bess-ded/secoc/command-key/v1" || 00 || target ||
 * 00000080). 0 on success. */
int bd_derive_command_key(const uint8_t master[BD_KEY_BYTES], const char *target,
                          uint8_t out[BD_KEY_BYTES]);

/* AUTH-34: the key of the λ tags agent `sender` ("agent_<i>") sends `receiver` (a node
 * label): CMAC(K_master, 00000001 || "bess-ded/secoc/lambda-tag-key/v1" || 00 || sender ||
 * ">" || receiver || 00000080). 0 on success. */
int bd_derive_lambda_tag_key(const uint8_t master[BD_KEY_BYTES], const char *sender,
                             const char *receiver, uint8_t out[BD_KEY_BYTES]);

/* The public fleet tag of a key set (the KDF with label "bess-ded/secoc/fleet-id/v1",
 * empty context, L = 64): 8 bytes. 0 on success. */
int bd_fleet_id(const uint8_t master[BD_KEY_BYTES], uint8_t out[8]);

/* AUTH-6..8: write the leading 24 bits of CMAC(key, id (2 bytes BE) || data[3] & 0xF0 ||
 * data[4..7] || fv (8 bytes BE)) into data[0..2] (MSB first). 0 on success. */
int bd_sign_frame(const uint8_t key[BD_KEY_BYTES], uint32_t frame_id, uint8_t data[8],
                  uint64_t fv);

/* 1 if data[0..2] is the MAC bd_sign_frame would write for (key, frame_id, data, fv),
 * 0 if it is not, -1 if the primitive failed (nothing can be verified: the caller
 * stops). The comparison does not stop at the first differing byte. */
int bd_frame_verifies(const uint8_t key[BD_KEY_BYTES], uint32_t frame_id,
                      const uint8_t data[8], uint64_t fv);

/* AUTH-34: the same 24 bits over the same input (data[3..7], fv) into tag[0..2], and
 * whether tag[0..2] is it (1, 0, or -1 if the primitive failed): a receiver's tag slot
 * of an FD AGENT_<i>_MC or its sync. bd_sign_frame and bd_frame_verifies are these with
 * tag = data. */
int bd_tag_frame(const uint8_t key[BD_KEY_BYTES], uint32_t frame_id, const uint8_t data[8],
                 uint64_t fv, uint8_t tag[3]);
int bd_tag_verifies(const uint8_t key[BD_KEY_BYTES], uint32_t frame_id, const uint8_t data[8],
                    uint64_t fv, const uint8_t tag[3]);

/* AUTH-9: the full freshness value a frame carrying the low tx_bits `truncated` is
 * verified with, from the last accepted value `last`: the high bits of last, plus one
 * step of 2^tx_bits when truncated <= the low bits of last. Returns 0 and *out, or -1
 * when the candidate would exceed max_value (re-key or resync needed). */
int bd_fv_candidate(uint64_t last, uint32_t truncated, unsigned tx_bits, uint64_t max_value,
                    uint64_t *out);

/* AUTH-25: the most recent freshness value at or below `last` whose low tx_bits are
 * `truncated` (a genuine frame that arrived late verifies with it; earlier windows are
 * *out - k * 2^tx_bits). Returns 0 and *out, or -1 when there is none (last too small). */
int bd_fv_past(uint64_t last, uint32_t truncated, unsigned tx_bits, uint64_t *out);

#ifdef __cplusplus
}
#endif

#endif /* BESSDED_SECOC_H */
