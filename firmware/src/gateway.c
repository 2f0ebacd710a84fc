/*
 * The gateway rules (canergy/gateway.h), as src/canergy/core/gateway.py's forward,
 * withdraw_for_return and (witnessed rules upstream) Gateway._drawn.
 */
#include "canergy/gateway.h"

#include "client_internal.h"
#include "rules.h"

#define GW_MJ 1000U

uint32_t canergy_gateway_forward(struct canergy_gateway *gw, struct canergy_out *out)
{
    const uint32_t amount = gw->up.rec.usable_uj;
    if (amount == 0U || gw->up.phase == CANERGY_JOINING ||
        rules_witnessed(gw->up.rules)) {
        return 0U; /* witnessed upstream: only through an acknowledged draw */
    }
    /* the client spends all of it (its record re-packed into out), the supervisor takes it in */
    const int spent = canergy_internal_spend(&gw->up, amount, out);
    CANERGY_ASSERT(spent == CANERGY_OK);
    if (spent != CANERGY_OK) {
        return 0U;
    }
    const int injected = canergy_supervisor_inject(&gw->down, amount);
    CANERGY_ASSERT(injected == CANERGY_OK);
    (void)injected;
    return amount;
}

bool canergy_gateway_upstream_waiting(const struct canergy_gateway *gw)
{
    return gw->up.phase == CANERGY_RESUMING || gw->up.phase == CANERGY_SYNCING;
}

#ifdef CANERGY_WITNESSED
/* What the client as it was before a step (phase, debit number, spent) tells about the step. */
struct up_before {
    uint64_t spent_uj;
    uint32_t return_seq;
    uint8_t phase;
};

static struct up_before up_before(const struct canergy_gateway *gw)
{
    const struct up_before b = {gw->up.rec.spent_uj, gw->up.rec.return_seq, gw->up.phase};
    return b;
}

/* Witnessed upstream, after a client step: a draw acknowledged goes below (spent grew: injected
 * by as much); a start found behind drops Us below, booked as withdrawn and out of spent (that Us
 * may hold what was returned upstream after an older copy was taken); then what the client holds
 * usable is drawn, one debit at a time, at most one frame's amount. */
static void drawn(struct canergy_gateway *gw, const struct up_before *b, uint64_t now,
                  struct canergy_out *out)
{
    struct canergy_client *up = &gw->up;
    if (up->rec.spent_uj > b->spent_uj) {
        const int injected = canergy_supervisor_inject(&gw->down, up->rec.spent_uj - b->spent_uj);
        CANERGY_ASSERT(injected == CANERGY_OK);
        (void)injected;
    }
    const bool starting = b->phase == CANERGY_RESUMING || b->phase == CANERGY_SYNCING;
    if (starting && up->phase == CANERGY_IDLE && up->rec.return_seq > b->return_seq + 1U) {
        out->events |= CANERGY_GW_EV_FOUND_BEHIND;
        const uint64_t us = gw->down.usable_uj > 0 ? (uint64_t)gw->down.usable_uj : 0U;
        const uint64_t dropped = us < up->rec.spent_uj ? us : up->rec.spent_uj;
        if (dropped != 0U) {
            const int withdrawn = canergy_supervisor_withdraw(&gw->down, dropped);
            CANERGY_ASSERT(withdrawn == CANERGY_OK);
            (void)withdrawn;
            up->rec.spent_uj -= dropped;
            canergy_internal_repack(up, out);
        }
    }
    uint32_t chunk = up->rec.usable_uj / GW_MJ;
    chunk = (chunk > (uint32_t)CANERGY_AMOUNT_MAX_MJ ? (uint32_t)CANERGY_AMOUNT_MAX_MJ : chunk) *
            GW_MJ;
    if (chunk != 0U && canergy_client_can_draw(up)) {
        const int drew = canergy_internal_draw(up, chunk, now, out);
        CANERGY_ASSERT(drew == CANERGY_OK);
        (void)drew;
    }
}
#endif

int canergy_gateway_on_up_frame(struct canergy_gateway *gw, const struct canergy_rx_frame *frame,
                                uint64_t now, struct canergy_out *out)
{
#ifdef CANERGY_WITNESSED
    if (rules_witnessed(gw->up.rules)) {
        const struct up_before b = up_before(gw);
        const int status = canergy_client_on_frame(&gw->up, frame, now, out);
        drawn(gw, &b, now, out);
        return status;
    }
#endif
    const int status = canergy_client_on_frame(&gw->up, frame, now, out);
    (void)canergy_gateway_forward(gw, out);
    return status;
}

void canergy_gateway_on_up_timer(struct canergy_gateway *gw, uint64_t now,
                                 struct canergy_out *out)
{
#ifdef CANERGY_WITNESSED
    if (rules_witnessed(gw->up.rules)) {
        const struct up_before b = up_before(gw);
        canergy_client_on_timer(&gw->up, now, out);
        drawn(gw, &b, now, out);
        return;
    }
#endif
    canergy_client_on_timer(&gw->up, now, out);
    (void)canergy_gateway_forward(gw, out);
}

int canergy_gateway_begin(struct canergy_gateway *gw, uint8_t node, uint32_t amount_uj,
                          uint64_t now, struct canergy_supervisor_out *out)
{
    if (canergy_gateway_upstream_waiting(gw)) {
        out->frame_count = 0U;
        out->event_count = 0U;
        out->persist = 0U;
        return CANERGY_ERR_UNCONFIRMED;
    }
    return canergy_supervisor_begin(&gw->down, node, amount_uj, now, out);
}

int canergy_gateway_give_back(struct canergy_gateway *gw, uint32_t uj, uint64_t now,
                              struct canergy_out *out)
{
    canergy_internal_out_clear(out);
    if (!canergy_client_can_give_back(&gw->up)) {
        return CANERGY_ERR_PHASE;
    }
    /* witnessed below: while a start waits for a node's books, Us may be an older copy's,
     * holding what nodes were granted since (core/gateway.py, Gateway.give_back) */
    if (canergy_supervisor_unconfirmed(&gw->down, NULL) != 0U) {
        return CANERGY_ERR_PHASE;
    }
    /* Us below holds only what came from above (link gap 0: spent = injected - withdrawn, and
     * nodes below return only what they were given): never more than spent */
    CANERGY_ASSERT(gw->down.usable_uj < 0 || (uint64_t)gw->down.usable_uj <= gw->up.rec.spent_uj);
    if (uj == 0U || (int64_t)uj > gw->down.usable_uj || (uint64_t)uj > gw->up.rec.spent_uj ||
        gw->up.rec.usable_uj > CANERGY_USABLE_MAX_UJ - uj) {
        return CANERGY_ERR_AMOUNT;
    }
    /* withdraw_for_return on copies: nothing moves unless the client takes the RETURN */
    struct canergy_client up = gw->up;
    up.rec.usable_uj += uj;
    up.rec.spent_uj -= uj;
    const int rc = canergy_internal_debit(&up, uj, now, 0U, out);
    if (rc != CANERGY_OK) {
        canergy_internal_out_clear(out);
        return rc;
    }
    gw->up = up;
#ifdef CANERGY_BREAK_GIVE_BACK_KEEPS /* the broken build for tests/test_c_gateway.py */
    return CANERGY_OK; /* returned upstream and still in Us below: energy created */
#endif
    const int withdrawn = canergy_supervisor_withdraw(&gw->down, uj);
    CANERGY_ASSERT(withdrawn == CANERGY_OK);
    (void)withdrawn;
    return CANERGY_OK;
}

int64_t canergy_gateway_link_gap(const struct canergy_gateway *gw)
{
    return (int64_t)(gw->down.injected_uj - gw->down.withdrawn_uj) - (int64_t)gw->up.rec.spent_uj;
}

static uint64_t gw_least(uint64_t a, uint64_t b)
{
    return a < b ? a : b;
}

uint32_t canergy_gateway_top_up(uint64_t target_uj, uint64_t min_uj, uint64_t level_uj,
                                int64_t usable_uj)
{
    if (level_uj >= target_uj || target_uj - level_uj < min_uj || usable_uj <= 0) {
        return 0U;
    }
    /* never above what the node's record holds, nor one frame, nor Us */
    const uint64_t room = CANERGY_USABLE_MAX_UJ - gw_least(level_uj, CANERGY_USABLE_MAX_UJ);
    uint64_t amount = gw_least(target_uj - level_uj, room);
    amount = gw_least(amount, gw_least((uint64_t)CANERGY_AMOUNT_MAX_MJ * GW_MJ, (uint64_t)usable_uj));
    return (uint32_t)(amount - amount % GW_MJ);
}

uint32_t canergy_gateway_give_back_amount(int64_t usable_uj, uint64_t return_above_uj)
{
    if (usable_uj <= 0 || (uint64_t)usable_uj <= return_above_uj) {
        return 0U;
    }
    const uint64_t excess =
        gw_least((uint64_t)usable_uj - return_above_uj, (uint64_t)CANERGY_AMOUNT_MAX_MJ * GW_MJ);
    return (uint32_t)(excess - excess % GW_MJ);
}
