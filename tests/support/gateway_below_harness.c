/*
 * Not a port: canergy-gateway's files (ports/linux) but canergy_gateway.c's main(), its bus
 * below on a socketpair instead of a CAN socket, time given by the test (this kernel has no
 * SocketCAN). tests/test_c_gateway_port_below.py builds it and drives it with lines on stdin:
 *   at US          the time is US µs: the JOINs held below that are due, admitted
 *   rx ID#HEX      a frame from below (candump's compact form)
 *   inject UJ      energy into the budget below (as if committed above)
 *   tick           the gateway's tick (held RETURNs, the refusals' line, the top-ups)
 *   status         the status file written
 * and prints each frame the gateway sends below as "tx ID#HEX". Its arguments are
 * canergy-gateway's (--upstream-channel and -c are required but not opened).
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

void gw_send_up(struct gateway_port *g, const struct canergy_frame *f)
{
    (void)g;
    (void)f; /* the bus above is not this harness's */
}

int main(int argc, char **argv)
{
    static struct gateway_port g;
    port_parse_gateway_args(argc, argv, &g.opt);
    if (g.opt.auth_path != NULL) {
        gw_down_keys(&g);
    }
    gw_check_nv(&g);
    int pair[2];
    if (socketpair(AF_UNIX, SOCK_SEQPACKET, 0, pair) != 0) {
        return 3;
    }
    g.down_sock = pair[0];
    g.up_sock = -1;
    uint64_t now = 1U;
    gw_start(&g, now);
    char line[512];
    while (fgets(line, sizeof line, stdin) != NULL) {
        if (strncmp(line, "at ", 3U) == 0) {
            now = strtoull(&line[3], NULL, 10);
        } else if (strncmp(line, "rx ", 3U) == 0) {
            harness_frame_in(pair[1], &line[3]);
        } else if (strncmp(line, "inject ", 7U) == 0) {
            (void)canergy_supervisor_inject(&g.gw.down, strtoull(&line[7], NULL, 10));
            gw_save(&g);
        } else if (strncmp(line, "tick", 4U) == 0) {
            gw_release_all(&g, now);
            gw_top_up(&g, now);
        } else if (strncmp(line, "status", 6U) == 0) {
            gw_save_status(&g, now);
        }
        gw_receive_down(&g, now);
        if (canergy_supervisor_deadline(&g.gw.down) <= now) {
            struct canergy_supervisor_out out;
            canergy_supervisor_on_timer(&g.gw.down, now, &out);
            gw_down_out(&g, &out, now);
        }
        harness_print_sent(pair[1], "tx");
    }
    (void)close(g.nv_fd);
    return 0;
}
