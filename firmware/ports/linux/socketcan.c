/*
 * canergy-node's bus (ports/linux): a raw SocketCAN socket with this node's kernel filter
 * (classic, or CAN FD with --fd), sending a frame (ENOBUFS: six tries with backoff), receiving
 * the frames waiting, and the poll() that sleeps until a frame comes or the loop's next wake-up.
 * Every frame, error and retry is counted in struct port_counters (the status file's).
 */
#define _GNU_SOURCE 1

#include "socketcan.h"

#include "args.h"

#include <errno.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>

#define SEND_ATTEMPTS 6

/* The raw CAN socket on o->channel with this node's filter (and CAN FD frames with --fd); exit
 * 2 when it cannot be opened. */
int port_can_open(const struct port_options *o)
{
    const int s = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (s < 0) {
        (void)fprintf(stderr, "%s: error: CAN socket: %s\n", PROG, strerror(errno));
        exit(EXIT_USAGE);
    }
    if (strlen(o->channel) >= IFNAMSIZ) {
        port_usage_error("argument -c: interface name '%s' is too long", o->channel);
    }
    const unsigned ifindex = if_nametoindex(o->channel);
    if (ifindex == 0U) {
        (void)fprintf(stderr, "%s: error: cannot open %s: %s\n", PROG, o->channel,
                      strerror(errno));
        exit(EXIT_USAGE);
    }
    /* this node's frames, both directions (Codec.client_watch_filters): id_base | type << 8 |
     * node, 29 bit; a frame in the node's own direction is an intrusion (a node never
     * receives its own frames back), and its TELEMETRY's witness counts it */
    struct can_filter filter;
    filter.can_id = (canid_t)(o->id_base | (uint32_t)o->node) | CAN_EFF_FLAG;
    filter.can_mask = (canid_t)(CANERGY_ID_MASK | 0xFFU) | CAN_EFF_FLAG;
    if (setsockopt(s, SOL_CAN_RAW, CAN_RAW_FILTER, &filter, sizeof filter) != 0) {
        (void)fprintf(stderr, "%s: error: CAN filter: %s\n", PROG, strerror(errno));
        exit(EXIT_USAGE);
    }
    if (o->fd) {
        const int on = 1;
        struct ifreq ifr;
        memset(&ifr, 0, sizeof ifr);
        memcpy(ifr.ifr_name, o->channel, strlen(o->channel));
        if (ioctl(s, SIOCGIFMTU, &ifr) != 0 || ifr.ifr_mtu != (int)CANFD_MTU) {
            port_usage_error("--fd: %s is not a CAN FD interface (ip link set %s mtu 72)",
                             o->channel, o->channel);
        }
        if (setsockopt(s, SOL_CAN_RAW, CAN_RAW_FD_FRAMES, &on, sizeof on) != 0) {
            (void)fprintf(stderr, "%s: error: CAN FD frames: %s\n", PROG, strerror(errno));
            exit(EXIT_USAGE);
        }
    }
    struct sockaddr_can addr;
    memset(&addr, 0, sizeof addr);
    addr.can_family = AF_CAN;
    addr.can_ifindex = (int)ifindex;
    if (bind(s, (const struct sockaddr *)&addr, sizeof addr) != 0) {
        (void)fprintf(stderr, "%s: error: cannot open %s: %s\n", PROG, o->channel,
                      strerror(errno));
        exit(EXIT_USAGE);
    }
    return s;
}

/* Replace the socket's kernel filter: extended frames whose id & mask is can_id & mask. */
void port_can_filter(int sock, uint32_t can_id, uint32_t mask)
{
    struct can_filter filter;
    filter.can_id = (canid_t)can_id | CAN_EFF_FLAG;
    filter.can_mask = (canid_t)mask | CAN_EFF_FLAG;
    if (setsockopt(sock, SOL_CAN_RAW, CAN_RAW_FILTER, &filter, sizeof filter) != 0) {
        (void)fprintf(stderr, "%s: error: CAN filter: %s\n", PROG, strerror(errno));
        exit(EXIT_USAGE);
    }
}

/* One frame: classic up to 8 bytes, CAN FD with bit rate switch above (FD layout). */
void port_can_send(int sock, struct port_counters *count, uint32_t id, const uint8_t *data,
                   size_t len)
{
    struct canfd_frame cf; /* a struct can_frame is its first CAN_MTU bytes */
    memset(&cf, 0, sizeof cf);
    cf.can_id = (canid_t)id | CAN_EFF_FLAG;
    cf.len = (uint8_t)(len <= CANFD_MAX_DLEN ? len : CANFD_MAX_DLEN);
    memcpy(cf.data, data, cf.len);
    const size_t size = len > CAN_MAX_DLEN ? CANFD_MTU : CAN_MTU;
    if (len > CAN_MAX_DLEN) {
        cf.flags = CANFD_BRS;
    }
    struct timespec backoff = {0, 1000000L}; /* 1 ms, doubling up to 50 ms */
    for (int attempt = 0; attempt < SEND_ATTEMPTS; attempt++) {
        const ssize_t n = send(sock, &cf, size, 0);
        if (n == (ssize_t)size) {
            count->frames_sent++;
            return;
        }
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n < 0 && (errno == ENOBUFS || errno == EAGAIN) && attempt + 1 < SEND_ATTEMPTS) {
            count->send_retries++;
            (void)nanosleep(&backoff, NULL);
            backoff.tv_nsec = backoff.tv_nsec * 2 > 50000000L ? 50000000L : backoff.tv_nsec * 2;
            continue;
        }
        break;
    }
    count->send_failures++; /* lost, as far as the protocol goes: it re-sends what matters */
}

/* The next frame waiting on sock into cf, and rx describing it (rx->data points into cf): 1,
 * or 0 when none is left. Error frames and reads of another size are counted and skipped. */
int port_can_receive(int sock, struct port_counters *count, struct canfd_frame *cf,
                     struct canergy_rx_frame *rx)
{
    for (;;) {
        const ssize_t n = recv(sock, cf, sizeof *cf, MSG_DONTWAIT); /* CAN_MTU bytes: classic */
        if (n < 0) {
            if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
                count->receive_errors++;
            }
            return 0;
        }
        if (n != (ssize_t)CAN_MTU && n != (ssize_t)CANFD_MTU) {
            count->receive_errors++;
            continue;
        }
        if ((cf->can_id & CAN_ERR_FLAG) != 0U) {
            count->error_frames++;
            continue;
        }
        count->frames_received++;
        const bool extended = (cf->can_id & CAN_EFF_FLAG) != 0U;
        rx->id = (uint32_t)(cf->can_id & (extended ? CAN_EFF_MASK : CAN_SFF_MASK));
        rx->data = cf->data;
        rx->len = cf->len <= CANFD_MAX_DLEN ? cf->len : CANFD_MAX_DLEN;
        rx->extended = extended;
        rx->remote = (cf->can_id & CAN_RTR_FLAG) != 0U;
        return 1;
    }
}

/* Sleep in poll() until a frame comes on sock or wake (us of port_now_us, now being now), at
 * most a second: 1 when frames wait. A signal ends it early; a poll() error is counted. */
int port_can_wait(int sock, struct port_counters *count, uint64_t wake, uint64_t now)
{
    int timeout_ms = 0;
    if (wake > now) {
        const uint64_t ms = (wake - now + 999U) / 1000U;
        timeout_ms = ms > 1000U ? 1000 : (int)ms;
    }
    struct pollfd pfd = {sock, POLLIN, 0};
    const int ready = poll(&pfd, 1U, timeout_ms);
    if (ready > 0 && (pfd.revents & POLLIN) != 0) {
        return 1;
    }
    if (ready < 0 && errno != EINTR) {
        count->receive_errors++;
    }
    return 0;
}
