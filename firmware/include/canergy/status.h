/*
 * Every status code the library returns, in one family of distinct values: whichever call
 * returned it, a value names one outcome, so a caller (a port, a binding) that meets several
 * of them in one int — a frame's decode status, a rule's verdict, an authentication refusal,
 * a request's refusal — never mistakes one for another.
 *
 *   0           CANERGY_OK, also CANERGY_DECODE_OK: done
 *   -1 .. -7    CANERGY_ERR_*: a request refused (nothing changed)
 *   1 .. 8      enum canergy_decode_status: a received frame the codec refused (codec.py's
 *               DecodeErrorReason, in its order)
 *   16 .. 19    CANERGY_RX_*: a received frame taken, with nothing for the rules to apply
 *   32 .. 37    CANERGY_AUTH_*: an authenticated frame's verdict (Python's AuthFailure)
 */
#ifndef CANERGY_STATUS_H
#define CANERGY_STATUS_H

#ifdef __cplusplus
extern "C" {
#endif

/* Results of calls that can refuse (0 is success). */
#define CANERGY_OK 0
#define CANERGY_ERR_ARGUMENT (-1) /* NULL pointer, bad configuration, field that does not fit */
#define CANERGY_ERR_PHASE (-2)    /* not allowed now: joining, or a return still pending */
#define CANERGY_ERR_AMOUNT (-3)   /* zero, not whole mJ, more than a frame or than usable */
#define CANERGY_ERR_RECORD (-4) /* NV holds a supervisor record of another version or node list */
#define CANERGY_ERR_END (-5) /* a counter at CANERGY_COUNTER_END, or a record beyond the bound */
/* canergy_session_begin under the witnessed rules: tx + 1 is beyond W + B (the node has not
 * shown it persisted a transaction close enough). */
#define CANERGY_ERR_WINDOW (-6)
/* canergy_supervisor_begin under the witnessed rules: a start still waits for some node's books
 * (canergy_supervisor_unconfirmed names them). */
#define CANERGY_ERR_UNCONFIRMED (-7)

/* The decoder's verdict on a frame: the first check that failed. */
enum canergy_decode_status {
    CANERGY_DECODE_OK = 0,
    CANERGY_DECODE_FOREIGN = 1,         /* not in this id block, or an 11-bit identifier */
    CANERGY_DECODE_UNKNOWN_TYPE = 2,
    CANERGY_DECODE_BAD_NODE = 3,        /* node 0, bit 7 set, or bits above the 29th */
    CANERGY_DECODE_REMOTE_FRAME = 4,
    CANERGY_DECODE_WRONG_DIRECTION = 5,
    CANERGY_DECODE_WRONG_DLC = 6,       /* also any length above 8 */
    CANERGY_DECODE_BAD_CRC = 7,
    CANERGY_DECODE_OUT_OF_RANGE = 8     /* a zero amount; a DEBIT of no known kind */
};

/* A received frame taken, nothing applied. */
#define CANERGY_RX_OTHER_NODE 16 /* a valid frame for another node (nothing happens, no error) */
#define CANERGY_RX_AHEAD 17  /* canergy_supervisor_on_answer: an answer naming a transaction after
                                the session's: no honest node sends it (an intrusion to report) */
#define CANERGY_RX_CALLER 18 /* canergy_supervisor_on_answer: a TELEMETRY, RETURN or JOIN: *m holds
                                it, nothing applied */
#define CANERGY_RX_NOT_CAN 19 /* an identifier beyond 29 bits (another transport's): no CAN frame
                                 carries it; not decoded */

/* canergy_auth_accept's verdicts besides CANERGY_DECODE_OK, the decode statuses (the codec's
 * refusal as without a key) and CANERGY_RX_OTHER_NODE. The refusals are Python's AuthFailure
 * values, named in the comments. */
#define CANERGY_AUTH_PENDING 32         /* nothing to act on (yet): a classic message waits for its
                                         * MAC frame, or a JOINING TELEMETRY of a JOIN not seen */
#define CANERGY_AUTH_MAC_BAD 33         /* "MAC BAD" */
#define CANERGY_AUTH_STALE 34           /* "freshness not the expected one" */
#define CANERGY_AUTH_NO_DATA 35         /* "MAC frame without its message" */
#define CANERGY_AUTH_MALFORMED 36       /* "malformed authenticated frame" */
#define CANERGY_AUTH_UNAUTHENTICATED 37 /* "frame without a MAC" */

#ifdef __cplusplus
}
#endif

#endif
