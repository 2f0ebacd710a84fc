/*
 * The hardened supervisor's rules for one node: src/canergy/core/hardened.py's SUPERVISOR
 * table, cell for cell (canergy/session.h). A cell the table does not list for a phase leaves
 * the record as it is (messages, timers) or refuses (local requests).
 */
#include "canergy/session.h"

#include "rules.h"
#include "serial.h"

#include <string.h>

#define MJ CANERGY_QUANTUM_UJ
#define AMOUNT_MAX_UJ (CANERGY_AMOUNT_MAX_MJ * CANERGY_QUANTUM_UJ)

static void step_clear(struct canergy_session_step *step)
{
    memset(step, 0, sizeof *step);
}

#ifdef CANERGY_WITNESSED
/* Counts answering a SYNC, afresh or not (Debit.is_counts). */
static bool is_counts(uint8_t flags)
{
    return (flags & (uint8_t)~CANERGY_DEBIT_RC_UNKNOWN) == CANERGY_DEBIT_COUNTS;
}
#endif

static bool open_phase(const struct canergy_session *s)
{
    return s->phase == CANERGY_S_WAIT_ACK || s->phase == CANERGY_S_ACKED ||
           s->phase == CANERGY_S_WAIT_CONFIRM;
}

static void put_msg(const struct canergy_session *s, uint8_t type,
                    struct canergy_session_step *step)
{
    step->send = 1U;
    step->msg.type = type;
    step->msg.node = s->node;
    step->msg.tx = (uint16_t)(s->tx & 0xFFFFUL);
}

/* INTENTION(tx, Ts, Gs mod 2^24) or COMMIT/ABORT(tx, Ts) as the record stands. */
static void send_intention(const struct canergy_session *s, struct canergy_session_step *step)
{
    put_msg(s, CANERGY_INTENTION, step);
    step->msg.amount_mj = (uint16_t)(s->reserved_uj / MJ);
    step->msg.delivered_mj = (uint32_t)((s->delivered_uj / MJ) & CANERGY_WIDE_MAX);
}

static void send_command(const struct canergy_session *s, struct canergy_session_step *step)
{
    const bool abort = s->decision == CANERGY_DECIDE_ABORT;
    put_msg(s, abort ? CANERGY_ABORT : CANERGY_COMMIT, step);
    step->msg.amount_mj = (uint16_t)(s->reserved_uj / MJ);
}

/* Close the open transaction: an abort credits Ts back to Us, anything else delivers it. */
static void resolve(struct canergy_session *s, uint8_t how, struct canergy_session_step *step)
{
    CANERGY_ASSERT(open_phase(s) && s->reserved_uj > 0U && s->reserved_uj <= AMOUNT_MAX_UJ);
    if (how == CANERGY_RESOLVED_ABORTED) {
        step->credit_uj += (int64_t)s->reserved_uj;
    } else {
        s->delivered_uj += s->reserved_uj;
    }
    s->phase = CANERGY_S_IDLE;
    s->reserved_uj = 0U;
    s->decision = CANERGY_DECIDE_NONE;
    s->tries = 0U;
    s->deadline = CANERGY_NEVER;
    step->resolved = how;
}

static bool other_tx(const struct canergy_session *s, uint16_t wire)
{
    return serial16(wire, s->tx) != 0;
}

bool canergy_session_syncing(const struct canergy_session *s)
{
    return s->phase == CANERGY_S_SYNCING || s->phase == CANERGY_S_SYNC_BOOKS;
}

#ifdef CANERGY_WITNESSED
static uint32_t window_of(const struct canergy_session_timing *t)
{
    return t->window != 0U ? t->window : CANERGY_DEFAULT_WINDOW;
}

/* An answer naming transaction k was taken (witnessed._witnessed): W moves up to k. */
static void witness_up(struct canergy_session *s, const struct canergy_session_timing *t,
                       int64_t k)
{
    if (rules_witnessed(t->rules) && k > s->witness) {
        s->witness = (int32_t)k; /* a transaction number: below CANERGY_COUNTER_BOUND */
    }
}

/* A SYNC's ltx (16 bits on the wire) widened against tx, as Python's unwrap (may be below 0
 * for a node claiming less than nothing: then it moves nothing), held below
 * CANERGY_COUNTER_BOUND as witnessed.ltx_of: counts repeated without a key walked tx past the
 * bound, W (int32) negative at 2^31 and tx back to 0 at 2^32. */
static int64_t settled_of(const struct canergy_session *s, uint16_t wire)
{
    const int64_t settled = (int64_t)s->tx + serial16(wire, s->tx);
    return settled < (int64_t)CANERGY_COUNTER_BOUND - 1 ? settled
                                                       : (int64_t)CANERGY_COUNTER_BOUND - 1;
}
#endif

void canergy_session_init(struct canergy_session *s, uint8_t node)
{
    memset(s, 0, sizeof *s);
    s->node = node;
    s->deadline = CANERGY_NEVER;
}

int canergy_session_begin(struct canergy_session *s, const struct canergy_session_timing *t,
                          uint32_t amount_uj, uint64_t now, struct canergy_session_step *step)
{
    step_clear(step);
    if (s->phase != CANERGY_S_IDLE) {
        return CANERGY_ERR_PHASE;
    }
#ifdef CANERGY_WITNESSED
    if (rules_witnessed(t->rules) &&
        (int64_t)s->tx + 1 > (int64_t)s->witness + (int64_t)window_of(t)) {
        return CANERGY_ERR_WINDOW; /* witnessed.begin: only within the window k <= W + B */
    }
#endif
    if (amount_uj == 0U || amount_uj % MJ != 0U || amount_uj > AMOUNT_MAX_UJ) {
        return CANERGY_ERR_AMOUNT;
    }
    if (s->tx >= CANERGY_COUNTER_END - 1U) {
        return CANERGY_ERR_END;
    }
    CANERGY_ASSERT(s->reserved_uj == 0U);
    s->phase = CANERGY_S_WAIT_ACK;
    s->tx += 1U;
    s->reserved_uj = amount_uj;
    s->decision = CANERGY_DECIDE_NONE;
    s->tries = 1U;
    s->deadline = serial_after(now, t->response_timeout_us);
    send_intention(s, step);
    step->credit_uj = -(int64_t)amount_uj;
    return CANERGY_OK;
}

int canergy_session_decide(struct canergy_session *s, const struct canergy_session_timing *t,
                           bool commit, uint64_t now, struct canergy_session_step *step)
{
    step_clear(step);
    if (s->phase != CANERGY_S_ACKED) {
        return CANERGY_ERR_PHASE;
    }
    s->phase = CANERGY_S_WAIT_CONFIRM;
    s->decision = commit ? CANERGY_DECIDE_COMMIT : CANERGY_DECIDE_ABORT;
    s->tries = 1U;
    s->deadline = serial_after(now, t->response_timeout_us);
    send_command(s, step);
    return CANERGY_OK;
}

/* RETURN(q, x): credit x and acknowledge if q is the next number; re-acknowledge an old q;
 * ignore one beyond, and the next at the end of the numbering (CANERGY_COUNTER_END). */
static void credit_return(struct canergy_session *s, const struct canergy_msg *m,
                          struct canergy_session_step *step)
{
    const int32_t ahead = serial16(m->seq, s->returns_credited);
    if (ahead > 1 || (ahead == 1 && s->returns_credited >= CANERGY_COUNTER_END - 1U)) {
        return;
    }
    if (ahead == 1) {
        const uint32_t amount = (uint32_t)m->amount_mj * MJ;
        s->returns_credited += 1U;
        s->returned_uj += amount;
        step->credit_uj = (int64_t)amount;
    }
#ifdef CANERGY_BREAK_RETURN_AGAIN /* the broken build for tests/test_c_session.py: hazard (c) */
    if (ahead == 0) {
        s->returned_uj += (uint32_t)m->amount_mj * MJ;
        step->credit_uj = (int64_t)m->amount_mj * (int64_t)MJ;
    }
#endif
    step->send = 1U;
    step->msg.type = CANERGY_RETURN_ACK;
    step->msg.node = s->node;
    step->msg.seq = m->seq;
}

/* JOIN(n): write off what is open, lift both counters to one high half, ADMIT(n, tx, q). */
static void admit(struct canergy_session *s, const struct canergy_msg *m,
                  struct canergy_session_step *step)
{
    if (s->phase != CANERGY_S_IDLE) {
        resolve(s, CANERGY_RESOLVED_WRITTEN_OFF, step);
    }
    const uint32_t high_tx = s->tx >> 16;
    const uint32_t high_seq = s->returns_credited >> 16;
    const uint32_t high = high_tx > high_seq ? high_tx : high_seq;
    s->tx = (high << 16) | (s->tx & 0xFFFFUL);
    s->returns_credited = (high << 16) | (s->returns_credited & 0xFFFFUL);
    put_msg(s, CANERGY_ADMIT, step);
    step->msg.nonce = m->nonce;
    step->msg.seq = (uint16_t)(s->returns_credited & 0xFFFFUL);
    step->admitted = 1U;
}

#ifdef CANERGY_WITNESSED
static void ack_debit(const struct canergy_session *s, uint16_t seq,
                      struct canergy_session_step *step)
{
    step->send = 1U;
    step->msg.type = CANERGY_RETURN_ACK;
    step->msg.node = s->node;
    step->msg.seq = seq;
}

/* DRAW(q, x): hold q as the node's last debit and acknowledge it (nothing to Us); re-ack an old
 * q; ignore one beyond, and the next at the end of the numbering (witnessed.hold_draw). */
static void hold_draw(struct canergy_session *s, const struct canergy_msg *m,
                      struct canergy_session_step *step)
{
    const int32_t ahead = serial16(m->seq, s->returns_credited);
    if (ahead > 1 || (ahead == 1 && s->returns_credited >= CANERGY_COUNTER_END - 1U)) {
        return;
    }
    if (ahead == 1) {
        s->returns_credited += 1U;
    }
    ack_debit(s, m->seq, step);
}

/* ADMIT(n, k, C): k the last transaction closed (all are, once a RESUME is answered). */
static void confirmation(const struct canergy_session *s, uint16_t nonce,
                         struct canergy_session_step *step)
{
    put_msg(s, CANERGY_ADMIT, step);
    step->msg.tx = (uint16_t)((s->phase == CANERGY_S_IDLE ? s->tx : s->tx - 1U) & 0xFFFFUL);
    step->msg.nonce = nonce;
    step->msg.seq = (uint16_t)(s->returns_credited & 0xFFFFUL);
}

/* A node admitted without books (JOIN, or a RESUME found behind; witnessed.admitted_afresh):
 * the hardened admission; W stays where it is. The admission is no evidence of what the node
 * holds (its ADMIT may be lost, the JOIN or RESUME a late frame of an earlier start): W moved up
 * to tx let begins run past the node's ltx + B, and a supervisor image from before them created
 * energy. A lift past W + B closes the window until a re-sync (canergy_session_resync). */
static void admit_afresh(struct canergy_session *s, const struct canergy_msg *m,
                         struct canergy_session_step *step)
{
    admit(s, m, step);
}

/* JOIN(n) (witnessed.admit): the admission afresh, and the number after C voided as at a
 * RESUME, so that no debit number is issued by both a lost record and the node's new life; the
 * admission remembered (join_*). A JOIN with the nonce of the last one admitted (join_seq 0:
 * none) is a copy of it: the same ADMIT again (same n, k and C) and nothing moves, as if the
 * first ADMIT had been duplicated. Admitted afresh, it moved W up to a tx that begins had moved
 * on since, past the ltx of a node that took the first ADMIT and lost the second. */
static void admit_voiding(struct canergy_session *s, const struct canergy_msg *m,
                          struct canergy_session_step *step)
{
    if (s->join_seq != 0U && s->join_nonce == m->nonce) {
        put_msg(s, CANERGY_ADMIT, step);
        step->msg.tx = (uint16_t)(s->join_tx & 0xFFFFUL);
        step->msg.nonce = m->nonce;
        step->msg.seq = (uint16_t)(s->join_seq & 0xFFFFUL);
        return;
    }
    admit_afresh(s, m, step);
    s->returns_credited = serial_capped(s->returns_credited + 1U);
    step->msg.seq = (uint16_t)(s->returns_credited & 0xFFFFUL);
    s->join_nonce = m->nonce;
    s->join_tx = s->tx;
    s->join_seq = s->returns_credited;
}

/* RESUME(n, q, x) (witnessed.confirm): a repeat gets the same answer (resume_to 0: none answered
 * yet, as every answer voids a number above 0); behind (q below the last debit held): write off,
 * lift, admit; otherwise write off what is open and credit a pending RETURN numbered next (not at
 * the end of the numbering); then void max(C, q) + 1 and answer ADMIT(n, k, C). A SYNC's counts
 * (n, q, ltx) are taken the same way, with tx moved up to ltx (never back; W not: late counts
 * may be a record's the node no longer holds), no pending amount, and n ^ CANERGY_SYNC_CONFIRMED
 * in the answer; what the last answer remembers tells a RESUME from counts (bit 16 of
 * resume_nonce). Counts that repeat the last answered write off what is open and move tx up
 * to an ltx above it first (another start answering a copy of the same SYNC), and void C + 1
 * after the answer. */
static void confirm(struct canergy_session *s, const struct canergy_msg *m,
                    struct canergy_session_step *step)
{
    const bool counts = is_counts(m->flags);
    const uint32_t key = m->nonce | (counts ? 0x10000UL : 0UL);
    const uint16_t nonce =
        (uint16_t)(counts ? (uint32_t)m->nonce ^ CANERGY_SYNC_CONFIRMED : m->nonce);
    const int32_t d = serial16(m->seq, s->returns_credited);
    const uint32_t seq = s->returns_credited + (uint32_t)d;
    if (s->resume_to != 0U && s->resume_to == s->returns_credited && s->resume_nonce == key &&
        s->resume_from == seq) {
        /* counts again, from a later start that answered a copy of the same SYNC (maybe an
         * older image's, which may not hold what its earlier record took): what is open is
         * written off, tx moves up to their ltx when it is above, C and W stay */
        if (counts) {
            const int64_t settled = settled_of(s, m->amount_mj);
            if (s->phase != CANERGY_S_IDLE) {
                resolve(s, CANERGY_RESOLVED_WRITTEN_OFF, step);
            }
            if (settled > (int64_t)s->tx) {
                s->tx = (uint32_t)settled;
            }
            confirmation(s, nonce, step);
            /* a RETURN C + 1 of the record that adopted the first answer may be in flight */
            s->returns_credited = serial_capped(s->returns_credited + 1U);
            return;
        }
        confirmation(s, nonce, step);
        return;
    }
    const bool behind = d < 0;
    if (behind) {
        admit_afresh(s, m, step); /* the record lacks a debit held here: start afresh */
    } else {
        if (s->phase != CANERGY_S_IDLE) {
            resolve(s, CANERGY_RESOLVED_WRITTEN_OFF, step); /* the old record may not know */
        }
        const bool draw = (m->flags & CANERGY_DEBIT_DRAW) != 0U;
        const bool room = s->returns_credited < CANERGY_COUNTER_END - 1U;
        if (d == 1 && m->amount_mj != 0U && !draw && !counts && room) { /* the RETURN numbered q */
            const uint32_t amount = (uint32_t)m->amount_mj * MJ;
            s->returns_credited = seq;
            s->returned_uj += amount;
            step->credit_uj += (int64_t)amount;
        }
    }
    if (counts) { /* the node settled up to its ltx: no transaction begins at or below it */
        const int64_t settled = settled_of(s, m->amount_mj);
        if (settled > (int64_t)s->tx) {
            s->tx = (uint32_t)settled;
        }
    }
    const uint32_t last = behind ? s->returns_credited : seq; /* max(C, q) */
    s->returns_credited = serial_capped(last + 1U); /* voids a debit in flight from an old life */
    s->resume_nonce = key;
    s->resume_from = seq;
    s->resume_to = s->returns_credited;
    confirmation(s, nonce, step);
}

/* A SYNC's counts outside a start (witnessed.counts_taken): under the nonce of the last start
 * answered (resume_to 0: none), whatever their ltx; under another only with an ltx from tx to
 * tx + B (a node with books answering an ADMIT it took for a SYNC). Other counts are an earlier
 * start's: with a key they verify for the whole epoch, and their 16-bit ltx widened against a
 * tx moved on by more than 2^15 moved tx and W up to 2^15 - 1 ahead and wrote off what was
 * open, or found the node behind. */
static bool counts_taken(const struct canergy_session *s,
                         const struct canergy_session_timing *t, const struct canergy_msg *m)
{
    if (s->resume_to != 0U && (uint16_t)(s->resume_nonce & 0xFFFFUL) == m->nonce) {
        return true;
    }
    const int64_t settled = settled_of(s, m->amount_mj);
    return settled >= (int64_t)s->tx && settled <= (int64_t)s->tx + (int64_t)window_of(t);
}

/* SYNC(n, tx, C): an ADMIT the node did not ask for. */
static void send_sync(const struct canergy_session *s, struct canergy_session_step *step)
{
    put_msg(s, CANERGY_ADMIT, step);
    step->msg.nonce = s->sync_nonce;
    step->msg.seq = (uint16_t)(s->returns_credited & 0xFFFFUL);
}

/* Books answering a SYNC, Rc known or not (witnessed.Debit.is_books). */
static bool is_books(uint8_t flags)
{
    return (flags & (uint8_t)~CANERGY_DEBIT_RC_UNKNOWN) == CANERGY_DEBIT_BOOKS;
}

/* The SYNC's books (n, Rc) (witnessed.take_books): Gs moves up to Rc, the difference out of Us
 * (which may go below zero: a debt); then the counts are awaited. Books with Rc unknown leave
 * Gs as it is (that node holds nothing and takes its next fresh intention's Gs as its Rc), as
 * do books answering a re-sync (nothing restored: Gs holds what the node received). Anything
 * else is ignored. */
static void take_books(struct canergy_session *s, const struct canergy_msg *m,
                       struct canergy_session_step *step)
{
    if (m->nonce != s->sync_nonce || !is_books(m->flags)) {
        return;
    }
    if (m->flags != CANERGY_DEBIT_BOOKS || s->resync != 0U) { /* Rc unknown, or a re-sync */
        s->phase = CANERGY_S_SYNC_BOOKS;
        return;
    }
    const uint32_t credited = (uint32_t)m->seq | (uint32_t)m->amount_mj << 16;
    const int32_t gain = serial24(credited, (uint32_t)(s->delivered_uj / MJ));
    if (gain > 0) {
        s->delivered_uj += (uint64_t)(uint32_t)gain * MJ;
        step->credit_uj = -(int64_t)gain * (int64_t)MJ;
    }
    s->phase = CANERGY_S_SYNC_BOOKS;
}

/* The SYNC's counts (n, q, ltx) after its books (witnessed.take_counts): the start is over
 * (W = ltx), then as a RESUME; the books again are taken again; anything else is ignored.
 * Counts afresh (a node admitted afresh, no fresh intention since) with q above C + 1 show an
 * image older than that admission: the most its q - C - 1 debits since could draw
 * (CANERGY_AMOUNT_MAX_MJ each) moves from Us to Gs (witnessed.ahead_of_image), a loss where
 * the image would grant again what the node used. */
static void take_counts(struct canergy_session *s, const struct canergy_msg *m,
                        struct canergy_session_step *step)
{
    if (m->nonce != s->sync_nonce) {
        return;
    }
    if (is_books(m->flags)) {
        take_books(s, m, step);
        return;
    }
    if (!is_counts(m->flags)) {
        return;
    }
    const int32_t ahead = serial16(m->seq, s->returns_credited) - 1;
    if (m->flags == CANERGY_DEBIT_COUNTS_AFRESH && ahead > 0) {
        const uint64_t amount = (uint64_t)(uint32_t)ahead * CANERGY_AMOUNT_MAX_MJ * MJ;
        s->delivered_uj += amount;
        step->credit_uj -= (int64_t)amount;
        step->ahead_numbers = (uint16_t)ahead;
    }
    s->phase = CANERGY_S_IDLE;
    s->sync_nonce = 0U;
    s->deadline = CANERGY_NEVER;
    s->resync = 0U;
    s->witness = (int32_t)settled_of(s, m->amount_mj);
    confirm(s, m, step);
}

/* A start's waiting phases: the SYNC's answer, and nothing else, is taken. */
static void syncing_msg(struct canergy_session *s, const struct canergy_msg *m,
                        struct canergy_session_step *step)
{
    if (m->type == CANERGY_JOIN && s->resync != 0U) { /* witnessed.join_while_syncing */
        s->phase = CANERGY_S_IDLE; /* the re-sync ends; the JOIN is taken as in IDLE */
        s->sync_nonce = 0U;
        s->deadline = CANERGY_NEVER;
        s->resync = 0U;
        admit_voiding(s, m, step);
        return;
    }
    if (m->type != CANERGY_DEBIT) {
        return; /* a JOIN, a RETURN, an answer: no cell while a start waits */
    }
    if (s->phase == CANERGY_S_SYNCING) {
        take_books(s, m, step);
    } else {
        take_counts(s, m, step);
    }
}
#endif

void canergy_session_on_msg(struct canergy_session *s, const struct canergy_session_timing *t,
                            const struct canergy_msg *m, uint64_t now,
                            struct canergy_session_step *step)
{
    (void)t;
    (void)now;
    step_clear(step);
#ifdef CANERGY_WITNESSED
    if (canergy_session_syncing(s)) {
        if (rules_witnessed(t->rules)) {
            syncing_msg(s, m, step);
        }
        return;
    }
#endif
    switch (m->type) {
    case CANERGY_ACK:
        if (s->phase == CANERGY_S_WAIT_ACK && !other_tx(s, m->tx)) {
            s->phase = CANERGY_S_ACKED;
            s->deadline = CANERGY_NEVER;
            step->acknowledged = 1U;
#ifdef CANERGY_WITNESSED
            witness_up(s, t, (int64_t)s->tx - 1); /* the node has persisted tx - 1 */
#endif
        }
        break;
    case CANERGY_COMMITTED:
        if (open_phase(s) && !other_tx(s, m->tx)) {
            resolve(s, CANERGY_RESOLVED_COMMITTED, step);
#ifdef CANERGY_WITNESSED
            witness_up(s, t, s->tx);
#endif
        }
        break;
    case CANERGY_ABORTED: /* only after an abort decision: the one way back to Us */
        if (s->phase == CANERGY_S_WAIT_CONFIRM && !other_tx(s, m->tx) &&
            s->decision == CANERGY_DECIDE_ABORT) {
            resolve(s, CANERGY_RESOLVED_ABORTED, step);
#ifdef CANERGY_WITNESSED
            witness_up(s, t, s->tx);
#endif
        }
        break;
    case CANERGY_RETURN:
        credit_return(s, m, step);
        break;
    case CANERGY_JOIN:
#ifdef CANERGY_WITNESSED
        if (rules_witnessed(t->rules)) {
            admit_voiding(s, m, step);
            break;
        }
#endif
        admit(s, m, step);
        break;
#ifdef CANERGY_WITNESSED
    case CANERGY_DEBIT:
        if (!rules_witnessed(t->rules)) {
            break; /* the hardened rules have no cell for it */
        }
        if (is_books(m->flags)) {
            break; /* books outside a start: ignored */
        }
        if (is_counts(m->flags) && !counts_taken(s, t, m)) {
            break; /* an earlier start's counts (a replay verifies with a key): ignored */
        }
        if ((m->flags & CANERGY_DEBIT_START) != 0U) {
            confirm(s, m, step);
        } else {
            hold_draw(s, m, step);
        }
        break;
#endif
    default:
        break;
    }
}

void canergy_session_timer(struct canergy_session *s, const struct canergy_session_timing *t,
                           uint64_t now, struct canergy_session_step *step)
{
    step_clear(step);
#ifdef CANERGY_WITNESSED
    if (canergy_session_syncing(s)) { /* witnessed.resend_sync: the node may be off */
        if (s->deadline != CANERGY_NEVER && s->deadline <= now) {
            s->deadline = serial_after(now, t->response_timeout_us);
            send_sync(s, step);
        }
        return;
    }
#endif
    if (s->phase != CANERGY_S_WAIT_ACK && s->phase != CANERGY_S_WAIT_CONFIRM) {
        return;
    }
    if (s->deadline == CANERGY_NEVER || s->deadline > now) {
        return;
    }
    if (s->tries > t->retries) {
        resolve(s, CANERGY_RESOLVED_WRITTEN_OFF, step); /* the passivity timeout */
        return;
    }
    s->tries = (uint8_t)(s->tries + 1U);
    s->deadline = serial_after(now, t->response_timeout_us);
    if (s->phase == CANERGY_S_WAIT_ACK) {
        send_intention(s, step);
    } else {
        send_command(s, step);
    }
}

void canergy_session_restart(struct canergy_session *s, uint64_t now,
                             struct canergy_session_step *step)
{
    step_clear(step);
    if (s->phase == CANERGY_S_ACKED) {
        s->phase = CANERGY_S_WAIT_ACK;
    }
    s->tries = 0U;
    s->deadline = open_phase(s) ? now : CANERGY_NEVER;
}

#ifdef CANERGY_WITNESSED
/* The nonce of a start's or a re-sync's SYNC (witnessed.sync_nonce_for): SYNC_CONFIRMED clear,
 * and never the nonce of the last start answered (its lowest bit flipped then): counts under
 * it with the same q would read as a repeat of that answer. */
static uint16_t sync_nonce_for(const struct canergy_session *s, uint16_t nonce)
{
    uint16_t n = (uint16_t)(nonce & ~CANERGY_SYNC_CONFIRMED);
    if (s->resume_to != 0U && (uint16_t)(s->resume_nonce & 0xFFFFUL) == n) {
        n = (uint16_t)(n ^ 1U);
    }
    return n;
}
#endif

void canergy_session_start(struct canergy_session *s, const struct canergy_session_timing *t,
                           uint16_t nonce, uint64_t now, struct canergy_session_step *step)
{
#ifdef CANERGY_WITNESSED
    if (rules_witnessed(t->rules)) {
        step_clear(step);
        if (open_phase(s)) {
            resolve(s, CANERGY_RESOLVED_WRITTEN_OFF, step); /* the older copy may not know */
        }
        s->phase = CANERGY_S_SYNCING;
        s->sync_nonce = sync_nonce_for(s, nonce);
        s->deadline = now;
        s->resync = 0U;
        return;
    }
#endif
    (void)t;
    (void)nonce;
    canergy_session_restart(s, now, step);
}

int canergy_session_resync(struct canergy_session *s, const struct canergy_session_timing *t,
                           uint16_t nonce, uint64_t now, struct canergy_session_step *step)
{
    step_clear(step);
#ifdef CANERGY_WITNESSED
    if (rules_witnessed(t->rules) && s->phase == CANERGY_S_IDLE) {
        s->phase = CANERGY_S_SYNCING;
        s->sync_nonce = sync_nonce_for(s, nonce);
        s->deadline = serial_after(now, t->response_timeout_us);
        s->resync = 1U;
        send_sync(s, step);
        return CANERGY_OK;
    }
#endif
    (void)s;
    (void)t;
    (void)nonce;
    (void)now;
    return CANERGY_ERR_PHASE;
}
