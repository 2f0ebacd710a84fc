/*
 * The gateway rules (canergy/gateway.h), as src/canergy/core/gateway.py's forward and
 * withdraw_for_return.
 */
#include "canergy/gateway.h"

#include "client_internal.h"

uint32_t canergy_gateway_forward(struct canergy_gateway *gw, struct canergy_out *out)
{
    const uint32_t amount = gw->up.rec.usable_uj;
    if (amount == 0U || gw->up.phase == CANERGY_JOINING) {
        return 0U;
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

int canergy_gateway_on_up_frame(struct canergy_gateway *gw, const struct canergy_rx_frame *frame,
                                uint64_t now, struct canergy_out *out)
{
    const int status = canergy_client_on_frame(&gw->up, frame, now, out);
    (void)canergy_gateway_forward(gw, out);
    return status;
}

void canergy_gateway_on_up_timer(struct canergy_gateway *gw, uint64_t now,
                                 struct canergy_out *out)
{
    canergy_client_on_timer(&gw->up, now, out);
    (void)canergy_gateway_forward(gw, out);
}

int canergy_gateway_give_back(struct canergy_gateway *gw, uint32_t uj, uint64_t now,
                              struct canergy_out *out)
{
    canergy_internal_out_clear(out);
    if (!canergy_client_can_give_back(&gw->up)) {
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
    const int rc = canergy_internal_give_back(&up, uj, now, out);
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
