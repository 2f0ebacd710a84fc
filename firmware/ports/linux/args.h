/*
 * canergy-node's command line (args.c; canergy-gateway's is declared in gateway_port.h): the
 * options and their units, and the one-line error (exit 2) that every refusal of a bad
 * argument, path or setting ends with.
 */
#ifndef CANERGY_PORT_LINUX_ARGS_H
#define CANERGY_PORT_LINUX_ARGS_H

#include "port.h"

#include <stdint.h>

/* "canergy-node: error: " and the message on stderr, then exit 2. */
void port_usage_error(const char *fmt, ...);

/* *out = a * b: 0 (and *out untouched) when it would not fit in 64 bits. */
int port_mul_fits(uint64_t a, uint64_t b, uint64_t *out);

/* The options of argv, with their defaults; -h prints the usage and exits 0, a bad argument
 * exits 2. Paths are not checked here (storage.h, keyfile.h). */
void port_parse_args(int argc, char **argv, struct port_options *o);
/* One value of a flag (exit 2 with one line when it is not one): an energy in uJ ("0.5J",
 * "250mJ", plain joules), a duration in us above 0 and at most max, an integer (0x.. too). */
uint64_t port_parse_energy(const char *flag, const char *text);
uint64_t port_parse_duration(const char *flag, const char *text, uint64_t max);
uint64_t port_parse_int(const char *flag, const char *text, uint64_t low, uint64_t high);
/* --rules: "hardened" (CANERGY_RULES_HARDENED) or "witnessed" (CANERGY_RULES_WITNESSED). */
uint8_t port_parse_rules(const char *flag, const char *text);

#endif /* CANERGY_PORT_LINUX_ARGS_H */
