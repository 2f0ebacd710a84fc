/*
 * The clock and the entropy of the Linux programs (system.h).
 */
#define _GNU_SOURCE 1

#include "system.h"

#include "port.h"

#include <stdio.h>
#include <stdlib.h>
#include <sys/random.h>
#include <time.h>

uint64_t port_now_us(void)
{
    struct timespec ts;
    if (clock_gettime(CLOCK_MONOTONIC, &ts) != 0) {
        (void)fprintf(stderr, "%s: error: clock_gettime failed\n", PROG);
        exit(EXIT_NV);
    }
    return (uint64_t)ts.tv_sec * US_PER_S + (uint64_t)ts.tv_nsec / 1000U;
}

uint16_t port_random16(void)
{
    uint16_t v = 0U;
    if (getrandom(&v, sizeof v, 0) == (ssize_t)sizeof v) {
        return v;
    }
    FILE *f = fopen("/dev/urandom", "rb");
    if (f == NULL || fread(&v, sizeof v, 1U, f) != 1U) {
        (void)fprintf(stderr, "%s: error: no entropy for the JOIN nonce\n", PROG);
        exit(EXIT_USAGE);
    }
    (void)fclose(f);
    return v;
}
