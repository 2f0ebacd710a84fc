/*
 * canergy-node's key file for --auth and canergy-gateway's for --upstream-auth and --auth
 * (keyfile.c): a key file of `canergy keys`, checked as src/canergy/auth/keys.py checks it.
 */
#ifndef CANERGY_PORT_LINUX_KEYFILE_H
#define CANERGY_PORT_LINUX_KEYFILE_H

#include "canergy/cmac.h"

#include <stdint.h>

/* key = the key of the node key file at path, which must be for_node's; any refusal exits 2
 * with one line that names flag and path and holds no byte of the key. The caller wipes key
 * after use. */
void port_load_key(const char *flag, const char *path, int for_node,
                   uint8_t key[CANERGY_KDF_KEY_SIZE]);

/* The same for a master key (kind=master: canergy-gateway's --auth), its epoch in *epoch. */
void port_load_master_key(const char *flag, const char *path, uint8_t key[CANERGY_KDF_KEY_SIZE],
                          uint32_t *epoch);

#endif /* CANERGY_PORT_LINUX_KEYFILE_H */
