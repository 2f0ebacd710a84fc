/*
 * A node around the client: what firmware_model/node.py adds to the protocol, still sans-IO.
 *   - TELEMETRY at start, every telemetry period, at once when the level falls below the
 *     low-water mark, after a commit, a pay-back or the admission;
 *   - the actuator's draw: the port says how much energy the actuator wants for the period it
 *     just ran; the node spends what usable allows (persisted before the actuator uses it) and
 *     reports the actuator halted when it got less;
 *   - the return policy: after each draw, give back whatever exceeds return_above (whole mJ);
 *   - the witness (firmware_model's FirmwareNode.witnessed): frames seen in the node's name
 *     that it did not send, counted modulo 256 and carried in every TELEMETRY (a change is
 *     reported at the next poll, as a new level is, but no sooner than 10 ms after the last
 *     TELEMETRY, so that two nodes on one id cannot answer each other's reports with no pause;
 *     at once at 128 unreported): a frame in its own direction with its id
 *     (a node never receives its own frames back), a RETURN_ACK for a return number it has not
 *     reached (ahead of its own), an ADMIT whose nonce is not its JOIN's of this start (any
 *     ADMIT when it started with books). Duplicates of genuine answers, which a lossy bus
 *     makes, are not counted. Counting only: such a frame moves nothing. The port's acceptance
 *     filter must pass the node's own direction for its id (README.md); with a filter that does
 *     not, the node works as before, unwitnessed.
 * The port keeps its actuator period itself (firmware_model's --tick): it calls
 * canergy_node_draw() once per period and canergy_node_poll() whenever canergy_node_deadline()
 * is reached. Same out contract as client.h: persist first, then send the frames.
 */
#ifndef CANERGY_NODE_H
#define CANERGY_NODE_H

#include "canergy/client.h"

#ifdef __cplusplus
extern "C" {
#endif

#define CANERGY_KEEP_ALL 0xFFFFFFFFUL /* return_above: never give anything back */

struct canergy_node_config {
    struct canergy_client_config client;
    uint32_t telemetry_period_us; /* > 0 */
    uint32_t low_water_uj;        /* report at once below this level */
    uint32_t return_above_uj;     /* give back what exceeds this; CANERGY_KEEP_ALL: keep */
};

struct canergy_node {
    bool was_low;
    bool halted;                /* the last draw got less than it wanted */
    uint8_t witness;            /* frames in its name it did not send, modulo 256 */
    bool joined;                /* this start JOINed or RESUMEd: join_nonce is its nonce */
    uint16_t join_nonce;
    uint8_t witness_reported;   /* the count its last TELEMETRY carried */
    struct canergy_client client;
    uint64_t next_telemetry;
    uint64_t early_telemetry;   /* the earliest a witnessed frame brings the next TELEMETRY
                                 * forward to: the last one's time + CANERGY_WITNESS_GAP_US */
    uint32_t telemetry_period_us;
    uint32_t low_water_uj;
    uint32_t return_above_uj;
    uint32_t decode_errors;     /* frames refused by the codec (any reason but FOREIGN) */
    uint32_t overflow_refused;  /* intentions and commits refused: usable would overflow */
    uint32_t released_uj;       /* witnessed: acknowledged draws the actuator has not used yet
                                 * (volatile: lost, i.e. dissipated, at a reset) */
};

/* Witnessed rules: a node draws this many periods' worth ahead of its need (one DRAW round trip
 * per chunk), at most one frame's worth and what usable holds in whole mJ. */
#define CANERGY_DRAW_AHEAD 4U

/* As canergy_client_start; the first telemetry is due at once (poll at now). */
int canergy_node_start(struct canergy_node *n, const struct canergy_node_config *cfg,
                       const uint8_t *nv_image, size_t nv_len, uint16_t nonce, uint64_t now,
                       struct canergy_out *out);

/* As canergy_client_on_frame, plus counting (decode errors, the witness) and telemetry
 * scheduling. A frame in the node's own direction is CANERGY_DECODE_WRONG_DIRECTION: with its
 * id it is witnessed (an intrusion, for the port's report), with another node's it is nobody's
 * error. */
int canergy_node_on_frame(struct canergy_node *n, const struct canergy_rx_frame *frame,
                          uint64_t now, struct canergy_out *out);

/* Timers and telemetry due at now. */
void canergy_node_poll(struct canergy_node *n, uint64_t now, struct canergy_out *out);

/* One actuator period: timers, the draw of wanted_uj, the return policy, telemetry (what
 * firmware_model's wake-up does on a tick). Returns the microjoules the actuator may use:
 * min(wanted_uj, usable), usable only after out->persist has been carried out. Witnessed
 * rules: min(wanted_uj, released_uj), what acknowledged DRAWs released; when that runs short
 * the next DRAW (CANERGY_DRAW_AHEAD periods' worth) leaves in out. */
uint32_t canergy_node_draw(struct canergy_node *n, uint32_t wanted_uj, uint64_t now,
                           struct canergy_out *out);

/* The earliest of the client's deadlines and the next telemetry. */
uint64_t canergy_node_deadline(const struct canergy_node *n);

#ifdef __cplusplus
}
#endif

#endif /* CANERGY_NODE_H */
