/*
 * The hardened supervisor's rules for one node (docs/protocol.md, "The hardened rules"),
 * sans-IO: the cells of src/canergy/core/hardened.py's SUPERVISOR table, one call each, on a
 * caller-owned struct canergy_session. This is the supervisor role's core; the supervisor
 * around it (the usable budget Us over all sessions, the node table, NV, frames) is built on it
 * (issue 33). tests/test_c_session.py compares every call with the Python table.
 *
 * Each call fills a struct canergy_session_step (overwritten): the message to send (encode it
 * with canergy_encode), what the step moves into (+) or out of (-) the usable budget Us, and
 * how it closed the transaction when it did. Counters are kept modulo 2^32 (the Python ones are
 * unbounded; every rule looks only at a wire value's signed distance from them).
 *
 * Time: as client.h (uint64_t microseconds, monotonic, below 2^63).
 */
#ifndef CANERGY_SESSION_H
#define CANERGY_SESSION_H

#include "canergy/assert.h"
#include "canergy/client.h"
#include "canergy/codec.h"

#ifdef __cplusplus
extern "C" {
#endif

enum canergy_session_phase {
    CANERGY_S_IDLE = 0,
    CANERGY_S_WAIT_ACK = 1,    /* intention sent */
    CANERGY_S_ACKED = 2,       /* intention acknowledged, awaiting the local decision */
    CANERGY_S_WAIT_CONFIRM = 3, /* commit or abort sent */
    CANERGY_S_SYNCING = 9,      /* witnessed: started, SYNC sent, awaiting the node's books (the
                                 * values of Python's Phase) */
    CANERGY_S_SYNC_BOOKS = 10   /* witnessed: the node's Rc taken, awaiting its counts */
};


enum canergy_decision {
    CANERGY_DECIDE_NONE = 0,
    CANERGY_DECIDE_COMMIT = 1,
    CANERGY_DECIDE_ABORT = 2
};

/* How a step closed the open transaction (Python's Outcome). */
enum canergy_resolution {
    CANERGY_RESOLVED_NONE = 0,
    CANERGY_RESOLVED_COMMITTED = 1,
    CANERGY_RESOLVED_ABORTED = 2,  /* Ts back into Us: the only way back */
    CANERGY_RESOLVED_WRITTEN_OFF = 4 /* given up (or a JOIN): counted as delivered */
};

/* The session's timing and its rule set (enum canergy_rules: 0, hardened, the default). */
struct canergy_session_timing {
    uint32_t response_timeout_us; /* re-send after this long (Python 50 ms) */
    uint8_t retries;              /* N: re-sends before the write-off (Python 3) */
    uint8_t rules;                /* witnessed: DEBIT is taken (on_debit), else ignored */
    uint16_t window;              /* witnessed: B, a transaction begins only at k <= W + B
                                   * (Python's Timing.window); 0: CANERGY_DEFAULT_WINDOW */
};

/* The supervisor's record for one node. 72 bytes. */
struct canergy_session {
    uint64_t delivered_uj;     /* Gs: all energy that left the supervisor's books for the node */
    uint64_t returned_uj;      /* all returns credited */
    uint64_t deadline;         /* response timer, CANERGY_NEVER when not armed (volatile) */
    uint32_t tx;               /* the transaction, modulo 2^32 */
    uint32_t returns_credited; /* number of the last debit held (RETURN or DRAW), modulo 2^32 */
    uint32_t reserved_uj;      /* Ts: at most 65,535,000 */
    uint32_t resume_from;      /* witnessed: the last RESUME answered, its q (widened) ... */
    uint32_t resume_to;        /* ... the number it voided ... */
    uint32_t resume_nonce;     /* ... and its nonce (bit 16: a SYNC's counts, not a RESUME): a
                                * repeat gets the same ADMIT */
    int32_t witness;           /* witnessed: W, the highest tx the node has shown it persisted
                                * (volatile: a start sets it again) */
    uint32_t join_tx;          /* witnessed: the last JOIN admitted, the k of its ADMIT ... */
    uint32_t join_seq;         /* ... the C it carried (0: none admitted yet) ... */
    uint16_t join_nonce;       /* ... and its nonce: a copy gets the same ADMIT */
    uint16_t sync_nonce;       /* witnessed: the nonce of the SYNC this start sent (volatile) */
    uint8_t node;
    uint8_t phase;             /* enum canergy_session_phase */
    uint8_t decision;          /* enum canergy_decision */
    uint8_t tries;             /* sends of the frame awaiting an answer (volatile) */
    uint8_t resync;            /* witnessed: 1 while the SYNC is a re-sync of this session alone
                                * (canergy_session_resync; volatile): no other waits for it */
};

struct canergy_session_step {
    struct canergy_msg msg; /* valid when send is 1 */
    int64_t credit_uj;      /* into Us (+), out of it (-) */
    uint8_t send;
    uint8_t resolved;       /* enum canergy_resolution */
    uint8_t acknowledged;   /* 1: an ACK of the open intention (Python's Acknowledged) */
    uint8_t admitted;       /* 1: a JOIN, or a RESUME found behind (Python's Admitted) */
    uint16_t ahead_numbers; /* witnessed: a start's counts afresh (books unknown or a floor),
                             * q - C - 1 > 0 debit numbers the image never held (each a draw at
                             * most): as many AMOUNT_MAX_MJ moved from Us to Gs (AheadOfImage) */
};

/* A new record for node (1..127): IDLE, nothing delivered. */
void canergy_session_init(struct canergy_session *s, uint8_t node);

/* Begin(a) in IDLE: Us -= a, tx += 1, INTENTION(tx, a, Gs). CANERGY_ERR_PHASE outside IDLE;
 * CANERGY_ERR_WINDOW (witnessed) when tx + 1 > W + B; CANERGY_ERR_AMOUNT unless a is a
 * positive whole number of mJ up to 65,535 mJ; CANERGY_ERR_END
 * when tx + 1 would reach CANERGY_COUNTER_END. The caller
 * checks a against Us (the one guard a session cannot see). */
int canergy_session_begin(struct canergy_session *s, const struct canergy_session_timing *t,
                          uint32_t amount_uj, uint64_t now, struct canergy_session_step *step);

/* Decide in ACKED: COMMIT or ABORT(tx, Ts). CANERGY_ERR_PHASE in any other phase. */
int canergy_session_decide(struct canergy_session *s, const struct canergy_session_timing *t,
                           bool commit, uint64_t now, struct canergy_session_step *step);

/* A decoded client message for this node (ACK, COMMITTED, ABORTED, RETURN, JOIN, and under the
 * witnessed rules DEBIT: a DRAW held as the last debit and acknowledged, a RESUME (or a SYNC's
 * counts) confirmed or found behind, as core/witnessed.py's on_debit; while a start waits
 * (SYNCING, SYNC_BOOKS) only the SYNC's books, then its counts, bound to its nonce; anything
 * else changes nothing). Under the witnessed rules an answer naming a transaction moves W. */
void canergy_session_on_msg(struct canergy_session *s, const struct canergy_session_timing *t,
                            const struct canergy_msg *m, uint64_t now,
                            struct canergy_session_step *step);

/* The response timer (early calls are harmless): the identical frame again, or after N
 * re-sends the write-off (Gs += Ts); while a start waits, SYNC again, without end. */
void canergy_session_timer(struct canergy_session *s, const struct canergy_session_timing *t,
                           uint64_t now, struct canergy_session_step *step);

/* A reset with the record kept: ACKED (not persisted) falls back to WAIT_ACK; an open
 * transaction's frame is due at once. */
void canergy_session_restart(struct canergy_session *s, uint64_t now,
                             struct canergy_session_step *step);

/* A start (power loss, or a record restored from an older copy: the supervisor cannot tell)
 * with a fresh nonce. Witnessed rules (witnessed.start): write off what is open, SYNCING, and
 * SYNC(nonce, tx, C) due at once (at the next timer call); hardened rules:
 * canergy_session_restart. */
void canergy_session_start(struct canergy_session *s, const struct canergy_session_timing *t,
                           uint16_t nonce, uint64_t now, struct canergy_session_step *step);

/* Witnessed rules (witnessed.resync_session): a re-sync of this node alone, from IDLE:
 * SYNC(nonce, tx, C) sent now and every response timeout after, its books then its counts
 * taken as at a start (tx = max(tx, ltx), W = ltx, C voided, ADMIT(nonce ^
 * CANERGY_SYNC_CONFIRMED)); nothing written off, no other session waits for it; a JOIN
 * meanwhile ends it and is taken as in IDLE. For a node whose window is used up (CANERGY_ERR_WINDOW) or whose counts are ignored.
 * CANERGY_ERR_PHASE outside IDLE or under other rules. */
int canergy_session_resync(struct canergy_session *s, const struct canergy_session_timing *t,
                           uint16_t nonce, uint64_t now, struct canergy_session_step *step);

/* True while a start waits for this node's books (SYNCING or SYNC_BOOKS). */
bool canergy_session_syncing(const struct canergy_session *s);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_SESSION_H */
