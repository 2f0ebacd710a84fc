/*
 * The clock, the entropy and the NV file's creation of the Linux programs (system.h).
 */
#define _GNU_SOURCE 1

#include "system.h"

#include "args.h"
#include "port.h"

#include <errno.h>
#include <fcntl.h>
#include <libgen.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/file.h>
#include <sys/random.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

/* CLOCK_BOOTTIME, as the Python live stack's clock: it never goes back and counts the time the
 * host was suspended, so every deadline then due fires at the resume. */
uint64_t port_now_us(void)
{
    struct timespec ts;
    if (clock_gettime(CLOCK_BOOTTIME, &ts) != 0) {
        (void)fprintf(stderr, "%s: error: clock_gettime failed\n", PROG);
        exit(EXIT_NV);
    }
    return (uint64_t)ts.tv_sec * US_PER_S + (uint64_t)ts.tv_nsec / 1000U;
}

uint16_t port_random16(void)
{
    uint16_t v = 0U;
    if (getrandom(&v, sizeof v, 0) == (ssize_t)sizeof v) {
        return v;
    }
    FILE *f = fopen("/dev/urandom", "rb");
    if (f == NULL || fread(&v, sizeof v, 1U, f) != 1U) {
        (void)fprintf(stderr, "%s: error: no entropy for the JOIN nonce\n", PROG);
        exit(EXIT_USAGE);
    }
    (void)fclose(f);
    return v;
}

/* fsync the directory holding path. */
static int sync_directory_of(const char *path)
{
    char dir[PATH_MAX];
    if (snprintf(dir, sizeof dir, "%s", path) >= (int)sizeof dir) {
        errno = ENAMETOOLONG;
        return -1;
    }
    const int fd = open(dirname(dir), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0) {
        return -1;
    }
    /* EINVAL: a filesystem that cannot sync a directory (some FUSE and 9p mounts) */
    const int rc = (fsync(fd) == 0 || errno == EINVAL) ? 0 : -1;
    const int saved = errno;
    (void)close(fd);
    errno = saved;
    return rc;
}

void port_nv_keep(int fd, const char *path, int how)
{
    /* One keeper per record: a second process on this file (or firmware_model, which locks it
     * alike) would spend what it holds again. */
    if (flock(fd, how | LOCK_NB) != 0) {
        port_usage_error("--nv %s is kept by another holder (%s): two holders of one record "
                         "would both spend what it holds; stop the other",
                         path, errno == EWOULDBLOCK ? "locked" : strerror(errno));
    }
}

int port_open_nv(const char *path, mode_t mode)
{
    const int fd = open(path, O_RDWR | O_CREAT | O_CLOEXEC, mode);
    if (fd < 0) {
        return -1;
    }
    port_nv_keep(fd, path, LOCK_EX); /* held until the process ends */
    /* An empty file may be new, or one whose creator stopped before syncing its directory:
     * sync it now (a file holding a record had its directory synced before the record). */
    struct stat st;
    if (fstat(fd, &st) != 0 || (st.st_size == 0 && sync_directory_of(path) != 0)) {
        const int saved = errno;
        (void)close(fd);
        errno = saved;
        return -1;
    }
    return fd;
}

void port_save_status_file(const char *path, void (*write)(const void *ctx, FILE *f),
                           const void *ctx)
{
    if (path == NULL) {
        write(ctx, stdout);
        return;
    }
    char tmp[PATH_MAX];
    if (snprintf(tmp, sizeof tmp, "%s.tmp.%ld", path, (long)getpid()) >= (int)sizeof tmp) {
        port_usage_error("--status-file %s: path too long", path);
    }
    FILE *f = fopen(tmp, "w");
    if (f == NULL) {
        (void)fprintf(stderr, "%s: status file %s: %s\n", PROG, tmp, strerror(errno));
        return;
    }
    write(ctx, f);
    const int ok = fflush(f) == 0 && fsync(fileno(f)) == 0;
    if (fclose(f) != 0 || !ok || rename(tmp, path) != 0) {
        (void)fprintf(stderr, "%s: status file %s: %s\n", PROG, path, strerror(errno));
        (void)unlink(tmp);
    }
}
