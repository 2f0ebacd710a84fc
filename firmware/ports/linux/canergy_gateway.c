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
 *                   [--upstream-auth NODE.key [--upstream-fd]] [--auth MASTER.key [--fd]]
 *
 * One record for both roles (the client's above, the supervisor's below) in two slots of the NV
 * file, written in turn with fsync before any frame of the step leaves: a kill -9 at any instant
 * restarts from books in which neither role owes the other (two records written apart is the
 * split-save counterexample of `canergy check --topology chain --broken-gateway split-save`);
 * the slot's layout is the library's (canergy_gateway_nv_*, nv.c).
 *
 * Below it tops every node up to --target from the level in its TELEMETRY (a level reported
 * after its last transaction ended; canergy_gateway_top_up), holds each fresh RETURN until the
 * node's own TELEMETRY confirms it (canergy/witness.h: no key, anyone can send one in its
 * name; --return-hold), commits what a node acknowledges, and settles on
 * SIGINT/SIGTERM (grants nothing more, waits for the open transactions up to --stop-timeout).
 * Above it reports its downstream Us as its level. Its status file is the Python gateway's
 * (role "gateway", the supervisor's keys, "upstream" with the client's record, "link_gap_uj"):
 * `canergy ledger` reads it. --upstream-auth NODE.key [--upstream-fd]: authenticated above, as
 * canergy-node --auth (canergy/auth.h); --auth MASTER.key [--fd]: below, as canergy supervisor
 * --auth (no RETURN held then: each carries a MAC). No limits besides --target. With either key
 * the NV slots are sealed (canergy/nv.h, "Sealed image"), under a key derived from
 * --upstream-auth's when given, else from --auth's: a slot whose seal does not hold is a
 * damaged slot, a record never sealed is refused.
 *
 * Exit status: 0 after SIGINT/SIGTERM, 1 when the NV file cannot be written, 2 for bad
 * arguments or a socket or file that cannot be opened.
 *
 * This file: main() and its loop; gateway_above.c the bus above, gateway_below.c the bus below,
 * args.c the command line, gateway_storage.c the NV and status files, gateway_report.c
 * intrusions and refusals below (gateway_port.h: the shared state).
 */
#define _GNU_SOURCE 1

#include "args.h"
#include "gateway_port.h"
#include "keyfile.h"
#include "paths.h"
#include "socketcan.h"
#include "system.h"

#include <errno.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>
#include <unistd.h>

const char *const port_prog = "canergy-gateway";

static volatile sig_atomic_t stop_requested;

static void on_stop_signal(int signum)
{
    (void)signum;
    stop_requested = 1;
}

static uint64_t least(uint64_t a, uint64_t b)
{
    return a < b ? a : b;
}

/* ---- main ---- */

static int open_bus(const char *channel, uint32_t id_base, uint8_t node, int fd)
{
    struct port_options o;
    memset(&o, 0, sizeof o);
    o.channel = channel;
    o.id_base = id_base;
    o.node = node;
    o.fd = fd;
    return port_can_open(&o);
}

/* --upstream-auth: this gateway's node key above (as canergy-node's --auth). */
static void up_key(struct gateway_port *g)
{
    uint8_t key[CANERGY_KDF_KEY_SIZE];
    port_load_key("--upstream-auth", g->opt.up_auth_path, g->opt.node, key);
    const int ok = canergy_auth_init(&g->up_auth, key, g->opt.id_base, g->opt.node,
                                     g->opt.up_fd ? CANERGY_AUTH_FD : CANERGY_AUTH_CLASSIC,
                                     CANERGY_TO_CLIENT);
    canergy_nv_seal_key(&g->seal, key, g->opt.node, true); /* the NV seal: this key first */
    g->sealed = 1;
    canergy_wipe(key, sizeof key);
    if (ok != CANERGY_OK) {
        port_usage_error("--upstream-auth: bad node or id base");
    }
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
    port_parse_gateway_args(argc, argv, &g.opt);
    const struct port_file files[] = {{"--nv", g.opt.nv_path},
                                      {"--status-file", g.opt.status_path},
                                      {"--upstream-auth", g.opt.up_auth_path},
                                      {"--auth", g.opt.auth_path}};
    port_check_distinct(files, sizeof files / sizeof files[0]);
    port_check_private_dir("--nv", g.opt.nv_path); /* then the keys, as canergy gateway */
    port_check_private_dir("--auth", g.opt.auth_path);
    port_check_private_dir("--upstream-auth", g.opt.up_auth_path);
    if (g.opt.up_auth_path != NULL) {
        up_key(&g);
    }
    if (g.opt.auth_path != NULL) {
        gw_down_keys(&g);
    }
    gw_check_nv(&g);
    g.up_sock = open_bus(g.opt.up_channel, g.opt.id_base, g.opt.node, g.opt.up_fd); /* its id */
    g.down_sock = open_bus(g.opt.down_channel, g.opt.id_base, 1U, g.opt.fd);
    port_can_filter(g.down_sock, g.opt.id_base, CANERGY_ID_MASK); /* every node below */
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_stop_signal;
    (void)sigaction(SIGINT, &sa, NULL);
    (void)sigaction(SIGTERM, &sa, NULL);
    uint64_t now = port_now_us();
    gw_start(&g, now);
    gw_say_up_waiting(&g, 0, 0U); /* witnessed above: a start with a record waits for its ADMIT */
    g.next_telemetry = now;
    uint64_t next_tick = now, next_status = now, stop_at = 0U;
    for (;;) {
        now = port_now_us();
        if (stop_requested && !g.stopping) {
            g.stopping = 1;
            stop_at = now + g.opt.stop_timeout_us;
        }
        if (g.stopping && (quiet(&g.gw.down) || now >= stop_at)) {
            break;
        }
        uint64_t wake = least(least(g.next_telemetry, next_tick), next_status);
        wake = least(wake, least(canergy_client_deadline(&g.gw.up),
                                       canergy_supervisor_deadline(&g.gw.down)));
        wake = least(wake, gw_joins_deadline(&g)); /* a JOIN held below, due */
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
        gw_receive_up(&g, now);
        gw_receive_down(&g, now);
        gw_up_timer(&g, now);
        if (canergy_supervisor_deadline(&g.gw.down) <= now) {
            struct canergy_supervisor_out out;
            canergy_supervisor_on_timer(&g.gw.down, now, &out);
            gw_down_out(&g, &out, now);
        }
        if (now >= next_tick) {
            next_tick = now + g.opt.tick_us;
            gw_release_all(&g, now);
            gw_say_waiting(&g);
            gw_top_up(&g, now);
            gw_give_back(&g, now);
        }
        if (now >= g.next_telemetry) {
            gw_telemetry(&g, now);
        }
        if (now >= next_status) {
            next_status = now + g.opt.status_period_us;
            gw_save_status(&g, now);
        }
    }
    gw_save_status(&g, port_now_us());
    canergy_auth_wipe(&g.up_auth);
    canergy_cmac_wipe(&g.seal);
    for (unsigned i = 0U; i < g.opt.count; i++) {
        canergy_auth_wipe(&g.down_auth[i]);
    }
    (void)close(g.nv_fd);
    return 0;
}
