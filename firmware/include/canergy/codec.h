/*
 * canergy wire format: one classic CAN data frame per message, 29-bit identifier
 * id_base | type << 8 | node, byte 0 an E2E CRC-8 (SAE J1850) over the 16-bit Data ID
 * (type << 8 | node, low byte first) and data bytes 1..n; fields little-endian.
 * See docs/protocol.md, "Frames". This mirrors src/canergy/codec.py exactly, including the
 * order in which a bad frame's reason is chosen.
 *
 * Every function here is total: any identifier, length and bytes give either a message or a
 * decode status naming the first check that failed. No heap, no globals that change.
 */
#ifndef CANERGY_CODEC_H
#define CANERGY_CODEC_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "canergy/status.h" /* CANERGY_OK, CANERGY_ERR_*, the decode statuses */

#ifdef __cplusplus
extern "C" {
#endif

/* The theorem's bounded life (canergy prove, assumption 4): a record holding a counter (tx,
 * return number) at or beyond CANERGY_COUNTER_BOUND is refused when it is loaded, and no rule
 * moves one to CANERGY_COUNTER_END or beyond (2^30 - 2^16: an admission's lift stays below it).
 * Python's canergy.messages.COUNTER_BOUND and COUNTER_END. */
#define CANERGY_COUNTER_BOUND 0x40000000UL
#define CANERGY_COUNTER_END 0x3FFF0000UL

#define CANERGY_DEFAULT_ID_BASE 0x0CE00000UL
#define CANERGY_ID_MASK 0x1FFFF000UL   /* the bits id_base owns; its low 12 bits are clear */
#define CANERGY_QUANTUM_UJ 1000UL      /* one wire energy unit: 1 mJ */
#define CANERGY_AMOUNT_MAX_MJ 0xFFFFUL /* most one frame carries: 65.535 J */
#define CANERGY_USABLE_MAX_UJ 0xFFFFFFFFUL
#define CANERGY_WIDE_MAX 0xFFFFFFUL    /* 24-bit fields: delivered Gs, telemetry level */
#define CANERGY_MIN_NODE 1U
#define CANERGY_MAX_NODE 127U

/* 4-bit type codes; bit 3 set means client -> supervisor. */
enum canergy_type {
    CANERGY_INTENTION = 0x1,
    CANERGY_COMMIT = 0x2,
    CANERGY_ABORT = 0x3,
    CANERGY_RETURN_ACK = 0x4,
    CANERGY_STATUS_REQUEST = 0x5, /* paper variant only: decoded, ignored by this client */
    CANERGY_FINAL_ACK = 0x6,      /* paper variant only: decoded, ignored by this client */
    CANERGY_ADMIT = 0x7,
    CANERGY_ACK = 0x9,
    CANERGY_COMMITTED = 0xA,
    CANERGY_ABORTED = 0xB,
    CANERGY_RETURN = 0xC,
    CANERGY_TELEMETRY = 0xD,
    CANERGY_JOIN = 0xE,
    CANERGY_DEBIT = 0xF /* witnessed rules: a numbered draw, a start (RESUME), a SYNC's answer */
};

#define CANERGY_FROM_CLIENT 0x8U /* the direction bit of a type code */

/* TELEMETRY flags */
#define CANERGY_TELEMETRY_LOW 0x01U
#define CANERGY_TELEMETRY_HALTED 0x02U
#define CANERGY_TELEMETRY_JOINING 0x04U
/* the sender runs the witnessed client rules (a node; a gateway: its rules above). A supervisor
 * whose rules differ grants it nothing: it moves no energy, so one forged only withholds grants */
#define CANERGY_TELEMETRY_WITNESSED 0x08U

/* DEBIT flags: DRAW alone is a draw (an amount, nonce 0); START is a resume (RESUME), DRAW set
 * when its pending amount is a draw rather than a return; START | SYNC is the counts answering a
 * supervisor's SYNC (seq the node's last debit number, amount_mj its ltx; RC_UNKNOWN set:
 * CANERGY_DEBIT_COUNTS_AFRESH); BOOKS alone is the
 * books answering it (Rc in mJ: its low 16 bits in seq, its high 8 in amount_mj). Decoding
 * refuses any other mix, and books above 24 bits, as CANERGY_DECODE_OUT_OF_RANGE; encoding
 * writes what it is given, as codec.py does. */
#define CANERGY_DEBIT_DRAW 0x01U
#define CANERGY_DEBIT_START 0x02U
#define CANERGY_DEBIT_SYNC 0x04U
#define CANERGY_DEBIT_BOOKS 0x08U
/* With BOOKS: the node's Rc is unknown (admitted, no fresh intention since; holds nothing). */
#define CANERGY_DEBIT_RC_UNKNOWN 0x10U
#define CANERGY_DEBIT_COUNTS (CANERGY_DEBIT_START | CANERGY_DEBIT_SYNC)
/* The counts of a node admitted afresh that has taken no fresh intention since (its books
 * unknown or a floor its record kept): messages.py's Debit.afresh. */
#define CANERGY_DEBIT_COUNTS_AFRESH (CANERGY_DEBIT_COUNTS | CANERGY_DEBIT_RC_UNKNOWN)

/* The ADMIT confirming the answer to SYNC(n) carries n with this bit flipped (messages.py's
 * SYNC_CONFIRMED). */
#define CANERGY_SYNC_CONFIRMED 0x8000U

enum canergy_direction {
    CANERGY_EITHER_WAY = 0,
    CANERGY_TO_CLIENT = 1,
    CANERGY_TO_SUPERVISOR = 2
};

/*
 * One message. Which fields a type uses (the others are zero after decoding):
 *   INTENTION      tx, amount_mj, delivered_mj (Gs, 24 bit)
 *   COMMIT, ABORT  tx, amount_mj
 *   RETURN_ACK     seq
 *   STATUS_REQUEST, FINAL_ACK, ACK, COMMITTED, ABORTED   tx
 *   ADMIT          nonce, tx, seq
 *   RETURN         seq, amount_mj
 *   TELEMETRY      level_mj (24 bit), flags, seq (the client's return number, as its RETURN
 *                  frames carry it), witness (frames seen in its name that it did not send)
 *   JOIN           nonce
 *   DEBIT          nonce, flags, seq, amount_mj (0 allowed in a resume)
 */
struct canergy_msg {
    uint32_t delivered_mj;
    uint32_t level_mj;
    uint16_t tx;
    uint16_t seq;
    uint16_t nonce;
    uint16_t amount_mj;
    uint8_t type;
    uint8_t node;
    uint8_t flags;
    uint8_t witness;
};

/* A frame to transmit: always a 29-bit (extended) data frame. */
struct canergy_frame {
    uint32_t id;
    uint8_t dlc;
    uint8_t data[8];
};

/* A frame as received. len is the payload length as the driver reports it; anything but the
 * type's DLC (so anything above 8, e.g. a CAN FD frame) is CANERGY_DECODE_WRONG_DLC. data may
 * be NULL only when len is 0. */
struct canergy_rx_frame {
    uint32_t id;
    const uint8_t *data;
    size_t len;
    bool extended;
    bool remote;
};

/* True for a 29-bit base with its low 12 bits clear. */
bool canergy_id_base_valid(uint32_t id_base);

/* The frame for msg. CANERGY_ERR_ARGUMENT (and *out untouched) when the type is unknown, the
 * node is not 1..127, an amount is not 1..65535 mJ or a 24-bit field does not fit. */
int canergy_encode(uint32_t id_base, const struct canergy_msg *msg, struct canergy_frame *out);

/* Strict decoding. expect: the direction the caller listens to (CANERGY_EITHER_WAY: both).
 * *msg is written only on CANERGY_DECODE_OK; msg may be NULL to validate only. */
enum canergy_decode_status canergy_decode(uint32_t id_base, const struct canergy_rx_frame *frame,
                                          enum canergy_direction expect,
                                          struct canergy_msg *msg);

/* The classic data length of a type code (CRC byte and fields, 2..8); 0 for a code no message
 * uses (0x0, 0x8, or above 0xF). Python's Codec.data_length. */
size_t canergy_data_length(uint32_t type);

/* CRC-8 SAE J1850 register update (no final XOR): crc = canergy_crc8(0xFF, p, n) ^ 0xFF. */
uint8_t canergy_crc8(uint8_t reg, const uint8_t *data, size_t len);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_CODEC_H */
