/*
 * JOINs held as evidence until the node's own TELEMETRY says whether it lost its books
 * (src/canergy/live/supervisor/joins.py's JoinHold, for one node), sans-IO, one caller-owned
 * struct per node. A JOIN writes off what the node held and anyone can send one, so it is held:
 * a TELEMETRY without books (JOINING) confirms the latest one, admitted hold_us later unless the
 * node shows its books meanwhile; a TELEMETRY with books refuses every JOIN held, except a copy
 * of the one admitted just before (the node re-sent it while its ADMIT was on the way: counted
 * in resent). tests/test_ccore_tables.py runs both side by side through the supervisor.
 */
#ifndef CANERGY_JOINS_H
#define CANERGY_JOINS_H

#include "canergy/codec.h"

#include <stdbool.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define CANERGY_JOINS_HELD 8U /* distinct JOINs held per node (Python's HELD_JOINS) */

/* canergy_joins_telemetry's result (bits). */
#define CANERGY_JOINS_DUE 0x01U     /* a held JOIN confirmed: admitted at admit_at */
#define CANERGY_JOINS_ADMIT 0x02U   /* admit the JOIN numbered *nonce now */
#define CANERGY_JOINS_REFUSED 0x04U /* the node has its books: the JOINs held are refused */
#define CANERGY_JOINS_PASS 0x08U    /* canergy_joins_route: neither a JOIN nor a TELEMETRY */

struct canergy_joins {
    uint64_t admit_at;              /* has_admitting */
    uint32_t resent;                /* copies of the JOIN just admitted, dropped */
    uint16_t held[CANERGY_JOINS_HELD]; /* their nonces, distinct, the latest last */
    uint16_t admitting;             /* has_admitting: the nonce confirmed */
    uint16_t admitted;              /* has_admitted: the nonce admitted last */
    uint8_t held_count;
    bool has_admitting;
    bool has_admitted;
};

/* A JOIN numbered nonce in the node's name: held. */
void canergy_joins_join(struct canergy_joins *j, uint16_t nonce);

/* The node's TELEMETRY (its flags); hold_us: how long a confirmed JOIN waits. The bits above;
 * *nonce: the JOIN to admit (CANERGY_JOINS_ADMIT). */
unsigned canergy_joins_telemetry(struct canergy_joins *j, uint8_t flags, uint64_t now,
                                 uint64_t hold_us, uint16_t *nonce);

/* A confirmed JOIN whose hold is over: true, *nonce to admit (the others held are dropped). */
bool canergy_joins_due(struct canergy_joins *j, uint64_t now, uint16_t *nonce);

/* The JOINs a TELEMETRY with books refused (canergy_joins_route): their nonces. */
struct canergy_joins_refuted {
    uint16_t nonces[CANERGY_JOINS_HELD];
    uint8_t count;
};

/* For a supervisor whose rules answer a JOIN at once (canergy_supervisor_on_msg; the gateway's
 * leg below, which holds them as `canergy supervisor` and `canergy gateway` do): m, a message of
 * j's node (decoded, verified with a key, past the witness), on its way to the rules. A JOIN is
 * held (0: nothing for the rules); a TELEMETRY is judged (the bits of canergy_joins_telemetry):
 * with CANERGY_JOINS_ADMIT, *to_rules is the JOIN to hand the rules now; with
 * CANERGY_JOINS_REFUSED, *refuted the JOINs refused (a copy of the one admitted last is the
 * node's own re-send, counted in j->resent instead), each evidence of a forgery (no key) or of a
 * replay of an earlier life (a key). Anything else: CANERGY_JOINS_PASS, *to_rules = *m. */
unsigned canergy_joins_route(struct canergy_joins *j, const struct canergy_msg *m, uint64_t now,
                             uint64_t hold_us, struct canergy_msg *to_rules,
                             struct canergy_joins_refuted *refuted);

/* canergy_joins_due for node: true, *join the JOIN to hand the rules now. */
bool canergy_joins_due_join(struct canergy_joins *j, uint8_t node, uint64_t now,
                            struct canergy_msg *join);

#ifdef __cplusplus
}
#endif

#endif
