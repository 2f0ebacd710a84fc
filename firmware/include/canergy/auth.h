/*
 * Authenticated frames (docs/security.md, "Authenticated mode"): a truncated AES-128-CMAC over
 * Data ID, freshness value and payload, AUTOSAR SecOC style, byte for byte what
 * src/canergy/auth/frames.py builds and checks.
 *
 *   MAC input: Data ID type << 8 | node (2 bytes, big-endian) || FV (4 bytes, big-endian)
 *              || the classic frame's data (CRC byte and fields, as canergy_encode lays them)
 *
 *   FV (canergy_auth_freshness), from the receiver's or sender's own counters:
 *     JOIN                 the nonce (with set_join: 16 random bits above it)
 *     ADMIT                the high half of its k (the wire tx extended next to last_tx)
 *                          << 16 | the nonce: k and C share it, so a JOIN answered again after
 *                          last_tx crossed a 2^16 block is signed as the first answer was; a
 *                          node takes any, and its counters from it.
 *                          Its MAC input ends with the FV of the JOIN it answers (4, BE).
 *     TELEMETRY            last_tx, the sender's last resolved transaction (the supervisor takes
 *                          it from the last one it knows the node resolved to its own tx);
 *                          JOINING (no books), the JOIN's FV once set_join gave one
 *     RETURN, RETURN_ACK   the wire seq extended next to return_seq (nearest value), mod 2^32
 *     every other type     the wire tx extended next to last_tx (nearest value), mod 2^32
 *
 *   FD layout: one CAN FD frame, data || zero padding || FV (4, BE) || MAC[0..8), its length the
 *     smallest CAN FD length >= len(data) + 12 (12, 16 or 20 for canergy's messages).
 *   Classic layout: the unchanged classic frame, then a MAC frame on id_base | M << 8 | node
 *     (M = 0x0 to a node, 0x8 to the supervisor): type (1) || FV >> 16 (2, BE) || MAC[0..5);
 *     TELEMETRY, which carries no counter, puts FV & 0xFFFF there instead. The receiver keeps
 *     the data frame (one per node) until its MAC frame arrives; the FV is the MAC frame's high
 *     half << 16 | the frame's own 16-bit counter (the nonce for JOIN and ADMIT), or for
 *     TELEMETRY the MAC frame's low half extended next to the receiver's last_tx.
 *
 * A received frame is verified (constant-time compare of the truncated MAC), then its FV must
 * be the one the receiver expects from its own counters; a JOINING TELEMETRY's must be the
 * JOIN's (set_join), any other TELEMETRY's window is the supervisor's to judge (as Python's
 * FrameAuth with a plain freshness). Refused frames change nothing but the classic layout's
 * waiting slot, as in Python.
 *
 * One struct canergy_auth serves one node (its key) in one direction; no heap, no globals.
 */
#ifndef CANERGY_AUTH_H
#define CANERGY_AUTH_H

#include "canergy/cmac.h"
#include "canergy/gateway.h"
#include "canergy/node.h"

#ifdef __cplusplus
extern "C" {
#endif

#define CANERGY_AUTH_FD_MAC 8U        /* MAC bytes in an FD frame (64 bits) */
#define CANERGY_AUTH_CLASSIC_MAC 5U   /* MAC bytes in a classic MAC frame (40 bits) */
#define CANERGY_AUTH_TRAILER 12U      /* FD: FV (4) and MAC (8) after the data */
#define CANERGY_AUTH_FRAME_MAX 20U    /* the longest frame: 8 data bytes + 12, an FD length */
#define CANERGY_AUTH_MAC_FRAME_LEN 8U /* classic MAC frame: type, FV high half, MAC */
#define CANERGY_AUTH_MAC_TO_CLIENT 0x0U
#define CANERGY_AUTH_MAC_TO_SUPERVISOR 0x8U

enum canergy_auth_layout {
    CANERGY_AUTH_FD = 0,
    CANERGY_AUTH_CLASSIC = 1
};

/* canergy_auth_accept's verdicts, CANERGY_AUTH_PENDING .. CANERGY_AUTH_UNAUTHENTICATED, are in
 * canergy/status.h with every other status. */

/* A frame to transmit: 29-bit; len above 8 is a CAN FD frame (send it with bit rate switch). */
struct canergy_auth_frame {
    uint32_t id;
    uint8_t len;
    uint8_t data[CANERGY_AUTH_FRAME_MAX];
};

/* One node's key and, in the classic layout, the data frame waiting for its MAC frame
 * (248 bytes on Cortex-M4; key material: canergy_auth_wipe when done). */
struct canergy_auth {
    struct canergy_cmac key;
    uint32_t id_base;
    uint32_t pending_id;
    uint32_t join_fv;     /* FV of this node's JOIN (0: the nonce alone); see set_join */
    uint32_t admit_fv;    /* FV of the ADMIT just verified: its high half is the counters' */
    uint32_t resume_fv;   /* a supervisor's: FV of the node's RESUME (kept: _KEPT_RESUME) */
    uint32_t floor;       /* a supervisor's: the oldest TELEMETRY FV still fresh (_KEPT_FLOOR) */
    uint8_t pending_data[8];
    uint8_t pending_len;  /* 0: nothing waits */
    uint8_t node;
    uint8_t layout;       /* enum canergy_auth_layout */
    uint8_t receives;     /* enum canergy_direction: CANERGY_TO_CLIENT on a node */
    uint8_t kept;         /* a supervisor's: CANERGY_AUTH_KEPT_* of what it holds */
};

/* What a supervisor's side keeps of a node (struct canergy_auth's kept), as Python's FrameAuth
 * keeps join_fv, resume_fv and telemetry_floor per node. */
#define CANERGY_AUTH_KEPT_JOIN 0x01U
#define CANERGY_AUTH_KEPT_RESUME 0x02U
#define CANERGY_AUTH_KEPT_FLOOR 0x04U

/* CANERGY_ERR_ARGUMENT for a bad id base, node, layout or a direction that is not one way. */
int canergy_auth_init(struct canergy_auth *a, const uint8_t key[CANERGY_KDF_KEY_SIZE],
                      uint32_t id_base, uint8_t node, enum canergy_auth_layout layout,
                      enum canergy_direction receives);

void canergy_auth_wipe(struct canergy_auth *a);

/* Before a node JOINs: 16 random bits above its JOIN nonce as the JOIN's FV, which the
 * supervisor's ADMIT binds in its MAC, so an ADMIT recorded in an earlier life (same 16-bit
 * nonce) fails unless 32 bits match. Without it JOIN and ADMIT carry the nonce alone. */
void canergy_auth_set_join(struct canergy_auth *a, uint16_t random_high, uint16_t nonce);

/* The FV of m for a side whose own counters are last_tx and return_seq (table above). */
uint32_t canergy_auth_freshness(const struct canergy_msg *m, uint32_t last_tx,
                                uint32_t return_seq);

/* The frames that carry plain (a classic frame from canergy_encode or a struct canergy_out, for
 * this node, either direction): 1 (FD) or 2 (classic: the frame, then its MAC frame), in
 * sending order; CANERGY_ERR_ARGUMENT for a frame that is not a valid message of this node. */
int canergy_auth_protect(const struct canergy_auth *a, const struct canergy_frame *plain,
                         uint32_t last_tx, uint32_t return_seq, struct canergy_auth_frame out[2]);

/* A received frame (any id, flags, length up to 64). CANERGY_DECODE_OK: *verified is the
 * verified classic frame, to be given to canergy_*_on_frame. Otherwise a decode status (the
 * codec's refusal; CANERGY_DECODE_WRONG_DIRECTION also for a MAC frame of the other
 * direction), CANERGY_RX_OTHER_NODE (a valid frame or a MAC frame of another node, ignored),
 * CANERGY_AUTH_PENDING, or a refusal CANERGY_AUTH_MAC_BAD .. _UNAUTHENTICATED. */
int canergy_auth_accept(struct canergy_auth *a, const struct canergy_rx_frame *frame,
                        uint32_t last_tx, uint32_t return_seq, struct canergy_frame *verified);

/* The node layer in authenticated mode: canergy_auth_accept with the node's counters, then
 * canergy_node_on_frame with the verified frame. Returns what either returned (out is empty
 * unless the frame was verified). A frame refused as the node's own direction with its id (a
 * MAC frame 0x8 too) is counted in the node's witness, as canergy_node_on_frame counts one. */
int canergy_auth_node_frame(struct canergy_auth *a, struct canergy_node *n,
                            const struct canergy_rx_frame *frame, uint64_t now,
                            struct canergy_out *out);

/* canergy_auth_protect with the node's counters, for each of out->frames in turn. */
int canergy_auth_node_protect(const struct canergy_auth *a, const struct canergy_node *n,
                              const struct canergy_frame *plain, struct canergy_auth_frame out[2]);

/* A gateway's bus above in authenticated mode, as the node layer's two above with its client
 * role's counters (a is the gateway's node key, CANERGY_TO_CLIENT): canergy_auth_accept, then
 * canergy_gateway_on_up_frame with the verified frame (a joining gateway's ADMIT gives its full
 * counters); canergy_auth_protect for each frame it sends above. A frame refused in the
 * gateway's own direction with its id is the port's to count, as without a key. */
int canergy_auth_gateway_up_frame(struct canergy_auth *a, struct canergy_gateway *gw,
                                  const struct canergy_rx_frame *frame, uint64_t now,
                                  struct canergy_out *out);
int canergy_auth_gateway_up_protect(const struct canergy_auth *a,
                                    const struct canergy_gateway *gw,
                                    const struct canergy_frame *plain,
                                    struct canergy_auth_frame out[2]);

/* A gateway's bus below in authenticated mode (canergy gateway --auth): the supervisor's side
 * of Python's FrameAuth (receiving CANERGY_TO_SUPERVISOR), with the freshness judgement of
 * canergy supervisor --auth, for the session of the frame's node in gw->down. keys: one per
 * session, in the sessions' order, each initialised with that node's key (derived from the
 * master key: canergy_auth_node_key) receiving CANERGY_TO_SUPERVISOR.
 *   JOIN, RESUME (a DEBIT with START): any FV whose low half is the nonce, kept for the ADMIT
 *     that answers it (its MAC binds it); a SYNC's books: the nonce alone;
 *   TELEMETRY without books (JOINING): taken only bound to the JOIN taken last, any other moves
 *     nothing and proves nothing (CANERGY_AUTH_PENDING, not a refusal);
 *   TELEMETRY: fresh from the last transaction the node is known to have resolved (its
 *     TELEMETRY, COMMITTED or ABORTED taken, its ACK of the next; until one is known, the
 *     session's tx - 1) up to the session's tx;
 *   every other frame: the FV the session's counters give (canergy_auth_freshness) and not
 *     before its counter (tx, or returns_credited for RETURN and DEBIT).
 * CANERGY_DECODE_OK: *verified is the verified classic frame, for canergy_decode and the rules.
 * Otherwise canergy_auth_accept's statuses: a refusal (CANERGY_AUTH_MAC_BAD ..
 * _UNAUTHENTICATED, the frame's node is id & 0xFF), CANERGY_AUTH_PENDING, a decode status, or
 * CANERGY_RX_OTHER_NODE for a node gw->down does not manage. A refused frame changes nothing
 * but the classic layout's waiting slot. */
int canergy_auth_gateway_down_frame(struct canergy_auth *keys, const struct canergy_gateway *gw,
                                    const struct canergy_rx_frame *frame,
                                    struct canergy_frame *verified);

/* The frames that carry plain, a frame gw->down sends (struct canergy_supervisor_out), under
 * its node's key with its session's counters: an ADMIT binds the FV of the JOIN or RESUME it
 * answers. As canergy_auth_protect; CANERGY_ERR_ARGUMENT for a node not managed. */
int canergy_auth_gateway_down_protect(const struct canergy_auth *keys,
                                      const struct canergy_gateway *gw,
                                      const struct canergy_frame *plain,
                                      struct canergy_auth_frame out[2]);

/* A node's key from the master key (src/canergy/auth/keys.py's derive_node_key): the KDF of
 * canergy/cmac.h with label "canergy node key" and context node || epoch (4 bytes, BE). */
void canergy_auth_node_key(const uint8_t master[CANERGY_KDF_KEY_SIZE], uint8_t node,
                           uint32_t epoch, uint8_t key[CANERGY_KDF_KEY_SIZE]);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_AUTH_H */
