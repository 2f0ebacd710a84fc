/*
 * canergy_aes128_init and _encrypt on mbedTLS (canergy_aes_port.h). An AES-128 key always
 * sets and a block always encrypts: CANERGY_ASSERT states it.
 */
#include "canergy/aes128.h"
#include "canergy/assert.h"

void canergy_aes128_init(struct canergy_aes128 *ctx, const uint8_t key[CANERGY_AES_BLOCK])
{
    mbedtls_aes_init(&ctx->aes);
    const int rc = mbedtls_aes_setkey_enc(&ctx->aes, key, 128U);
    CANERGY_ASSERT(rc == 0);
    (void)rc;
}

void canergy_aes128_encrypt(const struct canergy_aes128 *ctx, const uint8_t in[CANERGY_AES_BLOCK],
                            uint8_t out[CANERGY_AES_BLOCK])
{
    /* mbedTLS takes its context as non-const; encryption only reads it */
    mbedtls_aes_context *aes = (mbedtls_aes_context *)(uintptr_t)&ctx->aes;
    const int rc = mbedtls_aes_crypt_ecb(aes, MBEDTLS_AES_ENCRYPT, in, out);
    CANERGY_ASSERT(rc == 0);
    (void)rc;
}
