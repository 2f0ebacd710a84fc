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

#ifdef CANERGY_AES_PORT
/* The port's block cipher (hardware AES, mbedTLS, tinycrypt) instead of the table S-box below:
 * build with -DCANERGY_AES_PORT='"its_header.h"'. That header defines struct canergy_aes128 (the
 * port's key context; the library never copies it by value and wipes it with canergy_wipe),
 * the port implements the two functions below, and src/aes128.c compiles to nothing.
 * ports/aes_mbedtls is one; `make aes-port-test` runs every C known answer on it. */
#include CANERGY_AES_PORT
#else
/* The 11 round keys, 176 bytes: key material (wipe it with canergy_wipe when done). */
struct canergy_aes128 {
    uint8_t rk[11U * CANERGY_AES_BLOCK];
};
#endif

void canergy_aes128_init(struct canergy_aes128 *ctx, const uint8_t key[CANERGY_AES_BLOCK]);

/* out = AES-128(key, in); in and out may be the same buffer. */
void canergy_aes128_encrypt(const struct canergy_aes128 *ctx, const uint8_t in[CANERGY_AES_BLOCK],
                            uint8_t out[CANERGY_AES_BLOCK]);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_AES128_H */
