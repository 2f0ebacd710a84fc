/*
 * Wire format: layouts, CRC-8 and strict decoding (see include/canergy/codec.h).
 *
 * A layout is a list of at most four fields after the CRC byte; the DLC and whether the type
 * carries an amount (which must not be zero) follow from it, so the table below is the only
 * place a frame's shape is written down, as LAYOUTS is in codec.py.
 */
#include "canergy/codec.h"

#include "codec_internal.h"
#include "le.h"

#include <string.h>

enum field {
    F_END = 0,
    F_TX,        /* u16 */
    F_SEQ,       /* u16 */
    F_NONCE,     /* u16 */
    F_AMOUNT,    /* u16, 1..65535 */
    F_DELIVERED, /* u24 */
    F_LEVEL,     /* u24 */
    F_FLAGS,     /* u8 */
    F_WITNESS    /* u8 */
};

/* A type's fields after the CRC byte, four bits each, the first in the low bits. */
#define FIELDS(a, b, c, d) ((uint16_t)((a) | (b) << 4 | (c) << 8 | (d) << 12))

/* Indexed by the 4-bit type code; 0 (no field) is an unknown type. */
static const uint16_t layouts[16] = {
    [CANERGY_INTENTION] = FIELDS(F_TX, F_AMOUNT, F_DELIVERED, F_END),
    [CANERGY_COMMIT] = FIELDS(F_TX, F_AMOUNT, F_END, F_END),
    [CANERGY_ABORT] = FIELDS(F_TX, F_AMOUNT, F_END, F_END),
    [CANERGY_RETURN_ACK] = FIELDS(F_SEQ, F_END, F_END, F_END),
    [CANERGY_STATUS_REQUEST] = FIELDS(F_TX, F_END, F_END, F_END),
    [CANERGY_FINAL_ACK] = FIELDS(F_TX, F_END, F_END, F_END),
    [CANERGY_ADMIT] = FIELDS(F_NONCE, F_TX, F_SEQ, F_END),
    [CANERGY_ACK] = FIELDS(F_TX, F_END, F_END, F_END),
    [CANERGY_COMMITTED] = FIELDS(F_TX, F_END, F_END, F_END),
    [CANERGY_ABORTED] = FIELDS(F_TX, F_END, F_END, F_END),
    [CANERGY_RETURN] = FIELDS(F_SEQ, F_AMOUNT, F_END, F_END),
    [CANERGY_TELEMETRY] = FIELDS(F_LEVEL, F_FLAGS, F_SEQ, F_WITNESS),
    [CANERGY_JOIN] = FIELDS(F_NONCE, F_END, F_END, F_END),
    [CANERGY_DEBIT] = FIELDS(F_NONCE, F_FLAGS, F_SEQ, F_AMOUNT),
};

/* Bytes on the wire, by field. */
static const uint8_t widths[] = {
    [F_TX] = 2U, [F_SEQ] = 2U, [F_NONCE] = 2U, [F_AMOUNT] = 2U, [F_DELIVERED] = 3U,
    [F_LEVEL] = 3U, [F_FLAGS] = 1U, [F_WITNESS] = 1U,
};

/* 0 for an unknown type code. */
static size_t layout_dlc(uint32_t code)
{
    size_t dlc = 0U;
    for (unsigned fields = layouts[code & 0xFU]; fields != 0U; fields >>= 4) {
        dlc += widths[fields & 0xFU];
    }
    return dlc == 0U ? 0U : dlc + 1U;
}

size_t canergy_data_length(uint32_t type)
{
    return type > 0xFU ? 0U : layout_dlc(type);
}

/* A required amount is the second field (DEBIT's, the fourth, is optional). */
static bool has_amount(uint32_t code)
{
    return (layouts[code & 0xFU] >> 4 & 0xFU) == F_AMOUNT;
}

/* DEBIT is a draw (DRAW alone, an amount, no nonce), a resume (START, DRAW optional), or a
 * SYNC's answer: its counts (START | SYNC, RC_UNKNOWN optional: afresh) or its books (BOOKS
 * alone, 24 bits of Rc: the amount's high byte clear; with RC_UNKNOWN, none: both fields 0);
 * no other flags. codec.py's _debit_build. */
static bool debit_valid(const struct canergy_msg *m)
{
    /* the resumes and the counts: flags START, START | DRAW, START | SYNC (below 8) */
    const unsigned starts = 1U << CANERGY_DEBIT_START |
                            1U << (CANERGY_DEBIT_START | CANERGY_DEBIT_DRAW) |
                            1U << (CANERGY_DEBIT_START | CANERGY_DEBIT_SYNC);
    switch (m->flags) {
    case CANERGY_DEBIT_DRAW:
        return m->amount_mj != 0U && m->nonce == 0U;
    case CANERGY_DEBIT_BOOKS:
        return m->amount_mj <= 0xFFU;
    case CANERGY_DEBIT_BOOKS | CANERGY_DEBIT_RC_UNKNOWN:
        return m->seq == 0U && m->amount_mj == 0U;
    case CANERGY_DEBIT_COUNTS_AFRESH:
        return true;
    default:
        return m->flags < 8U && (starts >> m->flags & 1U) != 0U;
    }
}

uint8_t canergy_crc8(uint8_t reg, const uint8_t *data, size_t len)
{
    /* Bit by bit: at most 10 bytes per frame, and no 256-byte table in flash. */
    for (size_t i = 0U; i < len; i++) {
        reg ^= data[i];
        for (unsigned bit = 0U; bit < 8U; bit++) {
            const uint8_t poly = (reg & 0x80U) != 0U ? 0x1DU : 0x00U;
            reg = (uint8_t)((uint8_t)(reg << 1) ^ poly);
        }
    }
    return reg;
}

/* CRC of the Data ID (node, then type) followed by the body: byte 0 of the frame. */
static uint8_t frame_crc(uint32_t code, uint32_t node, const uint8_t *body, size_t len)
{
    const uint8_t data_id[2] = {(uint8_t)node, (uint8_t)code};
    uint8_t reg = canergy_crc8(0xFFU, data_id, sizeof data_id);
    return (uint8_t)(canergy_crc8(reg, body, len) ^ 0xFFU);
}

bool canergy_id_base_valid(uint32_t id_base)
{
    return (id_base & ~CANERGY_ID_MASK) == 0U;
}

static uint32_t field_value(const struct canergy_msg *m, uint8_t f)
{
    switch (f) {
    case F_TX: return m->tx;
    case F_SEQ: return m->seq;
    case F_NONCE: return m->nonce;
    case F_AMOUNT: return m->amount_mj;
    case F_DELIVERED: return m->delivered_mj;
    case F_LEVEL: return m->level_mj;
    case F_WITNESS: return m->witness;
    default: return m->flags;
    }
}

int canergy_internal_encode(uint32_t id_base, uint32_t code, uint32_t node,
                            const uint32_t values[4], struct canergy_frame *out)
{
    const size_t dlc = layout_dlc(code);
    if (has_amount(code) && values[1] == 0U) {
        return CANERGY_ERR_ARGUMENT;
    }
    memset(out->data, 0, sizeof out->data);
    size_t at = 1U;
    const uint32_t *v = values;
    for (unsigned fields = layouts[code]; fields != 0U; fields >>= 4) {
        const uint8_t width = widths[fields & 0xFU];
        le_put(&out->data[at], *v++, width);
        at += width;
    }
    out->data[0] = frame_crc(code, node, &out->data[1], dlc - 1U);
    out->id = id_base | code << 8 | node;
    out->dlc = (uint8_t)dlc;
    return CANERGY_OK;
}

int canergy_encode(uint32_t id_base, const struct canergy_msg *msg, struct canergy_frame *out)
{
    if (msg == NULL || out == NULL || !canergy_id_base_valid(id_base)) {
        return CANERGY_ERR_ARGUMENT;
    }
    const uint32_t code = msg->type;
    if (code > 0xFU || layouts[code] == 0U || msg->node < CANERGY_MIN_NODE ||
        msg->node > CANERGY_MAX_NODE) {
        return CANERGY_ERR_ARGUMENT;
    }
    uint32_t values[4]; /* the layout's fields: all that canergy_internal_encode reads */
    uint32_t *v = values;
    for (unsigned fields = layouts[code]; fields != 0U; fields >>= 4) {
        const uint8_t f = (uint8_t)(fields & 0xFU);
        *v = field_value(msg, f);
        if (widths[f] == 3U && *v > CANERGY_WIDE_MAX) {
            return CANERGY_ERR_ARGUMENT; /* a 24-bit field that does not fit */
        }
        v++;
    }
    return canergy_internal_encode(id_base, code, msg->node, values, out);
}

static bool wrong_way(uint32_t code, enum canergy_direction expect)
{
    const bool from_client = (code & CANERGY_FROM_CLIENT) != 0U;
    return (expect == CANERGY_TO_CLIENT && from_client) ||
           (expect == CANERGY_TO_SUPERVISOR && !from_client);
}

/* The identifier checks come first, in codec.py's order: only an exact id_base | known type |
 * node 1..127 passes; what fails is FOREIGN outside the block, then UNKNOWN_TYPE, then
 * BAD_NODE. A DEBIT's flag checks are canergy_decode's (codec_internal.h). */
enum canergy_decode_status canergy_internal_decode(uint32_t id_base,
                                                   const struct canergy_rx_frame *frame,
                                                   enum canergy_direction expect,
                                                   struct canergy_msg *msg)
{
    if (frame == NULL || !frame->extended || (frame->id & CANERGY_ID_MASK) != id_base) {
        return CANERGY_DECODE_FOREIGN;
    }
    const uint32_t code = frame->id >> 8 & 0xFU;
    const size_t dlc = layout_dlc(code);
    if (dlc == 0U) {
        return CANERGY_DECODE_UNKNOWN_TYPE;
    }
    const uint32_t node = frame->id & 0xFFU;
    if (node < CANERGY_MIN_NODE || node > CANERGY_MAX_NODE || (frame->id >> 29) != 0U) {
        return CANERGY_DECODE_BAD_NODE;
    }
    if (frame->remote) {
        return CANERGY_DECODE_REMOTE_FRAME;
    }
    if (wrong_way(code, expect)) {
        return CANERGY_DECODE_WRONG_DIRECTION;
    }
    if (frame->len != dlc || frame->data == NULL) {
        return CANERGY_DECODE_WRONG_DLC;
    }
    const uint8_t *d = frame->data;
    if (frame_crc(code, node, &d[1], dlc - 1U) != d[0]) {
        return CANERGY_DECODE_BAD_CRC;
    }
    uint32_t v[F_WITNESS + 1U] = {0}; /* by field (enum field): 0 where the type has none */
    size_t at = 1U;
    for (unsigned fields = layouts[code]; fields != 0U; fields >>= 4) {
        const uint8_t f = (uint8_t)(fields & 0xFU);
        v[f] = le_get(&d[at], widths[f]);
        at += widths[f];
    }
    msg->delivered_mj = v[F_DELIVERED];
    msg->level_mj = v[F_LEVEL];
    msg->tx = (uint16_t)v[F_TX];
    msg->seq = (uint16_t)v[F_SEQ];
    msg->nonce = (uint16_t)v[F_NONCE];
    msg->amount_mj = (uint16_t)v[F_AMOUNT];
    msg->type = (uint8_t)code;
    msg->node = (uint8_t)node;
    msg->flags = (uint8_t)v[F_FLAGS];
    msg->witness = (uint8_t)v[F_WITNESS];
    return has_amount(code) && msg->amount_mj == 0U ? CANERGY_DECODE_OUT_OF_RANGE
                                                    : CANERGY_DECODE_OK;
}

enum canergy_decode_status canergy_decode(uint32_t id_base, const struct canergy_rx_frame *frame,
                                          enum canergy_direction expect, struct canergy_msg *msg)
{
    struct canergy_msg m;
    enum canergy_decode_status status = canergy_internal_decode(id_base, frame, expect, &m);
    if (status == CANERGY_DECODE_OK && m.type == CANERGY_DEBIT && !debit_valid(&m)) {
        status = CANERGY_DECODE_OUT_OF_RANGE;
    }
    if (status == CANERGY_DECODE_OK && msg != NULL) {
        *msg = m;
    }
    return status;
}
