/*
 * Library-internal: little-endian fields of NV records, up to 32 bits at a time (a u64 is two
 * of them: 64-bit shifts cost flash on small cores).
 */
#ifndef CANERGY_LE_H
#define CANERGY_LE_H

#include <stddef.h>
#include <stdint.h>

static inline void le_put(uint8_t *p, uint32_t v, size_t n)
{
    for (size_t i = 0U; i < n; i++) {
        p[i] = (uint8_t)(v >> (8U * i));
    }
}

static inline uint32_t le_get(const uint8_t *p, size_t n)
{
    uint32_t v = 0U;
    for (size_t i = 0U; i < n; i++) {
        v |= (uint32_t)p[i] << (8U * i);
    }
    return v;
}

static inline void le_put64(uint8_t *p, uint64_t v)
{
    le_put(p, (uint32_t)v, 4U);
    le_put(&p[4], (uint32_t)(v >> 32), 4U);
}

static inline uint64_t le_get64(const uint8_t *p)
{
    return (uint64_t)le_get(&p[4], 4U) << 32 | le_get(p, 4U);
}

#endif /* CANERGY_LE_H */
