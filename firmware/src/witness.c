/*
 * The witness's RETURN hold (canergy/witness.h), as canergy.live.supervisor.witness.ReturnGate.
 */
#include "canergy/witness.h"

#include "canergy/client.h"

#include "rules.h"
#include "serial.h"

#include <string.h>

/* Python's unwrap(wire, ref, 16): the number congruent to wire nearest to ref. */
static int64_t unwrap16(uint16_t wire, int64_t ref)
{
    return ref + serial16(wire, (uint32_t)ref);
}

void canergy_witness_init(struct canergy_witness *w)
{
    memset(w, 0, sizeof *w);
}

void canergy_witness_refute(struct canergy_witness *w, uint64_t now)
{
    w->evidence_at = now;
    w->has_evidence = true;
    w->refuted += (uint32_t)w->held_count + (w->has_resume ? 1U : 0U);
    w->held_count = 0U;
    w->has_resume = false;
}

unsigned canergy_witness_telemetry(struct canergy_witness *w, const struct canergy_msg *m,
                                   uint32_t credited, uint64_t now)
{
    if ((m->flags & CANERGY_TELEMETRY_JOINING) != 0U) {
        return 0U; /* no books, no return number: nothing to compare yet */
    }
    unsigned found = 0U;
    const uint8_t seen = (uint8_t)(m->witness - (w->has_witness ? w->witness : 0U));
    if (!w->has_witness && seen != 0U) {
        found |= CANERGY_WITNESS_SINCE_START;
    } else if (seen > CANERGY_WITNESS_REPORT_AT) {
        found |= CANERGY_WITNESS_RESTARTED;
    } else if (seen != 0U) {
        found |= CANERGY_WITNESS_SAW;
    }
    w->witness = m->witness;
    w->has_witness = true;
    const int64_t ref =
        w->has_return_seq && w->return_seq > (int64_t)credited ? w->return_seq : (int64_t)credited;
    const int64_t seq = unwrap16(m->seq, ref);
    if (w->has_return_seq && seq < w->return_seq) {
        found |= CANERGY_WITNESS_WENT_BACK;
    } else { /* the node stands by the number: what it made is confirmed as of now */
        w->return_seq = seq;
        w->has_return_seq = true;
        w->confirmed_at = now;
        for (unsigned i = 0U; i < w->held_count; i++) {
            struct canergy_held *h = &w->held[i];
            if (h->seq <= seq && !h->confirmed) {
                h->confirmed = true;
                h->confirmed_at = now;
            }
        }
        if (w->has_resume && w->resume.seq == (uint16_t)seq && !w->resume_held.confirmed) {
            w->resume_held.confirmed = true;
            w->resume_held.confirmed_at = now;
        }
    }
    if ((found & CANERGY_WITNESS_EVIDENCE) != 0U) {
        canergy_witness_refute(w, now);
    }
    return found;
}

enum canergy_witness_verdict canergy_witness_hold(struct canergy_witness *w,
                                                  const struct canergy_msg *m, uint32_t credited,
                                                  uint64_t now)
{
    const int64_t seq = unwrap16(m->seq, (int64_t)credited);
    if (seq <= (int64_t)credited) {
        return CANERGY_WITNESS_OLD; /* the rules re-ack it: no energy moves */
    }
    unsigned at = 0U;
    while (at < w->held_count && w->held[at].seq < seq) {
        at++;
    }
    if (at < w->held_count && w->held[at].seq == seq) {
        if (w->held[at].amount_mj == m->amount_mj) {
            return CANERGY_WITNESS_HELD; /* a copy: the bus repeats frames */
        }
        canergy_witness_refute(w, now);
        return CANERGY_WITNESS_CONTRADICTED;
    }
    if (w->held_count == CANERGY_WITNESS_SLOTS) {
        return CANERGY_WITNESS_FULL;
    }
    (void)memmove(&w->held[at + 1U], &w->held[at], (w->held_count - at) * sizeof w->held[0]);
    w->held[at].seq = seq;
    w->held[at].amount_mj = m->amount_mj;
    w->held[at].confirmed = false;
    w->held[at].confirmed_at = 0U;
    w->held_count++;
    return CANERGY_WITNESS_HELD; /* confirmed by a later TELEMETRY only */
}

static bool same_debit(const struct canergy_msg *a, const struct canergy_msg *b)
{
    return a->node == b->node && a->nonce == b->nonce && a->flags == b->flags &&
           a->seq == b->seq && a->amount_mj == b->amount_mj;
}

bool canergy_witness_hold_resume(struct canergy_witness *w, const struct canergy_msg *m,
                                 uint32_t credited, uint64_t now, bool hold)
{
    (void)now;
    if (!w->has_resume_nonce || m->nonce != w->resume_nonce) {
        /* a start: from an older record it goes back, honestly */
        w->resume_nonce = m->nonce;
        w->has_resume_nonce = true;
        w->has_return_seq = false;
    }
    const int64_t seq = unwrap16(m->seq, (int64_t)credited);
    if (!hold || seq != (int64_t)credited + 1 || m->amount_mj == 0U ||
        (m->flags & CANERGY_DEBIT_DRAW) != 0U) {
        return false;
    }
    if (!w->has_resume || !same_debit(&w->resume, m)) {
        w->resume = *m;
        w->resume_held.seq = seq;
        w->resume_held.amount_mj = m->amount_mj;
        w->resume_held.confirmed = false;
        w->resume_held.confirmed_at = 0U;
        w->has_resume = true;
    }
    return true;
}

void canergy_witness_release(struct canergy_witness *w, uint32_t credited, uint64_t now,
                             uint64_t hold_us, struct canergy_witness_release *out)
{
    memset(out, 0, sizeof *out);
    if (!w->has_return_seq) {
        return;
    }
    int64_t done = (int64_t)credited;
    unsigned kept = 0U;
    for (unsigned i = 0U; i < w->held_count; i++) {
        const struct canergy_held h = w->held[i];
        const bool ready = h.confirmed && h.seq <= w->return_seq && now >= h.confirmed_at + hold_us;
        if (!ready || h.seq <= done) {
            if (h.seq > done) {
                w->held[kept++] = h; /* not ready: kept (a later number may pass it) */
            }
            continue;
        }
        out->returns[out->count].first_missed = done + 1;
        out->returns[out->count].seq = h.seq;
        out->returns[out->count].amount_mj = h.amount_mj;
        out->count++;
        w->resynced += (uint32_t)(h.seq - done - 1);
        done = h.seq;
    }
    w->held_count = (uint8_t)kept;
    if (w->has_resume && w->resume_held.confirmed &&
        now >= w->resume_held.confirmed_at + hold_us) {
        out->resume = true;
        out->resume_msg = w->resume; /* the rules judge it against their count now */
        w->has_resume = false;
    }
}

bool canergy_witness_release_at(const struct canergy_witness_release *r, uint8_t node,
                                uint32_t n, struct canergy_msg *m)
{
    memset(m, 0, sizeof *m);
    for (unsigned k = 0U; k < r->count; k++) {
        const uint32_t span = (uint32_t)(r->returns[k].seq - r->returns[k].first_missed) + 1U;
        if (n < span) {
            m->type = CANERGY_RETURN;
            m->node = node;
            m->seq = (uint16_t)(r->returns[k].first_missed + (int64_t)n);
            m->amount_mj = n + 1U == span ? r->returns[k].amount_mj : 0U;
            return true;
        }
        n -= span;
    }
    if (r->resume && n == 0U) {
        *m = r->resume_msg;
        return true;
    }
    return false;
}

bool canergy_witness_blocked(const struct canergy_witness *w, uint64_t now, uint64_t block_us)
{
    return w->has_evidence && now < w->evidence_at + block_us;
}

void canergy_witness_readmitted(struct canergy_witness *w)
{
    w->has_return_seq = false;
    w->confirmed_at = 0U;
    w->held_count = 0U;
    w->has_resume = false;
}

uint64_t canergy_witness_next_release(const struct canergy_witness *w, uint64_t hold_us)
{
    uint64_t next = UINT64_MAX;
    for (unsigned i = 0U; i < w->held_count; i++) {
        if (w->held[i].confirmed && w->held[i].confirmed_at + hold_us < next) {
            next = w->held[i].confirmed_at + hold_us;
        }
    }
    if (w->has_resume && w->resume_held.confirmed && w->resume_held.confirmed_at + hold_us < next) {
        next = w->resume_held.confirmed_at + hold_us;
    }
    return next;
}

bool canergy_witness_beyond_books(const struct canergy_session *s, const struct canergy_msg *m)
{
    const bool debits = m->type == CANERGY_RETURN ||
                        (m->type == CANERGY_DEBIT &&
                         (m->flags & (CANERGY_DEBIT_SYNC | CANERGY_DEBIT_BOOKS)) == 0U);
    /* books returned past what they gave (a forged RETURN credited while the node was off)
     * let it hold less than nothing: any debit is beyond them (no unsigned wrap) */
    const uint64_t given = s->delivered_uj + s->reserved_uj;
    return debits && serial16(m->seq, s->returns_credited) == 1 &&
           (s->returned_uj > given ||
            (uint64_t)m->amount_mj * CANERGY_QUANTUM_UJ > given - s->returned_uj);
}

static enum canergy_witness_route route(struct canergy_witness *w,
                                        const struct canergy_session *s,
                                        const struct canergy_msg *m, uint8_t rules, uint64_t now,
                                        uint32_t *intrusions, bool hold)
{
    const uint32_t credited = s->returns_credited;
    if (m->type == CANERGY_TELEMETRY) {
        const unsigned found = canergy_witness_telemetry(w, m, credited, now);
        *intrusions += (found & CANERGY_WITNESS_EVIDENCE) != 0U ? 1U : 0U;
        return CANERGY_WITNESS_TAKEN;
    }
    if (canergy_witness_beyond_books(s, m)) {
        canergy_witness_refute(w, now); /* no honest node sends it: no top-ups for a while */
        w->refuted++;
        (*intrusions)++;
        return CANERGY_WITNESS_DROPPED;
    }
    if (m->type == CANERGY_RETURN && !hold) {
        return CANERGY_WITNESS_TO_RULES; /* it carries a MAC: credited at once */
    }
    if (m->type == CANERGY_RETURN) {
        const enum canergy_witness_verdict v = canergy_witness_hold(w, m, credited, now);
        *intrusions += v == CANERGY_WITNESS_CONTRADICTED ? 1U : 0U;
        return v == CANERGY_WITNESS_OLD    ? CANERGY_WITNESS_TO_RULES
               : v == CANERGY_WITNESS_FULL ? CANERGY_WITNESS_DROPPED
                                           : CANERGY_WITNESS_TAKEN;
    }
    const bool resume = (m->flags & CANERGY_DEBIT_START) != 0U &&
                        (m->flags & (CANERGY_DEBIT_SYNC | CANERGY_DEBIT_BOOKS)) == 0U;
    const bool counts = (m->flags & CANERGY_DEBIT_COUNTS) == CANERGY_DEBIT_COUNTS;
    if (rules_witnessed(rules) && m->type == CANERGY_DEBIT && (resume || counts) &&
        canergy_witness_hold_resume(w, m, credited, now, hold && resume)) {
        return CANERGY_WITNESS_TAKEN;
    }
    return CANERGY_WITNESS_TO_RULES;
}

enum canergy_witness_route canergy_witness_route(struct canergy_witness *w,
                                                 const struct canergy_session *s,
                                                 const struct canergy_msg *m, uint8_t rules,
                                                 uint64_t now, uint32_t *intrusions)
{
    return route(w, s, m, rules, now, intrusions, true);
}

enum canergy_witness_route canergy_witness_route_keyed(struct canergy_witness *w,
                                                       const struct canergy_session *s,
                                                       const struct canergy_msg *m,
                                                       uint8_t rules, uint64_t now,
                                                       uint32_t *intrusions)
{
    return route(w, s, m, rules, now, intrusions, false);
}
