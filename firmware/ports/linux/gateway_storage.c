/*
 * canergy-gateway's files (gateway_port.h): the NV file holding both roles' one record (the slot
 * format is the library's: canergy_gateway_nv_*), the status file, and what stderr is told.
 */
#define _GNU_SOURCE 1

#include "args.h"
#include "gateway_port.h"
#include "socketcan.h"
#include "system.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#define GW_SLOT CANERGY_GW_NV_SLOT_SIZE
#define GW_SEALS_AT (2U * GW_SLOT) /* with a key: slot i's seal at GW_SEALS_AT + 8 i */
#define GW_SEALED (GW_SEALS_AT + 2U * CANERGY_NV_SEAL_SIZE)

/* ---- the NV file ---- */

/* Both records, fsynced, before anything else happens: exit 1 when that fails (nothing of the
 * step is sent). */
void gw_save(struct gateway_port *g)
{
    uint8_t slot[GW_SLOT];
    const uint8_t next = (uint8_t)(1U - g->nv_slot);
    canergy_gateway_nv_encode(&g->gw, g->nv_counter + 1U, slot);
    const off_t at = (off_t)next * (off_t)GW_SLOT;
    int ok = pwrite(g->nv_fd, slot, GW_SLOT, at) == (ssize_t)GW_SLOT;
    if (ok && g->sealed) { /* then its seal: torn between the two, this slot is not taken */
        uint8_t seal[CANERGY_NV_SEAL_SIZE];
        canergy_nv_seal(&g->seal, slot, GW_SLOT, seal);
        const off_t seal_at = (off_t)GW_SEALS_AT + (off_t)next * (off_t)CANERGY_NV_SEAL_SIZE;
        ok = pwrite(g->nv_fd, seal, sizeof seal, seal_at) == (ssize_t)sizeof seal;
    }
    if (!ok || fsync(g->nv_fd) != 0) {
        (void)fprintf(stderr, "%s: NV store: %s: write failed: %s\n", PROG, g->opt.nv_path,
                      strerror(errno));
        exit(EXIT_NV);
    }
    g->nv_slot = next;
    g->nv_counter++;
    g->nv_writes++;
}

/* The newest valid slot of image (len bytes read of a file of size bytes); exit 2 when a valid
 * slot's upstream record holds a counter beyond the bound the proof assumes, when the file is
 * longer than two slots (not this gateway's), or when no slot holds but one starts as a slot
 * does (cut short, or its CRC does not hold: damaged or edited). A slot so beside a valid one
 * is a write the gateway did not finish: the valid one is taken, and stderr says so (tell). */
static void load_nv(const char *path, const uint8_t *image, size_t len, long long size, int tell,
                    unsigned spoilt, struct canergy_gateway_nv *nv)
{
    const int end = canergy_gateway_nv_load(image, len, nv);
    nv->damaged &= (uint8_t)~spoilt; /* set aside for its seal: told by check_seals */
    if (end == CANERGY_ERR_END) {
        const int tx = nv->up.last_tx >= CANERGY_COUNTER_BOUND;
        port_usage_error("--nv %s: upstream: %s %lu is beyond the bound 2^30 - 1 the proof "
                         "assumes",
                         path, tx ? "last_tx" : "return_seq",
                         (unsigned long)(tx ? nv->up.last_tx : nv->up.return_seq));
    }
    if (nv->foreign || nv->older != 0U) {
        return; /* refused by name below */
    }
    if (size > 2LL * (long long)GW_SLOT && size != (long long)GW_SEALED) {
        port_usage_error("--nv %s: %lld bytes is not a canergy-gateway NV file (two slots of %u "
                         "bytes at most, and their seals); nothing taken",
                         path, size, (unsigned)GW_SLOT);
    }
    if (nv->damaged != 0U && nv->slot < 0) {
        port_usage_error("--nv %s: slot %s: cut short or its CRC does not hold (the record "
                         "damaged or edited), and no valid slot: nothing taken. Move the file "
                         "away to start without books (what they held is then lost, never "
                         "created)",
                         path, nv->damaged == 3U ? "0 and 1" : nv->damaged == 1U ? "0" : "1");
    }
    if (nv->damaged != 0U && tell) {
        (void)fprintf(stderr,
                      "%s: --nv %s: slot %u cut short or its CRC does not hold (a write not "
                      "finished?): the other slot, counter %lu, taken\n",
                      PROG, path, nv->damaged == 1U ? 0U : 1U, (unsigned long)nv->counter);
    }
}

static const char *slot_names(unsigned mask)
{
    return mask == 3U ? "0 and 1" : mask == 1U ? "0" : "1";
}

/* The seals of an image of len bytes read from a file of size bytes (canergy/nv.h, "Sealed
 * image"), as canergy-node checks its own: without a key a sealed file is refused; with one a
 * record in a file without seals is refused (never sealed), and a slot whose seal does not hold
 * is spoilt in image (a damaged slot), refused when no slot is left, else told on stderr (tell).
 * Returns the mask of the slots spoilt. */
static unsigned check_seals(const struct gateway_port *g, uint8_t *image, size_t len,
                            long long size, int tell)
{
    const char *path = g->opt.nv_path;
    struct canergy_gateway_nv nv;
    if (!g->sealed) {
        if (size == (long long)GW_SEALED) {
            port_usage_error("--nv %s: sealed by a gateway with a key (--upstream-auth or "
                             "--auth): without that key its seals cannot be checked; run with it",
                             path);
        }
        return 0U;
    }
    if (size != (long long)GW_SEALED) {
        const int end = canergy_gateway_nv_load(image, len, &nv);
        if (nv.older == 0U && (end == CANERGY_ERR_END || nv.slot >= 0)) {
            port_usage_error("--nv %s: a record that is not sealed (written without a key, or "
                             "its seals cut off): a gateway with a key takes sealed records "
                             "only, so nothing taken. Move the file away to start without books "
                             "(what they held is then lost, never created)",
                             path);
        }
        return 0U;
    }
    const unsigned spoilt =
        canergy_nv_unseal(&g->seal, image, len, GW_SLOT, 2U, &image[GW_SEALS_AT]);
    if (spoilt == 0U) {
        return 0U;
    }
    if (canergy_gateway_nv_load(image, len, &nv) != CANERGY_ERR_END && nv.slot < 0) {
        port_usage_error("--nv %s: slot %s: the seal does not hold (the record edited, or "
                         "sealed under another key), and no other slot holds a sealed record: "
                         "nothing taken. Move the file away to start without books (what they "
                         "held is then lost, never created)",
                         path, slot_names(spoilt));
    }
    if (tell) {
        (void)fprintf(stderr,
                      "%s: --nv %s: slot %s: the seal does not hold (a write not finished, or "
                      "the record edited): set aside, the other slot taken\n",
                      PROG, path, slot_names(spoilt));
    }
    return spoilt;
}

/* Exit 2 when the image holds a slot of an older layout (never taken as a new, blank file). */
static void refuse_older_layout(const char *path, const struct canergy_gateway_nv *nv)
{
    if (nv->older != 0U) {
        port_usage_error("--nv %s: written by an older canergy-gateway (supervisor record "
                         "version %u); this one reads version 5 only",
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
void gw_check_nv(const struct gateway_port *g)
{
    const struct gw_options *o = &g->opt;
    struct stat st;
    if (stat(o->nv_path, &st) != 0 || !S_ISREG(st.st_mode)) {
        return; /* new, or not a file: start() says so */
    }
    const int fd = open(o->nv_path, O_RDONLY | O_CLOEXEC);
    if (fd < 0) {
        return;
    }
    port_nv_keep(fd, o->nv_path, LOCK_SH); /* kept by another: refused before the buses */
    static uint8_t image[GW_SEALED];
    const ssize_t got = pread(fd, image, sizeof image, 0);
    (void)close(fd);
    struct canergy_gateway_nv nv;
    const size_t len = got > 0 ? (size_t)got : 0U;
    const unsigned spoilt = check_seals(g, image, len, (long long)st.st_size, 0);
    load_nv(o->nv_path, image, len, (long long)st.st_size, 0, spoilt, &nv);
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
void gw_start(struct gateway_port *g, uint64_t now)
{
    const struct gw_options *o = &g->opt;
    g->nv_fd = port_open_nv(o->nv_path, 0600);
    if (g->nv_fd < 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, o->nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
    static uint8_t image[GW_SEALED];
    const ssize_t got = pread(g->nv_fd, image, sizeof image, 0);
    if (got < 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, o->nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
    struct stat st;
    struct canergy_gateway_nv nv;
    const long long size = fstat(g->nv_fd, &st) == 0 ? (long long)st.st_size : 0;
    const unsigned spoilt = check_seals(g, image, (size_t)got, size, 1);
    load_nv(o->nv_path, image, (size_t)got, size, 1, spoilt, &nv);
    if (g->sealed && size < (long long)GW_SEALED && ftruncate(g->nv_fd, (off_t)GW_SEALED) != 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, o->nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
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
            gw_save(g);
        }
    } else {
        (void)canergy_client_start(&g->gw.up, &up, NULL, 0U, port_random16(), now, &out);
        if (canergy_supervisor_init(&g->gw.down, &down, o->nodes, o->count, 0U) != CANERGY_OK) {
            port_usage_error("argument --nodes: not a node list this gateway can hold");
        }
        g->joins++;
        g->nv_slot = 1U; /* slot 0 is written first */
    }
    if (canergy_client_joining(&g->gw.up) && o->up_auth_path != NULL) {
        canergy_auth_set_join(&g->up_auth, port_random16(), g->gw.up.nonce); /* 32-bit FV */
    }
    for (unsigned i = 0U; i < out.frame_count; i++) { /* the JOIN, when there are no books */
        gw_send_up(g, &out.frames[i]);
    }
}

/* Witnessed rules above: say on stderr when the gateway waits for the supervisor above to
 * confirm its record, and how the wait ended (each change once). */
static const char *const UP_WAITING =
    "no grant below until the supervisor above confirms this gateway's record (RESUME sent "
    "upstream, or its SYNC answered; the record may be an older copy)";

void gw_say_up_waiting(struct gateway_port *g, int behind, uint64_t dropped)
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

/* Witnessed rules: say on stderr whom a start below waits for before it grants anything, and
 * when every node has confirmed its books (each change once). */
void gw_say_waiting(struct gateway_port *g)
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

static uint32_t refused_of(const struct below *b)
{
    uint32_t n = 0U;
    for (unsigned k = 0U; k < REFUSAL_REASONS; k++) {
        n += b->refused[k];
    }
    return n;
}

static double node_rate(const struct below *b, uint64_t now)
{
    double per_s = 0.0;
    for (unsigned k = 0U; k < REFUSAL_REASONS; k++) {
        per_s += gw_rate_per_s(&b->rates[k], now);
    }
    return per_s;
}

static void write_time(FILE *f, const char *key, int known, uint64_t at)
{
    if (known) {
        (void)fprintf(f, "\"%s\": %llu", key, (unsigned long long)at);
    } else {
        (void)fprintf(f, "\"%s\": null", key);
    }
}

/* Frames refused below, as canergy supervisor's status shows them: "auth" (the layout),
 * "auth_failures" (the MAC and freshness check's, by reason), "refused" (a total and a rate, by
 * node and reason: those too, JOINs of an earlier life and frames in the supervisor's
 * direction); "intrusions", a total (each node's in "nodes"). */
static void write_refused(const struct gateway_port *g, FILE *f, uint64_t now)
{
    (void)fprintf(f, "\"auth\": %s, \"auth_failures\": {",
                  g->opt.auth_path == NULL ? "null" : g->opt.fd ? "\"fd\"" : "\"classic\"");
    for (unsigned k = 0U, n = 0U; k < AUTH_REASONS; k++) {
        uint32_t count = 0U;
        for (unsigned i = 0U; i < g->opt.count; i++) {
            count += g->below[i].refused[k];
        }
        if (count != 0U) {
            (void)fprintf(f, "%s\"%s\": %lu", n++ == 0U ? "" : ", ", gw_refusal_names[k],
                          (unsigned long)count);
        }
    }
    (void)fprintf(f, "}, \"refused\": {\"total\": %llu, \"per_s\": %.1f, \"by_node\": {",
                  (unsigned long long)g->refused_total, gw_rate_per_s(&g->refusal_rate, now));
    for (unsigned i = 0U, n = 0U; i < g->opt.count; i++) {
        const struct below *b = &g->below[i];
        if (refused_of(b) == 0U) {
            continue;
        }
        (void)fprintf(f, "%s\"%u\": {\"total\": %lu, \"per_s\": %.1f, \"reasons\": {",
                      n++ == 0U ? "" : ", ", (unsigned)g->opt.nodes[i],
                      (unsigned long)refused_of(b), node_rate(b, now));
        for (unsigned k = 0U, r = 0U; k < REFUSAL_REASONS; k++) {
            if (b->refused[k] != 0U) {
                (void)fprintf(f, "%s\"%s\": {\"count\": %lu, \"per_s\": %.1f}",
                              r++ == 0U ? "" : ", ", gw_refusal_names[k],
                              (unsigned long)b->refused[k], gw_rate_per_s(&b->rates[k], now));
            }
        }
        (void)fputs("}}", f);
    }
    (void)fputs("}, ", f);
    write_time(f, "first_at_us", g->refused_total != 0U, g->refused_first_at);
    (void)fputs(", ", f);
    write_time(f, "last_at_us", g->refused_total != 0U, g->refused_last_at);
    uint64_t intrusions = 0U;
    for (unsigned i = 0U; i < g->opt.count; i++) {
        intrusions += g->below[i].intrusions;
    }
    (void)fprintf(f, "}, \"intrusions\": %llu, ", (unsigned long long)intrusions);
    write_time(f, "intrusions_first_at_us", g->intrusions_seen, g->intrusions_first_at);
    (void)fputs(", ", f);
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
    write_refused(g, f, now);
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
                      "\"returns_refuted\": %lu, \"returns_resynchronised\": %lu, "
                      "\"intrusions\": %lu, \"refused\": %lu, \"joins_resent\": %lu, "
                      "\"joins_held\": %u, \"variant_mismatch\": %lu, \"resyncs\": %lu}",
                      i == 0U ? "" : ", ", (unsigned)s->node, phase_name(s->phase), open_tx,
                      (unsigned long)s->reserved_uj,
                      (unsigned long long)s->delivered_uj, (unsigned long long)s->returned_uj,
                      (unsigned long)s->returns_credited, (unsigned long long)b->level_uj,
                      lost ? "true" : "false", (unsigned long long)b->committed,
                      (unsigned long long)b->committed_uj, (unsigned long long)b->aborted,
                      (unsigned long long)b->written_off, (unsigned long long)b->admitted,
                      (unsigned)b->witness.held_count,
                      (unsigned long)b->witness.refuted, (unsigned long)b->witness.resynced,
                      (unsigned long)b->intrusions, (unsigned long)refused_of(b),
                      (unsigned long)b->joins.resent, (unsigned)b->joins.held_count,
                      (unsigned long)b->variant_mismatch, (unsigned long)b->resyncs);
    }
    (void)fprintf(f,
                  "}, \"upstream\": {\"node\": %u, \"usable_uj\": %lu, \"spent_uj\": %llu, "
                  "\"credited_uj\": %llu, \"return_pending_uj\": %lu, \"return_seq\": %lu, "
                  "\"last_tx\": %lu, \"joining\": %s, \"joins\": %d, "
                  "\"returned_this_run_uj\": %llu, \"witnessed\": %llu, \"rules\": \"%s\", "
                  "\"resuming\": %s, \"pending_draw\": %s, \"confirmed\": %llu, "
                  "\"found_behind\": %llu, \"dropped_below_uj\": %llu, "
                  "\"authenticated\": %s, \"auth_refused\": %llu, ",
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
                  (unsigned long long)g->dropped_uj,
                  g->opt.up_auth_path != NULL ? "true" : "false",
                  (unsigned long long)g->auth_refused);
    write_counters(f, "bus", &g->up_count);
    (void)fputs("}}\n", f);
}

struct status_now {
    const struct gateway_port *g;
    uint64_t now;
};

static void write_gateway_status(const void *ctx, FILE *f)
{
    const struct status_now *at = ctx;
    write_status(at->g, f, at->now);
}

void gw_save_status(const struct gateway_port *g, uint64_t now)
{
    if (g->opt.status_path != NULL) {
        const struct status_now at = {g, now};
        port_save_status_file(g->opt.status_path, write_gateway_status, &at);
    }
}
