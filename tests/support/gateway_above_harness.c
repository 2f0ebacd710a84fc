/*
 * Not a port: canergy-gateway's files (ports/linux) but canergy_gateway.c's main(), its bus
 * above on a socketpair instead of a CAN socket, time given by the test (this kernel has no
 * SocketCAN). tests/test_gateway_duplicate_id.py builds it and drives it with lines on stdin:
 *   at US          the time is US µs
 *   rx ID#HEX      a frame from above (candump's compact form)
 * After each line it takes the frames from above, runs the client's timer when due and sends
 * its TELEMETRY when due, as main()'s loop does, and prints each frame the gateway sends above
 * as "tx US ID#HEX" (US: the time it left). Its arguments are canergy-gateway's
 * (--upstream-channel and -c are required but not opened); the bus below is a socketpair no one
 * speaks on.
 */
#define _GNU_SOURCE 1

#include "gateway_port.h"
#include "harness_can.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

const char *const port_prog = "canergy-gateway";

/* What main()'s loop does above on each pass: the frames from above, the client's timer, the
 * TELEMETRY when due; then what left is printed. */
static void pass(struct gateway_port *g, int peer, uint64_t now)
{
    gw_receive_up(g, now);
    gw_up_timer(g, now);
    if (now >= g->next_telemetry) {
        gw_telemetry(g, now);
    }
    char label[32];
    (void)snprintf(label, sizeof label, "tx %llu", (unsigned long long)now);
    harness_print_sent(peer, label);
}

int main(int argc, char **argv)
{
    static struct gateway_port g;
    port_parse_gateway_args(argc, argv, &g.opt);
    gw_check_nv(&g);
    int up[2];
    int down[2];
    if (socketpair(AF_UNIX, SOCK_SEQPACKET, 0, up) != 0 ||
        socketpair(AF_UNIX, SOCK_SEQPACKET, 0, down) != 0) {
        return 3;
    }
    g.up_sock = up[0];
    g.down_sock = down[0];
    uint64_t now = 1U;
    g.next_telemetry = now;
    gw_start(&g, now);
    pass(&g, up[1], now);
    char line[512];
    while (fgets(line, sizeof line, stdin) != NULL) {
        if (strncmp(line, "at ", 3U) == 0) {
            now = strtoull(&line[3], NULL, 10);
        } else if (strncmp(line, "rx ", 3U) == 0) {
            harness_frame_in(up[1], &line[3]);
        }
        pass(&g, up[1], now);
    }
    (void)fflush(stdout);
    (void)close(g.nv_fd);
    return 0;
}
