/*
 * canergy-node's shared state (ports/linux): the program's name and exit codes, its options,
 * the counters and intrusion report of its status file, and struct port, which main() owns and
 * hands to the other files of the port. Not part of the library.
 */
#ifndef CANERGY_PORT_LINUX_PORT_H
#define CANERGY_PORT_LINUX_PORT_H

#include "canergy/auth.h"
#include "canergy/node.h"

#include <stdint.h>

extern const char *const port_prog; /* the program's name in its messages */
#define PROG port_prog
#define EXIT_NV 1
#define EXIT_USAGE 2
#define US_PER_S 1000000ULL
#define NV_IMAGE_BYTES (CANERGY_NV_SLOTS * CANERGY_NV_SLOT_SIZE)
#define NV_READ_BYTES CANERGY_NV_SEALED_SIZE /* what is read: the sealed image at most */

struct port_options {
    const char *interface;
    const char *channel;
    const char *nv_path;
    const char *status_path;
    uint64_t power_uw;
    uint64_t tick_us;
    uint64_t telemetry_period_us;
    uint64_t response_timeout_us;
    uint64_t status_period_us;
    uint64_t low_water_uj;
    uint64_t return_above_uj;
    uint32_t id_base;
    const char *auth_path;
    int node;
    int keep_all;
    int fd;
    uint8_t rules; /* enum canergy_rules */
};

/* What firmware_model's BusRuntime counts, with the same names in the status file. */
struct port_counters {
    uint64_t frames_sent;
    uint64_t frames_received;
    uint64_t decode_errors;
    uint64_t reasons[CANERGY_DECODE_OUT_OF_RANGE + 1];
    uint64_t foreign_frames;
    uint64_t send_retries;
    uint64_t send_failures;
    uint64_t receive_errors;
    uint64_t error_frames;
    uint64_t auth_failures[CANERGY_AUTH_UNAUTHENTICATED - CANERGY_AUTH_MAC_BAD + 1];
};

/* firmware_model's intrusion report: a count, when the first came, the latest few. */
#define INTRUSIONS_KEPT 20U
#define FRAME_TEXT 140U /* "0CE00D05#" and 64 bytes in hex */

struct port_intrusion {
    uint64_t time_us;
    const char *kind;
    char frame[FRAME_TEXT];
};

struct port_intrusions {
    uint64_t total;
    uint64_t first_at_us;
    struct port_intrusion recent[INTRUSIONS_KEPT]; /* a ring: the newest at (total - 1) % KEPT */
};

struct port {
    struct port_options opt;
    struct canergy_node node;
    struct port_counters count;
    struct port_intrusions intrusions;
    struct canergy_auth auth; /* with --auth */
    struct canergy_cmac seal; /* with --auth: the NV seal key (canergy_nv_seal_key) */
    int sealed;               /* with --auth: NV slots sealed (canergy/nv.h, "Sealed image") */
    uint64_t drawn_uj;
    uint64_t remainder_pj; /* energy owed below 1 uJ, in uW*us, as firmware_model's actuator */
    uint64_t last_draw_us;
    uint64_t nv_writes;
    uint64_t witnessed; /* the library's witness, not wrapped: firmware_model's "witnessed" */
    int nv_fallbacks;
    int joins;
    int sock;
    int nv_fd;
};

#endif /* CANERGY_PORT_LINUX_PORT_H */
