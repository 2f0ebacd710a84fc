/*
 * The host's frame path in C (canergy/host.h): the binding's calls, built with the library into
 * the Python extension (src/canergy/ccore/build.py), never into a device port.
 */
#include "canergy/host.h"

#include "canergy/codec.h"

/* The session index of node, or sup->count when it is not managed. */
static uint8_t canergy_host_index(const struct canergy_supervisor *sup, uint32_t node)
{
    uint8_t i = 0U;
    while (i < sup->count && sup->sessions[i].node != node) {
        i++;
    }
    return i;
}

/* A received frame as the library takes it. */
static struct canergy_rx_frame canergy_host_rx(uint32_t id, const uint8_t *data, size_t len,
                                               unsigned kind)
{
    struct canergy_rx_frame rx = {0};
    rx.id = id;
    rx.data = data;
    rx.len = len;
    rx.extended = (kind & 1U) != 0U;
    rx.remote = (kind & 2U) != 0U;
    return rx;
}

int canergy_host_answer(struct canergy_supervisor *sup, struct canergy_host_tables *t,
    uint32_t id, unsigned kind, const uint8_t *data, size_t len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_msg *m)
{
    struct canergy_rx_frame rx = canergy_host_rx(id, data, len, kind);
    const int status = canergy_supervisor_on_answer(sup, &rx, now, abort_acks, out, m);
    if (t == NULL) {
        return status;
    }
    t->verdict = 0U;
    if (status != CANERGY_RX_CALLER) {
        return status;
    }
    const uint8_t i = canergy_host_index(sup, m->node);
    struct canergy_session *s = &sup->sessions[i];
    if (m->type == CANERGY_TELEMETRY) {
        t->verdict = canergy_heard_telemetry(&t->heard[i], s, m, now, t->lost_after_us);
        t->witness_before = t->witness[i];
        t->verdict |= canergy_witness_telemetry(&t->witness[i], m, s->returns_credited, now) << 8;
        t->joins_before = t->joins[i];
        t->verdict |= canergy_joins_telemetry(&t->joins[i], m->flags, now, t->join_hold_us[i],
                                              &t->admit) << 16;
        return status;
    }
    if (m->type == CANERGY_JOIN) {
        canergy_joins_join(&t->joins[i], m->nonce);
        t->verdict = CANERGY_HOST_JOIN;
        return status;
    }
    if (m->type != CANERGY_RETURN || canergy_witness_beyond_books(s, m)) {
        return status;
    }
    const uint32_t ahead = (m->seq - s->returns_credited) & 0xFFFFU; /* Python's unwrap - ref */
    if (t->hold && ahead != 0U && ahead < 0x8000U) {                   /* not credited yet */
        t->witness_before = t->witness[i];
        t->verdict = CANERGY_HOST_HELD |
                     (unsigned)canergy_witness_hold(&t->witness[i], m, s->returns_credited, now);
        return status;
    }
    return canergy_supervisor_on_msg(sup, m, now, out);
}

void canergy_host_auth_protect(const struct canergy_supervisor *sup,
    const struct canergy_auth *keys, const struct canergy_supervisor_out *out,
    struct canergy_auth_frame *sent, uint8_t *sent_count)
{
    *sent_count = 0U;
    for (uint8_t k = 0U; k < out->frame_count; k++) {
        const uint8_t j = canergy_host_index(sup, out->frames[k].id & 0xFFU);
        struct canergy_auth_frame two[2];
        const int made = j < sup->count ? canergy_auth_protect(&keys[j], &out->frames[k],
                                                                sup->sessions[j].tx,
                                                                sup->sessions[j].returns_credited,
                                                                two)
                                         : 0;
        for (int f = 0; f < made; f++) { /* none: each frame the rules send is a managed */
            sent[(*sent_count)++] = two[f]; /* node's, encoded by the codec */
        }
    }
}

int canergy_host_auth_answer(struct canergy_supervisor *sup, struct canergy_auth *keys,
    uint32_t id, unsigned kind, const uint8_t *data, size_t len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_auth_frame *sent, uint8_t *sent_count,
    uint32_t *fv)
{
    *sent_count = 0U;
    const uint32_t type = id >> 8 & 0xFU;
    if ((kind & 3U) != 1U || id > 0x1FFFFFFFUL || (id & CANERGY_ID_MASK) != sup->id_base ||
        (type != CANERGY_ACK && type != CANERGY_COMMITTED && type != CANERGY_ABORTED)) {
        return CANERGY_RX_CALLER;
    }
    const uint8_t i = canergy_host_index(sup, id & 0xFFU);
    if (i == sup->count || keys[i].layout != CANERGY_AUTH_FD) {
        return CANERGY_RX_OTHER_NODE;
    }
    const struct canergy_session *s = &sup->sessions[i];
    struct canergy_rx_frame rx = canergy_host_rx(id, data, len, 1U);
    struct canergy_frame plain;
    int status = canergy_auth_accept(&keys[i], &rx, s->tx, s->returns_credited, &plain);
    if (status != CANERGY_DECODE_OK) {
        return status;
    }
    const uint8_t *t = &data[len - CANERGY_AUTH_TRAILER];
    const uint32_t got = (uint32_t)t[0] << 24 | (uint32_t)t[1] << 16 | (uint32_t)t[2] << 8 | t[3];
    if (got != s->tx && (uint32_t)(s->tx - got) < 0x80000000UL) {
        return CANERGY_AUTH_STALE; /* before the session's tx: a replay (Python's _older) */
    }
    struct canergy_msg m;
    rx.data = plain.data;
    rx.len = plain.dlc;
    status = canergy_supervisor_on_answer(sup, &rx, now, abort_acks, out, &m);
    if (status != CANERGY_DECODE_OK) {
        return status;
    }
    *fv = got;
    canergy_host_auth_protect(sup, keys, out, sent, sent_count);
    return CANERGY_DECODE_OK;
}

int canergy_host_auth_pair(struct canergy_supervisor *sup, struct canergy_auth *keys,
    uint32_t data_id, const uint8_t *data, size_t data_len, uint32_t mac_id, unsigned mac_kind,
    const uint8_t *mac, size_t mac_len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_auth_frame *sent, uint8_t *sent_count,
    uint32_t *fv)
{
    *sent_count = 0U;
    const uint32_t type = data_id >> 8 & 0xFU;
    const uint32_t mac_of = (data_id & ~(uint32_t)0xF00U) | (uint32_t)CANERGY_AUTH_MAC_TO_SUPERVISOR << 8;
    if ((mac_kind & 3U) != 1U || data_id > 0x1FFFFFFFUL ||
        (data_id & CANERGY_ID_MASK) != sup->id_base || mac_id != mac_of ||
        (type != CANERGY_ACK && type != CANERGY_COMMITTED && type != CANERGY_ABORTED)) {
        return CANERGY_RX_CALLER;
    }
    const uint8_t i = canergy_host_index(sup, data_id & 0xFFU);
    if (i == sup->count || keys[i].layout != CANERGY_AUTH_CLASSIC) {
        return CANERGY_RX_OTHER_NODE;
    }
    struct canergy_auth *a = &keys[i];
    const struct canergy_session *s = &sup->sessions[i];
    struct canergy_rx_frame rx = canergy_host_rx(data_id, data, data_len, 1U);
    struct canergy_frame plain;
    a->pending_len = 0U;
    int status = canergy_auth_accept(a, &rx, s->tx, s->returns_credited, &plain);
    if (status != CANERGY_AUTH_PENDING) {
        a->pending_len = 0U;
        return status == CANERGY_DECODE_OK ? CANERGY_RX_CALLER : status;
    }
    rx.id = mac_id;
    rx.data = mac;
    rx.len = mac_len;
    status = canergy_auth_accept(a, &rx, s->tx, s->returns_credited, &plain);
    a->pending_len = 0U; /* taken by the MAC frame whatever it was */
    if (status != CANERGY_DECODE_OK) {
        return status;
    }
    struct canergy_msg m;
    rx.id = plain.id;
    rx.data = plain.data;
    rx.len = plain.dlc;
    if (canergy_decode(sup->id_base, &rx, CANERGY_TO_SUPERVISOR, &m) != CANERGY_DECODE_OK) {
        return CANERGY_RX_CALLER; /* it was verified, so it decoded: not reached */
    }
    const uint32_t got = ((uint32_t)mac[1] << 8 | mac[2]) << 16 |
                         (canergy_auth_freshness(&m, 0U, 0U) & 0xFFFFUL);
    if (got != s->tx && (uint32_t)(s->tx - got) < 0x80000000UL) {
        return CANERGY_AUTH_STALE; /* before the session's tx: a replay (Python's _older) */
    }
    status = canergy_supervisor_on_answer(sup, &rx, now, abort_acks, out, &m);
    if (status != CANERGY_DECODE_OK) {
        return status;
    }
    *fv = got;
    canergy_host_auth_protect(sup, keys, out, sent, sent_count);
    return CANERGY_DECODE_OK;
}
