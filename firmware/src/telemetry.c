/*
 * The TELEMETRY table (canergy/telemetry.h), as canergy.live.supervisor.telemetry.
 */
#include "canergy/telemetry.h"

#include <string.h>

#define LEVEL_MAX_MJ 0xFFFFFFUL /* a saturated level: no judgement */

void canergy_heard_init(struct canergy_heard *h)
{
    memset(h, 0, sizeof *h);
}

/* Drop the returns credited more than lost_after_us ago, oldest first. */
static void prune(struct canergy_heard *h, uint64_t now, uint64_t lost_after_us)
{
    unsigned gone = 0U;
    while (gone < h->recent_count && now > h->recent_at[gone] &&
           now - h->recent_at[gone] > lost_after_us) {
        gone++;
    }
    if (gone != 0U) {
        const size_t left = (size_t)(h->recent_count - gone);
        (void)memmove(&h->recent_at[0], &h->recent_at[gone], left * sizeof h->recent_at[0]);
        (void)memmove(&h->recent_uj[0], &h->recent_uj[gone], left * sizeof h->recent_uj[0]);
        h->recent_count = (uint8_t)left;
    }
}

unsigned canergy_heard_telemetry(struct canergy_heard *h, const struct canergy_session *s,
                                 const struct canergy_msg *m, uint64_t now,
                                 uint64_t lost_after_us)
{
    prune(h, now, lost_after_us);
    uint64_t lagging = 0U;
    for (unsigned i = 0U; i < h->recent_count; i++) {
        lagging += h->recent_uj[i];
    }
    const int64_t holdable =
        (int64_t)(s->delivered_uj + s->reserved_uj) - (int64_t)s->returned_uj;
    const int64_t level = (int64_t)m->level_mj * (int64_t)CANERGY_QUANTUM_UJ;
    unsigned verdict = CANERGY_HEARD_TAKEN;
    if (m->level_mj < LEVEL_MAX_MJ && level > holdable + (int64_t)lagging) {
        verdict |= CANERGY_HEARD_BEYOND;
    }
    h->level_mj = m->level_mj;
    h->has_level = true;
    h->level_at = now;
    h->has_level_at = true;
    h->flags = m->flags;
    h->heard_at = now;
    h->has_heard = true;
    h->telemetry++;
    return verdict;
}

void canergy_heard_credited(struct canergy_heard *h, uint64_t amount_uj, uint64_t now,
                            uint64_t lost_after_us)
{
    prune(h, now, lost_after_us);
    if (h->recent_count == CANERGY_HEARD_RECENT) { /* the oldest lags as long as the next */
        h->recent_uj[1] += h->recent_uj[0];
        const size_t left = CANERGY_HEARD_RECENT - 1U;
        (void)memmove(&h->recent_at[0], &h->recent_at[1], left * sizeof h->recent_at[0]);
        (void)memmove(&h->recent_uj[0], &h->recent_uj[1], left * sizeof h->recent_uj[0]);
        h->recent_count = (uint8_t)left;
    }
    h->recent_at[h->recent_count] = now;
    h->recent_uj[h->recent_count] = amount_uj;
    h->recent_count++;
}
