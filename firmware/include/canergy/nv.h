/*
 * The client's non-volatile record and its two-slot store, byte for byte as
 * firmware_model/nvstore.py lays it out, so an NV image moves between the Python emulator and
 * a C node in both directions.
 *
 * Record (30 bytes, little-endian, packed):
 *   u32 usable_uj, u32 credited_mj (Rc modulo 2^32), u64 spent_uj, u32 last_tx (mod 2^32),
 *   u32 return_seq (mod 2^32), u32 return_pending_uj, u8 outcome, u8 flags (bit 0: admitted
 *   without books, Rc comes with the next fresh intention; bit 1, witnessed rules only: the
 *   pending debit is a draw for the actuator, not a return)
 * Slot (40 bytes): u16 magic 0xCE57, u32 counter, the record, u32 CRC-32 (zlib) over the 36
 * bytes before it.
 * Image: slot 0 at offset 0, slot 1 at offset 40; firmware_model keeps its parameters in a third
 * slot at offset 80, which this library never writes: a port must leave it alone.
 *
 * The library never writes storage itself: it hands the port a complete slot image and the slot
 * to put it in (see canergy_out in client.h). The port only reads the image back at start.
 *
 * Sealed image (a node or gateway that holds a key: docs/security.md, "The NV seal"): the same
 * slots, then one seal per record slot after everything else, 8 bytes each: the first 8 bytes
 * of AES-CMAC(seal key, the whole slot image). A node's image is then 136 bytes (seals at 120
 * and 128, after the parameter slot, which is configuration and not sealed); a gateway's
 * 2 * CANERGY_GW_NV_SLOT_SIZE + 16. The seal key is derived from the node's key (or the
 * gateway's) by the KDF of canergy/cmac.h, label "canergy node nv seal" (a gateway's:
 * "canergy gateway nv seal"), context the node id (1 byte): never the key of a frame MAC, so
 * no MAC on the bus verifies as a seal nor a seal as a frame's MAC. A port writes the slot,
 * then its seal, then syncs: a write torn between the two leaves that slot unsealed, which is
 * the slot not holding the newest record (the one the load falls back to).
 */
#ifndef CANERGY_NV_H
#define CANERGY_NV_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "canergy/cmac.h"

#ifdef __cplusplus
extern "C" {
#endif

#define CANERGY_NV_RECORD_SIZE 30U
#define CANERGY_NV_SLOT_SIZE 40U
#define CANERGY_NV_SLOTS 2U      /* the record's slots: offsets 0 and 40 */
#define CANERGY_NV_PARAM_SLOT 2U /* firmware_model's parameter slot, offset 80: not ours */
#define CANERGY_NV_MAGIC 0xCE57U

#define CANERGY_RECORD_CREDITED_UNKNOWN 0x01U
/* The witnessed rules' record: the pending debit (return_pending_uj, number return_seq) is a
 * DRAW. A record with it set is refused by a client running the hardened rules (it would
 * re-send the draw as a RETURN): it starts without books. A record without it means the same
 * under both rule sets. Other bits are ignored, as firmware_model's store ignores them. */
#define CANERGY_RECORD_PENDING_DRAW 0x02U
#define CANERGY_RECORD_FLAGS (CANERGY_RECORD_CREDITED_UNKNOWN | CANERGY_RECORD_PENDING_DRAW)
/* A record found behind keeps its Rc as its books' floor with CREDITED_UNKNOWN set, and
 * credited_mj 0 then means no floor: a known Rc of 0 is kept as this (the same 24 bits on the
 * wire), Python's witnessed.ZERO_FLOOR_UJ. */
#define CANERGY_ZERO_FLOOR_MJ 0x01000000U

/* How the last resolved transaction ended (Python's Outcome; WRITTEN_OFF is the supervisor's
 * but a record holding it is still a valid record, as in Python). */
enum canergy_outcome {
    CANERGY_OUTCOME_NONE = 0,
    CANERGY_OUTCOME_COMMITTED = 1,
    CANERGY_OUTCOME_ABORTED = 2,
    CANERGY_OUTCOME_SETTLED = 3,
    CANERGY_OUTCOME_WRITTEN_OFF = 4
};

/* The books: everything that survives a power loss. Counters are kept modulo 2^32 (see
 * README.md, "Counters"): 2^32 is a multiple of the wire's 2^16 and 2^24, so every serial
 * comparison with a wire value comes out as with Python's unbounded integers. */
struct canergy_record {
    uint8_t outcome;
    uint8_t flags;
    uint32_t usable_uj;
    uint32_t credited_mj;
    uint32_t last_tx;
    uint32_t return_seq;
    uint32_t return_pending_uj;
    uint64_t spent_uj;
};

/* What canergy_nv_load found in an image. */
struct canergy_nv_state {
    uint32_t counter;             /* counter of the newest valid slot (0 when none) */
    uint8_t newest_slot;          /* slot of that record; 1 when none, so slot 0 comes first */
    bool books;                   /* a record to trust; false: the node must JOIN */
    uint8_t fallbacks;            /* as NvStats.fallbacks: +1 a damaged slot, +1 impossible values */
    struct canergy_record record; /* valid when books is true */
};

/* Layout of one record. unpack refuses (CANERGY_ERR_ARGUMENT) values no client writes: an
 * outcome above 4, a pending draw flag with nothing pending, or a pending return that is not 0
 * or 1..65535 whole mJ (the Python store
 * accepts the latter and would fail later when re-sending it; see README.md); and
 * (CANERGY_ERR_END, *rec filled for the caller's message) a last_tx or return_seq at or beyond
 * CANERGY_COUNTER_BOUND. canergy_nv_load takes either as no books: the node JOINs. */
void canergy_record_pack(const struct canergy_record *rec, uint8_t out[CANERGY_NV_RECORD_SIZE]);
int canergy_record_unpack(const uint8_t in[CANERGY_NV_RECORD_SIZE], struct canergy_record *rec);

/* A slot image of up to 30 payload bytes (zero-padded), e.g. the record or parameters. */
void canergy_nv_slot_encode(uint32_t counter, const uint8_t *payload, size_t len,
                            uint8_t out[CANERGY_NV_SLOT_SIZE]);
/* True when raw holds exactly one slot (len 40) with the magic and a matching CRC-32. */
bool canergy_nv_slot_decode(const uint8_t *raw, size_t len, uint32_t *counter,
                            uint8_t payload[CANERGY_NV_RECORD_SIZE]);

/* Read an image of len bytes (what the port read from offset 0; shorter images simply lack
 * slots). Picks the valid slot written last, comparing counters as 32-bit serial numbers. */
void canergy_nv_load(const uint8_t *image, size_t len, struct canergy_nv_state *out);

#define CANERGY_NV_SEAL_SIZE 8U     /* seal bytes per slot: a truncated AES-CMAC */
#define CANERGY_NV_SEALS_AT 120U    /* a node's seals: slot i's at 120 + 8 i */
#define CANERGY_NV_SEALED_SIZE 136U /* a node's sealed image: 3 slots and 2 seals */

/* The seal key of a node's record (gateway false) or of a gateway's (true) from key (the node's
 * key, or the gateway's), into seal; the caller wipes it (canergy_cmac_wipe) when done. */
void canergy_nv_seal_key(struct canergy_cmac *seal, const uint8_t key[16], uint8_t node,
                         bool gateway);

/* out = the seal of the len bytes of one slot image. */
void canergy_nv_seal(const struct canergy_cmac *seal, const uint8_t *slot, size_t len,
                     uint8_t out[CANERGY_NV_SEAL_SIZE]);

/* Check count slots of slot_size bytes at image (image_len bytes read) against seals (count
 * seals of CANERGY_NV_SEAL_SIZE bytes). A slot neither erased (all zero) nor absent whose seal
 * does not hold is spoilt in place (its last byte, in the CRC, inverted): the loads then take it
 * as a damaged slot. Returns the mask of those slots (bit i: slot i). */
unsigned canergy_nv_unseal(const struct canergy_cmac *seal, uint8_t *image, size_t image_len,
                           size_t slot_size, unsigned count, const uint8_t *seals);

/* CRC-32 as zlib computes it: canergy_crc32(0, p, n) == zlib.crc32(p[:n]). */
uint32_t canergy_crc32(uint32_t crc, const uint8_t *data, size_t len);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_NV_H */
