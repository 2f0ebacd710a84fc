/*
 * Library-internal: wire counters against held ones. Python widens every wire counter to an
 * unbounded integer; the C code keeps counters modulo 2^32 and looks only at the signed
 * distance of a wire value from its reference, which is what Python's unwrap() adds to the
 * reference and depends only on the reference modulo 2^16 (2^24), which 2^32 preserves.
 */
#ifndef CANERGY_SERIAL_H
#define CANERGY_SERIAL_H

#include <stdbool.h>
#include <stdint.h>

#include "canergy/codec.h"

/* Signed distance of a 16-bit wire value from the reference's position: Python's
 * unwrap(wire, ref, 16) - ref, in [-32768, 32767]. */
static inline int32_t serial16(uint32_t wire, uint32_t ref)
{
    const uint32_t d = (wire - ref) & 0xFFFFUL;
    return d >= 0x8000UL ? (int32_t)d - 0x10000L : (int32_t)d;
}

/* The same for the 24-bit delivered count: unwrap(wire, ref, 24) - ref. */
static inline int32_t serial24(uint32_t wire, uint32_t ref)
{
    const uint32_t d = (wire - ref) & 0xFFFFFFUL;
    return d >= 0x800000UL ? (int32_t)d - 0x1000000L : (int32_t)d;
}

/* a < b as 32-bit serial numbers (exact while they are less than 2^31 apart). */
static inline bool serial_before(uint32_t a, uint32_t b)
{
    return (uint32_t)(a - b) >= 0x80000000UL;
}

/* now plus a delay: now < 2^63 (client.h), so no overflow and never CANERGY_NEVER. */
static inline uint64_t serial_after(uint64_t now, uint32_t delay)
{
    return now + delay;
}

/* A counter moved by a start (a void, a SYNC's lift), held below CANERGY_COUNTER_BOUND: above
 * CANERGY_COUNTER_END numbers only void, and no record leaves what the loaders take
 * (canergy.core.common.capped). The caller includes canergy/codec.h. */
static inline uint32_t serial_capped(uint32_t counter)
{
    return counter < CANERGY_COUNTER_BOUND - 1UL ? counter : CANERGY_COUNTER_BOUND - 1UL;
}

#endif /* CANERGY_SERIAL_H */
