/*
 * A crypto seam for the tests: mbedTLS's CMAC (src/crypto_mbedtls.c, linked under the
 * name bd_cmac_aes128_mbedtls) that fails on demand, as a hardware AES engine or an HSM
 * can (a locked key slot, a busy engine). libbessded_faulty.so links it in place of
 * src/crypto_mbedtls.c so that the runtime's handling of a failed primitive is tested
 * (BD_ERR_CRYPTO) on the same code that ships.
 */
#include "bessded/secoc.h"

int bd_cmac_aes128_mbedtls(const uint8_t key[BD_KEY_BYTES], const uint8_t *msg, size_t len,
                           uint8_t tag[16]);
void bd_test_cmac_fail_after(int32_t calls);
uint32_t bd_test_cmac_calls(void);

static int32_t fail_after = -1;   /* calls that still succeed; -1: never fail */
static uint32_t calls_made = 0u;

/* From now, `calls` more calls succeed and every later one fails; -1: none fails. */
void bd_test_cmac_fail_after(int32_t calls)
{
    fail_after = calls;
}

/* The calls made since the library was loaded. */
uint32_t bd_test_cmac_calls(void)
{
    return calls_made;
}

int bd_cmac_aes128(const uint8_t key[BD_KEY_BYTES], const uint8_t *msg, size_t len,
                   uint8_t tag[16])
{
    calls_made++;
    if (fail_after == 0) {
        return -1;
    }
    if (fail_after > 0) {
        fail_after--;
    }
    return bd_cmac_aes128_mbedtls(key, msg, len, tag);
}
