/*
 * What both Linux programs (canergy-node, canergy-gateway) take from the system besides the
 * CAN socket and their files: the monotonic clock, and entropy for a JOIN nonce.
 */
#ifndef CANERGY_PORT_LINUX_SYSTEM_H
#define CANERGY_PORT_LINUX_SYSTEM_H

#include <stdint.h>

/* CLOCK_MONOTONIC in microseconds; exits 1 when the clock cannot be read. */
uint64_t port_now_us(void);

/* 16 random bits from getrandom() (/dev/urandom when that fails); exits 2 without entropy. */
uint16_t port_random16(void);

#endif /* CANERGY_PORT_LINUX_SYSTEM_H */
