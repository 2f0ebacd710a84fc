/*
 * The gateway rules (src/canergy/core/gateway.py), sans-IO: a client upstream and a supervisor
 * downstream in one caller-owned struct, energy crossing between them only through two rules,
 * each inside the step that causes it:
 *   - forward: whatever the upstream client holds usable (a commit, a write-off's pay-back) goes
 *     at once into the downstream Us: spent above, injected below;
 *   - give back: energy of the downstream Us is withdrawn and returned upstream as the client's
 *     next numbered RETURN.
 * So up.spent == down.injected - down.withdrawn always (canergy_gateway_link_gap is 0): the
 * gateway neither creates nor loses energy between its roles. tests/test_c_gateway.py runs it
 * side by side with the Python Gateway.
 *
 * Witnessed rules upstream (up's config rules CANERGY_RULES_WITNESSED; docs/gateways.md, "A
 * gateway's record restored from an older copy"): forwarding is the client's draw. What it is
 * credited leaves its usable budget as a numbered DRAW (persisted before it leaves) and goes
 * below only on the supervisor's RETURN_ACK (spent above and injected below in that step). A
 * start with a record is RESUMING (canergy_client_start sends RESUME); until the supervisor
 * above confirms it (canergy_gateway_upstream_waiting) nothing is drawn, returned or granted
 * below (canergy_gateway_begin). A start found behind (CANERGY_GW_EV_FOUND_BEHIND in
 * out->events) drops the upstream books as a node does and Us below, booked as withdrawn and
 * out of spent (the link holds).
 *
 * Persist contract: both roles are one record. Whenever a call reports a persist (the client's
 * out->persist, or the supervisor's), write the client's record and the supervisor's record as
 * one (split-save, two records written apart, is the counterexample of `canergy check
 * --topology chain --broken-gateway split-save`) before any frame of that call leaves.
 */
#ifndef CANERGY_GATEWAY_H
#define CANERGY_GATEWAY_H

#include "canergy/client.h"
#include "canergy/supervisor.h"

#ifdef __cplusplus
extern "C" {
#endif

/* out->events of canergy_gateway_on_up_frame: the supervisor above found this gateway's record
 * behind (witnessed rules upstream); Us below was dropped (down.withdrawn grew by it). */
#define CANERGY_GW_EV_FOUND_BEHIND 0x0100U

struct canergy_gateway {
    struct canergy_client up;       /* node `up.node` of the bus above */
    struct canergy_supervisor down; /* the supervisor of its nodes on the bus below */
};

/* Move all of the upstream usable budget into the downstream Us; returns the amount (0: none;
 * always under the witnessed rules upstream, where only an acknowledged draw goes below).
 * The client's record is re-packed into out (out->persist) when anything moved. */
uint32_t canergy_gateway_forward(struct canergy_gateway *gw, struct canergy_out *out);

/* A frame from the bus above: the client's rules (canergy_client_on_frame), then forward
 * (witnessed upstream: a released draw goes below, a start found behind drops Us below, and
 * what is usable is drawn). */
int canergy_gateway_on_up_frame(struct canergy_gateway *gw, const struct canergy_rx_frame *frame,
                                uint64_t now, struct canergy_out *out);

/* The client's timers (a timeout-commit is forwarded too). */
void canergy_gateway_on_up_timer(struct canergy_gateway *gw, uint64_t now,
                                 struct canergy_out *out);

/* Return uj of the downstream Us upstream as the next numbered RETURN: CANERGY_ERR_PHASE while
 * a return awaits its acknowledgement, the client is joining or a start below waits for a
 * node's books (witnessed rules below), CANERGY_ERR_AMOUNT for an amount
 * the client cannot return (whole mJ, 1..65,535 mJ) or above the downstream Us. Nothing moves
 * on a refusal. */
int canergy_gateway_give_back(struct canergy_gateway *gw, uint32_t uj, uint64_t now,
                              struct canergy_out *out);

/* Witnessed upstream: the gateway's start is not confirmed by the supervisor above yet
 * (RESUMING, or answering its SYNC): nothing is granted below. */
bool canergy_gateway_upstream_waiting(const struct canergy_gateway *gw);

/* canergy_supervisor_begin on the supervisor below, refused (CANERGY_ERR_UNCONFIRMED, nothing
 * in *out) while canergy_gateway_upstream_waiting. */
int canergy_gateway_begin(struct canergy_gateway *gw, uint8_t node, uint32_t amount_uj,
                          uint64_t now, struct canergy_supervisor_out *out);

/* Energy created between the roles: injected - withdrawn - spent (0 unless the rules broke). */
int64_t canergy_gateway_link_gap(const struct canergy_gateway *gw);

/* ---- the gateway's policy (canergy-gateway's; Python's in canergy.live) ----
 * Each node's top-up below: TopUp(target_uj, min_uj).wanted(level) capped as capped_grant with
 * no limits (canergy.live.supervisor.policy): the shortfall from its reported level when at least min_uj,
 * within usable (Us below; a debt is 0), one frame's amount and what its record holds above
 * level; whole mJ, 0 for none. The caller grants only from a fresh level (reported after its last
 * transaction ended), to a node not JOINING nor blocked by its witness (canergy/witness.h). */
uint32_t canergy_gateway_top_up(uint64_t target_uj, uint64_t min_uj, uint64_t level_uj,
                                int64_t usable_uj);

/* What goes back above (canergy.live.gateway.process.Uplink's return): usable beyond return_above_uj,
 * whole mJ, at most one frame's amount; 0 for none. */
uint32_t canergy_gateway_give_back_amount(int64_t usable_uj, uint64_t return_above_uj);

/* ---- the gateway's NV slot (nv.c): both roles in one record ----
 * A slot: u32 magic "CNRG", u32 counter, the client's 30-byte record (canergy_record_pack), the
 * supervisor's slot image (canergy_supervisor_image), u32 CRC-32 of all before it; little-endian.
 * Two slots, at offsets 0 and CANERGY_GW_NV_SLOT_SIZE, written in turn. */
#define CANERGY_GW_NV_MAGIC 0x47524E43UL /* "CNRG" little-endian */
#define CANERGY_GW_NV_HEADER 8U
#define CANERGY_GW_NV_SLOT_SIZE                                                                   \
    (CANERGY_GW_NV_HEADER + CANERGY_NV_RECORD_SIZE + CANERGY_SUPERVISOR_SLOT_SIZE + 4U)

/* The slot image of both roles' books under counter. */
void canergy_gateway_nv_encode(const struct canergy_gateway *gw, uint32_t counter,
                               uint8_t out[CANERGY_GW_NV_SLOT_SIZE]);

/* What canergy_gateway_nv_load found in an image of two slots. */
struct canergy_gateway_nv {
    struct canergy_record up; /* the newest valid slot's client record; see the return value */
    const uint8_t *down;      /* its supervisor slot image (NULL: no valid slot) */
    uint32_t counter;         /* its counter */
    int8_t slot;              /* its slot, 0 or 1; -1: none valid */
    uint8_t older;            /* a slot of an older layout's supervisor record: its version (2,
                                 3, 4), else 0; only a refusal's reason, never loaded */
    bool foreign;             /* bytes, but neither slot starts with the magic (a node's file?) */
    uint8_t damaged;          /* slots (bit 0: the first, bit 1: the second) that start with the
                                 magic but whose CRC does not hold or that are cut short: a write
                                 cut short, or bytes edited (no older layout's either) */
};

/* Read an image of len bytes: the valid slot (magic, CRC, a record the client takes) written
 * last, comparing counters as 32-bit serial numbers. CANERGY_ERR_END (out->up holds that
 * record, for the caller's message) when a valid slot's client record holds a counter beyond
 * CANERGY_COUNTER_BOUND: neither slot is taken (the other may be an older copy). */
int canergy_gateway_nv_load(const uint8_t *image, size_t len, struct canergy_gateway_nv *out);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_GATEWAY_H */
