/*
 * AES-CMAC (RFC 4493, NIST SP 800-38B) for authenticated frames (AUTOSAR SecOC style: a MAC
 * over Data ID, payload and freshness, truncated to a few bytes on the bus), a constant-time
 * comparison for truncated MACs, key wiping, and a key derivation function for per-node keys.
 *
 * KDF: NIST SP 800-108 in counter mode with AES-CMAC as the PRF, one 128-bit block, so the PRF
 * runs once, keyed with the master key, over these bytes:
 *
 *     00 00 00 01 || label || 00 || context || 00 00 00 80
 *     counter i=1    label_len   context_len    L = 128 bits
 *     (32-bit BE)    bytes       bytes          (32-bit BE)
 *
 * This is what Python's cryptography produces with
 *     KBKDFCMAC(algorithms.AES, Mode.CounterMode, length=16, rlen=4, llen=4,
 *               location=CounterLocation.BeforeFixed, label=label, context=context, fixed=None)
 * (tests/test_c_cmac.py checks that byte for byte).
 *
 * Side channels: see canergy/aes128.h (table S-box: fine on a cacheless Cortex-M4, not on a
 * desktop shared with an attacker). No heap; the contexts are caller-owned and hold key
 * material until canergy_cmac_wipe.
 */
#ifndef CANERGY_CMAC_H
#define CANERGY_CMAC_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "canergy/aes128.h"

#ifdef __cplusplus
extern "C" {
#endif

#define CANERGY_CMAC_SIZE 16U
#define CANERGY_KDF_KEY_SIZE 16U

/* A key: the expanded AES key and the subkeys K1, K2 (208 bytes). Read-only once initialised,
 * so any number of MAC computations may share it. */
struct canergy_cmac {
    struct canergy_aes128 aes;
    uint8_t k1[CANERGY_AES_BLOCK];
    uint8_t k2[CANERGY_AES_BLOCK];
};

/* One MAC computation in progress (17 bytes): the chaining value with the current block XORed
 * in, and how many bytes of that block have arrived (0..16; 0 only before the first byte). */
struct canergy_cmac_stream {
    uint8_t x[CANERGY_AES_BLOCK];
    uint8_t n;
};

void canergy_cmac_init(struct canergy_cmac *ctx, const uint8_t key[CANERGY_AES_BLOCK]);

/* One shot: mac = AES-CMAC(key, msg[0..len)). msg may be NULL only when len is 0. A truncated
 * MAC is the first bytes of mac. */
void canergy_cmac(const struct canergy_cmac *ctx, const uint8_t *msg, size_t len,
                  uint8_t mac[CANERGY_CMAC_SIZE]);

/* Incremental: begin, update with the message in pieces of any size (also 0), final. The MAC
 * is the one-shot MAC of the concatenation; final wipes the stream. */
void canergy_cmac_begin(struct canergy_cmac_stream *s);
void canergy_cmac_update(const struct canergy_cmac *ctx, struct canergy_cmac_stream *s,
                         const uint8_t *msg, size_t len);
void canergy_cmac_final(const struct canergy_cmac *ctx, struct canergy_cmac_stream *s,
                        uint8_t mac[CANERGY_CMAC_SIZE]);

/* True when a[0..n) equals b[0..n), in a time that depends on n only (compare a received,
 * truncated MAC with the first n bytes of the computed one). n = 0 is never equal: a MAC of no
 * bytes authenticates nothing. */
bool canergy_mac_equal(const uint8_t *a, const uint8_t *b, size_t n);

/* Zero n bytes through a volatile pointer, so the compiler cannot drop the stores. */
void canergy_wipe(void *p, size_t n);

/* Zero the whole key context. */
void canergy_cmac_wipe(struct canergy_cmac *ctx);

/* out = PRF(master, layout above): a per-node key. label and context may be NULL only when
 * their length is 0. Every intermediate holding key material is wiped before returning. */
void canergy_kdf_cmac_ctr(const uint8_t master[CANERGY_KDF_KEY_SIZE], const uint8_t *label,
                          size_t label_len, const uint8_t *context, size_t context_len,
                          uint8_t out[CANERGY_KDF_KEY_SIZE]);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_CMAC_H */
