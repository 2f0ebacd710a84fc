/*
 * Host nanoseconds per received frame of the C client: decode + rules + the reply (and the NV
 * image when the books change), the work a node does per frame. Reads "ID HEX" lines (what
 * bench/compare.py writes), feeds them to one client REPEAT times and prints the median of the
 * repeats in ns per frame. The port's I/O (fsync, send) is not included, as in the Python run.
 */
#define _POSIX_C_SOURCE 200809L
#include "canergy/client.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define MAX_FRAMES 100000U
#define REPEAT 9U

struct raw {
    uint32_t id;
    uint8_t len;
    uint8_t data[8];
};

static struct raw frames[MAX_FRAMES];

static uint64_t ns(void)
{
    struct timespec ts;
    (void)clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ULL + (uint64_t)ts.tv_nsec;
}

static int cmp(const void *a, const void *b)
{
    const double x = *(const double *)a;
    const double y = *(const double *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv)
{
    FILE *f = fopen(argc > 1 ? argv[1] : "frames.txt", "r");
    if (f == NULL) {
        perror("bench_frames");
        return 2;
    }
    unsigned n = 0U;
    char hex[17];
    unsigned long id;
    while (n < MAX_FRAMES && fscanf(f, "%lx %16s", &id, hex) == 2) {
        frames[n].id = (uint32_t)id;
        frames[n].len = (uint8_t)(strlen(hex) / 2U);
        for (unsigned i = 0U; i < frames[n].len; i++) {
            unsigned byte;
            (void)sscanf(&hex[2U * i], "%2x", &byte);
            frames[n].data[i] = (uint8_t)byte;
        }
        n++;
    }
    (void)fclose(f);
    double per_frame[REPEAT];
    unsigned long long sink = 0U;
    uint32_t usable = 0U;
    for (unsigned r = 0U; r < REPEAT; r++) {
        /* a node with (empty) books, as Python's ClientState(node) */
        uint8_t rec[CANERGY_NV_RECORD_SIZE];
        uint8_t image[CANERGY_NV_SLOT_SIZE];
        const struct canergy_record zero = {0U, 0U, 0U, 0U, 0U, 0U, 0U, 0U};
        canergy_record_pack(&zero, rec);
        canergy_nv_slot_encode(1U, rec, sizeof rec, image);
        static struct canergy_client c;
        struct canergy_out out;
        const struct canergy_client_config cfg = {CANERGY_DEFAULT_ID_BASE, 200000U, 200000U, 5U, CANERGY_RULES_HARDENED, 0U};
        (void)canergy_client_start(&c, &cfg, image, sizeof image, 1U, 0U, &out);
        const uint64_t t0 = ns();
        for (unsigned i = 0U; i < n; i++) {
            const struct canergy_rx_frame rx = {frames[i].id, frames[i].data, frames[i].len, true,
                                                false};
            sink += (unsigned long long)canergy_client_on_frame(&c, &rx, 1000U + i, &out);
            sink += out.frame_count;
        }
        per_frame[r] = (double)(ns() - t0) / (double)n;
        usable = canergy_client_usable(&c);
    }
    qsort(per_frame, REPEAT, sizeof per_frame[0], cmp);
    printf("%.1f %u %lu %llu\n", per_frame[REPEAT / 2U], n, (unsigned long)usable, sink);
    return 0;
}
