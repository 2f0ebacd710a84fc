/*
 * The NV record and its two slots (see include/canergy/nv.h and firmware_model/nvstore.py).
 *
 * Why two slots: a write goes to the slot that does not hold the newest valid record, so a
 * power loss mid-write leaves that record readable. Nothing is acted on before its write has
 * completed, so the record a torn write falls back to was the last one anybody relied on.
 */
#include "canergy/nv.h"

#include "canergy/cmac.h"
#include "canergy/codec.h"
#include "canergy/gateway.h"
#include "le.h"

#include <string.h>

#define HEAD_SIZE 6U /* u16 magic, u32 counter */
#define CRC_AT (HEAD_SIZE + CANERGY_NV_RECORD_SIZE)
/* The record's seven u32 words (usable, Rc, spent low and high, ltx, q, pending), then two bytes */
#define RECORD_WORDS 7U

uint32_t canergy_crc32(uint32_t crc, const uint8_t *data, size_t len)
{
    /* Reflected polynomial 0xEDB88320, bit by bit: 36 bytes per slot, only at start and on a
     * write, so no 1 KiB table. */
    crc = ~crc;
    for (size_t i = 0U; i < len; i++) {
        crc ^= data[i];
        for (unsigned bit = 0U; bit < 8U; bit++) {
            crc = (crc & 1U) != 0U ? (crc >> 1) ^ 0xEDB88320UL : crc >> 1;
        }
    }
    return ~crc;
}

void canergy_record_pack(const struct canergy_record *rec, uint8_t out[CANERGY_NV_RECORD_SIZE])
{
    const uint32_t words[RECORD_WORDS] = {rec->usable_uj,
                               rec->credited_mj,
                               (uint32_t)rec->spent_uj,
                               (uint32_t)(rec->spent_uj >> 32),
                               rec->last_tx,
                               rec->return_seq,
                               rec->return_pending_uj};
    for (size_t i = 0U; i < RECORD_WORDS; i++) {
        le_put(&out[4U * i], words[i], 4U);
    }
    out[28] = rec->outcome;
    out[29] = (uint8_t)(rec->flags & CANERGY_RECORD_FLAGS);
}

/* A pending return the client can have sent: none, or one frame's worth of whole mJ. */
static bool return_possible(uint32_t pending_uj)
{
    return pending_uj == 0U || (pending_uj % CANERGY_QUANTUM_UJ == 0U &&
                                pending_uj <= CANERGY_AMOUNT_MAX_MJ * CANERGY_QUANTUM_UJ);
}

int canergy_record_unpack(const uint8_t in[CANERGY_NV_RECORD_SIZE], struct canergy_record *rec)
{
    uint32_t words[RECORD_WORDS];
    for (size_t i = 0U; i < RECORD_WORDS; i++) {
        words[i] = le_get(&in[4U * i], 4U);
    }
    const struct canergy_record r = {
        .spent_uj = (uint64_t)words[3] << 32 | words[2],
        .usable_uj = words[0], /* a u32 never exceeds USABLE_MAX_UJ */
        .credited_mj = words[1],
        .last_tx = words[4],
        .return_seq = words[5],
        .return_pending_uj = words[6],
        .outcome = in[28],
        .flags = (uint8_t)(in[29] & CANERGY_RECORD_FLAGS),
    };
    const bool draw_of_nothing =
        (r.flags & CANERGY_RECORD_PENDING_DRAW) != 0U && r.return_pending_uj == 0U;
    if (r.outcome > CANERGY_OUTCOME_WRITTEN_OFF || !return_possible(r.return_pending_uj) ||
        draw_of_nothing) {
        return CANERGY_ERR_ARGUMENT; /* a CRC collision over garbage: not books */
    }
    *rec = r;
    if (r.last_tx >= CANERGY_COUNTER_BOUND || r.return_seq >= CANERGY_COUNTER_BOUND) {
        return CANERGY_ERR_END; /* beyond the bound the proof assumes: not books either */
    }
    return CANERGY_OK;
}

void canergy_nv_slot_encode(uint32_t counter, const uint8_t *payload, size_t len,
                            uint8_t out[CANERGY_NV_SLOT_SIZE])
{
    memset(out, 0, CANERGY_NV_SLOT_SIZE);
    le_put(&out[0], CANERGY_NV_MAGIC, 2U);
    le_put(&out[2], counter, 4U);
    if (payload != NULL) {
        memcpy(&out[HEAD_SIZE], payload, len < CANERGY_NV_RECORD_SIZE ? len : CANERGY_NV_RECORD_SIZE);
    }
    le_put(&out[CRC_AT], canergy_crc32(0U, out, CRC_AT), 4U);
}

/* A whole slot whose magic and CRC hold: its counter into *counter. */
static bool slot_valid(const uint8_t *raw, size_t len, uint32_t *counter)
{
    if (raw == NULL || len != CANERGY_NV_SLOT_SIZE || le_get(raw, 2U) != CANERGY_NV_MAGIC ||
        canergy_crc32(0U, raw, CRC_AT) != le_get(&raw[CRC_AT], 4U)) {
        return false;
    }
    *counter = le_get(&raw[2], 4U);
    return true;
}

bool canergy_nv_slot_decode(const uint8_t *raw, size_t len, uint32_t *counter,
                            uint8_t payload[CANERGY_NV_RECORD_SIZE])
{
    if (!slot_valid(raw, len, counter)) {
        return false;
    }
    memcpy(payload, &raw[HEAD_SIZE], CANERGY_NV_RECORD_SIZE);
    return true;
}

/* Bytes of slot i present in an image of len bytes (a short image lacks the tail). */
static size_t slot_bytes(size_t len, size_t i)
{
    const size_t start = i * CANERGY_NV_SLOT_SIZE;
    if (len <= start) {
        return 0U;
    }
    return len - start < CANERGY_NV_SLOT_SIZE ? len - start : CANERGY_NV_SLOT_SIZE;
}

static bool all_zero(const uint8_t *p, size_t n)
{
    for (size_t i = 0U; i < n; i++) {
        if (p[i] != 0U) {
            return false;
        }
    }
    return true;
}

void canergy_nv_load(const uint8_t *image, size_t len, struct canergy_nv_state *out)
{
    memset(out, 0, sizeof *out);
    out->newest_slot = 1U; /* none valid: the first write goes to slot 0 */
    if (image == NULL) {
        len = 0U;
    }
    bool found = false;
    for (size_t i = 0U; i < CANERGY_NV_SLOTS; i++) {
        const size_t n = slot_bytes(len, i);
        const uint8_t *raw = n != 0U ? &image[i * CANERGY_NV_SLOT_SIZE] : NULL;
        uint32_t counter = 0U;
        if (!slot_valid(raw, n, &counter)) {
            if (n != 0U && !all_zero(raw, n)) {
                out->fallbacks = 1U; /* a torn or corrupted write; an erased slot is not damage */
            }
        } else if (!found || (uint32_t)(counter - out->counter) < 0x80000000UL) {
            /* Both valid: slot 1 is newer when its counter is at most 2^31 - 1 ahead of slot
             * 0's (serial-number order, so the choice survives the counter's wrap; equal:
             * slot 1). */
            found = true;
            out->counter = counter;
            out->newest_slot = (uint8_t)i;
        }
    }
    if (!found) {
        return;
    }
    const uint8_t *newest = &image[out->newest_slot * CANERGY_NV_SLOT_SIZE + HEAD_SIZE];
    if (canergy_record_unpack(newest, &out->record) == CANERGY_OK) {
        out->books = true;
    } else {
        out->fallbacks++; /* the newest valid slot holds impossible values: no books */
    }
}

/* ---- the seal of a keyed node's or gateway's slots (canergy/nv.h) ---- */

void canergy_nv_seal_key(struct canergy_cmac *seal, const uint8_t key[16], uint8_t node,
                         bool gateway)
{
    static const char node_label[] = "canergy node nv seal";
    static const char gateway_label[] = "canergy gateway nv seal";
    uint8_t derived[CANERGY_KDF_KEY_SIZE];
    const char *label = gateway ? gateway_label : node_label;
    const size_t len = gateway ? sizeof gateway_label - 1U : sizeof node_label - 1U;
    canergy_kdf_cmac_ctr(key, (const uint8_t *)label, len, &node, 1U, derived);
    canergy_cmac_init(seal, derived);
    canergy_wipe(derived, sizeof derived);
}

void canergy_nv_seal(const struct canergy_cmac *seal, const uint8_t *slot, size_t len,
                     uint8_t out[CANERGY_NV_SEAL_SIZE])
{
    uint8_t tag[CANERGY_CMAC_SIZE];
    canergy_cmac(seal, slot, len, tag);
    memcpy(out, tag, CANERGY_NV_SEAL_SIZE);
}

unsigned canergy_nv_unseal(const struct canergy_cmac *seal, uint8_t *image, size_t image_len,
                           size_t slot_size, unsigned count, const uint8_t *seals)
{
    unsigned spoilt = 0U;
    for (unsigned i = 0U; i < count; i++) {
        uint8_t *slot = &image[i * slot_size];
        if (image_len < (i + 1U) * slot_size || all_zero(slot, slot_size)) {
            continue; /* absent or erased: no record to take, nothing to check */
        }
        uint8_t tag[CANERGY_NV_SEAL_SIZE];
        canergy_nv_seal(seal, slot, slot_size, tag);
        if (!canergy_mac_equal(tag, &seals[i * CANERGY_NV_SEAL_SIZE], CANERGY_NV_SEAL_SIZE)) {
            slot[slot_size - 1U] ^= 0xFFU; /* its CRC no longer holds: a damaged slot */
            spoilt |= 1U << i;
        }
    }
    return spoilt;
}

/* ---- the gateway's slot (canergy/gateway.h) ---- */

#define GW_SLOT CANERGY_GW_NV_SLOT_SIZE
#define GW_CRC_AT (GW_SLOT - 4U)
/* The slot before the supervisor record's version 3 (32 bytes per node): refused by name. */
#define GW_SLOT_V2                                                                                \
    (CANERGY_GW_NV_HEADER + CANERGY_NV_RECORD_SIZE + 40U + 32U * CANERGY_SUPERVISOR_NODES + 4U)
/* The slot of the supervisor record's versions 3 and 4 (44 bytes per node, before the last JOIN
 * admitted was kept): refused by name. */
#define GW_SLOT_V4                                                                                \
    (CANERGY_GW_NV_HEADER + CANERGY_NV_RECORD_SIZE + 40U + 44U * CANERGY_SUPERVISOR_NODES + 4U)
#define GW_VERSION_AT (CANERGY_GW_NV_HEADER + CANERGY_NV_RECORD_SIZE + 4U)

void canergy_gateway_nv_encode(const struct canergy_gateway *gw, uint32_t counter,
                               uint8_t out[CANERGY_GW_NV_SLOT_SIZE])
{
    memset(out, 0, GW_SLOT);
    le_put(out, (uint32_t)CANERGY_GW_NV_MAGIC, 4U);
    le_put(&out[4], counter, 4U);
    canergy_record_pack(&gw->up.rec, &out[CANERGY_GW_NV_HEADER]);
    (void)canergy_supervisor_image(&gw->down, counter,
                                   &out[CANERGY_GW_NV_HEADER + CANERGY_NV_RECORD_SIZE]);
    le_put(&out[GW_CRC_AT], canergy_crc32(0U, out, GW_CRC_AT), 4U);
}

/* A slot of size bytes at s (within len bytes from image): its magic and CRC hold. */
static bool gw_slot_valid(const uint8_t *image, size_t len, size_t at, size_t size)
{
    if (len < at + size) {
        return false;
    }
    const uint8_t *s = &image[at];
    return le_get(s, 4U) == CANERGY_GW_NV_MAGIC &&
           le_get(&s[size - 4U], 4U) == canergy_crc32(0U, s, size - 4U);
}

int canergy_gateway_nv_load(const uint8_t *image, size_t len, struct canergy_gateway_nv *out)
{
    memset(out, 0, sizeof *out);
    out->slot = -1;
    if (image == NULL) {
        len = 0U;
    }
    out->foreign = len > 0U && le_get(image, len < 4U ? len : 4U) != CANERGY_GW_NV_MAGIC &&
                   (len < GW_SLOT + 4U || le_get(&image[GW_SLOT], 4U) != CANERGY_GW_NV_MAGIC);
    for (size_t i = 0U; i < 2U; i++) {
        const bool current = gw_slot_valid(image, len, i * GW_SLOT, GW_SLOT);
        if (gw_slot_valid(image, len, i * GW_SLOT_V2, GW_SLOT_V2)) {
            out->older = 2U;
        } else if (current && (image[i * GW_SLOT + GW_VERSION_AT] == 3U ||
                               image[i * GW_SLOT + GW_VERSION_AT] == 4U)) {
            out->older = out->older == 0U ? image[i * GW_SLOT + GW_VERSION_AT] : out->older;
        } else if (!current && gw_slot_valid(image, len, i * GW_SLOT_V4, GW_SLOT_V4) &&
                   (image[i * GW_SLOT_V4 + GW_VERSION_AT] == 3U ||
                    image[i * GW_SLOT_V4 + GW_VERSION_AT] == 4U)) {
            out->older = out->older == 0U ? image[i * GW_SLOT_V4 + GW_VERSION_AT] : out->older;
        } else if (!current && len >= i * GW_SLOT + 4U &&
                   le_get(&image[i * GW_SLOT], 4U) == CANERGY_GW_NV_MAGIC) {
            out->damaged |= (uint8_t)(1U << i);
        }
    }
    for (size_t i = 0U; i < 2U; i++) {
        if (!gw_slot_valid(image, len, i * GW_SLOT, GW_SLOT)) {
            continue;
        }
        const uint8_t *s = &image[i * GW_SLOT];
        const uint32_t c = le_get(&s[4], 4U);
        struct canergy_record rec;
        const int unpacked = canergy_record_unpack(&s[CANERGY_GW_NV_HEADER], &rec);
        if (unpacked == CANERGY_ERR_END) {
            out->up = rec;
            out->slot = -1;
            out->down = NULL;
            return CANERGY_ERR_END;
        }
        if (unpacked != CANERGY_OK) {
            continue;
        }
        if (out->slot < 0 || (uint32_t)(c - out->counter) - 1U < 0x7FFFFFFFUL) {
            out->slot = (int8_t)i;
            out->counter = c;
            out->up = rec;
            out->down = &s[CANERGY_GW_NV_HEADER + CANERGY_NV_RECORD_SIZE];
        }
    }
    return CANERGY_OK;
}
