/*
 * Library-internal: the client's steps without clearing *out, so the node layer can gather
 * several steps into one out (one persist, written before all of their frames); the node's
 * witness, which the authenticated layer counts too.
 */
#ifndef CANERGY_CLIENT_INTERNAL_H
#define CANERGY_CLIENT_INTERNAL_H

#include "canergy/client.h"
#include "canergy/witness.h" /* CANERGY_WITNESS_REPORT_AT, CANERGY_WITNESS_GAP_US */

void canergy_internal_out_clear(struct canergy_out *out);
int canergy_internal_start(struct canergy_client *c, const struct canergy_client_config *cfg,
                           const uint8_t *nv_image, size_t nv_len, uint16_t nonce, uint64_t now,
                           struct canergy_out *out);
/* *m: the decoded message, valid when the result is CANERGY_DECODE_OK or CANERGY_RX_OTHER_NODE */
int canergy_internal_frame(struct canergy_client *c, const struct canergy_rx_frame *frame,
                           uint64_t now, struct canergy_out *out, struct canergy_msg *m);
void canergy_internal_timers(struct canergy_client *c, uint64_t now, struct canergy_out *out);
/* The earliest armed deadline (canergy_client_deadline without its NULL check). */
static inline uint64_t canergy_internal_deadline(const struct canergy_client *c)
{
    return c->deadline < c->return_deadline ? c->deadline : c->return_deadline;
}
int canergy_internal_spend(struct canergy_client *c, uint32_t uj, struct canergy_out *out);
/* Write the record as it is now into out (persist): a caller that changed it (the gateway). */
void canergy_internal_repack(struct canergy_client *c, struct canergy_out *out);
int canergy_internal_draw(struct canergy_client *c, uint32_t uj, uint64_t now,
                          struct canergy_out *out);
/* Debit uj as the next numbered RETURN (draw 0: a give-back), or with draw
 * CANERGY_RECORD_PENDING_DRAW (witnessed) as a DRAW: canergy_client_give_back's refusals. */
int canergy_internal_debit(struct canergy_client *c, uint32_t uj, uint64_t now, uint8_t draw,
                           struct canergy_out *out);
/* A frame of type from the client's node, its fields in the type's layout order (codec.c):
 * appended to out (a frame the codec refuses is dropped). */
void canergy_internal_send(const struct canergy_client *c, uint8_t type, const uint32_t fields[4],
                           struct canergy_out *out);

struct canergy_node;
/* A frame in the node's name that it did not send: count it, report it at the next poll but
 * no sooner than CANERGY_WITNESS_GAP_US after the last TELEMETRY (two nodes on one id would
 * otherwise answer each other's reports with no pause: a storm), or at once (into out) when
 * CANERGY_WITNESS_REPORT_AT frames have gone unreported, so that no report is ever 256 frames
 * (a whole turn of the 8-bit count) after the last. The gap keeps a refutation well inside the
 * supervisor's RETURN and JOIN holds (500 ms by default). */
void canergy_internal_witness(struct canergy_node *n, struct canergy_out *out, uint64_t now);

#endif /* CANERGY_CLIENT_INTERNAL_H */
