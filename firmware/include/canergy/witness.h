/*
 * The supervisor's witness without a key (src/canergy/live/supervisor/witness.py's ReturnGate), sans-IO, one
 * caller-owned struct per node. Anyone can send a RETURN in a node's name on a bus without keys;
 * the node reports in its TELEMETRY the frames it saw in its name that it did not send
 * (``witness``) and its return number. So:
 *   - a TELEMETRY whose witness count moved (by 1..128), or whose return number went back, is
 *     evidence: every RETURN held is dropped (a genuine one is sent again) and the node gets no
 *     top-up for block_us (canergy_witness_blocked);
 *   - a fresh RETURN is held (canergy_witness_hold) until the node's own TELEMETRY shows that
 *     number and hold_us has passed since with no evidence; canergy_witness_release then hands
 *     it to the rules, each number missed before it as a 0 mJ RETURN (someone acknowledged a
 *     return in the supervisor's name: what it held is lost, never created);
 *   - a RESUME (witnessed rules) whose pending return would be credited is held the same way.
 * Times are the caller's microseconds; numbers are unwrapped against the session's
 * returns_credited as Python's unwrap does (int64: exact below CANERGY_COUNTER_BOUND).
 *
 * One difference from Python, by design: at most CANERGY_WITNESS_SLOTS return numbers are held
 * per node (an honest node has one outstanding); a RETURN with a further number is dropped
 * (CANERGY_WITNESS_FULL), never credited. tests/test_c_witness.py runs both side by side, and
 * tests/test_ccore_tables.py the host C core's frame path, which runs it, against the Python path.
 */
#ifndef CANERGY_WITNESS_H
#define CANERGY_WITNESS_H

#include "canergy/codec.h"
#include "canergy/session.h"

#include <stdbool.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#ifndef CANERGY_WITNESS_SLOTS
#define CANERGY_WITNESS_SLOTS 4U
#endif
#define CANERGY_WITNESS_REPORT_AT 128U /* a count that moved by more went back: a restart */
/* A client (the node, client_internal.h, the same value; the gateway port's leg above) brings
 * its next TELEMETRY forward for a frame in its name no sooner than this after its last one: two
 * clients on one id would otherwise answer each other's reports with no pause. */
#define CANERGY_WITNESS_GAP_US 10000U

/* canergy_witness_telemetry's findings (bits): evidence, or a note that is no evidence. */
#define CANERGY_WITNESS_SAW 0x01U       /* evidence: it saw frames in its name it did not send */
#define CANERGY_WITNESS_WENT_BACK 0x02U /* evidence: its return number went back */
#define CANERGY_WITNESS_SINCE_START 0x04U /* note: frames seen before its first report here */
#define CANERGY_WITNESS_RESTARTED 0x08U   /* note: its count went back (a restart) */
#define CANERGY_WITNESS_EVIDENCE (CANERGY_WITNESS_SAW | CANERGY_WITNESS_WENT_BACK)

/* canergy_witness_hold's verdicts. */
enum canergy_witness_verdict {
    CANERGY_WITNESS_OLD = 0,          /* a number credited already: to the rules (a re-ack) */
    CANERGY_WITNESS_HELD = 1,         /* held (or a copy of one held) */
    CANERGY_WITNESS_CONTRADICTED = 2, /* another amount under a number held: evidence */
    CANERGY_WITNESS_FULL = 3          /* no room: dropped, not held (C only, see above) */
};

struct canergy_held {
    int64_t seq;
    uint64_t confirmed_at;
    uint16_t amount_mj;
    bool confirmed;
};

struct canergy_witness {
    struct canergy_held held[CANERGY_WITNESS_SLOTS]; /* ascending by seq, held_count of them */
    struct canergy_held resume_held;
    struct canergy_msg resume; /* the RESUME held (has_resume) */
    int64_t return_seq;        /* the highest return number reported (has_return_seq) */
    uint64_t confirmed_at;
    uint64_t evidence_at; /* has_evidence */
    uint32_t refuted;
    uint32_t resynced;
    uint16_t resume_nonce; /* has_resume_nonce */
    uint8_t witness;       /* has_witness */
    uint8_t held_count;
    bool has_witness;
    bool has_return_seq;
    bool has_evidence;
    bool has_resume;
    bool has_resume_nonce;
};

/* What canergy_witness_release hands to the rules, in order: for each of returns[], the 0 mJ
 * RETURNs numbered first_missed..seq-1 (none when equal), then RETURN(seq, amount_mj); then
 * the RESUME held, when resume is set. */
struct canergy_witness_release {
    struct {
        int64_t first_missed;
        int64_t seq;
        uint16_t amount_mj;
    } returns[CANERGY_WITNESS_SLOTS];
    struct canergy_msg resume_msg;
    uint8_t count;
    bool resume;
};

void canergy_witness_init(struct canergy_witness *w);

/* A TELEMETRY of the node: its findings (bits above; 0 for a JOINING one). Evidence drops what
 * is held (canergy_witness_refute). */
unsigned canergy_witness_telemetry(struct canergy_witness *w, const struct canergy_msg *m,
                                   uint32_t credited, uint64_t now);

/* A RETURN of the node, its session at credited. */
enum canergy_witness_verdict canergy_witness_hold(struct canergy_witness *w,
                                                  const struct canergy_msg *m, uint32_t credited,
                                                  uint64_t now);

/* A RESUME of the node: true when held (hold, and its pending return is the next number and not
 * a draw) until a TELEMETRY shows that number. Any RESUME with a new nonce resets the number the
 * node's TELEMETRY is judged by. */
bool canergy_witness_hold_resume(struct canergy_witness *w, const struct canergy_msg *m,
                                 uint32_t credited, uint64_t now, bool hold);

/* What is confirmed and held hold_us since its confirmation (see the struct); removed here. */
void canergy_witness_release(struct canergy_witness *w, uint32_t credited, uint64_t now,
                             uint64_t hold_us, struct canergy_witness_release *out);

/* The n-th message (from 0) of a release for node, in the order above: false past the last.
 * Hand each to the rules as it comes (a 0 mJ RETURN: numbers acknowledged by someone else). */
bool canergy_witness_release_at(const struct canergy_witness_release *r, uint8_t node,
                                uint32_t n, struct canergy_msg *m);

/* Evidence against the node's reports: everything held is dropped (counted in refuted). */
void canergy_witness_refute(struct canergy_witness *w, uint64_t now);

/* No top-ups while evidence is younger than block_us. */
bool canergy_witness_blocked(const struct canergy_witness *w, uint64_t now, uint64_t block_us);

/* The node was admitted afresh: its return numbers start again (its witness count is kept). */
void canergy_witness_readmitted(struct canergy_witness *w);

/* The earliest time a held RETURN or RESUME confirmed may be released (UINT64_MAX, i.e.
 * CANERGY_NEVER: none). */
uint64_t canergy_witness_next_release(const struct canergy_witness *w, uint64_t hold_us);

/* What no honest node sends, judged by its session's books alone (SupervisorService's check
 * of a RETURN or DEBIT): a fresh RETURN, or a DEBIT other than a SYNC's answer, numbered next
 * and for more than the node can hold (delivered + reserved - returned). */
bool canergy_witness_beyond_books(const struct canergy_session *s, const struct canergy_msg *m);

/* Where a message of a node below goes (canergy_witness_route). */
enum canergy_witness_route {
    CANERGY_WITNESS_TO_RULES = 0, /* to the rules: canergy_supervisor_on_msg */
    CANERGY_WITNESS_TAKEN = 1,    /* a TELEMETRY, or held: canergy_witness_release says when */
    CANERGY_WITNESS_DROPPED = 2   /* beyond the books (counted in refuted), or no room */
};

/* One message of the node whose session is s, as `canergy gateway`'s supervisor below judges
 * it without a key: a TELEMETRY to canergy_witness_telemetry; a RETURN or DEBIT beyond the books
 * dropped, with evidence (no top-ups for a while); a fresh RETURN held; under the witnessed
 * rules (rules, enum canergy_rules) a RESUME owing the next return held, a SYNC's counts
 * resetting the baseline. *intrusions grows by one for each piece of evidence. The caller then
 * calls canergy_witness_release (something held may be due). */
enum canergy_witness_route canergy_witness_route(struct canergy_witness *w,
                                                 const struct canergy_session *s,
                                                 const struct canergy_msg *m, uint8_t rules,
                                                 uint64_t now, uint32_t *intrusions);

/* canergy_witness_route in authenticated mode (`canergy gateway --auth`: a RETURN and a RESUME
 * carry a MAC): nothing is held; a RETURN or DEBIT beyond the books is still dropped, with
 * evidence, and a TELEMETRY, a RESUME and a SYNC's counts are still noted. */
enum canergy_witness_route canergy_witness_route_keyed(struct canergy_witness *w,
                                                       const struct canergy_session *s,
                                                       const struct canergy_msg *m,
                                                       uint8_t rules, uint64_t now,
                                                       uint32_t *intrusions);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_WITNESS_H */
