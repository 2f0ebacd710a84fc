/*
 * JOINs held until the node's TELEMETRY (canergy/joins.h), as canergy.live.supervisor.joins.
 */
#include "canergy/joins.h"

#include "canergy/codec.h"

#include <string.h>

void canergy_joins_join(struct canergy_joins *j, uint16_t nonce)
{
    unsigned at = 0U;
    while (at < j->held_count && j->held[at] != nonce) {
        at++;
    }
    if (at < j->held_count) { /* a copy: moved to the end */
        const size_t after = (size_t)(j->held_count - at - 1U);
        (void)memmove(&j->held[at], &j->held[at + 1U], after * sizeof j->held[0]);
        j->held_count--;
    } else { /* another start (or a replay): only a TELEMETRY after it confirms it */
        j->has_admitting = false;
    }
    if (j->held_count == CANERGY_JOINS_HELD) { /* the oldest is pushed out */
        (void)memmove(&j->held[0], &j->held[1], (CANERGY_JOINS_HELD - 1U) * sizeof j->held[0]);
        j->held_count--;
    }
    j->held[j->held_count++] = nonce;
}

bool canergy_joins_due(struct canergy_joins *j, uint64_t now, uint16_t *nonce)
{
    if (!j->has_admitting || now < j->admit_at) {
        return false;
    }
    *nonce = j->admitting;
    j->held_count = 0U;
    j->has_admitting = false;
    j->admitted = *nonce;
    j->has_admitted = true;
    return true;
}

unsigned canergy_joins_telemetry(struct canergy_joins *j, uint8_t flags, uint64_t now,
                                 uint64_t hold_us, uint16_t *nonce)
{
    if ((flags & CANERGY_TELEMETRY_JOINING) != 0U) {
        if (j->held_count == 0U) {
            return 0U;
        }
        unsigned found = 0U;
        if (!j->has_admitting) {
            j->admitting = j->held[j->held_count - 1U];
            j->admit_at = now + hold_us;
            j->has_admitting = true;
            found |= CANERGY_JOINS_DUE;
        }
        return canergy_joins_due(j, now, nonce) ? found | CANERGY_JOINS_ADMIT : found;
    }
    const bool any = j->held_count != 0U;
    for (unsigned k = 0U; k < j->held_count; k++) {
        if (j->has_admitted && j->held[k] == j->admitted) {
            j->resent++;
        }
    }
    j->held_count = 0U;
    j->has_admitting = false;
    j->has_admitted = false;
    return any ? CANERGY_JOINS_REFUSED : 0U;
}

static void join_of(uint8_t node, uint16_t nonce, struct canergy_msg *join)
{
    memset(join, 0, sizeof *join);
    join->type = CANERGY_JOIN;
    join->node = node;
    join->nonce = nonce;
}

unsigned canergy_joins_route(struct canergy_joins *j, const struct canergy_msg *m, uint64_t now,
                             uint64_t hold_us, struct canergy_msg *to_rules,
                             struct canergy_joins_refuted *refuted)
{
    refuted->count = 0U;
    if (m->type == CANERGY_JOIN) {
        canergy_joins_join(j, m->nonce);
        return 0U;
    }
    if (m->type != CANERGY_TELEMETRY) {
        *to_rules = *m;
        return CANERGY_JOINS_PASS;
    }
    for (unsigned k = 0U; k < j->held_count; k++) { /* what a TELEMETRY with books refuses */
        if (!(j->has_admitted && j->held[k] == j->admitted)) {
            refuted->nonces[refuted->count++] = j->held[k];
        }
    }
    uint16_t nonce = 0U;
    const unsigned found = canergy_joins_telemetry(j, m->flags, now, hold_us, &nonce);
    if ((found & CANERGY_JOINS_ADMIT) != 0U) {
        join_of(m->node, nonce, to_rules);
    }
    if ((found & CANERGY_JOINS_REFUSED) == 0U) {
        refuted->count = 0U;
    }
    return found;
}

bool canergy_joins_due_join(struct canergy_joins *j, uint8_t node, uint64_t now,
                            struct canergy_msg *join)
{
    uint16_t nonce = 0U;
    if (!canergy_joins_due(j, now, &nonce)) {
        return false;
    }
    join_of(node, nonce, join);
    return true;
}
