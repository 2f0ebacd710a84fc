/*
 * canergy-gateway's shared state (ports/linux): its options, what it keeps per node below, and
 * struct gateway_port, which main() owns and hands to the port's other files: args.c (the
 * command line), gateway_below.c (the bus below), gateway_storage.c (the NV file, the status
 * file and what stderr is told).
 * The rules and the policy are the library's (canergy/gateway.h, canergy/witness.h).
 */
#ifndef CANERGY_PORT_LINUX_GATEWAY_PORT_H
#define CANERGY_PORT_LINUX_GATEWAY_PORT_H

#include "port.h"

#include "canergy/auth.h"
#include "canergy/gateway.h"
#include "canergy/joins.h"
#include "canergy/witness.h"

#include <stdint.h>

#define MJ 1000U
#define WITNESS_BLOCK_US (10U * US_PER_S) /* no top-ups after evidence, as `canergy gateway` */
#define JOIN_HOLD_US 500000U /* a confirmed JOIN admitted this long after, as `canergy gateway` */
#define AUTH_REASONS (CANERGY_AUTH_UNAUTHENTICATED - CANERGY_AUTH_MAC_BAD + 1)
/* Refusal reasons below: AUTH_REASONS (CANERGY_AUTH_MAC_BAD + k), then these two. */
#define REFUSED_OLD_JOIN ((unsigned)AUTH_REASONS)
#define REFUSED_OWN_DIRECTION ((unsigned)AUTH_REASONS + 1U)
#define REFUSAL_REASONS (AUTH_REASONS + 2)
#define GW_FRAME_TEXT 140U /* "0CE00D05#" and 64 bytes in hex */
#define GW_MSG_TEXT 96U

struct gw_rate { /* events per second over a sliding window (Python's Rate) */
    uint64_t index;
    uint32_t current;
    uint32_t previous;
};

struct gw_options {
    const char *down_channel;
    const char *up_channel;
    const char *nv_path;
    const char *status_path;
    const char *up_auth_path; /* --upstream-auth: this gateway's node key above */
    const char *auth_path;    /* --auth: its own master key, its nodes' keys below */
    uint64_t target_uj;
    uint64_t min_grant_uj;
    uint64_t return_above_uj;
    uint64_t telemetry_period_us;
    uint64_t response_timeout_us;
    uint64_t up_response_timeout_us;
    uint64_t status_period_us;
    uint64_t stop_timeout_us;
    uint64_t tick_us;
    uint64_t return_hold_us;
    uint32_t id_base;
    uint8_t nodes[CANERGY_SUPERVISOR_NODES];
    uint8_t count;
    uint8_t node;
    uint8_t retries;
    uint8_t rules;    /* below: enum canergy_rules */
    uint8_t up_rules; /* above: enum canergy_rules */
    int keep_all;
    int has_target;
    int up_fd; /* --upstream-fd: the FD layout above */
    int fd;    /* --fd: the FD layout below */
};

struct below {
    struct canergy_witness witness; /* its RETURNs held until its TELEMETRY confirms them */
    struct canergy_joins joins;     /* its JOINs held until its TELEMETRY judges them */
    struct gw_rate rates[REFUSAL_REASONS];
    uint64_t level_uj;
    uint64_t heard_at;
    uint64_t committed;
    uint64_t committed_uj;
    uint64_t aborted;
    uint64_t written_off;
    uint64_t admitted;
    uint32_t intrusions; /* evidence against it (canergy_witness_route, JOINs refuted, frames
                          * in the supervisor's direction, refused frames) */
    uint32_t loud;       /* of them, those told on stderr (the first, then one in 100) */
    uint32_t refused[REFUSAL_REASONS];  /* refused, by reason (gw_refusal_names) */
    uint32_t unlogged[REFUSAL_REASONS]; /* of them, not told on stderr yet */
    int fresh;   /* a level reported since the node's last transaction ended */
    int joining; /* its last TELEMETRY said JOINING */
    int other_rules; /* its last TELEMETRY said other client rules than --rules: no grant */
    uint32_t variant_mismatch; /* its TELEMETRY frames that said other rules */
    uint32_t resyncs; /* re-syncs of it alone (--rules witnessed: its window used up) */
    int heard;
};

struct gateway_port {
    struct gw_options opt;
    struct canergy_gateway gw;
    struct canergy_auth up_auth; /* --upstream-auth: the leg above's MACs */
    struct canergy_auth down_auth[CANERGY_SUPERVISOR_NODES]; /* --auth: each node's, below */
    struct canergy_cmac seal; /* with a key: the NV seal key (--upstream-auth's, else --auth's) */
    int sealed;               /* with a key: NV slots sealed (canergy/nv.h, "Sealed image") */
    struct below below[CANERGY_SUPERVISOR_NODES];
    struct port_counters up_count;
    struct port_counters down_count;
    uint64_t nv_writes;
    uint64_t returned_uj;
    uint64_t witnessed;    /* frames in its name above that it did not send (not wrapped) */
    uint64_t found_behind; /* starts the supervisor above found behind (witnessed above) */
    uint64_t dropped_uj;   /* Us below dropped by them */
    uint64_t confirmed;    /* starts the supervisor above confirmed or found behind */
    uint64_t auth_refused; /* frames above refused by --upstream-auth's check */
    uint64_t intrusions_first_at; /* intrusions_seen */
    uint64_t refused_total;       /* frames refused below */
    uint64_t refused_first_at;    /* refused_total != 0 */
    uint64_t refused_last_at;
    uint64_t refusals_logged_at;  /* refusals_logged */
    struct gw_rate refusal_rate;
    int intrusions_seen;
    int refusals_logged;
    uint32_t nv_counter;
    uint8_t nv_slot; /* slot holding the newest record: the next write goes to the other */
    unsigned waiting; /* nodes below a start waited for when last said (witnessed) */
    int joins;
    int up_sock;
    int down_sock;
    int nv_fd;
    int stopping;
    uint64_t next_telemetry;   /* the next TELEMETRY above: now when the level moved */
    uint64_t early_telemetry;  /* the soonest a frame in its name brings it forward to: the
                                * last one's time + CANERGY_WITNESS_GAP_US, as a node's */
    uint64_t witness_reported; /* witnessed as the last TELEMETRY carried it */
    int up_waiting;    /* the wait for the supervisor above, as last said on stderr */
};

/* gateway_above.c: one frame above (with its MAC frame or in the FD layout with
 * --upstream-auth); a step of the client role above carried out (the record saved first, then
 * its frames); the frames from above; the client's timer when due; what it holds above
 * --return-above given back; its TELEMETRY, the level it can still grant below (the next one a
 * period later). */
void gw_send_up(struct gateway_port *g, const struct canergy_frame *f);
void gw_up_out(struct gateway_port *g, const struct canergy_out *out);
void gw_receive_up(struct gateway_port *g, uint64_t now);
void gw_up_timer(struct gateway_port *g, uint64_t now);
void gw_give_back(struct gateway_port *g, uint64_t now);
void gw_telemetry(struct gateway_port *g, uint64_t now);

/* gateway_below.c: --auth's keys below, one per node derived from the master key (exits 2 for
 * a key file refused, or the master key the key above was derived from); the NV seal key from
 * the master key when --upstream-auth gave none. */
void gw_down_keys(struct gateway_port *g);

/* gateway_below.c: carry out a step of the supervisor below (both records saved first, then
 * its frames; an acknowledged intention decided at once); the nodes' frames; the held RETURNs
 * due; the top-ups. gw_count_decode counts a decode status on either bus. */
void gw_down_out(struct gateway_port *g, const struct canergy_supervisor_out *out, uint64_t now);
void gw_receive_down(struct gateway_port *g, uint64_t now);
void gw_release_all(struct gateway_port *g, uint64_t now);
void gw_top_up(struct gateway_port *g, uint64_t now);
void gw_count_decode(struct port_counters *c, int status);
/* gateway_below.c: the earliest time a JOIN held below is due (UINT64_MAX: none). */
uint64_t gw_joins_deadline(const struct gateway_port *g);

/* gateway_report.c: an intrusion for the node of g->below[i] (quiet: counted, not told); a
 * frame refused for it (reason: an index of gw_refusal_names; counted as a quiet intrusion,
 * told on stderr at once the first time, then at most once a second by gw_refusals_tick); a
 * received frame as candump shows it; a message as Python's repr shows it; a rate now. */
extern const char *const gw_refusal_names[REFUSAL_REASONS];
void gw_intrusion(struct gateway_port *g, unsigned i, const char *what, const char *kind,
                  int quiet, uint64_t now);
void gw_refused(struct gateway_port *g, unsigned i, unsigned reason, const char *what,
                uint64_t now);
void gw_refusals_tick(struct gateway_port *g, uint64_t now);
void gw_frame_text(char out[GW_FRAME_TEXT], const struct canergy_rx_frame *rx);
void gw_msg_text(char out[GW_MSG_TEXT], const struct canergy_msg *m); /* as Python's repr */
double gw_rate_per_s(const struct gw_rate *r, uint64_t now);

/* args.c: the options of argv with their defaults; -h prints the usage and exits 0, a bad
 * argument exits 2. */
void port_parse_gateway_args(int argc, char **argv, struct gw_options *o);

/* gateway_storage.c. Before the buses are opened: exit 2 when an existing NV file cannot be
 * taken (a counter beyond the bound in either role, an older layout; with a key, no slot whose
 * seal holds or a record never sealed; without one, a sealed file). */
void gw_check_nv(const struct gateway_port *g);
/* Open the NV file and start both roles from its newest slot (none: JOIN above, new below),
 * sending the start's frames above. Exits 2 when the file cannot be taken. */
void gw_start(struct gateway_port *g, uint64_t now);
/* Both records, fsynced, before any frame of the step leaves: exits 1 when that fails. */
void gw_save(struct gateway_port *g);
/* The status file (the Python gateway's keys; `canergy ledger` reads it). */
void gw_save_status(const struct gateway_port *g, uint64_t now);
/* stderr, each change once: whom a start below waits for (witnessed below); the wait for the
 * supervisor above to confirm this gateway's record, and how it ended (witnessed above). */
void gw_say_waiting(struct gateway_port *g);
void gw_say_up_waiting(struct gateway_port *g, int behind, uint64_t dropped);

#endif /* CANERGY_PORT_LINUX_GATEWAY_PORT_H */
