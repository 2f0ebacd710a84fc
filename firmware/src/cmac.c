/*
 * AES-CMAC (RFC 4493), the constant-time MAC comparison, wiping and the SP 800-108 counter-mode
 * KDF (see include/canergy/cmac.h for the KDF's byte layout).
 *
 * The stream XORs message bytes straight into the chaining value and encrypts a full block only
 * when the next byte arrives, so the last block is still open at final: complete (XOR K1) or
 * padded with 0x80 0x00... (XOR K2), as RFC 4493 section 2.4 says. No message buffer.
 */
#include "canergy/cmac.h"

#include <string.h>

/* Doubling in GF(2^128) (RFC 4493 section 2.3): shift left one bit, fold the carry with 0x87. */
static void dbl(const uint8_t in[CANERGY_AES_BLOCK], uint8_t out[CANERGY_AES_BLOCK])
{
    const uint8_t fold = (uint8_t)(0x87U & (0U - (unsigned)(in[0] >> 7)));
    for (size_t i = 0U; i + 1U < CANERGY_AES_BLOCK; i++) {
        out[i] = (uint8_t)((unsigned)(in[i] << 1) | (unsigned)(in[i + 1U] >> 7));
    }
    out[CANERGY_AES_BLOCK - 1U] = (uint8_t)((unsigned)(in[CANERGY_AES_BLOCK - 1U] << 1) ^ fold);
}

void canergy_cmac_init(struct canergy_cmac *ctx, const uint8_t key[CANERGY_AES_BLOCK])
{
    uint8_t l[CANERGY_AES_BLOCK] = {0};
    canergy_aes128_init(&ctx->aes, key);
    canergy_aes128_encrypt(&ctx->aes, l, l); /* L = AES(K, 0^128) */
    dbl(l, ctx->k1);
    dbl(ctx->k1, ctx->k2);
    canergy_wipe(l, sizeof l);
}

void canergy_cmac_begin(struct canergy_cmac_stream *s)
{
    memset(s, 0, sizeof *s);
}

void canergy_cmac_update(const struct canergy_cmac *ctx, struct canergy_cmac_stream *s,
                         const uint8_t *msg, size_t len)
{
    for (size_t i = 0U; i < len; i++) {
        if (s->n == CANERGY_AES_BLOCK) { /* more follows: this block was not the last */
            canergy_aes128_encrypt(&ctx->aes, s->x, s->x);
            s->n = 0U;
        }
        s->x[s->n] ^= msg[i];
        s->n++;
    }
}

void canergy_cmac_final(const struct canergy_cmac *ctx, struct canergy_cmac_stream *s,
                        uint8_t mac[CANERGY_CMAC_SIZE])
{
    const uint8_t *k = ctx->k1;
    if (s->n < CANERGY_AES_BLOCK) { /* incomplete (or empty) last block: pad, use K2 */
        s->x[s->n] ^= 0x80U;
        k = ctx->k2;
    }
    for (size_t i = 0U; i < CANERGY_AES_BLOCK; i++) {
        s->x[i] ^= k[i];
    }
    canergy_aes128_encrypt(&ctx->aes, s->x, mac);
    canergy_wipe(s, sizeof *s);
}

void canergy_cmac(const struct canergy_cmac *ctx, const uint8_t *msg, size_t len,
                  uint8_t mac[CANERGY_CMAC_SIZE])
{
    struct canergy_cmac_stream s;
    canergy_cmac_begin(&s);
    canergy_cmac_update(ctx, &s, msg, len);
    canergy_cmac_final(ctx, &s, mac);
}

bool canergy_mac_equal(const uint8_t *a, const uint8_t *b, size_t n)
{
    volatile uint8_t diff = 0U; /* volatile: no early exit once a difference is seen */
    for (size_t i = 0U; i < n; i++) {
        diff = (uint8_t)(diff | (a[i] ^ b[i]));
    }
    return n != 0U && diff == 0U;
}

void canergy_wipe(void *p, size_t n)
{
    volatile uint8_t *v = (volatile uint8_t *)p;
    for (size_t i = 0U; i < n; i++) {
        v[i] = 0U;
    }
}

void canergy_cmac_wipe(struct canergy_cmac *ctx)
{
    canergy_wipe(ctx, sizeof *ctx);
}

void canergy_kdf_cmac_ctr(const uint8_t master[CANERGY_KDF_KEY_SIZE], const uint8_t *label,
                          size_t label_len, const uint8_t *context, size_t context_len,
                          uint8_t out[CANERGY_KDF_KEY_SIZE])
{
    static const uint8_t counter[4] = {0x00U, 0x00U, 0x00U, 0x01U};   /* i = 1, 32-bit BE */
    static const uint8_t separator[1] = {0x00U};
    static const uint8_t bits[4] = {0x00U, 0x00U, 0x00U, 0x80U};      /* L = 128, 32-bit BE */
    struct canergy_cmac ctx;
    struct canergy_cmac_stream s;
    canergy_cmac_init(&ctx, master);
    canergy_cmac_begin(&s);
    canergy_cmac_update(&ctx, &s, counter, sizeof counter);
    canergy_cmac_update(&ctx, &s, label, label_len);
    canergy_cmac_update(&ctx, &s, separator, sizeof separator);
    canergy_cmac_update(&ctx, &s, context, context_len);
    canergy_cmac_update(&ctx, &s, bits, sizeof bits);
    canergy_cmac_final(&ctx, &s, out);
    canergy_cmac_wipe(&ctx);
}
