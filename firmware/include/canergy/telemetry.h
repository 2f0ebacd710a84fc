/*
 * What the supervisor records of a node's TELEMETRY (src/canergy/live/supervisor/telemetry.py),
 * sans-IO, one caller-owned struct per node: the level it last reported, when, its flags, when
 * anything was last heard from it, and the returns credited lately. A level above what the
 * books let the node hold (delivered + reserved - returned, plus the returns credited within
 * lost_after_us, which a level reported before them may still show) is evidence
 * (CANERGY_HEARD_BEYOND); the TELEMETRY is taken all the same. At most CANERGY_HEARD_RECENT
 * returns are kept: one more merges the oldest into the next, as Python's table does.
 * tests/test_ccore_tables.py runs both side by side.
 */
#ifndef CANERGY_TELEMETRY_H
#define CANERGY_TELEMETRY_H

#include "canergy/codec.h"
#include "canergy/session.h"

#include <stdbool.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define CANERGY_HEARD_RECENT 8U /* returns credited lately kept per node */

/* canergy_heard_telemetry's verdict (bits). */
#define CANERGY_HEARD_TAKEN 0x01U  /* recorded */
#define CANERGY_HEARD_BEYOND 0x02U /* its level is above what the books allow: evidence */

struct canergy_heard {
    uint64_t heard_at; /* has_heard */
    uint64_t level_at; /* has_level_at */
    uint64_t recent_at[CANERGY_HEARD_RECENT]; /* oldest first, recent_count of them */
    uint64_t recent_uj[CANERGY_HEARD_RECENT];
    uint32_t telemetry; /* TELEMETRY frames taken */
    uint32_t level_mj;  /* has_level */
    uint8_t flags;
    uint8_t recent_count;
    bool has_level;
    bool has_level_at;
    bool has_heard;
};

void canergy_heard_init(struct canergy_heard *h);

/* A TELEMETRY m of the node whose session is s: recorded; its verdict (bits above). */
unsigned canergy_heard_telemetry(struct canergy_heard *h, const struct canergy_session *s,
                                 const struct canergy_msg *m, uint64_t now,
                                 uint64_t lost_after_us);

/* A return of amount_uj credited to the node. */
void canergy_heard_credited(struct canergy_heard *h, uint64_t amount_uj, uint64_t now,
                            uint64_t lost_after_us);

#ifdef __cplusplus
}
#endif

#endif
