/*
 * canergy-node's bus (socketcan.c): the raw SocketCAN socket of one node, its frames out and in,
 * and the poll() of the main loop.
 */
#ifndef CANERGY_PORT_LINUX_SOCKETCAN_H
#define CANERGY_PORT_LINUX_SOCKETCAN_H

#include "port.h"

#include <linux/can.h>
#include <stddef.h>
#include <stdint.h>

/* A raw CAN socket bound to o->channel that passes this node's frames in both directions
 * (id_base | node, mask 0x1FFFF0FF, 29-bit); CAN FD frames with o->fd. Exits 2 on failure. */
int port_can_open(const struct port_options *o);
void port_can_filter(int sock, uint32_t can_id, uint32_t mask);

/* Send one 29-bit frame (CAN FD with bit rate switch above 8 bytes); ENOBUFS is tried again
 * with backoff, then counted in send_failures. */
void port_can_send(int sock, struct port_counters *count, uint32_t id, const uint8_t *data,
                   size_t len);

/* The next received frame into cf, described by rx: 1, or 0 when none waits. */
int port_can_receive(int sock, struct port_counters *count, struct canfd_frame *cf,
                     struct canergy_rx_frame *rx);

/* poll() until a frame or wake (us; now: the time now), at most a second: 1 when frames wait. */
int port_can_wait(int sock, struct port_counters *count, uint64_t wake, uint64_t now);

#endif /* CANERGY_PORT_LINUX_SOCKETCAN_H */
