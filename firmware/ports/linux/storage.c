/*
 * canergy-node's files (ports/linux): the NV record file and the status file.
 *   - the NV file in firmware_model's layout (slots at 0 and 40, bytes 80-119 untouched): read
 *     at start, each slot image pwrite + fsynced before the frames of its step leave;
 *   - the status file with the keys of firmware_model's single-node status, and what it counts
 *     of each received frame (decode errors, auth failures, the intrusion report), written to a
 *     temp file, fsynced and renamed.
 */
#define _GNU_SOURCE 1

#include "storage.h"

#include "args.h"
#include "system.h"

#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

/* ---- NV file ---- */

/* Exit 2 when the newest valid slot holds a counter beyond the bound the proof assumes (the
 * library would take it as no books and JOIN: refused here, with the field named, as
 * firmware_model refuses it). */
static void check_counters(const struct port_options *o, const uint8_t *image, size_t len)
{
    struct canergy_nv_state st;
    canergy_nv_load(image, len, &st);
    const size_t at = (size_t)st.newest_slot * CANERGY_NV_SLOT_SIZE;
    uint32_t counter;
    uint8_t payload[CANERGY_NV_RECORD_SIZE];
    struct canergy_record rec;
    if (st.books || len < at + CANERGY_NV_SLOT_SIZE ||
        !canergy_nv_slot_decode(&image[at], CANERGY_NV_SLOT_SIZE, &counter, payload) ||
        canergy_record_unpack(payload, &rec) != CANERGY_ERR_END) {
        return;
    }
    const int tx = rec.last_tx >= CANERGY_COUNTER_BOUND;
    port_usage_error("--nv %s: node %d: %s %lu is beyond the bound 2^30 - 1 the proof assumes",
                     o->nv_path, o->node, tx ? "last_tx" : "return_seq",
                     (unsigned long)(tx ? rec.last_tx : rec.return_seq));
}

/* Record slots of image (len bytes) whose magic and CRC hold, as a mask (bit i: slot i). */
static unsigned valid_slots(const uint8_t *image, size_t len)
{
    unsigned mask = 0U;
    for (unsigned i = 0U; i < CANERGY_NV_SLOTS; i++) {
        uint32_t counter;
        uint8_t payload[CANERGY_NV_RECORD_SIZE];
        const size_t at = (size_t)i * CANERGY_NV_SLOT_SIZE;
        if (len >= at + CANERGY_NV_SLOT_SIZE &&
            canergy_nv_slot_decode(&image[at], CANERGY_NV_SLOT_SIZE, &counter, payload)) {
            mask |= 1U << i;
        }
    }
    return mask;
}

static const char *slot_names(unsigned mask)
{
    return mask == 3U ? "0 and 1" : mask == 1U ? "0" : "1";
}

/* The seals of an image of len bytes read from a file of size bytes (canergy/nv.h, "Sealed
 * image"). Without a key: a sealed file is refused (its seals cannot be checked). With one: a
 * record slot that holds a record in a file without seals is refused (never sealed: written
 * without a key, or its seals cut off); a slot whose seal does not hold is spoilt in image (a
 * damaged slot: the library falls back to the other) and, when no slot is left, refused; with
 * tell, stderr names the slot set aside. */
static void check_seals(const struct port *p, uint8_t *image, size_t len, long long size, int tell)
{
    const char *path = p->opt.nv_path;
    if (!p->sealed) {
        if (size == (long long)CANERGY_NV_SEALED_SIZE) {
            port_usage_error("--nv %s: node %d: sealed by a node with a key (--auth): without "
                             "that key its seals cannot be checked; run with --auth and this "
                             "node's key file",
                             path, p->opt.node);
        }
        return;
    }
    if (size != (long long)CANERGY_NV_SEALED_SIZE) {
        const unsigned found = valid_slots(image, len);
        if (found != 0U) {
            port_usage_error("--nv %s: node %d: slot %s holds a record that is not sealed "
                             "(written without --auth, or its seals cut off): a node with a key "
                             "takes sealed records only, so nothing taken. Move the file away "
                             "to JOIN afresh (what it held is then lost, never created)",
                             path, p->opt.node, slot_names(found));
        }
        return; /* new, erased or damaged: no books either way */
    }
    const unsigned spoilt = canergy_nv_unseal(&p->seal, image, len, CANERGY_NV_SLOT_SIZE,
                                              CANERGY_NV_SLOTS, &image[CANERGY_NV_SEALS_AT]);
    if (spoilt == 0U) {
        return;
    }
    const unsigned left = valid_slots(image, len);
    if (left == 0U) {
        port_usage_error("--nv %s: node %d: slot %s: the seal does not hold (the record edited, "
                         "or sealed under another node's key), and no other slot holds a sealed "
                         "record: nothing taken. Move the file away to JOIN afresh (what it held "
                         "is then lost, never created)",
                         path, p->opt.node, slot_names(spoilt));
    }
    if (tell) {
        (void)fprintf(stderr,
                      "%s: --nv %s: node %d: slot %s: the seal does not hold (a write not "
                      "finished, or the record edited): set aside, slot %s taken\n",
                      PROG, path, p->opt.node, slot_names(spoilt), slot_names(left));
    }
}

void port_nv_check(const struct port *p)
{
    struct stat st;
    if (stat(p->opt.nv_path, &st) != 0 || !S_ISREG(st.st_mode)) {
        return; /* new, or not a file: port_nv_open says so */
    }
    const int fd = open(p->opt.nv_path, O_RDONLY | O_CLOEXEC);
    if (fd < 0) {
        return;
    }
    port_nv_keep(fd, p->opt.nv_path, LOCK_SH); /* kept by another: refused before the bus */
    uint8_t image[NV_READ_BYTES] = {0}; /* a short read leaves no stale seal bytes */
    const ssize_t n = pread(fd, image, sizeof image, 0);
    (void)close(fd);
    if (n > 0) {
        check_seals(p, image, (size_t)n, (long long)st.st_size, 0);
        check_counters(&p->opt, image, (size_t)n);
    }
}

void port_nv_open(struct port *p, uint8_t image[NV_READ_BYTES], size_t *len)
{
    p->nv_fd = port_open_nv(p->opt.nv_path, 0644);
    if (p->nv_fd < 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, p->opt.nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
    /* an existing file of another size is not an NV file: the first record would overwrite it
     * (0: new; two slots; three with firmware_model's CANopen parameter slot; three and the
     * seals) */
    struct stat size;
    if (fstat(p->nv_fd, &size) == 0 && size.st_size != 0 &&
        size.st_size != (off_t)NV_IMAGE_BYTES &&
        size.st_size != (off_t)(NV_IMAGE_BYTES + CANERGY_NV_SLOT_SIZE) &&
        size.st_size != (off_t)CANERGY_NV_SEALED_SIZE) {
        (void)fprintf(stderr, "%s: error: --nv %s: %lld bytes is not an NV file of canergy\n",
                      PROG, p->opt.nv_path, (long long)size.st_size);
        exit(EXIT_USAGE);
    }
    ssize_t n;
    do {
        n = pread(p->nv_fd, image, NV_READ_BYTES, 0);
    } while (n < 0 && errno == EINTR);
    if (n < 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, p->opt.nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
    *len = (size_t)n;
    check_seals(p, image, *len, (long long)size.st_size, 1);
    check_counters(&p->opt, image, *len);
    /* as firmware_model: the file always holds both record slots, and sealed the seals after
     * the parameter slot (never shrunk: the parameter slot at 80 stays as it is) */
    const off_t least = p->sealed ? (off_t)CANERGY_NV_SEALED_SIZE : (off_t)NV_IMAGE_BYTES;
    struct stat st;
    if (fstat(p->nv_fd, &st) == 0 && st.st_size < least && ftruncate(p->nv_fd, least) != 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, p->opt.nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
}

/* The persist half of the contract: the slot image (then its seal) is on disk before any frame
 * of its step leaves; a failed write ends the process at once (exit 1). A write torn between
 * slot and seal leaves that slot unsealed: it is the slot not holding the newest record. */
void port_nv_write(struct port *p, const struct canergy_out *out)
{
    const off_t at = (off_t)out->nv_slot * (off_t)CANERGY_NV_SLOT_SIZE;
    ssize_t n = pwrite(p->nv_fd, out->nv_image, CANERGY_NV_SLOT_SIZE, at);
    int ok = n == (ssize_t)CANERGY_NV_SLOT_SIZE;
    if (ok && p->sealed) {
        uint8_t seal[CANERGY_NV_SEAL_SIZE];
        canergy_nv_seal(&p->seal, out->nv_image, CANERGY_NV_SLOT_SIZE, seal);
        const off_t seal_at =
            (off_t)CANERGY_NV_SEALS_AT + (off_t)out->nv_slot * (off_t)CANERGY_NV_SEAL_SIZE;
        n = pwrite(p->nv_fd, seal, sizeof seal, seal_at);
        ok = n == (ssize_t)sizeof seal;
    }
    if (!ok || fsync(p->nv_fd) != 0) {
        (void)fprintf(stderr, "%s: NV store: %s: write failed: %s\n", PROG, p->opt.nv_path,
                      n < 0 ? strerror(errno) : "short write or fsync");
        _exit(EXIT_NV); /* reset: never send what this step produced */
    }
    p->nv_writes++;
}

/* ---- status file (the keys of firmware_model's single-node status) ---- */

static const char *const REASONS[] = {
    "", "not a canergy identifier", "unknown message type", "node id out of range",
    "remote frame", "message sent the wrong way", "wrong data length", "CRC mismatch",
    "field out of range"};

/* Python's AuthFailure values, indexed by CANERGY_AUTH_MAC_BAD .. _UNAUTHENTICATED. */
static const char *const AUTH_FAILURES[] = {
    "MAC BAD", "freshness not the expected one", "MAC frame without its message",
    "malformed authenticated frame", "frame without a MAC"};

/* candump's compact form, as firmware_model's frame_text: 0CE00905#450100 */
static void frame_text(char out[FRAME_TEXT], uint32_t id, bool remote, const uint8_t *data,
                       size_t len)
{
    int at = snprintf(out, FRAME_TEXT, "%08X#%s", (unsigned)id, remote ? "R" : "");
    for (size_t i = 0U; !remote && i < len && at + 3 <= (int)FRAME_TEXT; i++) {
        at += snprintf(&out[at], FRAME_TEXT - (size_t)at, "%02X", (unsigned)data[i]);
    }
}

static void record_intrusion(struct port *p, const char *kind, const struct canergy_rx_frame *rx,
                             uint64_t now)
{
    struct port_intrusions *in = &p->intrusions;
    struct port_intrusion *e = &in->recent[in->total % INTRUSIONS_KEPT];
    if (in->total == 0U) {
        in->first_at_us = now;
    }
    in->total++;
    e->time_us = now;
    e->kind = kind;
    frame_text(e->frame, rx->id, rx->remote, rx->data, rx->len);
    if (in->total == 1U || in->total % 100U == 0U) { /* as firmware_model logs them */
        (void)fprintf(stderr, "%s: node %d: intrusion #%llu: %s (%s)\n", PROG, p->opt.node,
                      (unsigned long long)in->total, e->frame, kind);
    }
}

/* A received frame's result, counted as firmware_model's BusRuntime counts it. */
void port_count_received(struct port *p, int status, const struct canergy_rx_frame *rx,
                         uint64_t now)
{
    if (status == CANERGY_DECODE_FOREIGN || status == CANERGY_RX_OTHER_NODE) {
        p->count.foreign_frames++;
    } else if (status == CANERGY_DECODE_WRONG_DIRECTION) {
        /* its own direction (MAC frames 0x8 too) with its id, as the filter passes no other
         * node's: a node never receives its own frames back, so someone speaks in its name. The
         * library counted it in the witness of its next TELEMETRY. */
        if ((rx->id & 0xFFU) == (uint32_t)p->opt.node) {
            record_intrusion(p, "a frame in its name", rx, now);
        }
    } else if (status > 0 && status <= (int)CANERGY_DECODE_OUT_OF_RANGE) {
        p->count.decode_errors++;
        p->count.reasons[status]++;
    } else if (status >= CANERGY_AUTH_MAC_BAD && status <= CANERGY_AUTH_UNAUTHENTICATED) {
        const size_t reason = (size_t)(status - CANERGY_AUTH_MAC_BAD);
        p->count.auth_failures[reason]++; /* moves nothing; an intrusion, as in Python */
        record_intrusion(p, AUTH_FAILURES[reason], rx, now);
    }
}

/* "intrusions" and "intrusion_report" as firmware_model's Intrusions.as_json */
static void write_intrusions(const struct port *p, FILE *f)
{
    const struct port_intrusions *in = &p->intrusions;
    (void)fprintf(f, "\"intrusions\": %llu, \"intrusion_report\": {\"total\": %llu, \"by_node\": {",
                  (unsigned long long)in->total, (unsigned long long)in->total);
    if (in->total != 0U) {
        (void)fprintf(f, "\"%d\": %llu}, \"first_at_us\": %llu, \"recent\": [", p->opt.node,
                      (unsigned long long)in->total, (unsigned long long)in->first_at_us);
    } else {
        (void)fprintf(f, "}, \"first_at_us\": null, \"recent\": [");
    }
    const uint64_t kept = in->total < INTRUSIONS_KEPT ? in->total : INTRUSIONS_KEPT;
    for (uint64_t i = in->total - kept; i < in->total; i++) { /* oldest first */
        const struct port_intrusion *e = &in->recent[i % INTRUSIONS_KEPT];
        (void)fprintf(f, "%s{\"time_us\": %llu, \"node\": %d, \"kind\": \"%s\", \"frame\": \"%s\"}",
                      i == in->total - kept ? "" : ", ", (unsigned long long)e->time_us,
                      p->opt.node, e->kind, e->frame);
    }
    (void)fprintf(f, "]}, ");
}

static void write_status(const struct port *p, FILE *f)
{
    const struct canergy_record *r = &p->node.client.rec;
    const long long credited = (long long)r->credited_mj * 1000LL;
    const long long returned = credited - (long long)r->spent_uj - (long long)r->usable_uj;
    (void)fprintf(f,
                  "{\"node\": %d, \"usable_uj\": %lu, \"spent_uj\": %llu, \"credited_uj\": %lld, "
                  "\"returned_uj\": %lld, \"return_pending_uj\": %lu, \"return_seq\": %lu, "
                  "\"last_tx\": %lu, \"halted\": %s, \"drawn_uj\": %llu, \"nv_writes\": %llu, "
                  "\"nv_fallbacks\": %d, \"nmt_state\": \"OPERATIONAL\", "
                  "\"intentions_refused\": 0, \"overflow_refused\": %lu, \"joining\": %s, "
                  "\"joins\": %d, \"implementation\": \"c\", ",
                  p->opt.node, (unsigned long)r->usable_uj, (unsigned long long)r->spent_uj,
                  credited, returned, (unsigned long)r->return_pending_uj,
                  (unsigned long)r->return_seq, (unsigned long)r->last_tx,
                  p->node.halted ? "true" : "false", (unsigned long long)p->drawn_uj,
                  (unsigned long long)p->nv_writes, p->nv_fallbacks,
                  (unsigned long)p->node.overflow_refused,
                  canergy_client_joining(&p->node.client) ? "true" : "false", p->joins);
    (void)fprintf(f, "\"rules\": \"%s\", \"resuming\": %s, \"syncing\": %s, \"released_uj\": %lu, ",
                  p->opt.rules == CANERGY_RULES_WITNESSED ? "witnessed" : "hardened",
                  p->node.client.phase == CANERGY_RESUMING ? "true" : "false",
                  p->node.client.phase == CANERGY_SYNCING ? "true" : "false",
                  (unsigned long)p->node.released_uj);
    (void)fprintf(f, "\"witnessed\": %llu, ", (unsigned long long)p->witnessed);
    write_intrusions(p, f);
    (void)fprintf(f,
                  "\"frames_sent\": %llu, \"frames_received\": %llu, \"decode_errors\": %llu, "
                  "\"decode_error_reasons\": {",
                  (unsigned long long)p->count.frames_sent,
                  (unsigned long long)p->count.frames_received,
                  (unsigned long long)p->count.decode_errors);
    const char *sep = "";
    for (unsigned i = 1U; i <= CANERGY_DECODE_OUT_OF_RANGE; i++) {
        if (p->count.reasons[i] != 0U) {
            (void)fprintf(f, "%s\"%s\": %llu", sep, REASONS[i],
                          (unsigned long long)p->count.reasons[i]);
            sep = ", ";
        }
    }
    (void)fprintf(f,
                  "}, \"foreign_frames\": %llu, \"send_retries\": %llu, \"send_failures\": %llu, "
                  "\"receive_errors\": %llu, \"error_frames\": %llu, \"bus_state\": \"%s\", "
                  "\"auth_failures\": {",
                  (unsigned long long)p->count.foreign_frames,
                  (unsigned long long)p->count.send_retries,
                  (unsigned long long)p->count.send_failures,
                  (unsigned long long)p->count.receive_errors,
                  (unsigned long long)p->count.error_frames, "unknown");
    sep = "";
    for (size_t i = 0U; i < sizeof AUTH_FAILURES / sizeof AUTH_FAILURES[0]; i++) {
        if (p->count.auth_failures[i] != 0U) {
            (void)fprintf(f, "%s\"%s\": %llu", sep, AUTH_FAILURES[i],
                          (unsigned long long)p->count.auth_failures[i]);
            sep = ", ";
        }
    }
    (void)fprintf(f, "}}\n");
}

static void write_node_status(const void *ctx, FILE *f)
{
    write_status((const struct port *)ctx, f);
}

void port_save_status(const struct port *p)
{
    port_save_status_file(p->opt.status_path, write_node_status, p);
}
