/*
 * The hardened client's rules: src/canergy/core/hardened.py (CLIENT) and core/common.py, cell
 * for cell, on fixed-width counters.
 *
 * Counters. Python widens every wire counter to an unbounded integer; here last_tx, return_seq
 * and credited_mj are kept modulo 2^32 and every rule looks only at the signed distance of a
 * wire value from its reference (serial16/serial24 below). That distance is what Python's
 * unwrap() adds to the reference, and it depends only on the reference modulo 2^16 (2^24),
 * which 2^32 preserves, so every "k > ltx", "k == ltx", "Gs > Rc" comes out the same. The one
 * comparison between two stored counters (a held tx against a newer one) is a 32-bit serial
 * comparison, exact because a held tx is at most 32767 ahead of ltx.
 *
 * Persisting. Each step compares the packed record before and after; a change asks the port
 * to write the new slot image before any frame of the step leaves (client.h).
 */
#include "canergy/client.h"

#include "canergy/assert.h"

#include "client_internal.h"
#include "codec_internal.h"
#include "rules.h"
#include "serial.h"

#include <string.h>

#define MJ CANERGY_QUANTUM_UJ
#define RETURN_MAX_UJ (CANERGY_AMOUNT_MAX_MJ * CANERGY_QUANTUM_UJ)

/* counts afresh move the record's CREDITED_UNKNOWN 4 bits up onto the DEBIT's RC_UNKNOWN (C99:
 * an array of -1 elements fails the build if they ever part) */
typedef char canergy_credited_unknown_is_rc_unknown_shifted
    [(CANERGY_RECORD_CREDITED_UNKNOWN << 4U) == CANERGY_DEBIT_RC_UNKNOWN ? 1 : -1];

/* -- output ----------------------------------------------------------------------------- */

void canergy_internal_out_clear(struct canergy_out *out)
{
    memset(out, 0, sizeof *out);
}

void canergy_internal_send(const struct canergy_client *c, uint8_t type, const uint32_t fields[4],
                           struct canergy_out *out)
{
    /* Never full by construction (CANERGY_OUT_FRAMES counts the worst step); a frame that did
     * not fit would be a lost frame, which the protocol survives. */
    if (out->frame_count < CANERGY_OUT_FRAMES &&
        canergy_internal_encode(c->id_base, type, c->node, fields,
                                &out->frames[out->frame_count]) == CANERGY_OK) {
        out->frame_count++;
    }
}

/* JOIN(nonce), RETURN(seq, amount), ACK/COMMITTED/ABORTED(tx): the counter is the first field. */
static void send(const struct canergy_client *c, uint8_t type, uint16_t counter,
                 uint16_t amount_mj, struct canergy_out *out)
{
    const uint32_t fields[4] = {counter, amount_mj, 0U, 0U};
    canergy_internal_send(c, type, fields, out);
}

/* The confirmation of a resolved transaction: none when it was settled or written off. */
static void reply_for(const struct canergy_client *c, uint32_t tx, uint8_t outcome,
                      struct canergy_out *out)
{
    if (outcome == CANERGY_OUTCOME_COMMITTED || outcome == CANERGY_OUTCOME_ABORTED) {
        send(c, outcome == CANERGY_OUTCOME_COMMITTED ? CANERGY_COMMITTED : CANERGY_ABORTED,
             (uint16_t)tx, 0U, out);
    }
}

/* Ask for the record to be written. Several steps gathered into one out write one image: the
 * slot and counter are chosen once, so the slot holding the last complete record is never the
 * one overwritten. */
static void persist(struct canergy_client *c, const uint8_t record[CANERGY_NV_RECORD_SIZE],
                    struct canergy_out *out)
{
    CANERGY_ASSERT(c->phase != CANERGY_JOINING); /* a blank record is not books: never written */
    if (out->persist == 0U) {
        out->persist = 1U;
        out->nv_slot = (uint8_t)(1U - c->nv_slot);
        out->nv_counter = c->nv_counter + 1U;
        c->nv_slot = out->nv_slot;
        c->nv_counter = out->nv_counter;
    }
    canergy_nv_slot_encode(out->nv_counter, record, CANERGY_NV_RECORD_SIZE, out->nv_image);
}

/* Persist the record as it is now: a step that changed it for certain. */
void canergy_internal_repack(struct canergy_client *c, struct canergy_out *out)
{
    uint8_t rec[CANERGY_NV_RECORD_SIZE];
    canergy_record_pack(&c->rec, rec);
    persist(c, rec, out);
}

/* Persist when the step changed the record (Python's client_record before != after). */
static void persist_if_changed(struct canergy_client *c,
                               const uint8_t before[CANERGY_NV_RECORD_SIZE],
                               struct canergy_out *out)
{
    uint8_t now_rec[CANERGY_NV_RECORD_SIZE];
    canergy_record_pack(&c->rec, now_rec);
    if (memcmp(before, now_rec, sizeof now_rec) != 0) {
        canergy_internal_repack(c, out);
    }
}

/* -- holding and resolving ---------------------------------------------------------------- */

static void drop_hold(struct canergy_client *c)
{
    c->phase = CANERGY_IDLE;
    c->held_tx = 0U;
    c->held_amount_mj = 0U;
    c->deadline = CANERGY_NEVER;
}

static void return_timer(struct canergy_client *c, uint64_t now, struct canergy_out *out);

/* A start waiting for the supervisor (JOINING, RESUMING, SYNCING): the hold dropped, its first
 * frame at once (the return timer's), again every return_retry_us until the ADMIT. */
static void wait_for_admit(struct canergy_client *c, uint8_t phase, uint16_t nonce, uint64_t now,
                           struct canergy_out *out)
{
    drop_hold(c);
    c->phase = phase;
    c->nonce = nonce;
    c->return_deadline = now;
    return_timer(c, now, out);
}

static void resolved(struct canergy_client *c, uint32_t tx, uint8_t outcome)
{
    c->rec.last_tx = tx;
    c->rec.outcome = outcome;
    drop_hold(c);
}

/* Commit an amount: Uc += a, Rc += a. Callers refuse what would overflow usable; the one
 * unguarded caller (the command timer) holds only what on_intention checked would fit, so the
 * clamp is unreachable and, were it reached, could only lose energy. */
static void commit_into(struct canergy_client *c, uint16_t amount_mj)
{
    const uint64_t usable = (uint64_t)c->rec.usable_uj + (uint64_t)amount_mj * MJ;
    CANERGY_ASSERT(usable <= CANERGY_USABLE_MAX_UJ); /* refused when held or commanded */
    c->rec.usable_uj = usable > CANERGY_USABLE_MAX_UJ ? CANERGY_USABLE_MAX_UJ : (uint32_t)usable;
    c->rec.credited_mj += amount_mj;
}

/* -- the cells ---------------------------------------------------------------------------- */

static bool witnessed(const struct canergy_client *c)
{
    return rules_witnessed(c->rules);
}

/* A transaction d ahead of ltx (serial16 of its wire tx) at or beyond CANERGY_COUNTER_END
 * (Python's _beyond_end). */
static bool beyond_end(const struct canergy_client *c, int32_t d)
{
    return d > 0 && c->rec.last_tx + (uint32_t)d >= CANERGY_COUNTER_END;
}

/* INTENTION(k, a, Gs). Worked out before anything changes: Gs may pay back more than usable can
 * hold, and then nothing at all happens (Python's overflow refusal); usable is summed in 64
 * bits. */
static void on_intention(struct canergy_client *c, const struct canergy_msg *m, uint64_t now,
                         struct canergy_out *out)
{
    const int32_t d = serial16(m->tx, c->rec.last_tx); /* every rule below reads this ltx */
    const bool unknown = (c->rec.flags & CANERGY_RECORD_CREDITED_UNKNOWN) != 0U;
    /* Rc unknown: a frame at or below ltx is of the node's earlier life. witnessed.on_intention:
     * Gs pays back only from a fresh intention (k > ltx); one at or below ltx may be of a
     * supervisor history a SYNC discarded, its Gs held by nobody (a duplicate: the recorded
     * reply). So under the witnessed rules only k > ltx goes on. */
    if (d <= 0 && (unknown || witnessed(c))) {
        if (d == 0 && !unknown) {
            reply_for(c, c->rec.last_tx, c->rec.outcome, out);
        }
        return;
    }
    if (beyond_end(c, d)) {
        return; /* no supervisor sends one: it would move ltx to the end of the numbering */
    }
    if (unknown) {
        c->rec.credited_mj = m->delivered_mj; /* admitted without books: Rc = Gs, no pay-back */
        c->rec.flags &= (uint8_t)~CANERGY_RECORD_CREDITED_UNKNOWN;
    }
    /* pay back what the supervisor wrote off but this node never got */
    const int32_t gs = serial24(m->delivered_mj, c->rec.credited_mj);
    const uint32_t paid_mj = gs > 0 ? (uint32_t)gs : 0U;
    const uint64_t usable = c->rec.usable_uj + (uint64_t)paid_mj * MJ;
    const uint32_t tx = c->rec.last_tx + (uint32_t)d;
    /* held after the step: this intention, unless it is held already (a hold below tx is
     * dropped when everything below tx is settled); nothing else changes the hold */
    const bool hold = d > 0 && !(c->phase == CANERGY_HOLDING && c->held_tx == tx);
    const uint16_t held_mj = hold ? m->amount_mj : c->held_amount_mj; /* 0 when none */
    if (usable + (uint64_t)held_mj * MJ > CANERGY_USABLE_MAX_UJ) {
        out->events |= CANERGY_EV_REFUSED; /* left unanswered: re-sent, written off, paid later */
        return;
    }
    c->rec.usable_uj = (uint32_t)usable;
    c->rec.credited_mj += paid_mj;
    if (paid_mj != 0U) {
        out->events |= CANERGY_EV_CREDITED;
    }
    if (d > 1) { /* everything below tx is settled by the supervisor */
        c->rec.last_tx = tx - 1U;
        c->rec.outcome = CANERGY_OUTCOME_SETTLED;
        if (c->phase == CANERGY_HOLDING && serial_before(c->held_tx, tx)) {
            drop_hold(c);
        }
    }
    if (hold) {
        c->phase = CANERGY_HOLDING;
        c->held_tx = tx;
        c->held_amount_mj = m->amount_mj;
        c->deadline = serial_after(now, c->command_timeout_us);
    }
    CANERGY_ASSERT(c->phase != CANERGY_HOLDING ||
                   (uint32_t)(c->held_tx - c->rec.last_tx) - 1U < 0x7FFFUL); /* 1..32767 */
    if (d > 0) {
        send(c, CANERGY_ACK, m->tx, 0U, out);
    } else if (d == 0) {
        reply_for(c, tx, c->rec.outcome, out); /* a duplicate: the recorded reply */
    }
}

static void on_command(struct canergy_client *c, const struct canergy_msg *m,
                       struct canergy_out *out)
{
    const int32_t d = serial16(m->tx, c->rec.last_tx);
#ifdef CANERGY_BREAK_REPEATED_TX
    /* Deliberately broken (tests only): a repeated COMMIT is applied again. */
    if (d == 0 && m->type == CANERGY_COMMIT) {
        commit_into(c, m->amount_mj);
    }
#endif
    if (d == 0) {
        reply_for(c, c->rec.last_tx, c->rec.outcome, out); /* late ABORT after a commit too */
        return;
    }
    if (d < 0 || beyond_end(c, d)) {
        return;
    }
    const uint32_t tx = c->rec.last_tx + (uint32_t)d;
    const bool abort = m->type == CANERGY_ABORT;
    if (!abort) {
        if ((uint64_t)c->rec.usable_uj + (uint64_t)m->amount_mj * MJ > CANERGY_USABLE_MAX_UJ) {
            out->events |= CANERGY_EV_REFUSED; /* never acknowledged so */
            return;
        }
        commit_into(c, m->amount_mj);
    }
    const uint8_t outcome = abort ? CANERGY_OUTCOME_ABORTED : CANERGY_OUTCOME_COMMITTED;
    resolved(c, tx, outcome);
    out->events |= abort ? CANERGY_EV_ABORTED : CANERGY_EV_COMMITTED;
    reply_for(c, tx, outcome, out); /* ABORTED or COMMITTED */
}

static void on_return_ack(struct canergy_client *c, const struct canergy_msg *m,
                          struct canergy_out *out)
{
    if (m->seq != (uint16_t)c->rec.return_seq || c->rec.return_pending_uj == 0U) {
        return; /* another return's number */
    }
#ifdef CANERGY_WITNESSED
    if ((c->rec.flags & CANERGY_RECORD_PENDING_DRAW) != 0U) {
        c->rec.spent_uj += c->rec.return_pending_uj; /* the actuator gets the draw now */
        c->rec.flags &= (uint8_t)~CANERGY_RECORD_PENDING_DRAW;
        out->events |= CANERGY_EV_RELEASED;
    }
#endif
    c->rec.return_pending_uj = 0U;
    c->return_deadline = CANERGY_NEVER;
    out->events |= CANERGY_EV_RETURN_ACKED;
}

static void on_admit(struct canergy_client *c, const struct canergy_msg *m,
                     struct canergy_out *out)
{
    if (m->nonce != c->nonce) {
        return; /* an answer to another start */
    }
    memset(&c->rec, 0, sizeof c->rec);
    c->rec.last_tx = m->tx; /* every frame of the earlier life is at or below these counters */
    c->rec.outcome = CANERGY_OUTCOME_SETTLED;
    c->rec.return_seq = m->seq;
    c->rec.flags = CANERGY_RECORD_CREDITED_UNKNOWN;
    c->nonce = 0U;
    c->return_deadline = CANERGY_NEVER;
    drop_hold(c);
    out->events |= CANERGY_EV_ADMITTED;
}

#ifdef CANERGY_WITNESSED
/* DEBIT: the pending draw (DRAW(q, x)), or with start the node's RESUME(n, q, pending). */
static void send_debit(const struct canergy_client *c, bool start, struct canergy_out *out)
{
    const bool draw = (c->rec.flags & CANERGY_RECORD_PENDING_DRAW) != 0U;
    const uint32_t fields[4] = {
        start ? c->nonce : 0U,
        (start ? CANERGY_DEBIT_START : 0U) | (draw ? CANERGY_DEBIT_DRAW : 0U),
        (uint16_t)c->rec.return_seq,
        (uint16_t)(c->rec.return_pending_uj / MJ),
    }; /* DEBIT: nonce, flags, seq, amount */
    canergy_internal_send(c, CANERGY_DEBIT, fields, out);
}

/* The answer to SYNC(n) (witnessed.answer_of): the books (n, Rc: 24 bits; after an admission
 * until a fresh intention, the floor kept when found behind, a known 0 kept as 2^24 mJ; without
 * one (0) Rc unknown: flagged, both fields 0), then the counts (n, q, ltx; afresh until that
 * fresh intention). */
static void send_sync_answer(const struct canergy_client *c, struct canergy_out *out)
{
    const bool unknown =
        (c->rec.flags & CANERGY_RECORD_CREDITED_UNKNOWN) != 0U && c->rec.credited_mj == 0U;
    uint32_t fields[4] = {
        c->nonce,
        CANERGY_DEBIT_BOOKS | (unknown ? CANERGY_DEBIT_RC_UNKNOWN : 0U),
        unknown ? 0U : (uint16_t)c->rec.credited_mj,
        unknown ? 0U : (c->rec.credited_mj >> 16) & 0xFFU,
    }; /* DEBIT: nonce, flags, seq, amount */
    canergy_internal_send(c, CANERGY_DEBIT, fields, out);
    /* afresh while Rc is unknown or a floor: CREDITED_UNKNOWN (0x01) moved to RC_UNKNOWN (0x10) */
    fields[1] = CANERGY_DEBIT_COUNTS | (c->rec.flags & CANERGY_RECORD_CREDITED_UNKNOWN) << 4U;
    fields[2] = (uint16_t)c->rec.return_seq;
    fields[3] = (uint16_t)c->rec.last_tx;
    canergy_internal_send(c, CANERGY_DEBIT, fields, out);
}

/* SYNC(n) (witnessed.answer_sync): the supervisor started, maybe from an older copy. Settle
 * the next B transactions (none of a discarded history can be above), drop the held intention,
 * answer with the books and the counts; nothing moves until ADMIT(n ^ SYNC_CONFIRMED). A
 * pending debit stays pending: dropped on that ADMIT, never credited. An ADMIT with
 * SYNC_CONFIRMED set is ignored: taking the confirmation of earlier counts as a SYNC looped. */
static void answer_sync(struct canergy_client *c, uint16_t nonce, uint64_t now,
                        struct canergy_out *out)
{
    if ((nonce & CANERGY_SYNC_CONFIRMED) != 0U) {
        return; /* no SYNC (its nonce has the bit clear): maybe a confirmation of earlier counts */
    }
    c->rec.last_tx = serial_capped(c->rec.last_tx + c->window);
    c->rec.outcome = CANERGY_OUTCOME_SETTLED;
    wait_for_admit(c, CANERGY_SYNCING, nonce, now, out);
}

/* ADMIT(n, k, Q) answering this start (witnessed.on_confirm): Q = q + 1 confirms the books
 * (settled up to k, the pending debit settled: a return credited, a draw dropped unreleased); a
 * larger Q finds them behind: admitted afresh at k and Q, what the actuator used still
 * counted; a smaller one changes nothing. A RESUME confirmed with k below ltx (the node settled
 * ahead for a SYNC whose counts never arrived) is followed by the counts under its nonce
 * (witnessed.resync): SYNCING until ADMIT(n ^ SYNC_CONFIRMED) has the supervisor's tx and W
 * caught up. */
static void on_confirm(struct canergy_client *c, const struct canergy_msg *m, uint64_t now,
                       struct canergy_out *out)
{
    const int32_t d = serial16(m->seq, c->rec.return_seq);
    if (d < 1) {
        return;
    }
    const uint32_t q = c->rec.return_seq + (uint32_t)d; /* Q: the supervisor's count */
    if (q >= CANERGY_COUNTER_BOUND) {
        return; /* no supervisor confirms a number there (serial_capped) */
    }
    bool behind_ltx = false;
    if (d == 1) {
        const int32_t closed = serial16(m->tx, c->rec.last_tx);
        behind_ltx = closed < 0 && c->phase == CANERGY_RESUMING;
        if (closed > 0) { /* resolved by the supervisor: never again by this record */
            c->rec.last_tx += (uint32_t)closed;
            c->rec.outcome = CANERGY_OUTCOME_SETTLED;
        }
        c->rec.flags &= (uint8_t)~CANERGY_RECORD_PENDING_DRAW;
    } else { /* a record as after JOIN, but spent kept and Rc kept as the books' floor */
        if (c->rec.credited_mj == 0U && (c->rec.flags & CANERGY_RECORD_CREDITED_UNKNOWN) == 0U) {
            c->rec.credited_mj = CANERGY_ZERO_FLOOR_MJ; /* witnessed.floor_of: not "unknown" */
        }
        c->rec.usable_uj = 0U;
        c->rec.last_tx = m->tx;
        c->rec.outcome = CANERGY_OUTCOME_SETTLED;
        c->rec.flags = CANERGY_RECORD_CREDITED_UNKNOWN;
    }
    c->rec.return_pending_uj = 0U;
    c->rec.return_seq = q;
    c->nonce = behind_ltx ? c->nonce : 0U;
    c->return_deadline = CANERGY_NEVER;
    drop_hold(c);
    if (behind_ltx) { /* the start goes on: nothing moves until the counts are confirmed */
        wait_for_admit(c, CANERGY_SYNCING, c->nonce, now, out);
        return;
    }
    out->events |= CANERGY_EV_ADMITTED;
}

/* ADMIT while a start waits (witnessed.on_start_answer): the answer to it (a SYNC's answer is
 * confirmed with CANERGY_SYNC_CONFIRMED flipped), the same SYNC again (answered again), or
 * another nonce: a supervisor's SYNC. */
static void on_start_answer(struct canergy_client *c, const struct canergy_msg *m, uint64_t now,
                            struct canergy_out *out)
{
    const bool syncing = c->phase == CANERGY_SYNCING;
    const uint16_t expected =
        (uint16_t)(syncing ? (uint32_t)c->nonce ^ CANERGY_SYNC_CONFIRMED : c->nonce);
    if (m->nonce == expected) {
        on_confirm(c, m, now, out);
    } else if (syncing && m->nonce == c->nonce) {
        send_sync_answer(c, out);
    } else {
        answer_sync(c, m->nonce, now, out);
    }
}

/* The power-loss cell from the books (or RESUMING): lose the hold, RESUME(n, q, pending). */
static void resume(struct canergy_client *c, uint16_t nonce, uint64_t now,
                   struct canergy_out *out)
{
    wait_for_admit(c, CANERGY_RESUMING, nonce, now, out);
}
#endif

/* The frame of a start waiting for its ADMIT (JOIN, RESUME, the SYNC's answer); false when no
 * start waits. */
static bool send_start(const struct canergy_client *c, struct canergy_out *out)
{
    if (c->phase == CANERGY_JOINING) {
        send(c, CANERGY_JOIN, c->nonce, 0U, out);
#ifdef CANERGY_WITNESSED
    } else if (c->phase == CANERGY_RESUMING) {
        send_debit(c, true, out);
    } else if (c->phase == CANERGY_SYNCING) {
        send_sync_answer(c, out);
#endif
    } else {
        return false;
    }
    return true;
}

/* The pending debit's frame: its DRAW (witnessed) or its RETURN. */
static void send_pending(const struct canergy_client *c, struct canergy_out *out)
{
#ifdef CANERGY_WITNESSED
    if ((c->rec.flags & CANERGY_RECORD_PENDING_DRAW) != 0U) {
        send_debit(c, false, out);
        return;
    }
#endif
    send(c, CANERGY_RETURN, (uint16_t)c->rec.return_seq,
         (uint16_t)(c->rec.return_pending_uj / MJ), out);
}

static void rx_message(struct canergy_client *c, const struct canergy_msg *m, uint64_t now,
                       struct canergy_out *out)
{
    if (c->phase >= CANERGY_JOINING) { /* a start waits: JOINING, RESUMING or SYNCING */
        if (m->type == CANERGY_INTENTION) {
            (void)send_start(c, out); /* moves nothing; the start's frame again at once */
        } else if (m->type == CANERGY_ADMIT) {
#ifdef CANERGY_WITNESSED
            if (c->phase != CANERGY_JOINING) {
                on_start_answer(c, m, now, out);
                return;
            }
#endif
            on_admit(c, m, out);
        }
        return; /* everything else is ignored */
    }
#ifdef CANERGY_WITNESSED
    if (witnessed(c) && m->type == CANERGY_ADMIT) {
        answer_sync(c, m->nonce, now, out); /* with books, an ADMIT is a supervisor's SYNC */
        return;
    }
#endif
    switch (m->type) {
    case CANERGY_INTENTION: on_intention(c, m, now, out); break;
    case CANERGY_COMMIT: /* fall through */
    case CANERGY_ABORT: on_command(c, m, out); break;
    case CANERGY_RETURN_ACK: on_return_ack(c, m, out); break;
    default: break; /* ADMIT with books, the paper's messages: ignored */
    }
}

static void command_timer(struct canergy_client *c, uint64_t now, struct canergy_out *out)
{
    if (c->phase != CANERGY_HOLDING || c->deadline > now) {
        return;
    }
    const uint32_t tx = c->held_tx;
    commit_into(c, c->held_amount_mj); /* safe: the intention's id never changes */
    resolved(c, tx, CANERGY_OUTCOME_COMMITTED);
    canergy_internal_repack(c, out); /* changed for certain: ltx moved up to the held tx */
    out->events |= CANERGY_EV_TIMEOUT_COMMIT;
    send(c, CANERGY_COMMITTED, (uint16_t)tx, 0U, out);
}

/* JOIN, RESUME, the SYNC's answer or the pending debit again; the same number until acked. */
static void return_timer(struct canergy_client *c, uint64_t now, struct canergy_out *out)
{
    if (c->return_deadline > now) {
        return;
    }
    if (send_start(c, out)) {
    } else if (c->rec.return_pending_uj != 0U) { /* a draw pending is an amount pending */
        send_pending(c, out);
    } else {
        return;
    }
    c->return_deadline = serial_after(now, c->return_retry_us);
}

static void restart(struct canergy_client *c, uint16_t nonce, uint64_t now,
                    struct canergy_out *out)
{
    if (c->phase == CANERGY_JOINING) {
        c->return_deadline = now; /* still no record: JOIN again at once */
        return;
    }
#ifdef CANERGY_WITNESSED
    if (witnessed(c)) {
        resume(c, nonce, now, out); /* a power loss or an older copy: the node cannot tell */
        return;
    }
#endif
    (void)nonce;
    (void)out;
    drop_hold(c);
    c->return_deadline = c->rec.return_pending_uj != 0U ? now : CANERGY_NEVER;
}

static void join(struct canergy_client *c, uint16_t nonce, uint64_t now, struct canergy_out *out)
{
    memset(&c->rec, 0, sizeof c->rec);
    wait_for_admit(c, CANERGY_JOINING, nonce, now, out);
}

/* -- entry points: each clears *out, or appends for the node layer ------------------------ */

static bool client_ok(const struct canergy_client *c, const struct canergy_out *out)
{
    return c != NULL && out != NULL;
}

static int message_step(struct canergy_client *c, const struct canergy_msg *m, uint64_t now,
                        struct canergy_out *out)
{
    if (m->node != c->node) {
        return CANERGY_RX_OTHER_NODE;
    }
    uint8_t before[CANERGY_NV_RECORD_SIZE];
    canergy_record_pack(&c->rec, before);
    rx_message(c, m, now, out);
    persist_if_changed(c, before, out);
    return CANERGY_DECODE_OK;
}

int canergy_internal_frame(struct canergy_client *c, const struct canergy_rx_frame *frame,
                           uint64_t now, struct canergy_out *out, struct canergy_msg *m)
{
    const enum canergy_decode_status status =
        canergy_internal_decode(c->id_base, frame, CANERGY_TO_CLIENT, m);
    if (status != CANERGY_DECODE_OK) {
        return (int)status;
    }
    return message_step(c, m, now, out);
}

int canergy_client_on_frame(struct canergy_client *c, const struct canergy_rx_frame *frame,
                            uint64_t now, struct canergy_out *out)
{
    if (!client_ok(c, out)) {
        return CANERGY_ERR_ARGUMENT;
    }
    canergy_internal_out_clear(out);
    struct canergy_msg m;
    return canergy_internal_frame(c, frame, now, out, &m);
}

/* The command timer persists what it commits; the return timer only re-sends (no record
 * changes). */
void canergy_internal_timers(struct canergy_client *c, uint64_t now, struct canergy_out *out)
{
    command_timer(c, now, out);
    return_timer(c, now, out);
}

void canergy_client_on_timer(struct canergy_client *c, uint64_t now, struct canergy_out *out)
{
    if (client_ok(c, out)) {
        canergy_internal_out_clear(out);
        canergy_internal_timers(c, now, out);
    }
}

void canergy_client_command_timer(struct canergy_client *c, uint64_t now, struct canergy_out *out)
{
    if (client_ok(c, out)) {
        canergy_internal_out_clear(out);
        command_timer(c, now, out);
    }
}

void canergy_client_return_timer(struct canergy_client *c, uint64_t now, struct canergy_out *out)
{
    if (client_ok(c, out)) {
        canergy_internal_out_clear(out);
        return_timer(c, now, out);
    }
}

uint64_t canergy_client_deadline(const struct canergy_client *c)
{
    return c != NULL ? canergy_internal_deadline(c) : CANERGY_NEVER;
}

int canergy_internal_spend(struct canergy_client *c, uint32_t uj, struct canergy_out *out)
{
    if (c->phase == CANERGY_JOINING || witnessed(c)) {
        return CANERGY_ERR_PHASE; /* witnessed: only through a draw */
    }
    if (uj == 0U || uj > c->rec.usable_uj) {
        return CANERGY_ERR_AMOUNT;
    }
    c->rec.usable_uj -= uj;
    c->rec.spent_uj += uj;
    canergy_internal_repack(c, out);
    return CANERGY_OK;
}

int canergy_client_spend(struct canergy_client *c, uint32_t uj, struct canergy_out *out)
{
    if (!client_ok(c, out)) {
        return CANERGY_ERR_ARGUMENT;
    }
    canergy_internal_out_clear(out);
    return canergy_internal_spend(c, uj, out);
}

/* One numbered debit at a time, none numbered at the end, none before admission; witnessed
 * (witnessed.can_debit), none while a start awaits its ADMIT either: the hardened rules have no
 * phase beyond JOINING, so IDLE or HOLDING says both. */
bool canergy_client_can_give_back(const struct canergy_client *c)
{
    return c != NULL && c->rec.return_pending_uj == 0U && c->phase <= CANERGY_HOLDING &&
           c->rec.return_seq < CANERGY_COUNTER_END - 1U;
}

bool canergy_client_can_draw(const struct canergy_client *c)
{
#ifdef CANERGY_WITNESSED
    if (c != NULL && witnessed(c)) {
        return canergy_client_can_give_back(c);
    }
#endif
    return c != NULL && c->phase != CANERGY_JOINING;
}

/* Debit uj as the next numbered RETURN, or (witnessed) DRAW: persisted before it leaves. */
int canergy_internal_debit(struct canergy_client *c, uint32_t uj, uint64_t now, uint8_t draw,
                           struct canergy_out *out)
{
    if (!canergy_client_can_give_back(c)) {
        return CANERGY_ERR_PHASE; /* one numbered debit at a time, none before admission */
    }
    if (uj == 0U || uj % MJ != 0U || uj > RETURN_MAX_UJ || uj > c->rec.usable_uj) {
        return CANERGY_ERR_AMOUNT;
    }
    c->rec.usable_uj -= uj; /* debited first: the RETURN may be duplicated, never credited twice */
    c->rec.return_seq++;
    c->rec.return_pending_uj = uj;
    c->rec.flags |= draw;
    c->return_deadline = serial_after(now, c->return_retry_us);
    canergy_internal_repack(c, out);
    send_pending(c, out);
    return CANERGY_OK;
}

int canergy_internal_draw(struct canergy_client *c, uint32_t uj, uint64_t now,
                          struct canergy_out *out)
{
#ifdef CANERGY_WITNESSED
    if (witnessed(c)) {
        return canergy_internal_debit(c, uj, now, CANERGY_RECORD_PENDING_DRAW, out);
    }
#endif
    (void)now;
    return canergy_internal_spend(c, uj, out);
}

int canergy_client_draw(struct canergy_client *c, uint32_t uj, uint64_t now,
                        struct canergy_out *out)
{
    if (!client_ok(c, out)) {
        return CANERGY_ERR_ARGUMENT;
    }
    canergy_internal_out_clear(out);
    return canergy_internal_draw(c, uj, now, out);
}

int canergy_client_give_back(struct canergy_client *c, uint32_t uj, uint64_t now,
                             struct canergy_out *out)
{
    if (!client_ok(c, out)) {
        return CANERGY_ERR_ARGUMENT;
    }
    canergy_internal_out_clear(out);
    return canergy_internal_debit(c, uj, now, 0U, out);
}

bool canergy_client_joining(const struct canergy_client *c)
{
    return c != NULL && c->phase == CANERGY_JOINING;
}

uint32_t canergy_client_usable(const struct canergy_client *c)
{
    return c != NULL ? c->rec.usable_uj : 0U;
}

void canergy_client_restart(struct canergy_client *c, uint64_t now, struct canergy_out *out)
{
    canergy_client_resume(c, 0U, now, out);
}

void canergy_client_resume(struct canergy_client *c, uint16_t nonce, uint64_t now,
                           struct canergy_out *out)
{
    if (client_ok(c, out)) {
        canergy_internal_out_clear(out);
        restart(c, nonce, now, out); /* the record is unchanged: nothing to persist */
    }
}

void canergy_client_join(struct canergy_client *c, uint16_t nonce, uint64_t now,
                         struct canergy_out *out)
{
    if (client_ok(c, out)) {
        canergy_internal_out_clear(out);
        join(c, nonce, now, out);
    }
}

static bool config_ok(const struct canergy_client_config *cfg)
{
    return canergy_id_base_valid(cfg->id_base) && cfg->node >= CANERGY_MIN_NODE &&
           cfg->node <= CANERGY_MAX_NODE && rules_kept(cfg->rules) &&
           cfg->window <= CANERGY_WINDOW_MAX;
}

int canergy_internal_start(struct canergy_client *c, const struct canergy_client_config *cfg,
                           const uint8_t *nv_image, size_t nv_len, uint16_t nonce, uint64_t now,
                           struct canergy_out *out)
{
    if (cfg == NULL || !config_ok(cfg)) {
        return CANERGY_ERR_ARGUMENT;
    }
    memset(c, 0, sizeof *c);
    c->id_base = cfg->id_base;
    c->node = cfg->node;
    c->command_timeout_us = cfg->command_timeout_us;
    c->return_retry_us = cfg->return_retry_us;
    c->rules = cfg->rules;
    c->window = cfg->window != 0U ? cfg->window : (uint16_t)CANERGY_DEFAULT_WINDOW;
    struct canergy_nv_state nv;
    canergy_nv_load(nv_image, nv_len, &nv);
    c->nv_counter = nv.counter;
    c->nv_slot = nv.newest_slot;
    const bool draw_pending = (nv.record.flags & CANERGY_RECORD_PENDING_DRAW) != 0U;
    if (nv.books && draw_pending && !witnessed(c)) {
        nv.books = false; /* the witnessed rules' record: not books for these rules */
        nv.fallbacks++;
    }
    /* Both arm the deadlines (drop_hold, the return timer). */
    if (nv.books) {
        c->rec = nv.record;
        restart(c, nonce, now, out); /* every start is a restart from the record */
    } else {
        join(c, nonce, now, out); /* new, wiped or corrupted: trust nothing of the past */
    }
    return (int)nv.fallbacks;
}

int canergy_client_start(struct canergy_client *c, const struct canergy_client_config *cfg,
                         const uint8_t *nv_image, size_t nv_len, uint16_t nonce, uint64_t now,
                         struct canergy_out *out)
{
    if (!client_ok(c, out)) {
        return CANERGY_ERR_ARGUMENT;
    }
    canergy_internal_out_clear(out);
    return canergy_internal_start(c, cfg, nv_image, nv_len, nonce, now, out);
}
