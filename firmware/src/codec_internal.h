/*
 * Library-internal: a frame from its field values, for the client's and the node's own frames
 * (no struct canergy_msg to fill and read back).
 */
#ifndef CANERGY_CODEC_INTERNAL_H
#define CANERGY_CODEC_INTERNAL_H

#include "canergy/codec.h"

/* The frame of type code (a known one) from node (1..127): values[i] is the type's i-th field in
 * its layout's order (codec.c; unused ones 0), a 16-bit field's value below 2^16, a 24-bit
 * one's at most CANERGY_WIDE_MAX (canergy_encode refuses one that does not fit; the client's
 * only 24-bit field, TELEMETRY's level, is saturated). What canergy_encode writes, with its
 * refusal of a zero required amount (CANERGY_ERR_ARGUMENT, *out untouched). */
int canergy_internal_encode(uint32_t id_base, uint32_t code, uint32_t node,
                            const uint32_t values[4], struct canergy_frame *out);

/* canergy_decode without a DEBIT's flag checks, msg not NULL: for the client, which refuses
 * the client's direction, so that a DEBIT is CANERGY_DECODE_WRONG_DIRECTION before those checks
 * (which a node port then does not link) would be reached. The message is decoded in place:
 * *msg holds it on CANERGY_DECODE_OK, and is written but means nothing on OUT_OF_RANGE. */
enum canergy_decode_status canergy_internal_decode(uint32_t id_base,
                                                   const struct canergy_rx_frame *frame,
                                                   enum canergy_direction expect,
                                                   struct canergy_msg *msg);

#endif /* CANERGY_CODEC_INTERNAL_H */
