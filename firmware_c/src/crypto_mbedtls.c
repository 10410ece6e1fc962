/*
 * The crypto seam on Linux: CMAC-AES-128 from mbedTLS (libmbedtls-dev). An MCU port
 * replaces this file with its AES engine's CMAC (secoc.h).
 */
#include "bessded/secoc.h"

#include <mbedtls/cipher.h>
#include <mbedtls/cmac.h>

int bd_cmac_aes128(const uint8_t key[BD_KEY_BYTES], const uint8_t *msg, size_t len,
                   uint8_t tag[16])
{
    const mbedtls_cipher_info_t *aes = mbedtls_cipher_info_from_type(MBEDTLS_CIPHER_AES_128_ECB);
    if (aes == NULL) {
        return -1;
    }
    return mbedtls_cipher_cmac(aes, key, 8u * BD_KEY_BYTES, msg, len, tag) == 0 ? 0 : -1;
}
