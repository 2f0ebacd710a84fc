/*
 * The host's frame path in C (src/canergy/ccore: CompiledSupervisor.on_answer, on_auth_answer,
 * on_auth_pair, begin_protected): one call per received frame, with the frame as arguments
 * rather than a struct filled field by field from Python. Only the host's binding (cffi) calls
 * these; no device port links them (firmware/Makefile builds host.c apart from the library).
 * tests/test_ccore_tables.py and tests/test_ccore_auth_path.py run them against the Python path.
 */
#ifndef CANERGY_HOST_H
#define CANERGY_HOST_H

#include "canergy/auth.h"
#include "canergy/joins.h"
#include "canergy/supervisor.h"
#include "canergy/telemetry.h"
#include "canergy/witness.h"

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define CANERGY_HOST_HELD 0x1000000U /* canergy_host_answer's verdict: a RETURN the witness took */
#define CANERGY_HOST_JOIN 0x2000000U /* canergy_host_answer's verdict: a JOIN held */

/* The service's tables in C, one record per session each. */
struct canergy_host_tables {
    struct canergy_heard *heard;
    struct canergy_witness *witness;
    struct canergy_joins *joins;
    const uint64_t *join_hold_us; /* per session: how long a confirmed JOIN waits */
    struct canergy_witness witness_before; /* the record the last call changed, as it was */
    struct canergy_joins joins_before;
    uint64_t lost_after_us;
    unsigned verdict;
    uint16_t admit; /* verdict's CANERGY_JOINS_ADMIT: the JOIN to admit */
    bool hold;      /* hold fresh RETURNs (no key) */
};

/* The fast path's call with the frame as arguments: one call, no struct filled field by field
   from Python (kind: bit 0 extended identifier, bit 1 remote frame). An ACK, COMMITTED or
   ABORTED of a managed node as canergy_supervisor_on_answer takes it. With the tables (t NULL:
   none, and the rest below is the caller's), for a managed node:
   - a TELEMETRY is taken by the TELEMETRY table, the witness and the held JOINs: t->verdict is
     the table's verdict, the witness's findings shifted left by 8 and the JOINs' by 16 (the
     JOIN to admit in t->admit); status CANERGY_RX_CALLER;
   - a RETURN the books allow: without hold, or an old number, to the rules (CANERGY_DECODE_OK,
     out as for an ACK, verdict 0); else held by the witness, verdict CANERGY_HOST_HELD with the
     witness's verdict (CANERGY_RX_CALLER);
   - a JOIN is held: verdict CANERGY_HOST_JOIN (CANERGY_RX_CALLER);
   the records as they were before, in t->witness_before and t->joins_before. Anything else (a
   RETURN beyond the books among it) leaves the verdict 0: the caller's. */
int canergy_host_answer(struct canergy_supervisor *sup, struct canergy_host_tables *t,
    uint32_t id, unsigned kind, const uint8_t *data, size_t len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_msg *m);

/* Authenticated mode: each of out's frames protected under its node's key (keys: one per
   session, in the sessions' order) with its session's counters, in order: one FD frame each,
   or in the classic layout two (the frame, then its MAC frame). */
void canergy_host_auth_protect(const struct canergy_supervisor *sup,
    const struct canergy_auth *keys, const struct canergy_supervisor_out *out,
    struct canergy_auth_frame *sent, uint8_t *sent_count);

/* Authenticated mode, FD layout (keys: one per session, in the sessions' order, receiving
   CANERGY_TO_SUPERVISOR): an ACK, COMMITTED or ABORTED of a managed node verified as Python's
   FrameAuth verifies it (MAC, then an FV that is the expected one and not before the
   session's tx), the rules run and each frame they send protected. Any other frame, or one
   that fails any check or that the rules leave to the caller, returns a status other than
   CANERGY_DECODE_OK before anything changed (an FD frame leaves no state in keys): the caller
   takes it the usual way, where a refusal is counted. *fv: the verified frame's FV. */
int canergy_host_auth_answer(struct canergy_supervisor *sup, struct canergy_auth *keys,
    uint32_t id, unsigned kind, const uint8_t *data, size_t len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_auth_frame *sent, uint8_t *sent_count,
    uint32_t *fv);

/* Authenticated mode, classic layout (keys as above, each CANERGY_AUTH_CLASSIC): a message and
   the MAC frame that completes it (the caller pairs them and keeps the message until its MAC
   frame, as Python's FrameAuth does; mac_kind as canergy_host_answer's kind). An ACK, COMMITTED
   or ABORTED of a managed node verified as FrameAuth verifies the pair (MAC, then an FV that is
   the expected one and not before the session's tx), the rules run and each frame they send
   protected (two frames each). Any other pair, or one that fails any check or that the rules
   leave to the caller, returns a status other than CANERGY_DECODE_OK before anything changed
   (the key's waiting slot is empty again): the caller takes the MAC frame the usual way, where
   the pair is judged and a refusal counted. *fv: the verified pair's FV. */
int canergy_host_auth_pair(struct canergy_supervisor *sup, struct canergy_auth *keys,
    uint32_t data_id, const uint8_t *data, size_t data_len, uint32_t mac_id, unsigned mac_kind,
    const uint8_t *mac, size_t mac_len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_auth_frame *sent, uint8_t *sent_count,
    uint32_t *fv);

#endif
