/*
 * canergy-node's files (storage.c): the NV record file and the status file, and what the status
 * file counts of each received frame.
 */
#ifndef CANERGY_PORT_LINUX_STORAGE_H
#define CANERGY_PORT_LINUX_STORAGE_H

#include "port.h"

#include <stddef.h>
#include <stdint.h>

/* Exit 2 when an existing NV file's newest record holds a counter beyond the bound the proof
 * assumes (2^30 - 1), naming it, or when its seals refuse it (p->sealed: no slot whose seal
 * holds, or records never sealed; without a key: a sealed file); reads only (before the bus is
 * opened). */
void port_nv_check(const struct port *p);

/* Open (or create) the NV file of p->opt.nv_path into p->nv_fd and read its slots into image
 * (*len bytes of it; 0 for a new file), with p->sealed its seals checked (a slot whose seal
 * does not hold is spoilt in image: a damaged slot, told on stderr); exit 2 when it cannot be
 * opened or read, is not an NV file of canergy, or its seals refuse it. */
void port_nv_open(struct port *p, uint8_t image[NV_READ_BYTES], size_t *len);

/* pwrite of out's slot image (out->persist set), with p->sealed then its seal, and fsync; exit 1
 * at once when that fails. */
void port_nv_write(struct port *p, const struct canergy_out *out);

/* Count what the library made of a received frame (status: its result): foreign frames, decode
 * errors by reason, auth failures by reason, intrusions (reported on stderr, as firmware_model
 * logs them). */
void port_count_received(struct port *p, int status, const struct canergy_rx_frame *rx,
                         uint64_t now);

/* Write the status file (stdout without --status-file): temp file, fsync, rename. */
void port_save_status(const struct port *p);

#endif /* CANERGY_PORT_LINUX_STORAGE_H */
