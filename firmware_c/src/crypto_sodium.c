/*
 * The signed price's crypto seam on Linux (secoc.h; AUTH-31, AUTH-32): Ed25519 from
 * libsodium (libsodium-dev). Built only with BD_SIGNED_PRICE (the default on a host);
 * the Cortex-M4 image has no libsodium and compiles the signed price out (README.md).
 */
#include "bessded/secoc.h"

#include <sodium.h>

/* libsodium wants sodium_init before its first use (idempotent, thread-safe). */
static int ready(void)
{
    return sodium_init() >= 0;
}

int bd_ed25519_verify(const uint8_t sig[BD_ED25519_SIG_BYTES], const uint8_t *msg, size_t len,
                      const uint8_t pk[BD_ED25519_PUBLIC_BYTES])
{
    if (!ready()) {
        return 0;
    }
    return crypto_sign_verify_detached(sig, msg, (unsigned long long)len, pk) == 0;
}

int bd_ed25519_public(const uint8_t seed[BD_ED25519_SEED_BYTES],
                      uint8_t pk[BD_ED25519_PUBLIC_BYTES])
{
    unsigned char sk[crypto_sign_SECRETKEYBYTES];
    if (!ready()) {
        return -1;
    }
    int rc = crypto_sign_seed_keypair(pk, sk, seed);
    sodium_memzero(sk, sizeof sk);
    return rc == 0 ? 0 : -1;
}
