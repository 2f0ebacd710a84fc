/*
 * canergy-node's key file for --auth, canergy-gateway's for --upstream-auth (a node key) and
 * --auth (a master key) (ports/linux), as src/canergy/auth/keys.py reads one: a
 * regular file of mode 0600 or stricter and at most KEY_FILE_MAX bytes, checked before it is
 * opened and again once open, opened non-blocking and read to exactly its size; then the text
 * (kind=node, node=, epoch=, key=) for this node. A refusal exits 2 with one line; no message
 * ever holds a byte of the key, and the text is wiped after use.
 */
#define _GNU_SOURCE 1

#include "keyfile.h"

#include "port.h"

#include <errno.h>
#include <fcntl.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#define KEY_FILE_MAX 4096 /* keys.py KEY_FILE_MAX: far above what canergy keys writes */

static const char *key_flag = "--auth"; /* the flag that named the file, for refusals */

static void key_error(const char *path, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    (void)fprintf(stderr, "%s: error: %s %s: ", PROG, key_flag, path);
    (void)vfprintf(stderr, fmt, ap);
    (void)fputc('\n', stderr);
    va_end(ap);
    exit(EXIT_USAGE);
}

static int is_space(char c)
{
    return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f';
}

/* s without leading and trailing white space (in place). */
static char *trim(char *s)
{
    while (is_space(*s)) {
        s++;
    }
    size_t n = strlen(s);
    while (n > 0U && is_space(s[n - 1U])) {
        s[--n] = '\0';
    }
    return s;
}

static int hex_value(char c)
{
    if (c >= '0' && c <= '9') {
        return c - '0';
    }
    if (c >= 'a' && c <= 'f') {
        return c - 'a' + 10;
    }
    return (c >= 'A' && c <= 'F') ? c - 'A' + 10 : -1;
}

/* A decimal integer, at most max: 0 when text is not one. */
static int decimal(const char *text, unsigned long long max, unsigned long long *out)
{
    unsigned long long v = 0U;
    if (*text == '\0' || strlen(text) > 12U) {
        return 0;
    }
    for (; *text != '\0'; text++) {
        if (*text < '0' || *text > '9') {
            return 0;
        }
        v = v * 10U + (unsigned long long)(*text - '0');
    }
    *out = v;
    return v <= max;
}

struct key_fields {
    char *kind;
    char *node;
    char *epoch;
    char *key;
    int others;
};

static void key_field(const char *path, struct key_fields *k, char *line, int number)
{
    char *eq = strchr(line, '=');
    char **slot = NULL;
    if (eq != NULL) {
        *eq = '\0';
        const char *name = trim(line);
        slot = strcmp(name, "kind") == 0    ? &k->kind
               : strcmp(name, "node") == 0  ? &k->node
               : strcmp(name, "epoch") == 0 ? &k->epoch
               : strcmp(name, "key") == 0   ? &k->key
                                            : NULL;
    }
    if (eq == NULL || (slot != NULL && *slot != NULL)) {
        key_error(path, "line %d: expected one name=value per line", number);
    }
    if (slot == NULL) {
        k->others++; /* (two unknown names with the same spelling pass as one: no matter) */
    } else {
        *slot = trim(eq + 1);
    }
}

static const char *file_kind(mode_t mode)
{
    return S_ISFIFO(mode)  ? "a FIFO"
           : S_ISCHR(mode) ? "a character device"
           : S_ISBLK(mode) ? "a block device"
           : S_ISDIR(mode) ? "a directory"
           : S_ISSOCK(mode) ? "a socket"
                            : "of an unknown type";
}

/* A key file's size, checked as keys.py does: a regular file, mode 0600 or stricter, at most
 * KEY_FILE_MAX bytes. */
static size_t check_key_file(const char *path, const struct stat *st)
{
    if (!S_ISREG(st->st_mode)) {
        key_error(path, "not a regular file (%s)", file_kind(st->st_mode));
    }
    if ((st->st_mode & 077) != 0U) {
        key_error(path, "mode %04o lets others read it; chmod 600 %s",
                  (unsigned)(st->st_mode & 07777), path);
    }
    if (st->st_size > KEY_FILE_MAX) {
        key_error(path, "%lld bytes, more than a key file holds (%d)", (long long)st->st_size,
                  KEY_FILE_MAX);
    }
    return (size_t)st->st_size;
}

/* The key file's text (NUL-terminated) and its length: checked before it is opened (a device is
 * never opened), opened with O_NONBLOCK (a FIFO put there meanwhile cannot block), checked again
 * on the opened file, read to exactly its size. */
static size_t read_key_file(const char *path, char text[KEY_FILE_MAX + 2])
{
    struct stat st;
    if (stat(path, &st) != 0) {
        key_error(path, "cannot read the key file (%s)", strerror(errno));
    }
    (void)check_key_file(path, &st);
    const int fd = open(path, O_RDONLY | O_NONBLOCK | O_NOCTTY | O_CLOEXEC);
    if (fd < 0 || fstat(fd, &st) != 0) {
        key_error(path, "cannot read the key file (%s)", strerror(errno));
    }
    const size_t size = check_key_file(path, &st);
    size_t len = 0U;
    while (len <= size) { /* one byte more than its size: a file that grew shows it */
        const ssize_t n = read(fd, &text[len], size + 1U - len);
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n < 0) {
            key_error(path, "cannot read the key file (%s)", strerror(errno));
        }
        if (n == 0) {
            break;
        }
        len += (size_t)n;
    }
    (void)close(fd);
    if (len != size) {
        key_error(path, "changed while read (%zu bytes by its size, %zu)", size, len);
    }
    text[len] = '\0';
    return len;
}

/* The key of the key file at path: kind=node, node=for_node; for_node 0: kind=master, its epoch
 * in *epoch. */
static void load_key(const char *flag, const char *path, int for_node,
                     uint8_t key[CANERGY_KDF_KEY_SIZE], uint32_t *epoch_out)
{
    key_flag = flag;
    char text[KEY_FILE_MAX + 2];
    const size_t len = read_key_file(path, text);
    for (size_t i = 0U; i < len; i++) {
        if (text[i] == '\0' || (unsigned char)text[i] > 0x7FU) {
            key_error(path, "cannot read the key file (not ASCII text)");
        }
    }
    struct key_fields k = {NULL, NULL, NULL, NULL, 0};
    int number = 0;
    for (char *line = text; line != NULL;) {
        char *next = strchr(line, '\n');
        if (next != NULL) {
            *next++ = '\0';
        }
        number++;
        line = trim(line);
        if (*line != '\0' && *line != '#') {
            key_field(path, &k, line, number);
        }
        line = next;
    }
    if (k.kind == NULL || (strcmp(k.kind, "master") != 0 && strcmp(k.kind, "node") != 0)) {
        key_error(path, "kind must be master or node");
    }
    const int is_node = strcmp(k.kind, "node") == 0;
    if (k.others != 0 || k.epoch == NULL || k.key == NULL || (k.node != NULL) != is_node) {
        key_error(path, "a %s key file holds exactly epoch, key, kind%s", k.kind,
                  is_node ? ", node" : "");
    }
    unsigned long long epoch = 0U;
    unsigned long long node = 0U;
    const size_t digits = strlen(k.key);
    int hex_ok = digits % 2U == 0U;
    for (size_t i = 0U; i < digits; i++) {
        hex_ok &= hex_value(k.key[i]) >= 0;
    }
    if (!hex_ok || !decimal(k.epoch, ~0ULL, &epoch) || (is_node && !decimal(k.node, ~0ULL, &node))) {
        key_error(path, "key must be hex, epoch and node integers");
    }
    if (digits != 2U * CANERGY_KDF_KEY_SIZE) {
        key_error(path, "key must be %u bytes (%u hex digits)", CANERGY_KDF_KEY_SIZE,
                  2U * CANERGY_KDF_KEY_SIZE);
    }
    if (epoch > 0xFFFFFFFFULL) {
        key_error(path, "epoch must be 0 to 4294967295");
    }
    if (for_node == 0 && is_node) {
        key_error(path, "a node key; downstream the gateway is a supervisor and needs a master "
                        "key of its own (canergy keys -o GATEWAY.key)");
    }
    if (for_node == 0) {
        *epoch_out = (uint32_t)epoch;
    } else if (!is_node) {
        key_error(path, "a node takes its own node key, not the master key");
    } else if (node < CANERGY_MIN_NODE || node > CANERGY_MAX_NODE) {
        key_error(path, "node must be %u to %u", CANERGY_MIN_NODE, CANERGY_MAX_NODE);
    } else if (node != (unsigned long long)for_node) {
        key_error(path, "a key for node %llu cannot serve node %d", node, for_node);
    }
    for (size_t i = 0U; i < CANERGY_KDF_KEY_SIZE; i++) {
        key[i] = (uint8_t)(hex_value(k.key[2U * i]) << 4 | hex_value(k.key[2U * i + 1U]));
    }
    canergy_wipe(text, sizeof text);
}

void port_load_key(const char *flag, const char *path, int for_node,
                   uint8_t key[CANERGY_KDF_KEY_SIZE])
{
    load_key(flag, path, for_node, key, NULL); /* a node id: 1 or more */
}

void port_load_master_key(const char *flag, const char *path, uint8_t key[CANERGY_KDF_KEY_SIZE],
                          uint32_t *epoch)
{
    load_key(flag, path, 0, key, epoch);
}
