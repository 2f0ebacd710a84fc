/*
 * canergy's block cipher from mbedTLS (2.28 or 3.x): build the library with
 * -DCANERGY_AES_PORT='"canergy_aes_port.h"' -Iports/aes_mbedtls, add aes_mbedtls.c, link
 * mbedcrypto. mbedTLS 2.x keeps a pointer into its context: never copy it by value (canergy
 * does not).
 */
#ifndef CANERGY_AES_PORT_H
#define CANERGY_AES_PORT_H

#include <mbedtls/aes.h>

struct canergy_aes128 {
    mbedtls_aes_context aes;
};

#endif /* CANERGY_AES_PORT_H */
