/*
 * The hardened canergy client (docs/protocol.md, "The hardened rules", "A node without books"),
 * sans-IO: the port passes time and frames in and carries out what comes back in a
 * struct canergy_out. The rules are those of src/canergy/core/hardened.py (CLIENT), cell for
 * cell; tests/test_c_*.py run both side by side.
 *
 * The witnessed rules (src/canergy/core/witnessed.py, CLIENT; docs/protocol.md, "Records
 * restored from older copies") are chosen at run time by cfg->rules: the actuator's energy is a
 * numbered DRAW the supervisor acknowledges first (canergy_client_draw), and every start with a
 * record is RESUMING until the supervisor's ADMIT confirms the books or finds them behind; an
 * ADMIT the node did not ask for is a supervisor's start, SYNC(n): the node settles B
 * transactions ahead (cfg->window), drops its held intention, answers with its books and counts
 * and is SYNCING (moves nothing) until ADMIT(n ^ CANERGY_SYNC_CONFIRMED). A build may keep
 * one rule set (CANERGY_RULES_*_ONLY below): cfg->rules naming the other is then refused as
 * CANERGY_ERR_ARGUMENT.
 *
 * Contract of every call that takes a struct canergy_out *out:
 *   - *out is overwritten (the call starts it empty);
 *   - if out->persist is set, write out->nv_image (CANERGY_NV_SLOT_SIZE bytes) to slot
 *     out->nv_slot (byte offset out->nv_slot * CANERGY_NV_SLOT_SIZE) and let the write complete
 *     BEFORE any of out->frames is handed to the CAN controller and before the actuator uses
 *     energy the call granted. If the write cannot complete, reset the node: never send.
 *   - then send out->frames[0 .. out->frame_count - 1] in order;
 *   - out->events tells what happened (CANERGY_EV_*), e.g. to report telemetry at once.
 *
 * Time: uint64_t microseconds from any monotonic clock, never going backwards, below 2^63
 * (so now + a timeout never reaches CANERGY_NEVER). 2^63 us is 292,000 years: the library
 * never wraps; a port with a 32-bit hardware timer extends it (README.md, "Time").
 *
 * All state lives in struct canergy_client, owned by the caller; nothing is global. Calls are
 * not reentrant on one client: call them from one context (README.md, "ISR or main loop").
 */
#ifndef CANERGY_CLIENT_H
#define CANERGY_CLIENT_H

#include "canergy/codec.h"
#include "canergy/nv.h"

#ifdef __cplusplus
extern "C" {
#endif

#define CANERGY_NEVER UINT64_MAX /* a deadline that is not armed */
#define CANERGY_OUT_FRAMES 4U    /* most frames one call produces (node layer included) */

enum canergy_phase {
    CANERGY_IDLE = 0,    /* books, no intention held */
    CANERGY_HOLDING = 1, /* an acknowledged intention awaits COMMIT/ABORT or the command timer */
    CANERGY_JOINING = 2, /* no books: JOIN sent, waiting for the ADMIT that echoes the nonce */
    CANERGY_RESUMING = 3, /* witnessed: started with books, RESUME sent, awaiting its ADMIT */
    CANERGY_SYNCING = 4   /* witnessed: a supervisor's SYNC answered, awaiting its ADMIT */
};

enum canergy_rules {
    CANERGY_RULES_HARDENED = 0, /* the default */
    CANERGY_RULES_WITNESSED = 1
};

/* The rule sets compiled in. A host build (the Python binding, the tests) has both, chosen at
 * run time by cfg->rules; a product port ships one, chosen at build time:
 * CANERGY_RULES_WITNESSED_ONLY (the node port's default: records restored from older copies
 * cannot create energy) or CANERGY_RULES_HARDENED_ONLY (CANERGY_HARDENED_ONLY, its earlier
 * name). A configuration naming a set left out is refused at start (CANERGY_ERR_ARGUMENT):
 * never run as the other. */
#if defined(CANERGY_HARDENED_ONLY) && !defined(CANERGY_RULES_HARDENED_ONLY)
#define CANERGY_RULES_HARDENED_ONLY 1
#endif
#if defined(CANERGY_RULES_HARDENED_ONLY) && defined(CANERGY_RULES_WITNESSED_ONLY)
#error "CANERGY_RULES_HARDENED_ONLY and CANERGY_RULES_WITNESSED_ONLY: a build keeps one set"
#endif
#ifndef CANERGY_RULES_HARDENED_ONLY
#define CANERGY_WITNESSED 1 /* the witnessed rules are compiled in */
#endif
#ifndef CANERGY_RULES_WITNESSED_ONLY
#define CANERGY_HARDENED 1 /* the hardened rules are compiled in */
#endif

/* out->events bits: the notes of the Python rules (ClientCommitted, ...), one bit each. */
#define CANERGY_EV_COMMITTED 0x01U       /* a COMMIT added its amount to usable */
#define CANERGY_EV_TIMEOUT_COMMIT 0x02U  /* the command timer committed the held intention */
#define CANERGY_EV_ABORTED 0x04U         /* an ABORT resolved a transaction */
#define CANERGY_EV_CREDITED 0x08U        /* Gs paid back a write-off into usable */
#define CANERGY_EV_RETURN_ACKED 0x10U    /* the pending return is acknowledged */
#define CANERGY_EV_REFUSED 0x20U         /* an intention or commit would overflow usable */
#define CANERGY_EV_ADMITTED 0x40U        /* the ADMIT for our JOIN (or RESUME) came */
#define CANERGY_EV_RELEASED 0x80U        /* witnessed: a DRAW was acknowledged, spent += it */


struct canergy_client_config {
    uint32_t id_base;            /* CANERGY_DEFAULT_ID_BASE unless the bus uses another block */
    uint32_t command_timeout_us; /* hold an intention this long, then commit it (Python 100 ms) */
    uint32_t return_retry_us;    /* re-send RETURN / JOIN this often (Python 100 ms) */
    uint8_t node;                /* 1..127 */
    uint8_t rules;               /* enum canergy_rules; 0 (zeroed config): hardened */
    uint16_t window;             /* witnessed: B, the transactions a SYNC's answer settles
                                  * ahead (Python's Timing.window); 0: CANERGY_DEFAULT_WINDOW */
};

#define CANERGY_DEFAULT_WINDOW 64U
#define CANERGY_WINDOW_MAX 0x7FFFU /* the most the 16-bit wire distance tells apart */

/* Opaque in spirit: read it through the accessors below; tests reach in. 80 bytes. */
struct canergy_client {
    uint8_t node;
    uint8_t phase;               /* enum canergy_phase */
    uint8_t nv_slot;             /* slot holding the newest record: the next write goes to the other */
    uint8_t rules;               /* enum canergy_rules */
    uint16_t held_amount_mj;
    uint16_t nonce;              /* of the pending JOIN or RESUME */
    uint16_t window;             /* B (witnessed), 1..CANERGY_WINDOW_MAX */
    uint32_t held_tx;            /* widened tx of the held intention, modulo 2^32 */
    struct canergy_record rec;   /* the books, exactly what the NV slot holds */
    uint64_t deadline;           /* command timer (HOLDING), CANERGY_NEVER when not armed */
    uint64_t return_deadline;    /* return re-send (or JOIN re-send), CANERGY_NEVER if none */
    uint32_t id_base;
    uint32_t command_timeout_us;
    uint32_t return_retry_us;
    uint32_t nv_counter;         /* counter of the newest slot written or loaded */
};

struct canergy_out {
    uint16_t events;       /* CANERGY_EV_* */
    uint8_t frame_count;
    uint8_t persist;       /* 1: write nv_image to nv_slot before anything else */
    uint8_t nv_slot;       /* 0 or 1 */
    uint32_t nv_counter;   /* the counter inside nv_image */
    struct canergy_frame frames[CANERGY_OUT_FRAMES];
    uint8_t nv_image[CANERGY_NV_SLOT_SIZE];
};

/*
 * Start (every boot): check cfg, read the NV image (len bytes from offset 0; NULL/0 when the
 * storage is blank) and either restart from its record or, with no valid record, JOIN with
 * nonce (draw it from a hardware entropy source: a fresh random 16-bit number each start).
 * Witnessed rules: a start with a record sends RESUME with nonce. The hardened rules take a
 * record holding a pending draw (CANERGY_RECORD_PENDING_DRAW) as no books: they JOIN.
 * Returns the number of fallbacks seen (0..2, see nv.h) or CANERGY_ERR_ARGUMENT (bad cfg).
 * The JOIN leaves in *out; a restart with a pending return re-sends it at the first timer call.
 */
int canergy_client_start(struct canergy_client *c, const struct canergy_client_config *cfg,
                         const uint8_t *nv_image, size_t nv_len, uint16_t nonce, uint64_t now,
                         struct canergy_out *out);

/* A received frame: decoded strictly (supervisor -> client only), then the rules. Returns
 * CANERGY_DECODE_OK, a decode status (count it, nothing else happens) or
 * CANERGY_RX_OTHER_NODE. */
int canergy_client_on_frame(struct canergy_client *c, const struct canergy_rx_frame *frame,
                            uint64_t now, struct canergy_out *out);

/* Fire whatever timer is due at now: the command timer, then the return/JOIN re-send. Calling
 * it early or often is harmless. */
void canergy_client_on_timer(struct canergy_client *c, uint64_t now, struct canergy_out *out);

/* The earliest armed deadline, CANERGY_NEVER when none: call on_timer then. */
uint64_t canergy_client_deadline(const struct canergy_client *c);

/* The actuator used uj microjoules: refused (CANERGY_ERR_AMOUNT) for 0 or more than usable,
 * CANERGY_ERR_PHASE while joining, and always under the witnessed rules (use draw). Persist
 * before the actuator runs on it. */
int canergy_client_spend(struct canergy_client *c, uint32_t uj, struct canergy_out *out);

/* Witnessed rules: debit uj (whole mJ, 1..65535 mJ, at most usable) as the next numbered DRAW;
 * the actuator gets it only when its RETURN_ACK comes (CANERGY_EV_RELEASED; rec.spent_uj grows
 * by it). CANERGY_ERR_PHASE while a debit is pending or the books are not confirmed. Hardened
 * rules: canergy_client_spend. */
int canergy_client_draw(struct canergy_client *c, uint32_t uj, uint64_t now,
                        struct canergy_out *out);

/* Give uj back to the supervisor as the next numbered RETURN (whole mJ, 1..65535 mJ, at most
 * usable); CANERGY_ERR_PHASE while joining, while a return awaits its acknowledgement, or when
 * the next number would reach CANERGY_COUNTER_END. */
int canergy_client_give_back(struct canergy_client *c, uint32_t uj, uint64_t now,
                             struct canergy_out *out);

bool canergy_client_can_give_back(const struct canergy_client *c);
/* Witnessed: no debit pending and the books confirmed; hardened: not joining. */
bool canergy_client_can_draw(const struct canergy_client *c);
bool canergy_client_joining(const struct canergy_client *c);
uint32_t canergy_client_usable(const struct canergy_client *c);

/*
 * Single cells of the rule table, for tests and model checking (a port needs none of them):
 * command_timer / return_timer fire one timer; restart is
 * the power-loss cell (volatile state dropped, books kept; start() runs it after loading);
 * join is the books-lost cell (start() runs it when there is no record). join never asks to
 * persist: a blank record is not books, and writing one would make the next start trust it.
 */
void canergy_client_command_timer(struct canergy_client *c, uint64_t now,
                                  struct canergy_out *out);
void canergy_client_return_timer(struct canergy_client *c, uint64_t now,
                                 struct canergy_out *out);
void canergy_client_restart(struct canergy_client *c, uint64_t now, struct canergy_out *out);
/* The power-loss cell with the start's nonce: witnessed rules RESUME with it (into *out);
 * hardened rules as canergy_client_restart. */
void canergy_client_resume(struct canergy_client *c, uint16_t nonce, uint64_t now,
                           struct canergy_out *out);
void canergy_client_join(struct canergy_client *c, uint16_t nonce, uint64_t now,
                         struct canergy_out *out);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_CLIENT_H */
