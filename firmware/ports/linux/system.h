/*
 * What both Linux programs (canergy-node, canergy-gateway) take from the system besides the
 * CAN socket: the monotonic clock, entropy for a JOIN nonce, and their NV file opened so that
 * a new one stays on disk.
 */
#ifndef CANERGY_PORT_LINUX_SYSTEM_H
#define CANERGY_PORT_LINUX_SYSTEM_H

#include <stdint.h>
#include <stdio.h>
#include <sys/types.h>

/* CLOCK_BOOTTIME in microseconds (suspended time counts); exits 1 when it cannot be read. */
uint64_t port_now_us(void);

/* 16 random bits from getrandom() (/dev/urandom when that fails); exits 2 without entropy. */
uint16_t port_random16(void);

/* The NV file at path, read-write, created with mode when missing. While it is empty (new, or
 * made by a start that stopped before this step) its directory is fsynced too, so that the
 * records fsynced into it later cannot vanish with an unwritten directory entry on a power
 * loss; a filesystem that cannot sync a directory (EINVAL) is taken as it is. -1 with errno
 * set on failure. */
/* Exit 2 naming --nv PATH when another holder keeps the file open as fd is (flock: LOCK_EX to
 * keep it, LOCK_SH to look before the bus is opened). */
void port_nv_keep(int fd, const char *path, int how);
int port_open_nv(const char *path, mode_t mode);

/* A status file: write(ctx, f) into a temporary file beside path, fsynced and renamed over it
 * (a reader sees the old or the new status, never half of one); to stdout when path is NULL.
 * A failure is said on stderr and the old file kept; a path too long for the temporary file
 * exits 2. */
void port_save_status_file(const char *path, void (*write)(const void *ctx, FILE *f),
                           const void *ctx);

#endif /* CANERGY_PORT_LINUX_SYSTEM_H */
