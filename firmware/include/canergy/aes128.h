/*
 * AES-128 block encryption (FIPS-197), the block cipher under canergy/cmac.h. Encryption only:
 * CMAC and the KDF never decrypt. The key is expanded once into a caller-owned context.
 *
 * Side channels: the S-box is a 256-byte table indexed by secret bytes. On a Cortex-M4 without
 * a data cache (the target) a lookup takes the same time whatever the index; on a desktop CPU
 * with caches the access pattern leaks through cache timing, so do not use this code there
 * against an attacker who shares the machine. Everything else is free of secret-dependent
 * branches and indices.
 */
#ifndef CANERGY_AES128_H
#define CANERGY_AES128_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define CANERGY_AES_BLOCK 16U

/* The 11 round keys, 176 bytes: key material (wipe it with canergy_wipe when done). */
struct canergy_aes128 {
    uint8_t rk[11U * CANERGY_AES_BLOCK];
};

void canergy_aes128_init(struct canergy_aes128 *ctx, const uint8_t key[CANERGY_AES_BLOCK]);

/* out = AES-128(key, in); in and out may be the same buffer. */
void canergy_aes128_encrypt(const struct canergy_aes128 *ctx, const uint8_t in[CANERGY_AES_BLOCK],
                            uint8_t out[CANERGY_AES_BLOCK]);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_AES128_H */
