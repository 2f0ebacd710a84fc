/*
 * canergy-gateway: a canergy gateway on Linux SocketCAN, built on the C library's gateway rules
 * (canergy/gateway.h): node --node of the bus above, supervisor of --nodes on the bus below.
 * Energy committed to it above becomes its budget below at once; what it holds above
 * --return-above goes back up as numbered RETURNs. A subset of `canergy gateway`'s flags:
 *
 *   canergy-gateway --node N --nodes 1-5 -i socketcan -c vcan1 --upstream-channel vcan0
 *                   --nv PATH [--status-file PATH] [--target E] [--min-grant E]
 *                   [--return-above E] [--telemetry-period T] [--response-timeout T]
 *                   [--upstream-response-timeout T] [--retries N] [--status-period T]
 *                   [--stop-timeout T] [--return-hold T] [--id-base ID]
 *
 * One record for both roles (the client's above, the supervisor's below) in two slots of the NV
 * file, written in turn with fsync before any frame of the step leaves: a kill -9 at any instant
 * restarts from books in which neither role owes the other (two records written apart is the
 * split-save counterexample of `canergy check --topology chain --broken-gateway split-save`).
 * A slot: "CNRG", counter, the client's 30-byte record, the supervisor's slot image
 * (canergy/supervisor.h), CRC-32 of all of it.
 *
 * Below it tops every node up to --target from the level in its TELEMETRY (a level reported
 * after its last transaction ended), commits what a node acknowledges, and settles on
 * SIGINT/SIGTERM (grants nothing more, waits for the open transactions up to --stop-timeout).
 * Above it reports its downstream Us as its level. Its status file is the Python gateway's
 * (role "gateway", the supervisor's keys, "upstream" with the client's record, "link_gap_uj"):
 * `canergy ledger` reads it. Without a key on either bus; no limits besides --target.
 *
 * Exit status: 0 after SIGINT/SIGTERM, 1 when the NV file cannot be written, 2 for bad
 * arguments or a socket or file that cannot be opened.
 */
#define _GNU_SOURCE 1

#include "args.h"
#include "paths.h"
#include "port.h"
#include "socketcan.h"
#include "system.h"

#include "canergy/gateway.h"

#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

const char *const port_prog = "canergy-gateway";

#define MJ 1000U

struct gw_options {
    const char *down_channel;
    const char *up_channel;
    const char *nv_path;
    const char *status_path;
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
    uint8_t rules; /* below: enum canergy_rules */
    uint8_t up_rules; /* above: enum canergy_rules */
    int keep_all;
    int has_target;
};

struct below {
    uint64_t level_uj;
    uint64_t heard_at;
    uint64_t committed;
    uint64_t committed_uj;
    uint64_t aborted;
    uint64_t written_off;
    uint64_t admitted;
    int fresh;   /* a level reported since the node's last transaction ended */
    int joining; /* its last TELEMETRY said JOINING */
    int heard;
    /* The RETURN held until the node's own TELEMETRY confirms it (no key on the bus: anyone
     * can send one in its name), as canergy.live.witness does. */
    uint64_t confirmed_at; /* 0: not confirmed yet */
    uint64_t evidence_at;  /* the last evidence against its reports (no top-ups for a while) */
    uint64_t refuted;      /* RETURNs dropped on evidence */
    uint64_t intrusions;
    uint16_t held_seq;
    uint16_t held_mj;
    uint8_t witness; /* its last reported witness count */
    uint8_t held;
    uint8_t witness_known;
    uint8_t evidence;    /* evidence_at is set */
};

struct gateway_port {
    struct gw_options opt;
    struct canergy_gateway gw;
    struct below below[CANERGY_SUPERVISOR_NODES];
    struct port_counters up_count;
    struct port_counters down_count;
    uint64_t nv_writes;
    uint64_t returned_uj;
    uint32_t nv_counter;
    uint8_t nv_slot; /* slot holding the newest record: the next write goes to the other */
    int joins;
    int up_sock;
    int down_sock;
    int nv_fd;
    int stopping;
    int telemetry_now; /* a commit or pay-back above: report the new level at once */
    uint64_t witnessed; /* frames in its name above that it did not send (not wrapped) */
    unsigned waiting;   /* nodes below a start waited for when last said (witnessed) */
    uint64_t found_behind; /* starts the supervisor above found behind (witnessed above) */
    uint64_t dropped_uj;   /* Us below dropped by them */
    uint64_t confirmed;    /* starts the supervisor above confirmed or found behind */
    int up_waiting;        /* the wait for the supervisor above, as last said on stderr */
};

static volatile sig_atomic_t stop_requested;

static void on_stop_signal(int signum)
{
    (void)signum;
    stop_requested = 1;
}

/* ---- the command line ---- */

/* "1-5,9": ascending distinct ids into o->nodes. */
static void parse_nodes(const char *text, struct gw_options *o)
{
    uint8_t seen[CANERGY_MAX_NODE + 1U] = {0};
    char buf[512];
    if (strlen(text) >= sizeof buf) {
        port_usage_error("argument --nodes: too long");
    }
    memcpy(buf, text, strlen(text) + 1U);
    for (char *rest = NULL, *part = strtok_r(buf, ",", &rest); part != NULL;
         part = strtok_r(NULL, ",", &rest)) {
        char *dash = strchr(part, '-');
        if (dash != NULL) {
            *dash = '\0';
        }
        const uint64_t lo = port_parse_int("--nodes", part, CANERGY_MIN_NODE, CANERGY_MAX_NODE);
        const uint64_t hi = dash == NULL ? lo
                                         : port_parse_int("--nodes", dash + 1, lo, CANERGY_MAX_NODE);
        for (uint64_t n = lo; n <= hi; n++) {
            seen[n] = 1U;
        }
    }
    o->count = 0U;
    for (unsigned n = CANERGY_MIN_NODE; n <= CANERGY_MAX_NODE; n++) {
        if (seen[n] != 0U) {
            if (o->count == CANERGY_SUPERVISOR_NODES) {
                port_usage_error("argument --nodes: more than %u nodes",
                                 (unsigned)CANERGY_SUPERVISOR_NODES);
            }
            o->nodes[o->count++] = (uint8_t)n;
        }
    }
}

static void usage(void)
{
    (void)printf("usage: %s --node N --nodes 1-5 [-i socketcan] -c CHANNEL\n"
                 "       --upstream-channel CHANNEL --nv PATH [--status-file PATH]\n"
                 "       [--target E] [--min-grant E] [--return-above E]\n"
                 "       [--telemetry-period T] [--response-timeout T]\n"
                 "       [--upstream-response-timeout T] [--retries N] [--status-period T]\n"
                 "       [--stop-timeout T] [--return-hold T] [--id-base ID]\n"
                 "       [--rules hardened|witnessed] [--upstream-rules hardened|witnessed]\n"
                 "A canergy gateway on Linux SocketCAN (the C library's gateway rules): node\n"
                 "--node above (--upstream-channel), supervisor of --nodes below (-c); flags\n"
                 "as canergy gateway's. Energies 0.5J, 250mJ; durations 50ms, 1.5s.\n"
                 "--rules witnessed: the nodes below draw through DEBIT and RESUME at\n"
                 "every start (the supervisor side below).\n"
                 "--upstream-rules witnessed: what goes below is a DRAW the supervisor\n"
                 "above acknowledges first, and every start waits, granting nothing below,\n"
                 "until it confirms this gateway's record (an older copy creates nothing).\n",
                 PROG);
    exit(0);
}

static void parse_args(int argc, char **argv, struct gw_options *o)
{
    memset(o, 0, sizeof *o);
    o->min_grant_uj = MJ;
    o->telemetry_period_us = 100000U;
    o->response_timeout_us = 50000U;
    o->up_response_timeout_us = 50000U;
    o->status_period_us = 1000000U;
    o->stop_timeout_us = 5000000U;
    o->tick_us = 50000U;
    o->return_hold_us = 500000U;
    o->retries = 3U;
    o->keep_all = 1;
    o->id_base = (uint32_t)CANERGY_DEFAULT_ID_BASE;
    for (int i = 1; i < argc; i++) {
        const char *flag = argv[i];
        if (strcmp(flag, "-h") == 0 || strcmp(flag, "--help") == 0) {
            usage();
        }
        if (i + 1 >= argc) {
            port_usage_error("argument %s: expected one argument", flag);
        }
        const char *v = argv[++i];
        if (strcmp(flag, "--node") == 0) {
            o->node = (uint8_t)port_parse_int(flag, v, CANERGY_MIN_NODE, CANERGY_MAX_NODE);
        } else if (strcmp(flag, "--nodes") == 0) {
            parse_nodes(v, o);
        } else if (strcmp(flag, "-i") == 0 || strcmp(flag, "--interface") == 0 ||
                   strcmp(flag, "--upstream-interface") == 0) {
            if (strcmp(v, "socketcan") != 0) {
                port_usage_error("argument %s: this port speaks socketcan only, not '%s'", flag,
                                 v);
            }
        } else if (strcmp(flag, "-c") == 0 || strcmp(flag, "--channel") == 0) {
            o->down_channel = v;
        } else if (strcmp(flag, "--upstream-channel") == 0) {
            o->up_channel = v;
        } else if (strcmp(flag, "--nv") == 0) {
            o->nv_path = v;
        } else if (strcmp(flag, "--status-file") == 0) {
            o->status_path = v;
        } else if (strcmp(flag, "--target") == 0) {
            o->target_uj = port_parse_energy(flag, v);
            o->has_target = 1;
        } else if (strcmp(flag, "--min-grant") == 0) {
            o->min_grant_uj = port_parse_energy(flag, v);
        } else if (strcmp(flag, "--return-above") == 0) {
            o->return_above_uj = port_parse_energy(flag, v);
            o->keep_all = 0;
        } else if (strcmp(flag, "--telemetry-period") == 0) {
            o->telemetry_period_us = port_parse_duration(flag, v, UINT32_MAX);
        } else if (strcmp(flag, "--response-timeout") == 0) {
            o->response_timeout_us = port_parse_duration(flag, v, UINT32_MAX / 2U);
        } else if (strcmp(flag, "--upstream-response-timeout") == 0) {
            o->up_response_timeout_us = port_parse_duration(flag, v, UINT32_MAX / 4U);
        } else if (strcmp(flag, "--rules") == 0) {
            o->rules = port_parse_rules(flag, v);
        } else if (strcmp(flag, "--upstream-rules") == 0) {
            o->up_rules = port_parse_rules(flag, v);
        } else if (strcmp(flag, "--retries") == 0) {
            o->retries = (uint8_t)port_parse_int(flag, v, 0U, 255U);
        } else if (strcmp(flag, "--status-period") == 0) {
            o->status_period_us = port_parse_duration(flag, v, UINT32_MAX);
        } else if (strcmp(flag, "--return-hold") == 0) {
            o->return_hold_us = port_parse_duration(flag, v, UINT32_MAX);
        } else if (strcmp(flag, "--stop-timeout") == 0) {
            o->stop_timeout_us = port_parse_duration(flag, v, UINT32_MAX);
        } else if (strcmp(flag, "--id-base") == 0) {
            o->id_base = (uint32_t)port_parse_int(flag, v, 0U, 0x1FFFFFFFU);
            if (!canergy_id_base_valid(o->id_base)) {
                port_usage_error("argument %s: id base 0x%08X has bits in its low 12", flag,
                                 (unsigned)o->id_base);
            }
        } else {
            port_usage_error("unrecognized argument: %s", flag);
        }
    }
    if (o->node == 0U || o->count == 0U || o->down_channel == NULL || o->up_channel == NULL ||
        o->nv_path == NULL) {
        port_usage_error("the following arguments are required: --node, --nodes, -c, "
                         "--upstream-channel, --nv");
    }
    if (strcmp(o->down_channel, o->up_channel) == 0) {
        port_usage_error("-c and --upstream-channel name the same bus: a gateway joins two");
    }
    if (o->min_grant_uj < MJ) {
        port_usage_error("argument --min-grant: at least 1 mJ (one frame's unit)");
    }
}

/* ---- the one record: both roles in a slot (canergy_gateway_nv_*, nv.c) ---- */

#define GW_SLOT CANERGY_GW_NV_SLOT_SIZE

/* Both records, fsynced, before anything else happens: exit 1 when that fails (nothing of the
 * step is sent). */
static void save(struct gateway_port *g)
{
    uint8_t slot[GW_SLOT];
    const uint8_t next = (uint8_t)(1U - g->nv_slot);
    canergy_gateway_nv_encode(&g->gw, g->nv_counter + 1U, slot);
    const off_t at = (off_t)next * (off_t)GW_SLOT;
    if (pwrite(g->nv_fd, slot, GW_SLOT, at) != (ssize_t)GW_SLOT || fsync(g->nv_fd) != 0) {
        (void)fprintf(stderr, "%s: NV store: %s: write failed: %s\n", PROG, g->opt.nv_path,
                      strerror(errno));
        exit(EXIT_NV);
    }
    g->nv_slot = next;
    g->nv_counter++;
    g->nv_writes++;
}

/* The newest valid slot of image; exit 2 when a valid slot's upstream record holds a counter
 * beyond the bound the proof assumes. */
static void load_nv(const char *path, const uint8_t *image, size_t len,
                    struct canergy_gateway_nv *nv)
{
    if (canergy_gateway_nv_load(image, len, nv) == CANERGY_ERR_END) {
        const int tx = nv->up.last_tx >= CANERGY_COUNTER_BOUND;
        port_usage_error("--nv %s: upstream: %s %lu is beyond the bound 2^30 - 1 the proof "
                         "assumes",
                         path, tx ? "last_tx" : "return_seq",
                         (unsigned long)(tx ? nv->up.last_tx : nv->up.return_seq));
    }
}

/* Exit 2 when the image holds a slot of an older layout (never taken as a new, blank file). */
static void refuse_older_layout(const char *path, const struct canergy_gateway_nv *nv)
{
    if (nv->older != 0U) {
        port_usage_error("--nv %s: written by an older canergy-gateway (supervisor record "
                         "version %u); this one reads version 4 only",
                         path, (unsigned)nv->older);
    }
}

static void refuse_below_beyond(const char *path)
{
    port_usage_error("--nv %s: downstream: a node's tx or returns_credited is beyond the bound "
                     "2^30 - 1 the proof assumes",
                     path);
}

/* Before the buses are opened: exit 2 when an existing NV file holds a counter beyond the bound
 * in either role (reads only). */
static void check_nv(const struct gw_options *o)
{
    struct stat st;
    if (stat(o->nv_path, &st) != 0 || !S_ISREG(st.st_mode)) {
        return; /* new, or not a file: start() says so */
    }
    const int fd = open(o->nv_path, O_RDONLY | O_CLOEXEC);
    if (fd < 0) {
        return;
    }
    static uint8_t image[2U * GW_SLOT];
    const ssize_t got = pread(fd, image, sizeof image, 0);
    (void)close(fd);
    struct canergy_gateway_nv nv;
    load_nv(o->nv_path, image, got > 0 ? (size_t)got : 0U, &nv);
    if (nv.slot < 0) {
        refuse_older_layout(o->nv_path, &nv);
        return;
    }
    static struct canergy_supervisor down;
    const struct canergy_supervisor_config cfg = {
        o->id_base, {(uint32_t)o->response_timeout_us, o->retries, o->rules, 0U}};
    uint32_t counter = 0U;
    uint8_t slot = 0U;
    const int loaded = canergy_supervisor_load(&down, &cfg, o->nodes, o->count, 0U, nv.down,
                                               CANERGY_SUPERVISOR_SLOT_SIZE, &counter, &slot);
    if (loaded == CANERGY_ERR_END) {
        refuse_below_beyond(o->nv_path);
    }
    if (loaded == CANERGY_ERR_RECORD) {
        refuse_older_layout(o->nv_path, &nv);
    }
}

/* Start: the newest valid slot of the NV file gives both roles their books; none (a new or
 * wiped file) starts the client JOINing above and the supervisor new below. */
static void start(struct gateway_port *g, uint64_t now)
{
    const struct gw_options *o = &g->opt;
    g->nv_fd = port_open_nv(o->nv_path, 0600);
    if (g->nv_fd < 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, o->nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
    static uint8_t image[2U * GW_SLOT];
    const ssize_t got = pread(g->nv_fd, image, sizeof image, 0);
    if (got < 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, o->nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
    struct canergy_gateway_nv nv;
    load_nv(o->nv_path, image, (size_t)got, &nv);
    if (nv.foreign) {
        (void)fprintf(stderr, "%s: error: --nv %s: not a gateway's NV file (a node's?)\n",
                      PROG, o->nv_path);
        exit(EXIT_USAGE);
    }
    const struct canergy_supervisor_config down = {
        o->id_base, {(uint32_t)o->response_timeout_us, o->retries, o->rules, 0U}};
    const struct canergy_client_config up = {o->id_base, (uint32_t)(2U * o->up_response_timeout_us),
                                             (uint32_t)(2U * o->up_response_timeout_us), o->node,
                                             o->up_rules, 0U};
    struct canergy_out out;
    uint32_t sup_counter = 0U;
    uint8_t sup_slot = 0U;
    if (nv.slot >= 0) {
        uint8_t client_nv[CANERGY_NV_SLOTS * CANERGY_NV_SLOT_SIZE];
        memset(client_nv, 0, sizeof client_nv);
        uint8_t rec[CANERGY_NV_RECORD_SIZE];
        canergy_record_pack(&nv.up, rec);
        canergy_nv_slot_encode(nv.counter, rec, sizeof rec, client_nv);
        (void)canergy_client_start(&g->gw.up, &up, client_nv, sizeof client_nv, port_random16(), now,
                                   &out);
        const int loaded = canergy_supervisor_load(
            &g->gw.down, &down, o->nodes, o->count, 0U, nv.down, CANERGY_SUPERVISOR_SLOT_SIZE,
            &sup_counter, &sup_slot);
        if (loaded == CANERGY_ERR_END) {
            refuse_below_beyond(o->nv_path);
        }
        if (loaded != 1 || canergy_client_joining(&g->gw.up)) {
            (void)fprintf(stderr, "%s: error: --nv %s: a record of other nodes or damaged\n",
                          PROG, o->nv_path);
            exit(EXIT_USAGE);
        }
        g->nv_counter = nv.counter;
        g->nv_slot = (uint8_t)nv.slot;
        /* every start is one below (witnessed: what is open written off, SYNC with a fresh
         * nonce, no grant until the nodes have confirmed their books) */
        struct canergy_supervisor_out sout;
        canergy_supervisor_start(&g->gw.down, port_random16(), now, &sout);
        if (sout.persist != 0U) {
            save(g);
        }
    } else {
        (void)canergy_client_start(&g->gw.up, &up, NULL, 0U, port_random16(), now, &out);
        if (canergy_supervisor_init(&g->gw.down, &down, o->nodes, o->count, 0U) != CANERGY_OK) {
            port_usage_error("argument --nodes: not a node list this gateway can hold");
        }
        g->joins++;
        g->nv_slot = 1U; /* slot 0 is written first */
    }
    for (unsigned i = 0U; i < out.frame_count; i++) { /* the JOIN, when there are no books */
        port_can_send(g->up_sock, &g->up_count, out.frames[i].id, out.frames[i].data,
                      out.frames[i].dlc);
    }
}

static uint64_t least(uint64_t a, uint64_t b)
{
    return a < b ? a : b;
}

/* ---- carrying out what the library asks ---- */

static void up_out(struct gateway_port *g, const struct canergy_out *out)
{
    if (out->persist) {
        save(g); /* both records, before any frame of the step */
    }
    for (unsigned i = 0U; i < out->frame_count; i++) {
        const struct canergy_frame *f = &out->frames[i];
        port_can_send(g->up_sock, &g->up_count, f->id, f->data, f->dlc);
    }
}

static struct below *below_of(struct gateway_port *g, uint8_t node)
{
    for (unsigned i = 0U; i < g->opt.count; i++) {
        if (g->opt.nodes[i] == node) {
            return &g->below[i];
        }
    }
    return NULL;
}

static void down_out(struct gateway_port *g, const struct canergy_supervisor_out *out,
                     uint64_t now);

/* What each session step did: an acknowledged intention is committed (aborted when stopping)
 * at once; an ended transaction makes the node's level stale until it reports again. */
static void down_events(struct gateway_port *g, const struct canergy_supervisor_out *out,
                        uint64_t now)
{
    for (unsigned k = 0U; k < out->event_count; k++) {
        const struct canergy_supervisor_event *e = &out->events[k];
        struct below *b = below_of(g, e->node);
        if (b == NULL) {
            continue;
        }
        if (e->resolved != CANERGY_RESOLVED_NONE) {
            b->fresh = 0;
            b->committed += e->resolved == CANERGY_RESOLVED_COMMITTED ? 1U : 0U;
            b->committed_uj += e->resolved == CANERGY_RESOLVED_COMMITTED ? e->amount_uj : 0U;
            b->aborted += e->resolved == CANERGY_RESOLVED_ABORTED ? 1U : 0U;
            b->written_off += e->resolved == CANERGY_RESOLVED_WRITTEN_OFF ? 1U : 0U;
        }
        if ((e->flags & CANERGY_SUP_ADMITTED) != 0U) {
            b->admitted++;
            b->fresh = 0;
            b->held = 0U; /* its return numbers start again from the session's */
        }
        if ((e->flags & CANERGY_SUP_ACKNOWLEDGED) != 0U) {
            struct canergy_supervisor_out decided;
            if (canergy_supervisor_decide(&g->gw.down, e->node, !g->stopping, now, &decided) ==
                CANERGY_OK) {
                down_out(g, &decided, now);
            }
        }
    }
}

static void down_out(struct gateway_port *g, const struct canergy_supervisor_out *out,
                     uint64_t now)
{
    if (out->persist) {
        save(g);
    }
    for (unsigned i = 0U; i < out->frame_count; i++) {
        const struct canergy_frame *f = &out->frames[i];
        port_can_send(g->down_sock, &g->down_count, f->id, f->data, f->dlc);
    }
    down_events(g, out, now);
}

/* ---- the two buses ---- */

static void count_decode(struct port_counters *c, int status)
{
    if (status == CANERGY_DECODE_FOREIGN) {
        c->foreign_frames++;
    } else if (status != CANERGY_DECODE_OK && status != CANERGY_RX_OTHER_NODE) {
        c->decode_errors++;
        if (status > 0 && status <= (int)CANERGY_DECODE_OUT_OF_RANGE) {
            c->reasons[status]++;
        }
    }
}

/* Witnessed rules above: say on stderr when the gateway waits for the supervisor above to
 * confirm its record, and how the wait ended (each change once). */
static const char *const UP_WAITING =
    "no grant below until the supervisor above confirms this gateway's record (RESUME sent "
    "upstream, or its SYNC answered; the record may be an older copy)";

static void say_up_waiting(struct gateway_port *g, int behind, uint64_t dropped)
{
    const int waiting = canergy_gateway_upstream_waiting(&g->gw) ? 1 : 0;
    if (waiting == g->up_waiting) {
        return;
    }
    g->up_waiting = waiting;
    if (waiting) {
        (void)fprintf(stderr, "%s: %s\n", PROG, UP_WAITING);
        return;
    }
    g->confirmed++;
    if (behind) {
        (void)fprintf(stderr,
                      "%s: the supervisor above found this gateway's record behind (an older "
                      "copy): upstream books dropped, admitted afresh, %llu uJ of the budget "
                      "below dropped; granting below again\n",
                      PROG, (unsigned long long)dropped);
    } else {
        (void)fprintf(stderr,
                      "%s: the supervisor above confirmed this gateway's record (debit %lu): "
                      "granting below again\n",
                      PROG, (unsigned long)g->gw.up.rec.return_seq);
    }
}

static void receive_up(struct gateway_port *g, uint64_t now)
{
    struct canfd_frame cf;
    struct canergy_rx_frame rx;
    while (port_can_receive(g->up_sock, &g->up_count, &cf, &rx) == 1) {
        struct canergy_out out;
        const uint64_t withdrawn = g->gw.down.withdrawn_uj;
        const int status = canergy_gateway_on_up_frame(&g->gw, &rx, now, &out);
        const int behind = (out.events & CANERGY_GW_EV_FOUND_BEHIND) != 0U;
        if (behind) {
            g->found_behind++;
            g->dropped_uj += g->gw.down.withdrawn_uj - withdrawn;
        }
        say_up_waiting(g, behind, g->gw.down.withdrawn_uj - withdrawn);
        count_decode(&g->up_count, status);
        if (status == CANERGY_DECODE_WRONG_DIRECTION && (rx.id & 0xFFU) == g->opt.node) {
            g->witnessed++; /* someone speaks in its name above: say so in TELEMETRY at once */
            g->telemetry_now = 1;
        }
        up_out(g, &out);
        if ((out.events & (CANERGY_EV_COMMITTED | CANERGY_EV_TIMEOUT_COMMIT | CANERGY_EV_CREDITED |
                           CANERGY_EV_ADMITTED)) != 0U) {
            g->telemetry_now = 1;
        }
    }
}

/* How far a 16-bit wire number is ahead of a counter (negative: behind). */
static int32_t ahead16(uint16_t wire, uint32_t counter)
{
    return (int32_t)(int16_t)(uint16_t)(wire - (uint16_t)counter);
}

/* Evidence against a node's reports (a RETURN or a witness count contradicting it): what it
 * holds is dropped, not credited (a genuine RETURN is sent again), and no top-ups for 10 s. */
static void refute(struct below *b, uint64_t now)
{
    b->refuted += b->held;
    b->held = 0U;
    b->intrusions++;
    b->evidence = 1U;
    b->evidence_at = now;
}

/* A fresh RETURN waits for the node's confirmation; an old one goes to the rules (re-ack). */
static int hold_return(struct gateway_port *g, struct below *b, const struct canergy_msg *m,
                       uint64_t now)
{
    const struct canergy_session *s = &g->gw.down.sessions[b - g->below];
    if (ahead16(m->seq, s->returns_credited) != 1) {
        return 0;
    }
    const uint64_t holdable = s->delivered_uj + s->reserved_uj - s->returned_uj;
    if ((uint64_t)m->amount_mj * MJ > holdable) {
        refute(b, now); /* more than its books let it hold: no honest node sends it */
        b->refuted++;
        return 1;
    }
    if (!b->held) {
        b->held = 1U;
        b->held_seq = m->seq;
        b->held_mj = m->amount_mj;
        b->confirmed_at = 0U;
    } else if (b->held_seq != m->seq || b->held_mj != m->amount_mj) {
        refute(b, now); /* two different RETURNs of one number: someone else's */
    }
    return 1;
}

/* A TELEMETRY: its witness count (frames in the node's name it did not send) and its return
 * number confirm the held RETURN, or refute it. */
static void witness(struct below *b, const struct canergy_msg *m, uint64_t now)
{
    if ((m->flags & CANERGY_TELEMETRY_JOINING) != 0U) {
        return; /* no books, no return number yet */
    }
    const uint8_t seen = (uint8_t)(m->witness - b->witness);
    const int evidence = b->witness_known && seen != 0U && seen <= 128U; /* more: a restart */
    b->witness = m->witness;
    b->witness_known = 1U;
    if (evidence || (b->held && ahead16(m->seq, b->held_seq) < 0)) {
        refute(b, now);
    } else if (b->held && m->seq == b->held_seq && b->confirmed_at == 0U) {
        b->confirmed_at = now;
    }
}

/* Held RETURNs confirmed --return-hold ago with no evidence since: credited by the rules. */
static void release_returns(struct gateway_port *g, uint64_t now)
{
    for (unsigned i = 0U; i < g->opt.count; i++) {
        struct below *b = &g->below[i];
        if (!b->held || b->confirmed_at == 0U || now < b->confirmed_at + g->opt.return_hold_us) {
            continue;
        }
        struct canergy_msg m;
        memset(&m, 0, sizeof m);
        m.type = CANERGY_RETURN;
        m.node = g->opt.nodes[i];
        m.seq = b->held_seq;
        m.amount_mj = b->held_mj;
        b->held = 0U;
        struct canergy_supervisor_out out;
        (void)canergy_supervisor_on_msg(&g->gw.down, &m, now, &out);
        down_out(g, &out, now);
    }
}

static void receive_down(struct gateway_port *g, uint64_t now)
{
    struct canfd_frame cf;
    struct canergy_rx_frame rx;
    while (port_can_receive(g->down_sock, &g->down_count, &cf, &rx) == 1) {
        struct canergy_msg m;
        const int status = (int)canergy_decode(g->opt.id_base, &rx, CANERGY_TO_SUPERVISOR, &m);
        count_decode(&g->down_count, status);
        struct below *b = status == CANERGY_DECODE_OK ? below_of(g, m.node) : NULL;
        if (b == NULL) {
            continue;
        }
        b->heard = 1;
        b->heard_at = now;
        if (m.type == CANERGY_TELEMETRY) {
            b->level_uj = (uint64_t)m.level_mj * MJ;
            b->joining = (m.flags & CANERGY_TELEMETRY_JOINING) != 0U;
            b->fresh = 1;
            witness(b, &m, now);
            continue;
        }
        if (m.type == CANERGY_RETURN && hold_return(g, b, &m, now)) {
            continue;
        }
        struct canergy_supervisor_out out;
        (void)canergy_supervisor_on_msg(&g->gw.down, &m, now, &out);
        down_out(g, &out, now);
    }
}

/* Us below as the grants and returns size it: a debt (below 0, after a witnessed start) is 0. */
static uint64_t usable_below(const struct gateway_port *g)
{
    return g->gw.down.usable_uj < 0 ? 0U : (uint64_t)g->gw.down.usable_uj;
}

/* Top every node up to --target from its last fresh level, within Us and one frame. */
/* Witnessed rules: say on stderr whom a start below waits for before it grants anything, and
 * when every node has confirmed its books (each change once). */
static void say_waiting(struct gateway_port *g)
{
    uint8_t waiting[CANERGY_SUPERVISOR_NODES];
    const uint8_t n = canergy_supervisor_unconfirmed(&g->gw.down, waiting);
    if (n == g->waiting) {
        return;
    }
    if (n == 0U) {
        (void)fprintf(stderr, "%s: every node below has confirmed its books: granting\n", PROG);
    } else {
        (void)fprintf(stderr, "%s: no grant below before node(s) ", PROG);
        for (uint8_t i = 0U; i < n; i++) {
            (void)fprintf(stderr, "%s%u", i == 0U ? "" : ", ", (unsigned)waiting[i]);
        }
        (void)fputs(" have confirmed their books after this start (SYNC re-sent)\n", stderr);
    }
    g->waiting = n;
}

static void top_up(struct gateway_port *g, uint64_t now)
{
    if (!g->opt.has_target || g->stopping) {
        return;
    }
    for (unsigned i = 0U; i < g->opt.count; i++) {
        struct below *b = &g->below[i];
        const struct canergy_session *s = &g->gw.down.sessions[i];
        const int distrusted = b->evidence && now < b->evidence_at + 10U * US_PER_S;
        if (s->phase != CANERGY_S_IDLE || !b->heard || !b->fresh || b->joining || distrusted ||
            b->level_uj >= g->opt.target_uj) {
            continue;
        }
        const uint64_t wanted = g->opt.target_uj - b->level_uj;
        if (wanted < g->opt.min_grant_uj) {
            continue;
        }
        /* never above what the node's record holds, nor one frame, nor Us */
        const uint64_t room = CANERGY_USABLE_MAX_UJ - least(b->level_uj, CANERGY_USABLE_MAX_UJ);
        uint64_t amount = least(least(least(wanted, room), (uint64_t)CANERGY_AMOUNT_MAX_MJ * MJ),
                                usable_below(g));
        amount -= amount % MJ;
        if (amount == 0U) {
            continue;
        }
        struct canergy_supervisor_out out;
        if (canergy_gateway_begin(&g->gw, s->node, (uint32_t)amount, now, &out) == CANERGY_OK) {
            b->fresh = 0;
            down_out(g, &out, now);
        }
    }
}

/* What Us below holds above --return-above goes back up, one RETURN at a time. */
static void give_back(struct gateway_port *g, uint64_t now)
{
    if (g->opt.keep_all || !canergy_client_can_give_back(&g->gw.up) ||
        usable_below(g) <= g->opt.return_above_uj) {
        return;
    }
    uint64_t excess = least(usable_below(g) - g->opt.return_above_uj,
                            (uint64_t)CANERGY_AMOUNT_MAX_MJ * MJ);
    excess -= excess % MJ;
    struct canergy_out out;
    if (excess > 0U &&
        canergy_gateway_give_back(&g->gw, (uint32_t)excess, now, &out) == CANERGY_OK) {
        g->returned_uj += excess;
        up_out(g, &out);
    }
}

/* The gateway's level above: what it can still grant below. */
static void telemetry(struct gateway_port *g)
{
    const uint64_t mj = usable_below(g) / MJ;
    struct canergy_msg m;
    memset(&m, 0, sizeof m);
    m.type = CANERGY_TELEMETRY;
    m.node = g->opt.node;
    m.level_mj = mj > CANERGY_WIDE_MAX ? (uint32_t)CANERGY_WIDE_MAX : (uint32_t)mj;
    m.flags = canergy_client_joining(&g->gw.up) ? CANERGY_TELEMETRY_JOINING : 0U;
    m.seq = (uint16_t)(g->gw.up.rec.return_seq & 0xFFFFU);
    m.witness = (uint8_t)(g->witnessed & 0xFFU);
    struct canergy_frame f;
    if (canergy_encode(g->opt.id_base, &m, &f) == CANERGY_OK) {
        port_can_send(g->up_sock, &g->up_count, f.id, f.data, f.dlc);
    }
}

/* ---- the status file (the Python gateway's keys) ---- */

static const char *phase_name(uint8_t phase)
{
    static const char *const names[] = {"IDLE", "WAIT_ACK", "ACKED", "WAIT_CONFIRM"};
    if (phase == CANERGY_S_SYNCING) {
        return "SYNCING";
    }
    if (phase == CANERGY_S_SYNC_BOOKS) {
        return "SYNC_BOOKS";
    }
    return phase <= CANERGY_S_WAIT_CONFIRM ? names[phase] : "?";
}

static void write_counters(FILE *f, const char *name, const struct port_counters *c)
{
    (void)fprintf(f,
                  "\"%s\": {\"frames_sent\": %llu, \"frames_received\": %llu, "
                  "\"decode_errors\": %llu, \"foreign_frames\": %llu, \"send_failures\": %llu, "
                  "\"receive_errors\": %llu, \"error_frames\": %llu}",
                  name, (unsigned long long)c->frames_sent, (unsigned long long)c->frames_received,
                  (unsigned long long)c->decode_errors, (unsigned long long)c->foreign_frames,
                  (unsigned long long)c->send_failures, (unsigned long long)c->receive_errors,
                  (unsigned long long)c->error_frames);
}

static void write_status(const struct gateway_port *g, FILE *f, uint64_t now)
{
    const struct canergy_supervisor *d = &g->gw.down;
    const struct canergy_record *r = &g->gw.up.rec;
    uint64_t reserved = 0U, delivered = 0U, returned = 0U;
    for (unsigned i = 0U; i < d->count; i++) {
        reserved += d->sessions[i].reserved_uj;
        delivered += d->sessions[i].delivered_uj;
        returned += d->sessions[i].returned_uj;
    }
    (void)fprintf(f,
                  "{\"role\": \"gateway\", \"core\": \"c\", \"variant\": \"%s\", "
                  "\"stopping\": %s, \"initial_uj\": 0, \"usable_uj\": %lld, "
                  "\"injected_uj\": %llu, \"withdrawn_uj\": %llu, \"reserved_uj\": %llu, "
                  "\"delivered_uj\": %llu, \"returns_credited_uj\": %llu, "
                  "\"link_gap_uj\": %lld, \"state_writes\": %llu, ",
                  g->opt.rules == CANERGY_RULES_WITNESSED ? "witnessed" : "hardened",
                  g->stopping ? "true" : "false", (long long)d->usable_uj,
                  (unsigned long long)d->injected_uj, (unsigned long long)d->withdrawn_uj,
                  (unsigned long long)reserved, (unsigned long long)delivered,
                  (unsigned long long)returned, (long long)canergy_gateway_link_gap(&g->gw),
                  (unsigned long long)g->nv_writes);
    write_counters(f, "downstream_bus", &g->down_count);
    uint8_t waiting[CANERGY_SUPERVISOR_NODES];
    const uint8_t n = canergy_supervisor_unconfirmed(d, waiting);
    (void)fputs(", \"unconfirmed\": [", f);
    for (uint8_t i = 0U; i < n; i++) {
        (void)fprintf(f, "%s%u", i == 0U ? "" : ", ", (unsigned)waiting[i]);
    }
    (void)fprintf(f, "], \"waiting_for_upstream\": %s%s%s, \"nodes\": {",
                  canergy_gateway_upstream_waiting(&g->gw) ? "\"" : "",
                  canergy_gateway_upstream_waiting(&g->gw) ? UP_WAITING : "null",
                  canergy_gateway_upstream_waiting(&g->gw) ? "\"" : "");
    for (unsigned i = 0U; i < d->count; i++) {
        const struct canergy_session *s = &d->sessions[i];
        const struct below *b = &g->below[i];
        const int lost = !b->heard || now - b->heard_at > 3U * US_PER_S;
        char open_tx[24] = "null";
        if (s->phase != CANERGY_S_IDLE && !canergy_session_syncing(s)) {
            (void)snprintf(open_tx, sizeof open_tx, "%lu", (unsigned long)s->tx);
        }
        (void)fprintf(f,
                      "%s\"%u\": {\"state\": \"%s\", \"open_tx\": %s, \"reserved_uj\": %lu, "
                      "\"delivered_uj\": %llu, \"returns_credited_uj\": %llu, "
                      "\"returns_credited\": %lu, \"level_uj\": %llu, \"lost\": %s, "
                      "\"committed\": %llu, \"committed_uj\": %llu, \"aborted\": %llu, "
                      "\"written_off\": %llu, \"admitted\": %llu, \"returns_held\": %u, "
                      "\"returns_refuted\": %llu, \"intrusions\": %llu}",
                      i == 0U ? "" : ", ", (unsigned)s->node, phase_name(s->phase), open_tx,
                      (unsigned long)s->reserved_uj,
                      (unsigned long long)s->delivered_uj, (unsigned long long)s->returned_uj,
                      (unsigned long)s->returns_credited, (unsigned long long)b->level_uj,
                      lost ? "true" : "false", (unsigned long long)b->committed,
                      (unsigned long long)b->committed_uj, (unsigned long long)b->aborted,
                      (unsigned long long)b->written_off, (unsigned long long)b->admitted,
                      (unsigned)b->held, (unsigned long long)b->refuted,
                      (unsigned long long)b->intrusions);
    }
    (void)fprintf(f,
                  "}, \"upstream\": {\"node\": %u, \"usable_uj\": %lu, \"spent_uj\": %llu, "
                  "\"credited_uj\": %llu, \"return_pending_uj\": %lu, \"return_seq\": %lu, "
                  "\"last_tx\": %lu, \"joining\": %s, \"joins\": %d, "
                  "\"returned_this_run_uj\": %llu, \"witnessed\": %llu, \"rules\": \"%s\", "
                  "\"resuming\": %s, \"pending_draw\": %s, \"confirmed\": %llu, "
                  "\"found_behind\": %llu, \"dropped_below_uj\": %llu, ",
                  (unsigned)g->opt.node, (unsigned long)r->usable_uj,
                  (unsigned long long)r->spent_uj, (unsigned long long)r->credited_mj * MJ,
                  (unsigned long)r->return_pending_uj, (unsigned long)r->return_seq,
                  (unsigned long)r->last_tx, canergy_client_joining(&g->gw.up) ? "true" : "false",
                  g->joins, (unsigned long long)g->returned_uj,
                  (unsigned long long)g->witnessed,
                  g->opt.up_rules == CANERGY_RULES_WITNESSED ? "witnessed" : "hardened",
                  canergy_gateway_upstream_waiting(&g->gw) ? "true" : "false",
                  (r->flags & CANERGY_RECORD_PENDING_DRAW) != 0U ? "true" : "false",
                  (unsigned long long)g->confirmed, (unsigned long long)g->found_behind,
                  (unsigned long long)g->dropped_uj);
    write_counters(f, "bus", &g->up_count);
    (void)fputs("}}\n", f);
}

/* Written to a temporary file and renamed over the status file: a reader never sees half. */
static void save_status(const struct gateway_port *g, uint64_t now)
{
    if (g->opt.status_path == NULL) {
        return;
    }
    char tmp[PATH_MAX];
    if (snprintf(tmp, sizeof tmp, "%s.tmp", g->opt.status_path) >= (int)sizeof tmp) {
        return;
    }
    FILE *f = fopen(tmp, "w");
    if (f == NULL) {
        (void)fprintf(stderr, "%s: status file %s: %s\n", PROG, tmp, strerror(errno));
        return;
    }
    write_status(g, f, now);
    if (fclose(f) != 0 || rename(tmp, g->opt.status_path) != 0) {
        (void)fprintf(stderr, "%s: status file %s: %s\n", PROG, g->opt.status_path,
                      strerror(errno));
    }
}

/* ---- main ---- */

static int open_bus(const char *channel, uint32_t id_base, uint8_t node)
{
    struct port_options o;
    memset(&o, 0, sizeof o);
    o.channel = channel;
    o.id_base = id_base;
    o.node = node;
    return port_can_open(&o);
}

static int quiet(const struct canergy_supervisor *d)
{
    for (unsigned i = 0U; i < d->count; i++) {
        if (d->sessions[i].phase != CANERGY_S_IDLE) {
            return 0;
        }
    }
    return 1;
}

int main(int argc, char **argv)
{
    static struct gateway_port g;
    parse_args(argc, argv, &g.opt);
    const struct port_file files[] = {{"--nv", g.opt.nv_path},
                                      {"--status-file", g.opt.status_path}};
    port_check_distinct(files, sizeof files / sizeof files[0]);
    check_nv(&g.opt);
    g.up_sock = open_bus(g.opt.up_channel, g.opt.id_base, g.opt.node); /* its own id above */
    g.down_sock = open_bus(g.opt.down_channel, g.opt.id_base, 1U);
    port_can_filter(g.down_sock, g.opt.id_base, CANERGY_ID_MASK); /* every node below */
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_stop_signal;
    (void)sigaction(SIGINT, &sa, NULL);
    (void)sigaction(SIGTERM, &sa, NULL);
    uint64_t now = port_now_us();
    start(&g, now);
    say_up_waiting(&g, 0, 0U); /* witnessed above: a start with a record waits for its ADMIT */
    uint64_t next_telemetry = now, next_tick = now, next_status = now, stop_at = 0U;
    for (;;) {
        now = port_now_us();
        if (stop_requested && !g.stopping) {
            g.stopping = 1;
            stop_at = now + g.opt.stop_timeout_us;
        }
        if (g.stopping && (quiet(&g.gw.down) || now >= stop_at)) {
            break;
        }
        uint64_t wake = least(least(next_telemetry, next_tick), next_status);
        wake = least(wake, least(canergy_client_deadline(&g.gw.up),
                                       canergy_supervisor_deadline(&g.gw.down)));
        int timeout_ms = 0;
        if (wake > now) {
            const uint64_t ms = (wake - now + 999U) / 1000U;
            timeout_ms = ms > 100U ? 100 : (int)ms;
        }
        struct pollfd fds[2] = {{g.up_sock, POLLIN, 0}, {g.down_sock, POLLIN, 0}};
        if (poll(fds, 2U, timeout_ms) < 0 && errno != EINTR) {
            g.down_count.receive_errors++;
        }
        now = port_now_us();
        receive_up(&g, now);
        receive_down(&g, now);
        if (canergy_client_deadline(&g.gw.up) <= now) {
            struct canergy_out out;
            canergy_gateway_on_up_timer(&g.gw, now, &out);
            up_out(&g, &out);
            if ((out.events & (CANERGY_EV_TIMEOUT_COMMIT | CANERGY_EV_CREDITED)) != 0U) {
                g.telemetry_now = 1;
            }
        }
        if (canergy_supervisor_deadline(&g.gw.down) <= now) {
            struct canergy_supervisor_out out;
            canergy_supervisor_on_timer(&g.gw.down, now, &out);
            down_out(&g, &out, now);
        }
        if (now >= next_tick) {
            next_tick = now + g.opt.tick_us;
            release_returns(&g, now);
            say_waiting(&g);
            top_up(&g, now);
            give_back(&g, now);
        }
        if (now >= next_telemetry || g.telemetry_now) {
            g.telemetry_now = 0;
            next_telemetry = now + g.opt.telemetry_period_us;
            telemetry(&g);
        }
        if (now >= next_status) {
            next_status = now + g.opt.status_period_us;
            save_status(&g, now);
        }
    }
    save_status(&g, port_now_us());
    (void)close(g.nv_fd);
    return 0;
}
