/*
 * canergy-node: one canergy client node per process on Linux SocketCAN, built on the C library's
 * node layer. It behaves as `python -m firmware_model --node N` with a constant power: same
 * flags (the subset below), same NV file, same status file, so a node can move between the two
 * with its NV file in either direction.
 *
 *   canergy-node --node N -i socketcan -c vcan0 --nv PATH [--power 0.2W] [--status-file PATH]
 *                [--telemetry-period 1s] [--return-above 2J] [--response-timeout 100ms]
 *                [--tick 100ms] [--low-water 0J] [--status-period 1s] [--id-base 0x0CE00000]
 *                [--auth NODE.key [--fd]]
 *
 * The port may use libc and POSIX; only the library is restricted. One loop: poll() on a raw
 * CAN socket (kernel filters pass exactly this node's frames, both directions: a frame in the
 * node's own direction with its id is someone speaking in its name, an intrusion) until the
 * earliest of the library's deadline, the actuator tick and the status write. Every canergy_out
 * is carried out in order: pwrite + fsync of the slot image, then the frames. kill -9 at any
 * instant is safe.
 *
 * --auth: authenticated mode (canergy/auth.h) with the node's key file (src/canergy/auth/keys.py:
 * mode 0600, kind=node, this node's id; the key is never printed); --fd: CAN FD frames with a
 * 64-bit MAC, otherwise the classic layout (each frame followed by a MAC frame). With --auth the
 * NV slots are sealed too (canergy/nv.h, "Sealed image"): a record whose seal does not hold is
 * a damaged slot, one never sealed is refused.
 *
 * Exit status: 0 after SIGINT/SIGTERM (final status written), 1 when the NV file cannot be
 * written (the node stops without sending what that step produced), 2 for bad arguments or a
 * socket or file that cannot be opened.
 *
 * This file: main(), its loop and the glue between the library and the port's other files:
 * port.h (shared state), args.c (options, units), keyfile.c (--auth key file), paths.c (no two
 * file flags naming one file; no folder of the NV file's or the key's that others may write),
 * storage.c (NV file, status file), socketcan.c (the CAN socket).
 */
#define _GNU_SOURCE 1

#include "args.h"
#include "keyfile.h"
#include "paths.h"
#include "port.h"
#include "socketcan.h"
#include "system.h"
#include "storage.h"

#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

const char *const port_prog = "canergy-node";

static volatile sig_atomic_t stop_requested;

static void on_stop_signal(int signum)
{
    (void)signum;
    stop_requested = 1;
}

/* ---- the loop ---- */

/* What the actuator wants for the time since its last period, firmware_model's integration:
 * power (uW) * dt (us) in pJ, the sub-uJ remainder carried. */
static uint32_t actuator_need(struct port *p, uint64_t now)
{
    const uint64_t dt = now > p->last_draw_us ? now - p->last_draw_us : 0U;
    p->last_draw_us = now;
    uint64_t pj = 0U;
    if (!port_mul_fits(p->opt.power_uw, dt, &pj) || pj > UINT64_MAX - p->remainder_pj) {
        p->remainder_pj = 0U;
        return UINT32_MAX; /* more than any budget holds */
    }
    pj += p->remainder_pj;
    p->remainder_pj = pj % 1000000U;
    const uint64_t uj = pj / 1000000U;
    return uj > UINT32_MAX ? UINT32_MAX : (uint32_t)uj;
}

/* The persist-before-send contract: the slot image is on disk before any frame leaves. */
static void carry_out(struct port *p, const struct canergy_out *out)
{
    if (out->persist) {
        port_nv_write(p, out); /* exits 1 when it fails: never send what this step produced */
    }
    for (unsigned i = 0U; i < out->frame_count; i++) {
        const struct canergy_frame *f = &out->frames[i];
        if (p->opt.auth_path == NULL) {
            port_can_send(p->sock, &p->count, f->id, f->data, f->dlc);
            continue;
        }
        struct canergy_auth_frame frames[2];
        const int n = canergy_auth_node_protect(&p->auth, &p->node, f, frames);
        for (int k = 0; k < n; k++) {
            port_can_send(p->sock, &p->count, frames[k].id, frames[k].data, frames[k].len);
        }
    }
}

static void receive_one(struct port *p, const struct canergy_rx_frame *rx)
{
    const uint64_t now = port_now_us();
    struct canergy_out out;
    const uint8_t witness = p->node.witness;
    const uint8_t phase = p->node.client.phase;
    const bool starting = phase == CANERGY_RESUMING || phase == CANERGY_SYNCING;
    const uint32_t seq = p->node.client.rec.return_seq; /* confirmed: it moves to seq + 1 */
    const int status = p->opt.auth_path != NULL
                           ? canergy_auth_node_frame(&p->auth, &p->node, rx, now, &out)
                           : canergy_node_on_frame(&p->node, rx, now, &out);
    p->witnessed += (uint8_t)(p->node.witness - witness); /* 0 or 1 per frame */
    port_count_received(p, status, rx, now);
    carry_out(p, &out);
    if (p->node.client.phase == CANERGY_SYNCING && phase != CANERGY_SYNCING) {
        (void)fprintf(stderr,
                      "%s: node %d: the supervisor started (SYNC): books answered, no energy to "
                      "the actuator until it confirms them\n",
                      PROG, p->opt.node);
    } else if (starting && (p->node.client.phase == CANERGY_IDLE ||
                            p->node.client.phase == CANERGY_HOLDING)) {
        const bool behind = p->node.client.rec.return_seq != seq + 1U;
        (void)fprintf(stderr, "%s: node %d: %s\n", PROG, p->opt.node,
                      behind ? "the supervisor found this record behind (an older copy): "
                               "admitted afresh, its usable budget dropped"
                             : "the supervisor confirmed this record");
    }
}

static void receive_all(struct port *p)
{
    struct canfd_frame cf; /* CAN_MTU bytes of it for a classic frame */
    struct canergy_rx_frame rx;
    while (port_can_receive(p->sock, &p->count, &cf, &rx)) {
        receive_one(p, &rx);
    }
}

static uint64_t min3(uint64_t a, uint64_t b, uint64_t c)
{
    const uint64_t ab = a < b ? a : b;
    return ab < c ? ab : c;
}

int main(int argc, char **argv)
{
    static struct port p;
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_stop_signal; /* no SA_RESTART: poll() returns at once */
    (void)sigemptyset(&sa.sa_mask);
    (void)sigaction(SIGINT, &sa, NULL);
    (void)sigaction(SIGTERM, &sa, NULL);

    port_parse_args(argc, argv, &p.opt);
    const struct port_file files[] = {{"--nv", p.opt.nv_path},
                                      {"--status-file", p.opt.status_path},
                                      {"--auth", p.opt.auth_path}};
    port_check_distinct(files, sizeof files / sizeof files[0]);
    port_check_private_dir("--nv", p.opt.nv_path);
    port_check_private_dir("--auth", p.opt.auth_path); /* as python -m firmware_model */
    if (p.opt.auth_path != NULL) {
        uint8_t key[CANERGY_KDF_KEY_SIZE];
        port_load_key("--auth", p.opt.auth_path, p.opt.node, key);
        const int ok = canergy_auth_init(&p.auth, key, p.opt.id_base, (uint8_t)p.opt.node,
                                         p.opt.fd ? CANERGY_AUTH_FD : CANERGY_AUTH_CLASSIC,
                                         CANERGY_TO_CLIENT);
        canergy_nv_seal_key(&p.seal, key, (uint8_t)p.opt.node, false); /* the NV seal */
        p.sealed = 1;
        canergy_wipe(key, sizeof key);
        if (ok != CANERGY_OK) {
            port_usage_error("--auth: bad node or id base");
        }
    }
    port_nv_check(&p);
    p.sock = port_can_open(&p.opt);
    uint8_t image[NV_READ_BYTES] = {0}; /* a short read leaves no stale seal bytes */
    size_t image_len = 0U;
    port_nv_open(&p, image, &image_len);

    const struct canergy_node_config cfg = {
        .client = {.id_base = p.opt.id_base,
                   .command_timeout_us = (uint32_t)(2U * p.opt.response_timeout_us),
                   .return_retry_us = (uint32_t)(2U * p.opt.response_timeout_us),
                   .node = (uint8_t)p.opt.node,
                   .rules = p.opt.rules},
        .telemetry_period_us = (uint32_t)p.opt.telemetry_period_us,
        .low_water_uj = p.opt.low_water_uj > UINT32_MAX ? UINT32_MAX
                                                        : (uint32_t)p.opt.low_water_uj,
        .return_above_uj = (p.opt.keep_all || p.opt.return_above_uj >= CANERGY_KEEP_ALL)
                               ? (uint32_t)CANERGY_KEEP_ALL
                               : (uint32_t)p.opt.return_above_uj,
    };
    struct canergy_out out;
    uint64_t now = port_now_us();
    const uint16_t nonce = port_random16();
    const int fallbacks = canergy_node_start(&p.node, &cfg, image, image_len, nonce, now, &out);
    if (fallbacks < 0) {
        port_usage_error("bad node configuration");
    }
    p.nv_fallbacks = fallbacks;
    p.joins = canergy_client_joining(&p.node.client) ? 1 : 0;
    if (p.node.client.phase == CANERGY_RESUMING) {
        (void)fprintf(stderr,
                      "%s: node %d: witnessed rules: RESUME sent; no energy to the actuator until "
                      "the supervisor confirms this record (an older copy is found behind)\n",
                      PROG, p.opt.node);
    }
    if (p.joins && p.opt.auth_path != NULL) {
        canergy_auth_set_join(&p.auth, port_random16(), nonce); /* a 32-bit JOIN freshness */
    }
    carry_out(&p, &out);
    p.last_draw_us = now;
    uint64_t next_tick = now + p.opt.tick_us;
    uint64_t next_status = now;

    while (!stop_requested) {
        now = port_now_us();
        if (now >= canergy_node_deadline(&p.node)) {
            canergy_node_poll(&p.node, now, &out);
            carry_out(&p, &out);
        }
        if (now >= next_tick) {
            next_tick = now + p.opt.tick_us;
            const uint32_t wanted = actuator_need(&p, now);
            const uint32_t granted = canergy_node_draw(&p.node, wanted, now, &out);
            carry_out(&p, &out); /* the spend is on disk before the actuator uses it */
            p.drawn_uj += granted;
            if (granted < wanted) {
                p.remainder_pj = 0U; /* a halted actuator keeps no debt */
            }
        }
        if (now >= next_status) {
            port_save_status(&p);
            next_status = now + p.opt.status_period_us;
        }
        const uint64_t wake = min3(canergy_node_deadline(&p.node), next_tick, next_status);
        now = port_now_us();
        if (port_can_wait(p.sock, &p.count, wake, now)) {
            receive_all(&p);
        }
    }
    port_save_status(&p);
    canergy_auth_wipe(&p.auth);
    canergy_cmac_wipe(&p.seal);
    (void)close(p.sock);
    (void)close(p.nv_fd);
    return 0;
}
