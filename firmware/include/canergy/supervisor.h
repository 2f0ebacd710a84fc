/*
 * The hardened supervisor (src/canergy/core/supervisor.py's Supervisor), sans-IO: one usable
 * budget Us, one struct canergy_session per node (canergy/session.h), frames in and out through
 * the codec. No heap: the caller owns the struct and the session table, whose size is fixed at
 * build time (CANERGY_SUPERVISOR_NODES). tests/test_c_supervisor.py runs it side by side with
 * the Python supervisor.
 *
 * Contract of every call that takes a struct canergy_supervisor_out *out (overwritten): if
 * out->persist is set, write the supervisor's record (Us, and per session its phase with ACKED
 * stored as WAIT_ACK, tx, Ts, Gs, decision and the last return credited) and let the write
 * complete before any of out->frames is sent; then send out->frames[0 .. out->frame_count - 1]
 * in order.
 *
 * The record (canergy_supervisor_image) goes to NV in two slots written in turn, as the
 * client's does: canergy_supervisor_load takes the valid one written last at start.
 */
#ifndef CANERGY_SUPERVISOR_H
#define CANERGY_SUPERVISOR_H

#include "canergy/nv.h"
#include "canergy/session.h"

#ifdef __cplusplus
extern "C" {
#endif

#ifndef CANERGY_SUPERVISOR_NODES
#define CANERGY_SUPERVISOR_NODES 16U /* sessions one supervisor holds: choose at build time */
#endif

struct canergy_supervisor_config {
    uint32_t id_base; /* CANERGY_DEFAULT_ID_BASE unless the bus uses another block */
    struct canergy_session_timing timing;
};

struct canergy_supervisor {
    int64_t usable_uj;    /* Us: below 0 (a debt) only after a witnessed start took books that
                           * hold more than the record (nothing is granted until it is covered) */
    uint64_t injected_uj; /* energy added from outside since start (a gateway's upstream) */
    uint64_t withdrawn_uj; /* energy taken out to outside (a gateway's returns upstream) */
    struct canergy_session sessions[CANERGY_SUPERVISOR_NODES]; /* by node, ascending */
    struct canergy_session_timing timing;
    uint32_t id_base;
    uint32_t start_without[4]; /* witnessed: bit n set: a start does not wait for node n */
    uint8_t count;        /* sessions in use */
};


/* What one session's step did, beside its frame: for the port's application (a grant's
 * outcome) and for the host's books (Python's Acknowledged, Resolved, ReturnCredited,
 * Admitted). */
#define CANERGY_SUP_ACKNOWLEDGED 0x01U   /* the open intention was acknowledged: decide it */
#define CANERGY_SUP_RETURN_CREDITED 0x02U /* a fresh RETURN: amount_uj went into Us */
#define CANERGY_SUP_ADMITTED 0x04U       /* a JOIN: the node starts again at the session's tx */
/* a start's counts afresh (books unknown or a floor), ahead_numbers debit numbers past C + 1:
 * as many CANERGY_AMOUNT_MAX_MJ moved from Us to Gs (Python's AheadOfImage) */
#define CANERGY_SUP_AHEAD 0x08U

struct canergy_supervisor_event {
    uint32_t tx;        /* the transaction acknowledged or resolved (before an admission's lift) */
    uint32_t amount_uj; /* resolved: its Ts; else a RETURN credited: the amount (a witnessed
                         * RESUME that does both: its Ts; the session's returned_uj grew by
                         * the credit) */
    uint16_t ahead_numbers; /* CANERGY_SUP_AHEAD: the session step's ahead_numbers */
    uint8_t node;
    uint8_t resolved;   /* enum canergy_resolution */
    uint8_t flags;      /* CANERGY_SUP_* */
};

struct canergy_supervisor_out {
    struct canergy_frame frames[CANERGY_SUPERVISOR_NODES]; /* a timer call answers every node */
    struct canergy_supervisor_event events[CANERGY_SUPERVISOR_NODES]; /* one per session step */
    uint8_t frame_count;
    uint8_t event_count;
    uint8_t persist; /* 1: write the record before sending */
};

/* Nodes 1..127, ascending and distinct, at most CANERGY_SUPERVISOR_NODES of them; Us starts
 * at initial_uj. CANERGY_ERR_ARGUMENT otherwise (and for a bad id_base, or timing rules this
 * build left out: canergy/client.h). */
int canergy_supervisor_init(struct canergy_supervisor *sup,
                            const struct canergy_supervisor_config *cfg, const uint8_t *nodes,
                            uint8_t count, uint64_t initial_uj);

/* Reserve amount_uj from Us and send node an intention. CANERGY_ERR_ARGUMENT for a node not
 * managed here, CANERGY_ERR_UNCONFIRMED while a start waits for any node's books (witnessed),
 * CANERGY_ERR_PHASE outside IDLE, CANERGY_ERR_WINDOW beyond the window (witnessed),
 * CANERGY_ERR_AMOUNT for an amount that is not whole mJ up to 65,535 mJ or exceeds Us. */
int canergy_supervisor_begin(struct canergy_supervisor *sup, uint8_t node, uint32_t amount_uj,
                             uint64_t now, struct canergy_supervisor_out *out);

/* Decide the acknowledged intention of node: COMMIT or ABORT. */
int canergy_supervisor_decide(struct canergy_supervisor *sup, uint8_t node, bool commit,
                              uint64_t now, struct canergy_supervisor_out *out);

/* A received frame: decoded strictly (client -> supervisor), then the node's rules. Returns
 * CANERGY_DECODE_OK, a decode status (count it; nothing else happens) or CANERGY_RX_OTHER_NODE
 * (a valid frame of a node not managed here). */
int canergy_supervisor_on_frame(struct canergy_supervisor *sup,
                                const struct canergy_rx_frame *frame, uint64_t now,
                                struct canergy_supervisor_out *out);

/* A client message already decoded (the host's own decoder, a gateway): the node's rules, as
 * canergy_supervisor_on_frame after its decode. CANERGY_RX_OTHER_NODE for a node not managed
 * here; a message in the other direction changes nothing. */
int canergy_supervisor_on_msg(struct canergy_supervisor *sup, const struct canergy_msg *m,
                              uint64_t now, struct canergy_supervisor_out *out);

/* What canergy_supervisor_on_answer leaves to the caller: CANERGY_RX_AHEAD, CANERGY_RX_CALLER
 * (canergy/status.h). */

/* The answers to the supervisor's own frames at once, for a port that decides every
 * acknowledged intention when it comes (a gateway, the host's fast path): the frame decoded
 * strictly; an ACK, COMMITTED or ABORTED of a managed node runs its rules, and an ACK's
 * intention is decided in the same out (committed, aborted when abort_acks). Returns
 * CANERGY_DECODE_OK, a decode status, CANERGY_RX_OTHER_NODE, CANERGY_RX_AHEAD or
 * CANERGY_RX_CALLER; *m is the decoded message whenever the decode succeeded. */
int canergy_supervisor_on_answer(struct canergy_supervisor *sup,
                                 const struct canergy_rx_frame *frame, uint64_t now,
                                 bool abort_acks, struct canergy_supervisor_out *out,
                                 struct canergy_msg *m);

/* Fire every session whose deadline is at or before now (calling early is harmless). */
void canergy_supervisor_on_timer(struct canergy_supervisor *sup, uint64_t now,
                                 struct canergy_supervisor_out *out);

/* The earliest armed deadline, CANERGY_NEVER when none. */
uint64_t canergy_supervisor_deadline(const struct canergy_supervisor *sup);

/* A reset with the record kept: every session restarts (open ones re-send at the next timer);
 * under the witnessed rules, canergy_supervisor_start with nonce 0. */
void canergy_supervisor_restart(struct canergy_supervisor *sup, uint64_t now);

/* A start with a fresh nonce (draw it from a hardware entropy source). Witnessed rules
 * (witnessed.start): every session writes off what is open and waits for its node's books,
 * SYNC(nonce) going out at the next timer call and every response timeout after; nothing is
 * granted until every node (but those set with canergy_supervisor_start_without) has answered.
 * Hardened rules: canergy_supervisor_restart. *out tells whether the record changed (a
 * write-off): write it before the first SYNC leaves. */
void canergy_supervisor_start(struct canergy_supervisor *sup, uint16_t nonce, uint64_t now,
                              struct canergy_supervisor_out *out);

/* Witnessed: re-sync node alone (canergy_session_resync) with a fresh nonce: SYNC(nonce) in
 * *out; no grant to other nodes waits for it. For a node refused with CANERGY_ERR_WINDOW, or
 * whose counts the rules ignore. CANERGY_ERR_ARGUMENT for a node not managed here,
 * CANERGY_ERR_PHASE unless its session is IDLE (or under the hardened rules). */
int canergy_supervisor_resync(struct canergy_supervisor *sup, uint8_t node, uint16_t nonce,
                              uint64_t now, struct canergy_supervisor_out *out);

/* Witnessed: a start no longer waits for node (the operator's risk: the node may hold energy
 * the restored books count in Us again, and Us grants it to others); its own session still
 * waits for its books. CANERGY_ERR_ARGUMENT for a node not managed here. */
int canergy_supervisor_start_without(struct canergy_supervisor *sup, uint8_t node);

/* The nodes a start still waits for (ascending, into nodes[]; NULL: only count them), those
 * set with canergy_supervisor_start_without and those in a re-sync of their own left out:
 * their number. */
uint8_t canergy_supervisor_unconfirmed(const struct canergy_supervisor *sup,
                                       uint8_t nodes[CANERGY_SUPERVISOR_NODES]);

/* Energy from outside into Us (counted as injected). CANERGY_ERR_AMOUNT for 0. Write the
 * record after it, before the energy is granted. */
int canergy_supervisor_inject(struct canergy_supervisor *sup, uint64_t amount_uj);

/* Energy out of Us to outside (counted as withdrawn): a gateway returning it upstream.
 * CANERGY_ERR_AMOUNT for 0 or more than Us. Write the record in the same step. */
int canergy_supervisor_withdraw(struct canergy_supervisor *sup, uint64_t amount_uj);

/* -- the record in NV --------------------------------------------------------------------- */

/* One slot: a 12-byte header ("CNRS", version 5, count, counter), Us (signed), injected and
 * withdrawn, 56 bytes per session (node, stored phase, decision, tx, last debit held, Ts, Gs,
 * returned, the last RESUME answered: its q, the number it voided, its nonce with bit 16 set
 * for a SYNC's counts, and the last JOIN admitted: its ADMIT's k and C, its nonce) and a CRC-32
 * of all that. Two slots of CANERGY_SUPERVISOR_SLOT_SIZE bytes back to back. A slot of version
 * 2 to 4 (before the witnessed rules, before the supervisor's start was confirmed, before the
 * last JOIN was remembered) is refused as CANERGY_ERR_RECORD, as another node list is. A
 * start's waiting phases are stored as IDLE: every start is one. */
#define CANERGY_SUPERVISOR_SLOT_SIZE (40U + 56U * CANERGY_SUPERVISOR_NODES)

/* The record as slot bytes with this counter (the slot written before it has counter - 1);
 * returns the bytes used, 40 + 56 per session (the rest of the slot is left as it is). */
size_t canergy_supervisor_image(const struct canergy_supervisor *sup, uint32_t counter,
                                uint8_t out[CANERGY_SUPERVISOR_SLOT_SIZE]);


/* Start: init, then take the valid slot written last in image (len bytes, both slots; NULL/0
 * when blank) whose nodes are these. Returns 1 with *counter and *slot of that record, 0 when
 * there is none (the supervisor starts new: its nodes may still hold books of an earlier life,
 * so the port should not grant before they have told it, e.g. by JOIN), CANERGY_ERR_RECORD
 * when there is none of these nodes but a record of another version or node list (never start
 * new over it: its Us would be granted a second time), CANERGY_ERR_END when a valid slot of
 * these nodes holds a tx or return number at or beyond CANERGY_COUNTER_BOUND (neither slot is
 * taken), or an init error. */
int canergy_supervisor_load(struct canergy_supervisor *sup,
                            const struct canergy_supervisor_config *cfg, const uint8_t *nodes,
                            uint8_t count, uint64_t initial_uj, const uint8_t *image, size_t len,
                            uint32_t *counter, uint8_t *slot);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_SUPERVISOR_H */
