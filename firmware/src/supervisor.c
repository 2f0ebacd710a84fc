/*
 * The hardened supervisor: Us and one session per node (canergy/supervisor.h), as
 * src/canergy/core/supervisor.py's Supervisor drives the SUPERVISOR table.
 */
#include "canergy/supervisor.h"

#include "le.h"
#include "rules.h"
#include "serial.h"

#include <string.h>

static void out_clear(struct canergy_supervisor_out *out)
{
    out->frame_count = 0U;
    out->event_count = 0U;
    out->persist = 0U;
}

static struct canergy_session *session_of(struct canergy_supervisor *sup, uint8_t node)
{
    for (uint8_t i = 0U; i < sup->count; i++) {
        if (sup->sessions[i].node == node) {
            return &sup->sessions[i];
        }
    }
    return NULL;
}

/* What the supervisor persists of a session changed (ACKED is stored as WAIT_ACK, a start's
 * waiting phases as IDLE: every start is one). */
static uint8_t stored_phase(const struct canergy_session *s)
{
    if (canergy_session_syncing(s)) {
        return CANERGY_S_IDLE;
    }
    return s->phase == CANERGY_S_ACKED ? (uint8_t)CANERGY_S_WAIT_ACK : s->phase;
}

static bool record_changed(const struct canergy_session *a, const struct canergy_session *b)
{
    return stored_phase(a) != stored_phase(b) || a->tx != b->tx ||
           a->reserved_uj != b->reserved_uj || a->delivered_uj != b->delivered_uj ||
           a->decision != b->decision || a->returns_credited != b->returns_credited ||
           a->resume_from != b->resume_from || a->resume_to != b->resume_to ||
           a->resume_nonce != b->resume_nonce || a->join_tx != b->join_tx ||
           a->join_seq != b->join_seq || a->join_nonce != b->join_nonce;
}

/* What a step did besides its frame (in: the client message it handled, NULL for the
 * supervisor's own calls; s the session before the step, after it after). */
static void record_event(const struct canergy_session *s, const struct canergy_session *after,
                         const struct canergy_session_step *step, const struct canergy_msg *in,
                         struct canergy_supervisor_out *out)
{
    if (out->event_count >= CANERGY_SUPERVISOR_NODES) {
        return;
    }
    struct canergy_supervisor_event *e = &out->events[out->event_count++];
    e->node = s->node;
    e->tx = s->tx;
    e->resolved = step->resolved;
    e->flags = step->acknowledged != 0U ? CANERGY_SUP_ACKNOWLEDGED : 0U;
    e->amount_uj = step->resolved != CANERGY_RESOLVED_NONE ? s->reserved_uj : 0U;
    const bool debit = in != NULL && (in->type == CANERGY_RETURN || in->type == CANERGY_DEBIT);
    /* a RETURN credited (a witness's 0 mJ one too, as Python's ReturnCredited), or one pending
     * at a RESUME */
    const bool numbered = in != NULL && in->type == CANERGY_RETURN &&
                          after->returns_credited != s->returns_credited;
    if ((debit && step->credit_uj > 0) || numbered) {
        e->flags |= CANERGY_SUP_RETURN_CREDITED;
        if (step->resolved == CANERGY_RESOLVED_NONE) { /* else the session's returned tells */
            e->amount_uj = (uint32_t)step->credit_uj;
        }
    }
    if (step->admitted != 0U) { /* a JOIN, or a RESUME found behind */
        e->flags |= CANERGY_SUP_ADMITTED;
    }
    e->ahead_numbers = step->ahead_numbers;
    if (step->ahead_numbers != 0U) {
        e->flags |= CANERGY_SUP_AHEAD;
    }
}

/* Apply a session step worked out on a copy: its credit to Us, a persist when the record or Us
 * changed, its frame, what it did, then the session itself. */
static void apply(struct canergy_supervisor *sup, struct canergy_session *s,
                  const struct canergy_session *after, const struct canergy_session_step *step,
                  const struct canergy_msg *in, struct canergy_supervisor_out *out)
{
    /* a grant is checked against Us first; only a start's books, and its counts afresh,
     * take Us below 0 (a debt) */
    CANERGY_ASSERT(step->credit_uj >= 0 || step->send == 0U || step->ahead_numbers != 0U ||
                   -step->credit_uj <= sup->usable_uj);
    sup->usable_uj += step->credit_uj;
    if (step->credit_uj != 0 || record_changed(s, after)) {
        out->persist = 1U;
    }
    if (step->send && out->frame_count < CANERGY_SUPERVISOR_NODES) {
        struct canergy_frame *f = &out->frames[out->frame_count];
        const int encoded = canergy_encode(sup->id_base, &step->msg, f);
        CANERGY_ASSERT(encoded == CANERGY_OK); /* the rules send only what the codec takes */
        if (encoded == CANERGY_OK) {
            out->frame_count++;
        }
    }
    record_event(s, after, step, in, out);
    *s = *after;
}

int canergy_supervisor_init(struct canergy_supervisor *sup,
                            const struct canergy_supervisor_config *cfg, const uint8_t *nodes,
                            uint8_t count, uint64_t initial_uj)
{
    if (sup == NULL || cfg == NULL || nodes == NULL || count == 0U ||
        count > CANERGY_SUPERVISOR_NODES || !canergy_id_base_valid(cfg->id_base) ||
        !rules_kept(cfg->timing.rules) || initial_uj > (uint64_t)INT64_MAX) {
        return CANERGY_ERR_ARGUMENT;
    }
    for (uint8_t i = 0U; i < count; i++) {
        const bool ascending = i == 0U || nodes[i] > nodes[i - 1U];
        if (nodes[i] < CANERGY_MIN_NODE || nodes[i] > CANERGY_MAX_NODE || !ascending) {
            return CANERGY_ERR_ARGUMENT;
        }
    }
    memset(sup, 0, sizeof *sup);
    for (uint8_t i = 0U; i < count; i++) {
        canergy_session_init(&sup->sessions[i], nodes[i]);
    }
    sup->count = count;
    sup->usable_uj = (int64_t)initial_uj;
    sup->id_base = cfg->id_base;
    sup->timing = cfg->timing;
    return CANERGY_OK;
}

int canergy_supervisor_begin(struct canergy_supervisor *sup, uint8_t node, uint32_t amount_uj,
                             uint64_t now, struct canergy_supervisor_out *out)
{
    out_clear(out);
    struct canergy_session *s = session_of(sup, node);
    if (s == NULL) {
        return CANERGY_ERR_ARGUMENT;
    }
    if (canergy_supervisor_unconfirmed(sup, NULL) != 0U) {
        return CANERGY_ERR_UNCONFIRMED; /* no grant before every node has confirmed its books */
    }
    struct canergy_session next = *s;
    struct canergy_session_step step;
    const int rc = canergy_session_begin(&next, &sup->timing, amount_uj, now, &step);
    if (rc != CANERGY_OK) {
        return rc;
    }
    if ((int64_t)amount_uj > sup->usable_uj) { /* the one guard a session cannot see */
        return CANERGY_ERR_AMOUNT;
    }
    apply(sup, s, &next, &step, NULL, out);
    return CANERGY_OK;
}

int canergy_supervisor_decide(struct canergy_supervisor *sup, uint8_t node, bool commit,
                              uint64_t now, struct canergy_supervisor_out *out)
{
    out_clear(out);
    struct canergy_session *s = session_of(sup, node);
    if (s == NULL) {
        return CANERGY_ERR_ARGUMENT;
    }
    struct canergy_session next = *s;
    struct canergy_session_step step;
    const int rc = canergy_session_decide(&next, &sup->timing, commit, now, &step);
    if (rc == CANERGY_OK) {
        apply(sup, s, &next, &step, NULL, out);
    }
    return rc;
}

int canergy_supervisor_on_frame(struct canergy_supervisor *sup,
                                const struct canergy_rx_frame *frame, uint64_t now,
                                struct canergy_supervisor_out *out)
{
    out_clear(out);
    struct canergy_msg m;
    const enum canergy_decode_status status =
        canergy_decode(sup->id_base, frame, CANERGY_TO_SUPERVISOR, &m);
    if (status != CANERGY_DECODE_OK) {
        return (int)status;
    }
    return canergy_supervisor_on_msg(sup, &m, now, out);
}

int canergy_supervisor_on_msg(struct canergy_supervisor *sup, const struct canergy_msg *m,
                              uint64_t now, struct canergy_supervisor_out *out)
{
    out_clear(out);
    struct canergy_session *s = session_of(sup, m->node);
    if (s == NULL) {
        return CANERGY_RX_OTHER_NODE;
    }
    if ((m->type & CANERGY_FROM_CLIENT) == 0U) {
        return CANERGY_DECODE_OK;
    }
    struct canergy_session next = *s;
    struct canergy_session_step step;
    canergy_session_on_msg(&next, &sup->timing, m, now, &step);
    apply(sup, s, &next, &step, m, out);
    return CANERGY_DECODE_OK;
}

int canergy_supervisor_on_answer(struct canergy_supervisor *sup,
                                 const struct canergy_rx_frame *frame, uint64_t now,
                                 bool abort_acks, struct canergy_supervisor_out *out,
                                 struct canergy_msg *m)
{
    out_clear(out);
    const enum canergy_decode_status status =
        canergy_decode(sup->id_base, frame, CANERGY_TO_SUPERVISOR, m);
    if (status != CANERGY_DECODE_OK) {
        return (int)status;
    }
    struct canergy_session *s = session_of(sup, m->node);
    if (s == NULL) {
        return CANERGY_RX_OTHER_NODE;
    }
    if (m->type != CANERGY_ACK && m->type != CANERGY_COMMITTED && m->type != CANERGY_ABORTED) {
        return CANERGY_RX_CALLER;
    }
    if (serial16(m->tx, s->tx) > 0) {
        return CANERGY_RX_AHEAD;
    }
    struct canergy_session next = *s;
    struct canergy_session_step step;
    canergy_session_on_msg(&next, &sup->timing, m, now, &step);
    apply(sup, s, &next, &step, m, out);
    if (step.acknowledged != 0U) {
        next = *s;
        if (canergy_session_decide(&next, &sup->timing, !abort_acks, now, &step) == CANERGY_OK) {
            apply(sup, s, &next, &step, NULL, out);
        }
    }
    return CANERGY_DECODE_OK;
}

void canergy_supervisor_on_timer(struct canergy_supervisor *sup, uint64_t now,
                                 struct canergy_supervisor_out *out)
{
    out_clear(out);
    for (uint8_t i = 0U; i < sup->count; i++) {
        struct canergy_session *s = &sup->sessions[i];
        if (s->deadline == CANERGY_NEVER || s->deadline > now) {
            continue;
        }
        struct canergy_session next = *s;
        struct canergy_session_step step;
        canergy_session_timer(&next, &sup->timing, now, &step);
        apply(sup, s, &next, &step, NULL, out);
    }
}

uint64_t canergy_supervisor_deadline(const struct canergy_supervisor *sup)
{
    uint64_t earliest = CANERGY_NEVER;
    for (uint8_t i = 0U; i < sup->count; i++) {
        if (sup->sessions[i].deadline < earliest) {
            earliest = sup->sessions[i].deadline;
        }
    }
    return earliest;
}

void canergy_supervisor_start(struct canergy_supervisor *sup, uint16_t nonce, uint64_t now,
                              struct canergy_supervisor_out *out)
{
    out_clear(out);
    for (uint8_t i = 0U; i < sup->count; i++) {
        struct canergy_session *s = &sup->sessions[i];
        struct canergy_session next = *s;
        struct canergy_session_step step;
        canergy_session_start(&next, &sup->timing, nonce, now, &step);
        apply(sup, s, &next, &step, NULL, out);
    }
}

void canergy_supervisor_restart(struct canergy_supervisor *sup, uint64_t now)
{
    struct canergy_supervisor_out out;
    canergy_supervisor_start(sup, 0U, now, &out);
}

int canergy_supervisor_resync(struct canergy_supervisor *sup, uint8_t node, uint16_t nonce,
                              uint64_t now, struct canergy_supervisor_out *out)
{
    out_clear(out);
    struct canergy_session *s = session_of(sup, node);
    if (s == NULL) {
        return CANERGY_ERR_ARGUMENT;
    }
    struct canergy_session next = *s;
    struct canergy_session_step step;
    const int rc = canergy_session_resync(&next, &sup->timing, nonce, now, &step);
    if (rc == CANERGY_OK) {
        apply(sup, s, &next, &step, NULL, out);
    }
    return rc;
}

int canergy_supervisor_start_without(struct canergy_supervisor *sup, uint8_t node)
{
    if (session_of(sup, node) == NULL) {
        return CANERGY_ERR_ARGUMENT;
    }
    sup->start_without[node >> 5] |= (uint32_t)1U << (node & 31U);
    return CANERGY_OK;
}

uint8_t canergy_supervisor_unconfirmed(const struct canergy_supervisor *sup,
                                       uint8_t nodes[CANERGY_SUPERVISOR_NODES])
{
    uint8_t n = 0U;
    for (uint8_t i = 0U; i < sup->count; i++) {
        const struct canergy_session *s = &sup->sessions[i];
        const bool without = (sup->start_without[s->node >> 5] >> (s->node & 31U) & 1UL) != 0U;
        if (canergy_session_syncing(s) && s->resync == 0U && !without) {
            if (nodes != NULL) {
                nodes[n] = s->node;
            }
            n++;
        }
    }
    return n;
}

int canergy_supervisor_inject(struct canergy_supervisor *sup, uint64_t amount_uj)
{
    if (amount_uj == 0U || amount_uj > (uint64_t)INT64_MAX ||
        sup->usable_uj > INT64_MAX - (int64_t)amount_uj) {
        return CANERGY_ERR_AMOUNT;
    }
    sup->usable_uj += (int64_t)amount_uj;
    sup->injected_uj += amount_uj;
    return CANERGY_OK;
}

int canergy_supervisor_withdraw(struct canergy_supervisor *sup, uint64_t amount_uj)
{
    if (amount_uj == 0U || sup->usable_uj < 0 || amount_uj > (uint64_t)sup->usable_uj) {
        return CANERGY_ERR_AMOUNT;
    }
    sup->usable_uj -= (int64_t)amount_uj;
    sup->withdrawn_uj += amount_uj;
    return CANERGY_OK;
}

/* -- the record in NV --------------------------------------------------------------------- */

#define SLOT_MAGIC 0x534E5243UL /* "CNRS" little-endian */
#define SLOT_VERSION 5U /* 3: the last RESUME answered (witnessed rules) in each session; 4: its
                          * nonce's bit 16 (a SYNC's counts), Us signed; 5: the last JOIN
                          * admitted */
#define SLOT_HEADER 36U /* magic, version, count, 2 spare, counter, Us, injected, withdrawn */
#define SESSION_BYTES 56U

static size_t slot_bytes(uint8_t count)
{
    return SLOT_HEADER + SESSION_BYTES * (size_t)count + 4U;
}

size_t canergy_supervisor_image(const struct canergy_supervisor *sup, uint32_t counter,
                                uint8_t out[CANERGY_SUPERVISOR_SLOT_SIZE])
{
    le_put(&out[0], SLOT_MAGIC, 4U);
    out[4] = SLOT_VERSION;
    out[5] = sup->count;
    out[6] = 0U;
    out[7] = 0U;
    le_put(&out[8], counter, 4U);
    le_put64(&out[12], (uint64_t)sup->usable_uj);
    le_put64(&out[20], sup->injected_uj);
    le_put64(&out[28], sup->withdrawn_uj);
    for (uint8_t i = 0U; i < sup->count; i++) {
        const struct canergy_session *s = &sup->sessions[i];
        uint8_t *r = &out[SLOT_HEADER + SESSION_BYTES * (size_t)i];
        r[0] = s->node;
        r[1] = stored_phase(s);
        r[2] = s->decision;
        r[3] = 0U;
        le_put(&r[4], s->tx, 4U);
        le_put(&r[8], s->returns_credited, 4U);
        le_put(&r[12], s->reserved_uj, 4U);
        le_put64(&r[16], s->delivered_uj);
        le_put64(&r[24], s->returned_uj);
        le_put(&r[32], s->resume_from, 4U);
        le_put(&r[36], s->resume_to, 4U);
        le_put(&r[40], s->resume_nonce, 4U);
        le_put(&r[44], s->join_tx, 4U);
        le_put(&r[48], s->join_seq, 4U);
        le_put(&r[52], s->join_nonce, 4U);
    }
    const size_t body = slot_bytes(sup->count) - 4U;
    le_put(&out[body], canergy_crc32(0U, out, body), 4U);
    return body + 4U;
}

/* A slot holding this supervisor's record: magic, version, its nodes, a matching CRC, and
 * values the rules can produce. */
static bool slot_valid(const struct canergy_supervisor *sup, const uint8_t *p)
{
    const size_t body = slot_bytes(sup->count) - 4U;
    if (le_get(p, 4U) != SLOT_MAGIC || p[4] != SLOT_VERSION || p[5] != sup->count ||
        le_get(&p[body], 4U) != canergy_crc32(0U, p, body)) {
        return false;
    }
    for (uint8_t i = 0U; i < sup->count; i++) {
        const uint8_t *r = &p[SLOT_HEADER + SESSION_BYTES * (size_t)i];
        const uint32_t reserved = le_get(&r[12], 4U);
        const bool idle = r[1] == CANERGY_S_IDLE;
        const bool confirm = r[1] == CANERGY_S_WAIT_CONFIRM;
        if (r[0] != sup->sessions[i].node || r[1] > CANERGY_S_WAIT_CONFIRM ||
            r[1] == CANERGY_S_ACKED || r[2] > CANERGY_DECIDE_ABORT ||
            (confirm != (r[2] != CANERGY_DECIDE_NONE)) || (idle != (reserved == 0U)) ||
            reserved % CANERGY_QUANTUM_UJ != 0U ||
            reserved > CANERGY_AMOUNT_MAX_MJ * CANERGY_QUANTUM_UJ || le_get(&r[40], 4U) > 0x1FFFFUL ||
            le_get(&r[52], 4U) > 0xFFFFUL) {
            return false;
        }
    }
    return true;
}

/* A slot holding a supervisor's record that is not this one's: another version, or another
 * node list under a matching CRC (a torn or damaged slot is not foreign, only invalid). */
static bool slot_foreign(const struct canergy_supervisor *sup, const uint8_t *p, size_t room)
{
    if (le_get(p, 4U) != SLOT_MAGIC) {
        return false;
    }
    if (p[4] != SLOT_VERSION) {
        return true;
    }
    const uint8_t count = p[5];
    if (count > CANERGY_SUPERVISOR_NODES || slot_bytes(count) > room) {
        return false;
    }
    const size_t body = slot_bytes(count) - 4U;
    if (le_get(&p[body], 4U) != canergy_crc32(0U, p, body)) {
        return false;
    }
    if (count != sup->count) {
        return true;
    }
    for (uint8_t i = 0U; i < count; i++) {
        if (p[SLOT_HEADER + SESSION_BYTES * (size_t)i] != sup->sessions[i].node) {
            return true;
        }
    }
    return false;
}

/* A slot with a session whose tx or last return credited is at or beyond the bound the proof
 * assumes (CANERGY_COUNTER_BOUND): no rule writes one. */
static bool slot_beyond(const struct canergy_supervisor *sup, const uint8_t *p)
{
    for (uint8_t i = 0U; i < sup->count; i++) {
        const uint8_t *r = &p[SLOT_HEADER + SESSION_BYTES * (size_t)i];
        if (le_get(&r[4], 4U) >= CANERGY_COUNTER_BOUND ||
            le_get(&r[8], 4U) >= CANERGY_COUNTER_BOUND ||
            le_get(&r[44], 4U) >= CANERGY_COUNTER_BOUND ||
            le_get(&r[48], 4U) >= CANERGY_COUNTER_BOUND) {
            return true;
        }
    }
    return false;
}

static void slot_take(struct canergy_supervisor *sup, const uint8_t *p)
{
    sup->usable_uj = (int64_t)le_get64(&p[12]);
    sup->injected_uj = le_get64(&p[20]);
    sup->withdrawn_uj = le_get64(&p[28]);
    for (uint8_t i = 0U; i < sup->count; i++) {
        const uint8_t *r = &p[SLOT_HEADER + SESSION_BYTES * (size_t)i];
        struct canergy_session *s = &sup->sessions[i];
        s->phase = r[1];
        s->decision = r[2];
        s->tx = le_get(&r[4], 4U);
        s->returns_credited = le_get(&r[8], 4U);
        s->reserved_uj = le_get(&r[12], 4U);
        s->delivered_uj = le_get64(&r[16]);
        s->returned_uj = le_get64(&r[24]);
        s->resume_from = le_get(&r[32], 4U);
        s->resume_to = le_get(&r[36], 4U);
        s->resume_nonce = le_get(&r[40], 4U);
        s->join_tx = le_get(&r[44], 4U);
        s->join_seq = le_get(&r[48], 4U);
        s->join_nonce = (uint16_t)le_get(&r[52], 4U);
    }
}

int canergy_supervisor_load(struct canergy_supervisor *sup,
                            const struct canergy_supervisor_config *cfg, const uint8_t *nodes,
                            uint8_t count, uint64_t initial_uj, const uint8_t *image, size_t len,
                            uint32_t *counter, uint8_t *slot)
{
    const int rc = canergy_supervisor_init(sup, cfg, nodes, count, initial_uj);
    if (rc != CANERGY_OK || counter == NULL || slot == NULL) {
        return rc != CANERGY_OK ? rc : CANERGY_ERR_ARGUMENT;
    }
    const size_t each = CANERGY_SUPERVISOR_SLOT_SIZE;
    int newest = -1;
    uint32_t best = 0U;
    bool foreign = false;
    bool beyond = false;
    for (uint8_t i = 0U; i < 2U; i++) {
        const size_t start = (size_t)i * each;
        if (image == NULL || len < start + 8U) {
            continue;
        }
        const uint8_t *p = &image[start];
        const size_t room = len - start < each ? len - start : each;
        foreign = foreign || slot_foreign(sup, p, room);
        if (room < slot_bytes(count)) {
            continue;
        }
        const uint32_t c = le_get(&p[8], 4U);
        beyond = beyond || (slot_valid(sup, p) && slot_beyond(sup, p));
        if (slot_valid(sup, p) && (newest < 0 || (uint32_t)(c - best) - 1U < 0x7FFFFFFFUL)) {
            newest = (int)i;
            best = c;
        }
    }
    *counter = best;
    *slot = newest < 0 ? 1U : (uint8_t)newest; /* none: slot 0 is written first */
    if (beyond) { /* neither slot: the other may be older, and an older copy grants again */
        return CANERGY_ERR_END;
    }
    if (newest < 0) {
        return foreign ? CANERGY_ERR_RECORD : 0;
    }
    slot_take(sup, &image[(size_t)newest * each]);
    canergy_supervisor_restart(sup, 0U);
    return 1;
}
