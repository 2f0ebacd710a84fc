/*
 * Authenticated frames (see include/canergy/auth.h): FrameAuth of src/canergy/auth/frames.py,
 * check for check and in its order, for one node's key.
 */
#include "canergy/auth.h"

#include "client_internal.h"

#include <string.h>

static const uint8_t fd_lengths[] = {12U, 16U, 20U, 24U, 32U, 48U, 64U};

/* The smallest CAN FD length >= n (n <= 20 here); 0 past 64. */
static size_t fd_length(size_t n)
{
    for (size_t i = 0U; i < sizeof fd_lengths; i++) {
        if (fd_lengths[i] >= n) {
            return fd_lengths[i];
        }
    }
    return 0U;
}

/* Python's unwrap(wire, ref, 16) & 0xFFFFFFFF: the value nearest ref with these low 16 bits. */
static uint32_t extend16(uint32_t wire, uint32_t ref)
{
    const uint32_t d = (uint32_t)((wire - ref) & 0xFFFFU);
    return d >= 0x8000U ? ref + d - 0x10000U : ref + d;
}

uint32_t canergy_auth_freshness(const struct canergy_msg *m, uint32_t last_tx,
                                uint32_t return_seq)
{
    switch (m->type) {
    case CANERGY_JOIN: return m->nonce;
    case CANERGY_ADMIT: return (extend16(m->tx, last_tx) & 0xFFFF0000UL) | m->nonce;
    case CANERGY_TELEMETRY: return last_tx;
    case CANERGY_DEBIT:
        if ((m->flags & (CANERGY_DEBIT_START | CANERGY_DEBIT_BOOKS)) != 0U) {
            return m->nonce; /* a resume, as a JOIN; a SYNC's books and counts, by its nonce */
        }
        return extend16(m->seq, return_seq); /* a draw is numbered as a return */
    case CANERGY_RETURN:
    case CANERGY_RETURN_ACK: return extend16(m->seq, return_seq);
    default: return extend16(m->tx, last_tx);
    }
}

void canergy_auth_set_join(struct canergy_auth *a, uint16_t random_high, uint16_t nonce)
{
    a->join_fv = (uint32_t)random_high << 16 | nonce;
}

/* The FV of the JOIN that m (a JOIN or an ADMIT) belongs to: set_join's, or the nonce alone; a
 * supervisor's ADMIT binds first the RESUME it kept, then the JOIN (Python's _join_fv). */
static uint32_t join_fv_of(const struct canergy_auth *a, const struct canergy_msg *m)
{
    if (m->type == CANERGY_ADMIT && (a->kept & CANERGY_AUTH_KEPT_RESUME) != 0U &&
        (a->resume_fv & 0xFFFFU) == m->nonce) {
        return a->resume_fv;
    }
    return (a->join_fv & 0xFFFFU) == m->nonce ? a->join_fv : m->nonce;
}

/* The FV of m on this side: a JOIN takes the JOIN FV; a TELEMETRY sent without books
 * (JOINING) too, once one is set. */
static uint32_t fv_of(const struct canergy_auth *a, const struct canergy_msg *m, uint32_t last_tx,
                      uint32_t return_seq)
{
    if (m->type == CANERGY_JOIN) {
        return join_fv_of(a, m);
    }
    const bool joining =
        m->type == CANERGY_TELEMETRY && (m->flags & CANERGY_TELEMETRY_JOINING) != 0U;
    if (joining && a->join_fv != 0U) {
        return a->join_fv;
    }
    return canergy_auth_freshness(m, last_tx, return_seq);
}

static void put_be32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v >> 24);
    p[1] = (uint8_t)(v >> 16);
    p[2] = (uint8_t)(v >> 8);
    p[3] = (uint8_t)v;
}

static uint32_t get_be32(const uint8_t *p)
{
    return (uint32_t)p[0] << 24 | (uint32_t)p[1] << 16 | (uint32_t)p[2] << 8 | p[3];
}

/* AES-CMAC over Data ID (type << 8 | node, BE) || FV (BE) || the classic data, and for ADMIT
 * || the FV of the JOIN it answers (BE; both sides know it, so it is bound without travelling). */
static void mac(const struct canergy_auth *a, const struct canergy_msg *m, uint32_t fv,
                const uint8_t *data, size_t len, uint8_t tag[CANERGY_CMAC_SIZE])
{
    uint8_t head[6] = {m->type, m->node, 0U, 0U, 0U, 0U};
    struct canergy_cmac_stream s;
    put_be32(&head[2], fv);
    canergy_cmac_begin(&s);
    canergy_cmac_update(&a->key, &s, head, sizeof head);
    canergy_cmac_update(&a->key, &s, data, len);
    if (m->type == CANERGY_ADMIT) {
        uint8_t join[4];
        put_be32(join, join_fv_of(a, m));
        canergy_cmac_update(&a->key, &s, join, sizeof join);
    }
    canergy_cmac_final(&a->key, &s, tag);
}

int canergy_auth_init(struct canergy_auth *a, const uint8_t key[CANERGY_KDF_KEY_SIZE],
                      uint32_t id_base, uint8_t node, enum canergy_auth_layout layout,
                      enum canergy_direction receives)
{
    if (a == NULL || key == NULL || !canergy_id_base_valid(id_base) ||
        node < CANERGY_MIN_NODE || node > CANERGY_MAX_NODE ||
        (layout != CANERGY_AUTH_FD && layout != CANERGY_AUTH_CLASSIC) ||
        (receives != CANERGY_TO_CLIENT && receives != CANERGY_TO_SUPERVISOR)) {
        return CANERGY_ERR_ARGUMENT;
    }
    memset(a, 0, sizeof *a);
    canergy_cmac_init(&a->key, key);
    a->id_base = id_base;
    a->node = node;
    a->layout = (uint8_t)layout;
    a->receives = (uint8_t)receives;
    return CANERGY_OK;
}

void canergy_auth_wipe(struct canergy_auth *a)
{
    canergy_wipe(a, sizeof *a);
}

static uint32_t mac_type(uint32_t type)
{
    return (type & CANERGY_FROM_CLIENT) != 0U ? CANERGY_AUTH_MAC_TO_SUPERVISOR
                                              : CANERGY_AUTH_MAC_TO_CLIENT;
}

int canergy_auth_protect(const struct canergy_auth *a, const struct canergy_frame *plain,
                         uint32_t last_tx, uint32_t return_seq, struct canergy_auth_frame out[2])
{
    if (a == NULL || plain == NULL || out == NULL || plain->dlc > 8U) {
        return CANERGY_ERR_ARGUMENT;
    }
    const struct canergy_rx_frame rx = {plain->id, plain->data, plain->dlc, true, false};
    struct canergy_msg m;
    if (canergy_decode(a->id_base, &rx, CANERGY_EITHER_WAY, &m) != CANERGY_DECODE_OK ||
        m.node != a->node) {
        return CANERGY_ERR_ARGUMENT;
    }
    const uint32_t fv = fv_of(a, &m, last_tx, return_seq);
    uint8_t tag[CANERGY_CMAC_SIZE];
    mac(a, &m, fv, plain->data, plain->dlc, tag);
    memset(out, 0, 2U * sizeof out[0]);
    out[0].id = plain->id;
    memcpy(out[0].data, plain->data, plain->dlc);
    if (a->layout == CANERGY_AUTH_FD) {
        const size_t len = fd_length(plain->dlc + CANERGY_AUTH_TRAILER);
        put_be32(&out[0].data[len - CANERGY_AUTH_TRAILER], fv);
        memcpy(&out[0].data[len - CANERGY_AUTH_FD_MAC], tag, CANERGY_AUTH_FD_MAC);
        out[0].len = (uint8_t)len;
        return 1;
    }
    out[0].len = plain->dlc;
    out[1].id = a->id_base | mac_type(m.type) << 8 | m.node;
    out[1].len = CANERGY_AUTH_MAC_FRAME_LEN;
    /* TELEMETRY carries no counter: its MAC frame carries the FV's low half, not the high */
    const uint32_t half = m.type == CANERGY_TELEMETRY ? fv : fv >> 16;
    out[1].data[0] = m.type;
    out[1].data[1] = (uint8_t)(half >> 8);
    out[1].data[2] = (uint8_t)half;
    memcpy(&out[1].data[3], tag, CANERGY_AUTH_CLASSIC_MAC);
    return 2;
}

/* FV a comes before b (serial-number order on 32 bits: Python's fv_before). */
static bool fv_before(uint32_t a, uint32_t b)
{
    return a != b && (uint32_t)(b - a) < 0x80000000UL;
}

static bool is_joining(const struct canergy_msg *m)
{
    return m->type == CANERGY_TELEMETRY && (m->flags & CANERGY_TELEMETRY_JOINING) != 0U;
}

/* A supervisor's JOINING TELEMETRY is bound to the JOIN it took last (when it kept one). */
static bool sup_join(const struct canergy_auth *a, uint32_t *fv)
{
    *fv = a->join_fv;
    return (a->kept & CANERGY_AUTH_KEPT_JOIN) != 0U;
}

/* A supervisor's judgement of a verified m (Python's FrameAuth._verdict with the supervisor's
 * expected_freshness, counters tx and credited): true when stale. */
static bool sup_stale(const struct canergy_auth *a, const struct canergy_msg *m, uint32_t fv,
                      uint32_t tx, uint32_t credited)
{
    const bool debit = m->type == CANERGY_DEBIT;
    if (m->type == CANERGY_JOIN || (debit && (m->flags & CANERGY_DEBIT_START) != 0U)) {
        return (fv & 0xFFFFU) != m->nonce; /* any fresh nonce, kept for the ADMIT */
    }
    if (debit && (m->flags & ~CANERGY_DEBIT_RC_UNKNOWN) == CANERGY_DEBIT_BOOKS) {
        return fv != m->nonce; /* a SYNC's books: bound to its nonce */
    }
    if (m->type == CANERGY_TELEMETRY) { /* the window: resolved .. the session's tx */
        const uint32_t floor = (a->kept & CANERGY_AUTH_KEPT_FLOOR) != 0U ? a->floor : tx - 1U;
        return fv_before(fv, floor) || fv_before(tx, fv);
    }
    const bool numbered = m->type == CANERGY_RETURN || m->type == CANERGY_RETURN_ACK || debit;
    return canergy_auth_freshness(m, tx, credited) != fv || fv_before(fv, numbered ? credited : tx);
}

/* What a verified m taken by a supervisor shows (Python's FrameAuth._verdict and took): the
 * JOIN or RESUME kept, the JOIN dropped by anything else, how far the node has resolved. */
static void sup_took(struct canergy_auth *a, const struct canergy_msg *m, uint32_t fv)
{
    if (m->type == CANERGY_JOIN) {
        a->join_fv = fv;
        a->kept = (uint8_t)((a->kept | CANERGY_AUTH_KEPT_JOIN) & ~CANERGY_AUTH_KEPT_RESUME);
        return;
    }
    if (m->type == CANERGY_DEBIT && (m->flags & CANERGY_DEBIT_START) != 0U) {
        a->resume_fv = fv;
        a->kept |= CANERGY_AUTH_KEPT_RESUME;
    }
    a->join_fv = 0U; /* admitted: no TELEMETRY without books is fresh now */
    a->kept &= (uint8_t)~CANERGY_AUTH_KEPT_JOIN;
    uint32_t resolved = fv;
    if (m->type == CANERGY_ACK) {
        resolved = fv - 1U;
    } else if (m->type != CANERGY_TELEMETRY && m->type != CANERGY_COMMITTED &&
               m->type != CANERGY_ABORTED) {
        return;
    }
    if ((a->kept & CANERGY_AUTH_KEPT_FLOOR) == 0U || fv_before(a->floor, resolved)) {
        a->floor = resolved;
        a->kept |= CANERGY_AUTH_KEPT_FLOOR;
    }
}

/* A supervisor's judgement: its counters and the two functions above (NULL: the plain one of
 * canergy_auth_accept; called through pointers, so that a node's image links neither). */
struct sup_counters {
    uint32_t tx;
    uint32_t credited;
    bool (*stale)(const struct canergy_auth *a, const struct canergy_msg *m, uint32_t fv,
                  uint32_t tx, uint32_t credited);
    void (*took)(struct canergy_auth *a, const struct canergy_msg *m, uint32_t fv);
};

/* The MAC, then (but for TELEMETRY) the FV the receiver expects; the verified classic frame.
 * With sup, a supervisor's judgement instead (sup_stale, sup_took). */
static int verdict(struct canergy_auth *a, const struct canergy_msg *m, uint32_t id,
                   const uint8_t *body, size_t len, uint32_t fv, const uint8_t *tag,
                   size_t tag_len, uint32_t last_tx, uint32_t return_seq,
                   const struct sup_counters *sup, struct canergy_frame *verified)
{
    uint8_t expected[CANERGY_CMAC_SIZE];
    mac(a, m, fv, body, len, expected);
    const bool good = canergy_mac_equal(expected, tag, tag_len);
    canergy_wipe(expected, sizeof expected);
    const bool joining = is_joining(m);
    uint32_t bound = a->join_fv;
    const bool has_join = sup != NULL ? sup_join(a, &bound) : a->join_fv != 0U;
    if (joining && (good || a->layout == CANERGY_AUTH_CLASSIC) &&
        !(good && has_join && bound == fv)) {
        /* bound to a JOIN not seen (or a classic MAC extended next to another): moves nothing,
         * proves nothing, as in Python */
        return CANERGY_AUTH_PENDING;
    }
    if (!good) {
        return CANERGY_AUTH_MAC_BAD;
    }
    bool stale;
    if (joining) {
        stale = false; /* its JOIN's, checked above */
    } else if (sup != NULL) {
        stale = sup->stale(a, m, fv, sup->tx, sup->credited);
    } else if (m->type == CANERGY_ADMIT) {
        stale = (fv & 0xFFFFU) != m->nonce; /* any high half: the counters the node starts from */
    } else {
        stale = m->type != CANERGY_TELEMETRY && fv_of(a, m, last_tx, return_seq) != fv;
    }
    if (stale) {
        return CANERGY_AUTH_STALE; /* without sup, TELEMETRY's window is the supervisor's */
    }
    if (m->type == CANERGY_ADMIT) {
        a->admit_fv = fv;
    }
    if (sup != NULL && !joining) {
        sup->took(a, m, fv);
    }
    memset(verified, 0, sizeof *verified);
    verified->id = id;
    verified->dlc = (uint8_t)len;
    memcpy(verified->data, body, len);
    return CANERGY_DECODE_OK;
}

/* Classic: a MAC frame of the direction this side receives completes the waiting message. */
static int mac_frame(struct canergy_auth *a, const struct canergy_rx_frame *f, uint32_t last_tx,
                     uint32_t return_seq, const struct sup_counters *sup,
                     struct canergy_frame *verified)
{
    if ((f->id & 0xFFU) != a->node) {
        return CANERGY_RX_OTHER_NODE;
    }
    const size_t waiting = a->pending_len;
    a->pending_len = 0U; /* taken, whatever the MAC frame turns out to be */
    if (f->len != CANERGY_AUTH_MAC_FRAME_LEN || f->data == NULL) {
        return CANERGY_AUTH_MALFORMED;
    }
    const uint32_t type = a->pending_id >> 8 & 0xFU;
    if (waiting == 0U || f->data[0] != type) {
        return CANERGY_AUTH_NO_DATA;
    }
    const struct canergy_rx_frame rx = {a->pending_id, a->pending_data, waiting, true, false};
    struct canergy_msg m;
    (void)canergy_decode(a->id_base, &rx, CANERGY_EITHER_WAY, &m); /* it decoded when it came */
    const uint32_t half = (uint32_t)f->data[1] << 8 | f->data[2];
    uint32_t near = fv_of(a, &m, last_tx, return_seq); /* a TELEMETRY's low half extends */
    if (sup != NULL && !(is_joining(&m) && sup_join(a, &near))) {
        near = sup->tx; /* next to the JOIN taken last, or the session's tx */
    }
    const uint32_t fv = m.type == CANERGY_TELEMETRY
                            ? extend16(half, near)
                            : half << 16 | (canergy_auth_freshness(&m, 0U, 0U) & 0xFFFFUL);
    return verdict(a, &m, a->pending_id, a->pending_data, waiting, fv, &f->data[3],
                   CANERGY_AUTH_CLASSIC_MAC, last_tx, return_seq, sup, verified);
}

/* Classic: a data frame waits (replacing any other) until its MAC frame comes. */
static int data_frame(struct canergy_auth *a, const struct canergy_rx_frame *f)
{
    struct canergy_msg m;
    const enum canergy_decode_status status =
        canergy_decode(a->id_base, f, (enum canergy_direction)a->receives, &m);
    if (status != CANERGY_DECODE_OK) {
        return (int)status;
    }
    if (m.node != a->node) {
        return CANERGY_RX_OTHER_NODE;
    }
    /* a message still waiting here never got its MAC frame: it is dropped, and counted */
    const bool displaced = a->pending_len != 0U;
    a->pending_id = f->id;
    a->pending_len = (uint8_t)f->len;
    memcpy(a->pending_data, f->data, f->len);
    return displaced ? CANERGY_AUTH_UNAUTHENTICATED : CANERGY_AUTH_PENDING;
}

static bool all_zero(const uint8_t *p, size_t n)
{
    uint8_t any = 0U;
    for (size_t i = 0U; i < n; i++) {
        any |= p[i];
    }
    return any == 0U;
}

/* FD: data || zero padding || FV || MAC in one frame of exactly the type's length. */
static int fd_frame(struct canergy_auth *a, const struct canergy_rx_frame *f,
                    uint32_t last_tx, uint32_t return_seq, const struct sup_counters *sup,
                    struct canergy_frame *verified)
{
    const enum canergy_direction dir = (enum canergy_direction)a->receives;
    const size_t length = canergy_data_length(f->id >> 8 & 0xFU);
    struct canergy_msg m;
    if (length == 0U || f->data == NULL ||
        f->len != fd_length(length + CANERGY_AUTH_TRAILER) ||
        !all_zero(&f->data[length], f->len - length - CANERGY_AUTH_TRAILER)) {
        const enum canergy_decode_status status = canergy_decode(a->id_base, f, dir, &m);
        if (status != CANERGY_DECODE_OK) {
            return (int)status; /* the codec's own refusal, if it has one */
        }
        return m.node == a->node ? CANERGY_AUTH_UNAUTHENTICATED : CANERGY_RX_OTHER_NODE;
    }
    const struct canergy_rx_frame body = {f->id, f->data, length, f->extended, false};
    const enum canergy_decode_status status = canergy_decode(a->id_base, &body, dir, &m);
    if (status != CANERGY_DECODE_OK) {
        return (int)status;
    }
    if (m.node != a->node) {
        return CANERGY_RX_OTHER_NODE;
    }
    const uint8_t *trailer = &f->data[f->len - CANERGY_AUTH_TRAILER];
    return verdict(a, &m, f->id, f->data, length, get_be32(trailer), &trailer[4],
                   CANERGY_AUTH_FD_MAC, last_tx, return_seq, sup, verified);
}

static int accept(struct canergy_auth *a, const struct canergy_rx_frame *frame,
                  uint32_t last_tx, uint32_t return_seq, const struct sup_counters *sup,
                  struct canergy_frame *verified)
{
    if (a == NULL || frame == NULL || verified == NULL || !frame->extended ||
        (frame->id & CANERGY_ID_MASK) != a->id_base) {
        return CANERGY_DECODE_FOREIGN;
    }
    if (frame->remote) {
        return CANERGY_DECODE_REMOTE_FRAME;
    }
    if (frame->len > 64U || (frame->data == NULL && frame->len != 0U)) {
        return CANERGY_DECODE_WRONG_DLC;
    }
    if (a->layout == CANERGY_AUTH_FD) {
        return fd_frame(a, frame, last_tx, return_seq, sup, verified);
    }
    const uint32_t kind = frame->id >> 8 & 0xFU;
    if (kind == CANERGY_AUTH_MAC_TO_CLIENT || kind == CANERGY_AUTH_MAC_TO_SUPERVISOR) {
        const uint32_t mine = a->receives == CANERGY_TO_CLIENT ? CANERGY_AUTH_MAC_TO_CLIENT
                                                               : CANERGY_AUTH_MAC_TO_SUPERVISOR;
        if (kind != mine) {
            return CANERGY_DECODE_WRONG_DIRECTION;
        }
        return mac_frame(a, frame, last_tx, return_seq, sup, verified);
    }
    return data_frame(a, frame);
}

int canergy_auth_accept(struct canergy_auth *a, const struct canergy_rx_frame *frame,
                        uint32_t last_tx, uint32_t return_seq, struct canergy_frame *verified)
{
    return accept(a, frame, last_tx, return_seq, NULL, verified);
}

/* Refused as the node's own direction (MAC frames 0x8 too) with its id: sent in its name. */
static bool in_its_name(const struct canergy_node *n, const struct canergy_rx_frame *f, int result)
{
    return result == CANERGY_DECODE_WRONG_DIRECTION && (f->id & 0xE00000FFUL) == n->client.node;
}

/* A joining client's ADMIT verified and taken: its full counters, whose high half the ADMIT's
 * FV carries (before out->persist is carried out). */
static void admitted_counters(const struct canergy_auth *a, struct canergy_client *c)
{
    const uint32_t high = a->admit_fv & 0xFFFF0000UL;
    c->rec.last_tx = high | (c->rec.last_tx & 0xFFFFU);
    c->rec.return_seq = high | (c->rec.return_seq & 0xFFFFU);
}

int canergy_auth_node_frame(struct canergy_auth *a, struct canergy_node *n,
                            const struct canergy_rx_frame *frame, uint64_t now,
                            struct canergy_out *out)
{
    if (a == NULL || n == NULL || out == NULL) {
        return CANERGY_ERR_ARGUMENT;
    }
    struct canergy_frame plain;
    a->admit_fv = 0U;
    const int result =
        canergy_auth_accept(a, frame, n->client.rec.last_tx, n->client.rec.return_seq, &plain);
    if (result != CANERGY_DECODE_OK) {
        canergy_internal_out_clear(out);
        if (in_its_name(n, frame, result)) {
            canergy_internal_witness(n, out, now);
        }
        return result;
    }
    const struct canergy_rx_frame rx = {plain.id, plain.data, plain.dlc, true, false};
    const bool joining = canergy_client_joining(&n->client); /* not a witnessed RESUME's ADMIT */
    const int taken = canergy_node_on_frame(n, &rx, now, out);
    if (joining && taken == CANERGY_DECODE_OK && (out->events & CANERGY_EV_ADMITTED) != 0U) {
        admitted_counters(a, &n->client);
    }
    return taken;
}

int canergy_auth_gateway_up_frame(struct canergy_auth *a, struct canergy_gateway *gw,
                                  const struct canergy_rx_frame *frame, uint64_t now,
                                  struct canergy_out *out)
{
    if (a == NULL || gw == NULL || out == NULL) {
        return CANERGY_ERR_ARGUMENT;
    }
    struct canergy_frame plain;
    a->admit_fv = 0U;
    const int result =
        canergy_auth_accept(a, frame, gw->up.rec.last_tx, gw->up.rec.return_seq, &plain);
    if (result != CANERGY_DECODE_OK) {
        canergy_internal_out_clear(out);
        return result;
    }
    const struct canergy_rx_frame rx = {plain.id, plain.data, plain.dlc, true, false};
    const bool joining = canergy_client_joining(&gw->up);
    const int taken = canergy_gateway_on_up_frame(gw, &rx, now, out);
    if (joining && taken == CANERGY_DECODE_OK && (out->events & CANERGY_EV_ADMITTED) != 0U) {
        admitted_counters(a, &gw->up);
    }
    return taken;
}

int canergy_auth_gateway_up_protect(const struct canergy_auth *a,
                                    const struct canergy_gateway *gw,
                                    const struct canergy_frame *plain,
                                    struct canergy_auth_frame out[2])
{
    if (gw == NULL) {
        return CANERGY_ERR_ARGUMENT;
    }
    return canergy_auth_protect(a, plain, gw->up.rec.last_tx, gw->up.rec.return_seq, out);
}

int canergy_auth_node_protect(const struct canergy_auth *a, const struct canergy_node *n,
                              const struct canergy_frame *plain, struct canergy_auth_frame out[2])
{
    if (n == NULL) {
        return CANERGY_ERR_ARGUMENT;
    }
    return canergy_auth_protect(a, plain, n->client.rec.last_tx, n->client.rec.return_seq, out);
}

/* The session index of node in gw->down (gw->down.count: none). */
static unsigned down_index(const struct canergy_gateway *gw, uint32_t node)
{
    unsigned i = 0U;
    while (i < gw->down.count && gw->down.sessions[i].node != node) {
        i++;
    }
    return i;
}

int canergy_auth_gateway_down_frame(struct canergy_auth *keys, const struct canergy_gateway *gw,
                                    const struct canergy_rx_frame *frame,
                                    struct canergy_frame *verified)
{
    if (keys == NULL || gw == NULL || frame == NULL || verified == NULL || gw->down.count == 0U) {
        return CANERGY_ERR_ARGUMENT;
    }
    const unsigned i = down_index(gw, frame->id & 0xFFU);
    if (i == gw->down.count) { /* the codec's refusal, else another node's (no key of ours) */
        const int status = accept(&keys[0], frame, 0U, 0U, NULL, verified);
        return status == CANERGY_DECODE_OK ? CANERGY_RX_OTHER_NODE : status;
    }
    const struct canergy_session *s = &gw->down.sessions[i];
    const struct sup_counters sup = {s->tx, s->returns_credited, sup_stale, sup_took};
    return accept(&keys[i], frame, s->tx, s->returns_credited, &sup, verified);
}

int canergy_auth_gateway_down_protect(const struct canergy_auth *keys,
                                      const struct canergy_gateway *gw,
                                      const struct canergy_frame *plain,
                                      struct canergy_auth_frame out[2])
{
    if (keys == NULL || gw == NULL || plain == NULL) {
        return CANERGY_ERR_ARGUMENT;
    }
    const unsigned i = down_index(gw, plain->id & 0xFFU);
    if (i == gw->down.count) {
        return CANERGY_ERR_ARGUMENT;
    }
    const struct canergy_session *s = &gw->down.sessions[i];
    return canergy_auth_protect(&keys[i], plain, s->tx, s->returns_credited, out);
}

void canergy_auth_node_key(const uint8_t master[CANERGY_KDF_KEY_SIZE], uint8_t node,
                           uint32_t epoch, uint8_t key[CANERGY_KDF_KEY_SIZE])
{
    static const uint8_t label[] = "canergy node key";
    const uint8_t context[5] = {node, (uint8_t)(epoch >> 24), (uint8_t)(epoch >> 16),
                                (uint8_t)(epoch >> 8), (uint8_t)epoch};
    canergy_kdf_cmac_ctr(master, label, sizeof label - 1U, context, sizeof context, key);
}
