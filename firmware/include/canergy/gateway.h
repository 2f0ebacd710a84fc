/*
 * The gateway rules (src/canergy/core/gateway.py), sans-IO: a client upstream and a supervisor
 * downstream in one caller-owned struct, energy crossing between them only through two rules,
 * each inside the step that causes it:
 *   - forward: whatever the upstream client holds usable (a commit, a write-off's pay-back) goes
 *     at once into the downstream Us: spent above, injected below;
 *   - give back: energy of the downstream Us is withdrawn and returned upstream as the client's
 *     next numbered RETURN.
 * So up.spent == down.injected - down.withdrawn always (canergy_gateway_link_gap is 0): the
 * gateway neither creates nor loses energy between its roles. tests/test_c_gateway.py runs it
 * side by side with the Python Gateway.
 *
 * Persist contract: both roles are one record. Whenever a call reports a persist (the client's
 * out->persist, or the supervisor's), write the client's record and the supervisor's record as
 * one (split-save, two records written apart, is the counterexample of `canergy check
 * --topology chain --broken-gateway split-save`) before any frame of that call leaves.
 */
#ifndef CANERGY_GATEWAY_H
#define CANERGY_GATEWAY_H

#include "canergy/client.h"
#include "canergy/supervisor.h"

#ifdef __cplusplus
extern "C" {
#endif

struct canergy_gateway {
    struct canergy_client up;       /* node `up.node` of the bus above */
    struct canergy_supervisor down; /* the supervisor of its nodes on the bus below */
};

/* Move all of the upstream usable budget into the downstream Us; returns the amount (0: none).
 * The client's record is re-packed into out (out->persist) when anything moved. */
uint32_t canergy_gateway_forward(struct canergy_gateway *gw, struct canergy_out *out);

/* A frame from the bus above: the client's rules (canergy_client_on_frame), then forward. */
int canergy_gateway_on_up_frame(struct canergy_gateway *gw, const struct canergy_rx_frame *frame,
                                uint64_t now, struct canergy_out *out);

/* The client's timers (a timeout-commit is forwarded too). */
void canergy_gateway_on_up_timer(struct canergy_gateway *gw, uint64_t now,
                                 struct canergy_out *out);

/* Return uj of the downstream Us upstream as the next numbered RETURN: CANERGY_ERR_PHASE while
 * a return awaits its acknowledgement or the client is joining, CANERGY_ERR_AMOUNT for an amount
 * the client cannot return (whole mJ, 1..65,535 mJ) or above the downstream Us. Nothing moves
 * on a refusal. */
int canergy_gateway_give_back(struct canergy_gateway *gw, uint32_t uj, uint64_t now,
                              struct canergy_out *out);

/* Energy created between the roles: injected - withdrawn - spent (0 unless the rules broke). */
int64_t canergy_gateway_link_gap(const struct canergy_gateway *gw);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_GATEWAY_H */
