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
 * earliest of the
 * library's deadline, the actuator tick and the status write. Every canergy_out is carried out
 * in order: pwrite + fsync of the slot image, then the frames. kill -9 at any instant is safe.
 *
 * --auth: authenticated mode (canergy/auth.h) with the node's key file (src/canergy/auth/keys.py:
 * mode 0600, kind=node, this node's id; the key is never printed); --fd: CAN FD frames with a
 * 64-bit MAC, otherwise the classic layout (each frame followed by a MAC frame).
 *
 * Exit status: 0 after SIGINT/SIGTERM (final status written), 1 when the NV file cannot be
 * written (the node stops without sending what that step produced), 2 for bad arguments or a
 * socket or file that cannot be opened.
 */
#define _GNU_SOURCE 1

#include "canergy/auth.h"
#include "canergy/node.h"

#include <errno.h>
#include <fcntl.h>
#include <libgen.h>
#include <limits.h>
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/random.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#define PROG "canergy-node"
#define EXIT_NV 1
#define EXIT_USAGE 2
#define US_PER_S 1000000ULL
#define MAX_DURATION_US (7ULL * 24U * 3600U * US_PER_S) /* a week, as the Python flags */
#define MAX_QUANTITY_U (1000000000ULL * 1000000ULL)     /* 1 GJ, 1 GW */
#define SEND_ATTEMPTS 6
#define NV_IMAGE_BYTES (CANERGY_NV_SLOTS * CANERGY_NV_SLOT_SIZE)

struct options {
    const char *interface;
    const char *channel;
    const char *nv_path;
    const char *status_path;
    uint64_t power_uw;
    uint64_t tick_us;
    uint64_t telemetry_period_us;
    uint64_t response_timeout_us;
    uint64_t status_period_us;
    uint64_t low_water_uj;
    uint64_t return_above_uj;
    uint32_t id_base;
    const char *auth_path;
    int node;
    int keep_all;
    int fd;
};

/* What firmware_model's BusRuntime counts, with the same names in the status file. */
struct counters {
    uint64_t frames_sent;
    uint64_t frames_received;
    uint64_t decode_errors;
    uint64_t reasons[CANERGY_DECODE_OUT_OF_RANGE + 1];
    uint64_t foreign_frames;
    uint64_t send_retries;
    uint64_t send_failures;
    uint64_t receive_errors;
    uint64_t error_frames;
    uint64_t auth_failures[CANERGY_AUTH_UNAUTHENTICATED - CANERGY_AUTH_MAC_BAD + 1];
};

/* firmware_model's intrusion report: a count, when the first came, the latest few. */
#define INTRUSIONS_KEPT 20U
#define FRAME_TEXT 140U /* "0CE00D05#" and 64 bytes in hex */

struct intrusion {
    uint64_t time_us;
    const char *kind;
    char frame[FRAME_TEXT];
};

struct intrusions {
    uint64_t total;
    uint64_t first_at_us;
    struct intrusion recent[INTRUSIONS_KEPT]; /* a ring: the newest at (total - 1) % KEPT */
};

struct port {
    struct options opt;
    struct canergy_node node;
    struct counters count;
    struct intrusions intrusions;
    struct canergy_auth auth; /* with --auth */
    uint64_t drawn_uj;
    uint64_t remainder_pj; /* energy owed below 1 uJ, in uW*us, as firmware_model's actuator */
    uint64_t last_draw_us;
    uint64_t nv_writes;
    uint64_t witnessed; /* the library's witness, not wrapped: firmware_model's "witnessed" */
    int nv_fallbacks;
    int joins;
    int sock;
    int nv_fd;
};

static volatile sig_atomic_t stop_requested;

static void on_stop_signal(int signum)
{
    (void)signum;
    stop_requested = 1;
}

static void usage_error(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    (void)fprintf(stderr, "%s: error: ", PROG);
    (void)vfprintf(stderr, fmt, ap);
    (void)fputc('\n', stderr);
    va_end(ap);
    exit(EXIT_USAGE);
}

static uint64_t now_us(void)
{
    struct timespec ts;
    if (clock_gettime(CLOCK_MONOTONIC, &ts) != 0) {
        perror(PROG ": clock_gettime");
        exit(EXIT_NV);
    }
    return (uint64_t)ts.tv_sec * US_PER_S + (uint64_t)ts.tv_nsec / 1000U;
}

/* ---- quantities: "0.5J", "250mJ", "1.5s", "200mW", "2" (plain: the kind's base unit) ---- */

struct unit {
    const char *name;  /* lower case; "" is a plain number */
    uint64_t factor;   /* micro-units per unit */
};

static const struct unit ENERGY_UNITS[] = {
    {"", 1000000U}, {"j", 1000000U}, {"kj", 1000000000U}, {"mj", 1000U}, {"uj", 1U},
    {"\xc2\xb5j", 1U}, {NULL, 0U}};
static const struct unit POWER_UNITS[] = {
    {"", 1000000U}, {"w", 1000000U}, {"kw", 1000000000U}, {"mw", 1000U}, {"uw", 1U},
    {"\xc2\xb5w", 1U}, {NULL, 0U}};
static const struct unit DURATION_UNITS[] = {
    {"", 1000000U}, {"s", 1000000U}, {"ms", 1000U}, {"us", 1U}, {"\xc2\xb5s", 1U},
    {"min", 60000000U}, {"h", 3600000000U}, {NULL, 0U}};

/* Multiply with an overflow check: 0 when a * b would not fit. */
static int mul_fits(uint64_t a, uint64_t b, uint64_t *out)
{
    if (a != 0U && b > UINT64_MAX / a) {
        return 0;
    }
    *out = a * b;
    return 1;
}

/* Parse text as a non-negative decimal (optional fraction and exponent) with a unit from
 * units; the value in micro-units, exact, at most max. Exits 2 with one line otherwise. */
static uint64_t parse_quantity(const char *flag, const char *text, const struct unit *units,
                               uint64_t max, const char *examples)
{
    char digits[72];
    size_t nd = 0U;
    long exp10 = 0;
    int seen_digit = 0;
    int seen_dot = 0;
    const char *p = text;
    if (strlen(text) > 64U) {
        usage_error("argument %s: %.16s... is over 64 characters", flag, text);
    }
    while (*p == ' ' || *p == '\t') {
        p++;
    }
    if (*p == '-') {
        usage_error("argument %s: '%s' is negative", flag, text);
    }
    for (; (*p >= '0' && *p <= '9') || (*p == '.' && !seen_dot); p++) {
        if (*p == '.') {
            seen_dot = 1;
            continue;
        }
        seen_digit = 1;
        if (nd == 0U && *p == '0') {
            if (seen_dot) {
                exp10--;
            }
            continue; /* leading zeros carry no digit */
        }
        digits[nd++] = *p;
        if (seen_dot) {
            exp10--;
        }
    }
    if (!seen_digit || p[-1] == '.') {
        usage_error("argument %s: '%s' (expected e.g. %s)", flag, text, examples);
    }
    if (*p == 'e' || *p == 'E') {
        char *end = NULL;
        errno = 0;
        const long e = strtol(p + 1, &end, 10);
        if (end == p + 1 || (p[1] == ' ') || errno != 0 || e > 200 || e < -200) {
            usage_error("argument %s: '%s' (expected e.g. %s)", flag, text, examples);
        }
        exp10 += e;
        p = end;
    }
    while (*p == ' ' || *p == '\t') {
        p++;
    }
    const int mega = *p == 'M';
    char unit[8];
    size_t nu = 0U;
    while (*p != '\0' && *p != ' ' && *p != '\t') {
        if (nu + 1U >= sizeof unit) {
            usage_error("argument %s: unknown unit in '%s' (expected e.g. %s)", flag, text,
                        examples);
        }
        const char c = *p++;
        unit[nu++] = (c >= 'A' && c <= 'Z') ? (char)(c - 'A' + 'a') : c;
    }
    unit[nu] = '\0';
    while (*p == ' ' || *p == '\t') {
        p++;
    }
    if (*p != '\0') {
        usage_error("argument %s: '%s' (expected e.g. %s)", flag, text, examples);
    }
    uint64_t factor = 0U;
    for (const struct unit *u = units; u->name != NULL; u++) {
        if (mega && strcmp(u->name, &unit[1]) == 0) {
            usage_error("argument %s: mega-units are not supported: '%s' (did you mean m%s?)",
                        flag, text, &unit[1]);
        }
        if (strcmp(u->name, unit) == 0) {
            factor = u->factor;
        }
    }
    if (factor == 0U) {
        usage_error("argument %s: unknown unit '%s' in '%s' (expected e.g. %s)", flag, unit, text,
                    examples);
    }
    /* value = digits * 10^exp10 * factor; drop trailing zeros into the exponent first */
    while (nd > 0U && digits[nd - 1U] == '0') {
        nd--;
        exp10++;
    }
    if (nd == 0U) {
        return 0U;
    }
    while (factor % 10U == 0U && exp10 < 0) {
        factor /= 10U;
        exp10++;
    }
    if (nd > 19U) {
        usage_error("argument %s: '%s' is too large or not a whole number of micro-units", flag,
                    text);
    }
    uint64_t mant = 0U;
    for (size_t i = 0U; i < nd; i++) {
        mant = mant * 10U + (uint64_t)(digits[i] - '0');
    }
    uint64_t value = 0U;
    if (!mul_fits(mant, factor, &value)) {
        usage_error("argument %s: '%s' is too large", flag, text);
    }
    for (; exp10 > 0; exp10--) {
        if (!mul_fits(value, 10U, &value)) {
            usage_error("argument %s: '%s' is too large", flag, text);
        }
    }
    for (; exp10 < 0; exp10++) {
        if (value % 10U != 0U) {
            usage_error("argument %s: '%s' is not a whole number of micro-units", flag, text);
        }
        value /= 10U;
    }
    if (value > max) {
        usage_error("argument %s: '%s' is too large", flag, text);
    }
    return value;
}

static uint64_t parse_duration(const char *flag, const char *text, uint64_t max)
{
    const uint64_t us = parse_quantity(flag, text, DURATION_UNITS, MAX_DURATION_US,
                                       "50ms, 1.5s, 200us, 2min or 0.5 (seconds)");
    if (us == 0U) {
        usage_error("argument %s: a duration must be more than zero: '%s'", flag, text);
    }
    if (us > max) {
        usage_error("argument %s: '%s' is too long for this port (at most %llu s)", flag, text,
                    (unsigned long long)(max / US_PER_S));
    }
    return us;
}

static uint64_t parse_int(const char *flag, const char *text, uint64_t low, uint64_t high)
{
    char *end = NULL;
    errno = 0;
    if (text[0] == '-' || text[0] == '\0' || strlen(text) > 32U) {
        usage_error("argument %s: not an integer in %llu..%llu: '%s'", flag,
                    (unsigned long long)low, (unsigned long long)high, text);
    }
    int base = 10;
    const char *digits = text;
    if (text[0] == '0' && (text[1] == 'x' || text[1] == 'X')) {
        base = 16;
        digits = text + 2;
    } else if (text[0] == '0' && (text[1] == 'o' || text[1] == 'O')) {
        base = 8;
        digits = text + 2;
    } else if (text[0] == '0' && (text[1] == 'b' || text[1] == 'B')) {
        base = 2;
        digits = text + 2;
    }
    const unsigned long long v = strtoull(digits, &end, base);
    if (errno != 0 || end == digits || *end != '\0') {
        usage_error("argument %s: not an integer: '%s'", flag, text);
    }
    if (v < low || v > high) {
        usage_error("argument %s: %llu outside %llu..%llu", flag, v, (unsigned long long)low,
                    (unsigned long long)high);
    }
    return (uint64_t)v;
}

/* ---- paths: two names for one file (canergy.live.atomic.same_file) ---- */

/* dst = src, or a usage error naming what was too long. */
static void copy_path(char dst[PATH_MAX], const char *src)
{
    if (snprintf(dst, PATH_MAX, "%s", src) >= PATH_MAX) {
        usage_error("path too long: %.64s...", src);
    }
}

/* dst = "dir/name" ("/name" when dir is "/"), or a usage error naming what was too long. */
static void join_path(char dst[PATH_MAX], const char *dir, const char *name)
{
    const char *sep = strcmp(dir, "/") == 0 ? "" : "/";
    if (snprintf(dst, PATH_MAX, "%s%s%s", dir, sep, name) >= PATH_MAX) {
        usage_error("path too long: %.64s...", name);
    }
}

/* A path that does not exist: its resolved directory and its last part (as written when the
 * directory does not exist either: nothing can be created there). */
static void resolve_missing(const char *p, char out[PATH_MAX])
{
    char dir[PATH_MAX];
    char base[PATH_MAX];
    char real_dir[PATH_MAX];
    copy_path(dir, p);
    copy_path(base, p);
    if (realpath(dirname(dir), real_dir) == NULL) {
        copy_path(out, p);
    } else {
        join_path(out, real_dir, basename(base));
    }
}

/* path's file once symlinks are resolved, as Python's Path.resolve(): a missing file (the target
 * of a dangling symlink too) is named below its resolved directory. */
static void resolve(const char *path, char out[PATH_MAX])
{
    char p[PATH_MAX];
    copy_path(p, path);
    for (int hops = 0; hops < 40; hops++) {
        if (realpath(p, out) != NULL) {
            return;
        }
        char target[PATH_MAX];
        const ssize_t n = readlink(p, target, sizeof target - 1U);
        if (n < 0) { /* not a symlink: missing */
            resolve_missing(p, out);
            return;
        }
        target[n] = '\0';
        char dir[PATH_MAX];
        copy_path(dir, p);
        if (target[0] == '/') {
            copy_path(p, target);
        } else {
            join_path(p, dirname(dir), target);
        }
    }
    copy_path(out, p); /* a symlink loop: as written */
}

/* a and b name one file: the same inode when both exist (hard links too), otherwise the same
 * path once resolved. */
static int same_file(const char *a, const char *b)
{
    struct stat sa;
    struct stat sb;
    if (stat(a, &sa) == 0 && stat(b, &sb) == 0) {
        return sa.st_dev == sb.st_dev && sa.st_ino == sb.st_ino;
    }
    char ra[PATH_MAX];
    char rb[PATH_MAX];
    resolve(a, ra);
    resolve(b, rb);
    return strcmp(ra, rb) == 0;
}

static void parse_args(int argc, char **argv, struct options *o)
{
    memset(o, 0, sizeof *o);
    o->tick_us = 100000U;
    o->telemetry_period_us = 1000000U;
    o->response_timeout_us = 100000U;
    o->status_period_us = 1000000U;
    o->id_base = (uint32_t)CANERGY_DEFAULT_ID_BASE;
    o->keep_all = 1;
    for (int i = 1; i < argc; i++) {
        const char *flag = argv[i];
        if (strcmp(flag, "-h") == 0 || strcmp(flag, "--help") == 0) {
            (void)printf("usage: %s --node N -i socketcan -c CHANNEL --nv PATH [--power P]\n"
                         "       [--status-file PATH] [--status-period T] [--tick T]\n"
                         "       [--telemetry-period T] [--low-water E] [--return-above E]\n"
                         "       [--response-timeout T] [--id-base ID] [--auth KEY [--fd]]\n"
                         "One canergy client node on Linux SocketCAN (the C library's node\n"
                         "layer); flags as python -m firmware_model --node N. Energies 0.5J,\n"
                         "250mJ; powers 0.2W, 200mW; durations 50ms, 1.5s or plain seconds.\n"
                         "--auth: authenticated mode with this node's key file (mode 0600);\n"
                         "--fd: CAN FD (64-bit MAC; the interface needs mtu 72).\n",
                         PROG);
            exit(0);
        }
        if (strcmp(flag, "--fd") == 0) {
            o->fd = 1;
            continue;
        }
        if (i + 1 >= argc) {
            usage_error("argument %s: expected one argument", flag);
        }
        const char *v = argv[++i];
        if (strcmp(flag, "--node") == 0) {
            o->node = (int)parse_int(flag, v, CANERGY_MIN_NODE, CANERGY_MAX_NODE);
        } else if (strcmp(flag, "-i") == 0 || strcmp(flag, "--interface") == 0) {
            o->interface = v;
        } else if (strcmp(flag, "-c") == 0 || strcmp(flag, "--channel") == 0) {
            o->channel = v;
        } else if (strcmp(flag, "--nv") == 0) {
            o->nv_path = v;
        } else if (strcmp(flag, "--status-file") == 0) {
            o->status_path = v;
        } else if (strcmp(flag, "--power") == 0) {
            o->power_uw = parse_quantity(flag, v, POWER_UNITS, MAX_QUANTITY_U,
                                         "0.5W, 200mW or 2");
        } else if (strcmp(flag, "--tick") == 0) {
            o->tick_us = parse_duration(flag, v, MAX_DURATION_US);
        } else if (strcmp(flag, "--telemetry-period") == 0) {
            o->telemetry_period_us = parse_duration(flag, v, UINT32_MAX);
        } else if (strcmp(flag, "--status-period") == 0) {
            o->status_period_us = parse_duration(flag, v, MAX_DURATION_US);
        } else if (strcmp(flag, "--response-timeout") == 0) {
            o->response_timeout_us = parse_duration(flag, v, UINT32_MAX / 2U);
        } else if (strcmp(flag, "--low-water") == 0) {
            o->low_water_uj = parse_quantity(flag, v, ENERGY_UNITS, MAX_QUANTITY_U,
                                             "10J, 250mJ, 1500uJ or 2.5");
        } else if (strcmp(flag, "--return-above") == 0) {
            o->return_above_uj = parse_quantity(flag, v, ENERGY_UNITS, MAX_QUANTITY_U,
                                                "10J, 250mJ, 1500uJ or 2.5");
            o->keep_all = 0;
        } else if (strcmp(flag, "--auth") == 0) {
            o->auth_path = v;
        } else if (strcmp(flag, "--id-base") == 0) {
            o->id_base = (uint32_t)parse_int(flag, v, 0U, CAN_EFF_MASK);
            if (!canergy_id_base_valid(o->id_base)) {
                usage_error("argument %s: id base 0x%08X has bits in its low 12 (mask 0x1FFFF000)",
                            flag, (unsigned)o->id_base);
            }
        } else {
            usage_error("unrecognized argument: %s", flag);
        }
    }
    if (o->node == 0 || o->nv_path == NULL || o->channel == NULL) {
        usage_error("the following arguments are required: --node, -c/--channel, --nv");
    }
    if (o->interface != NULL && strcmp(o->interface, "socketcan") != 0) {
        usage_error("argument -i: this port speaks socketcan only, not '%s'", o->interface);
    }
    if (o->status_path != NULL && same_file(o->nv_path, o->status_path)) {
        usage_error("--nv %s and --status-file %s name the same file; give each its own path",
                    o->nv_path, o->status_path);
    }
}

/* ---- key file (src/canergy/auth/keys.py): no message ever holds a byte of the key ---- */

#define KEY_FILE_MAX 4096 /* keys.py KEY_FILE_MAX: far above what canergy keys writes */

static void key_error(const char *path, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    (void)fprintf(stderr, "%s: error: --auth %s: ", PROG, path);
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

/* The node's key from the key file at o->auth_path (kind=node, node=o->node). */
static void load_key(const struct options *o, uint8_t key[CANERGY_KDF_KEY_SIZE])
{
    const char *path = o->auth_path;
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
    if (!is_node) {
        key_error(path, "a node takes its own node key, not the master key");
    }
    if (node < CANERGY_MIN_NODE || node > CANERGY_MAX_NODE) {
        key_error(path, "node must be %u to %u", CANERGY_MIN_NODE, CANERGY_MAX_NODE);
    }
    if (node != (unsigned long long)o->node) {
        key_error(path, "a key for node %llu cannot serve node %d", node, o->node);
    }
    for (size_t i = 0U; i < CANERGY_KDF_KEY_SIZE; i++) {
        key[i] = (uint8_t)(hex_value(k.key[2U * i]) << 4 | hex_value(k.key[2U * i + 1U]));
    }
    canergy_wipe(text, sizeof text);
}

/* ---- bus ---- */

static int open_can(const struct options *o)
{
    const int s = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (s < 0) {
        (void)fprintf(stderr, "%s: error: CAN socket: %s\n", PROG, strerror(errno));
        exit(EXIT_USAGE);
    }
    if (strlen(o->channel) >= IFNAMSIZ) {
        usage_error("argument -c: interface name '%s' is too long", o->channel);
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
            usage_error("--fd: %s is not a CAN FD interface (ip link set %s mtu 72)", o->channel,
                        o->channel);
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

/* One frame: classic up to 8 bytes, CAN FD with bit rate switch above (FD layout). */
static void send_frame(struct port *p, uint32_t id, const uint8_t *data, size_t len)
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
        const ssize_t n = send(p->sock, &cf, size, 0);
        if (n == (ssize_t)size) {
            p->count.frames_sent++;
            return;
        }
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n < 0 && (errno == ENOBUFS || errno == EAGAIN) && attempt + 1 < SEND_ATTEMPTS) {
            p->count.send_retries++;
            (void)nanosleep(&backoff, NULL);
            backoff.tv_nsec = backoff.tv_nsec * 2 > 50000000L ? 50000000L : backoff.tv_nsec * 2;
            continue;
        }
        break;
    }
    p->count.send_failures++; /* lost, as far as the protocol goes: it re-sends what matters */
}

/* The persist-before-send contract: the slot image is on disk before any frame leaves. */
static void carry_out(struct port *p, const struct canergy_out *out)
{
    if (out->persist) {
        const off_t at = (off_t)out->nv_slot * (off_t)CANERGY_NV_SLOT_SIZE;
        const ssize_t n = pwrite(p->nv_fd, out->nv_image, CANERGY_NV_SLOT_SIZE, at);
        if (n != (ssize_t)CANERGY_NV_SLOT_SIZE || fsync(p->nv_fd) != 0) {
            (void)fprintf(stderr, "%s: NV store: %s: write failed: %s\n", PROG, p->opt.nv_path,
                          n < 0 ? strerror(errno) : "short write or fsync");
            _exit(EXIT_NV); /* reset: never send what this step produced */
        }
        p->nv_writes++;
    }
    for (unsigned i = 0U; i < out->frame_count; i++) {
        const struct canergy_frame *f = &out->frames[i];
        if (p->opt.auth_path == NULL) {
            send_frame(p, f->id, f->data, f->dlc);
            continue;
        }
        struct canergy_auth_frame frames[2];
        const int n = canergy_auth_node_protect(&p->auth, &p->node, f, frames);
        for (int k = 0; k < n; k++) {
            send_frame(p, frames[k].id, frames[k].data, frames[k].len);
        }
    }
}

/* ---- NV file ---- */

static void open_nv(struct port *p, uint8_t image[NV_IMAGE_BYTES], size_t *len)
{
    p->nv_fd = open(p->opt.nv_path, O_RDWR | O_CREAT | O_CLOEXEC, 0644);
    if (p->nv_fd < 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, p->opt.nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
    /* an existing file of another size is not an NV file: the first record would overwrite it
     * (0: new; two slots; three with firmware_model's CANopen parameter slot) */
    struct stat size;
    if (fstat(p->nv_fd, &size) == 0 && size.st_size != 0 &&
        size.st_size != (off_t)NV_IMAGE_BYTES &&
        size.st_size != (off_t)(NV_IMAGE_BYTES + CANERGY_NV_SLOT_SIZE)) {
        (void)fprintf(stderr, "%s: error: --nv %s: %lld bytes is not an NV file of canergy\n",
                      PROG, p->opt.nv_path, (long long)size.st_size);
        exit(EXIT_USAGE);
    }
    ssize_t n;
    do {
        n = pread(p->nv_fd, image, NV_IMAGE_BYTES, 0);
    } while (n < 0 && errno == EINTR);
    if (n < 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, p->opt.nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
    *len = (size_t)n;
    /* as firmware_model: the file always holds both record slots (never shrunk: the
     * parameter slot at 80 stays as it is) */
    struct stat st;
    if (fstat(p->nv_fd, &st) == 0 && st.st_size < (off_t)NV_IMAGE_BYTES &&
        ftruncate(p->nv_fd, (off_t)NV_IMAGE_BYTES) != 0) {
        (void)fprintf(stderr, "%s: error: --nv %s: %s\n", PROG, p->opt.nv_path, strerror(errno));
        exit(EXIT_USAGE);
    }
}

static uint16_t random16(void)
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

/* ---- status file (the keys of firmware_model's single-node status) ---- */

static const char *const REASONS[] = {
    "", "not a canergy identifier", "unknown message type", "node id out of range",
    "remote frame", "message sent the wrong way", "wrong data length", "CRC mismatch",
    "field out of range"};

/* Python's AuthFailure values, indexed by CANERGY_AUTH_MAC_BAD .. _UNAUTHENTICATED. */
static const char *const AUTH_FAILURES[] = {
    "MAC BAD", "freshness not the expected one", "MAC frame without its message",
    "malformed authenticated frame", "frame without a MAC"};

/* "intrusions" and "intrusion_report" as firmware_model's Intrusions.as_json */
static void write_intrusions(const struct port *p, FILE *f)
{
    const struct intrusions *in = &p->intrusions;
    (void)fprintf(f, "\"intrusions\": %llu, \"intrusion_report\": {\"total\": %llu, \"by_node\": {",
                  (unsigned long long)in->total, (unsigned long long)in->total);
    if (in->total != 0U) {
        (void)fprintf(f, "\"%d\": %llu}, \"first_at_us\": %llu, \"recent\": [", p->opt.node,
                      (unsigned long long)in->total, (unsigned long long)in->first_at_us);
    } else {
        (void)fprintf(f, "}, \"first_at_us\": null, \"recent\": [");
    }
    const uint64_t kept = in->total < INTRUSIONS_KEPT ? in->total : INTRUSIONS_KEPT;
    for (uint64_t i = in->total - kept; i < in->total; i++) { /* oldest first */
        const struct intrusion *e = &in->recent[i % INTRUSIONS_KEPT];
        (void)fprintf(f, "%s{\"time_us\": %llu, \"node\": %d, \"kind\": \"%s\", \"frame\": \"%s\"}",
                      i == in->total - kept ? "" : ", ", (unsigned long long)e->time_us,
                      p->opt.node, e->kind, e->frame);
    }
    (void)fprintf(f, "]}, ");
}

static void write_status(const struct port *p, FILE *f)
{
    const struct canergy_record *r = &p->node.client.rec;
    const long long credited = (long long)r->credited_mj * 1000LL;
    const long long returned = credited - (long long)r->spent_uj - (long long)r->usable_uj;
    (void)fprintf(f,
                  "{\"node\": %d, \"usable_uj\": %lu, \"spent_uj\": %llu, \"credited_uj\": %lld, "
                  "\"returned_uj\": %lld, \"return_pending_uj\": %lu, \"return_seq\": %lu, "
                  "\"last_tx\": %lu, \"halted\": %s, \"drawn_uj\": %llu, \"nv_writes\": %llu, "
                  "\"nv_fallbacks\": %d, \"nmt_state\": \"OPERATIONAL\", "
                  "\"intentions_refused\": 0, \"overflow_refused\": %lu, \"joining\": %s, "
                  "\"joins\": %d, \"implementation\": \"c\", ",
                  p->opt.node, (unsigned long)r->usable_uj, (unsigned long long)r->spent_uj,
                  credited, returned, (unsigned long)r->return_pending_uj,
                  (unsigned long)r->return_seq, (unsigned long)r->last_tx,
                  p->node.halted ? "true" : "false", (unsigned long long)p->drawn_uj,
                  (unsigned long long)p->nv_writes, p->nv_fallbacks,
                  (unsigned long)p->node.overflow_refused,
                  canergy_client_joining(&p->node.client) ? "true" : "false", p->joins);
    (void)fprintf(f, "\"witnessed\": %llu, ", (unsigned long long)p->witnessed);
    write_intrusions(p, f);
    (void)fprintf(f,
                  "\"frames_sent\": %llu, \"frames_received\": %llu, \"decode_errors\": %llu, "
                  "\"decode_error_reasons\": {",
                  (unsigned long long)p->count.frames_sent,
                  (unsigned long long)p->count.frames_received,
                  (unsigned long long)p->count.decode_errors);
    const char *sep = "";
    for (unsigned i = 1U; i <= CANERGY_DECODE_OUT_OF_RANGE; i++) {
        if (p->count.reasons[i] != 0U) {
            (void)fprintf(f, "%s\"%s\": %llu", sep, REASONS[i],
                          (unsigned long long)p->count.reasons[i]);
            sep = ", ";
        }
    }
    (void)fprintf(f,
                  "}, \"foreign_frames\": %llu, \"send_retries\": %llu, \"send_failures\": %llu, "
                  "\"receive_errors\": %llu, \"error_frames\": %llu, \"bus_state\": \"%s\", "
                  "\"auth_failures\": {",
                  (unsigned long long)p->count.foreign_frames,
                  (unsigned long long)p->count.send_retries,
                  (unsigned long long)p->count.send_failures,
                  (unsigned long long)p->count.receive_errors,
                  (unsigned long long)p->count.error_frames, "unknown");
    sep = "";
    for (size_t i = 0U; i < sizeof AUTH_FAILURES / sizeof AUTH_FAILURES[0]; i++) {
        if (p->count.auth_failures[i] != 0U) {
            (void)fprintf(f, "%s\"%s\": %llu", sep, AUTH_FAILURES[i],
                          (unsigned long long)p->count.auth_failures[i]);
            sep = ", ";
        }
    }
    (void)fprintf(f, "}}\n");
}

/* temp file + fsync + rename: a reader sees the old or the new status, never half of one */
static void save_status(const struct port *p)
{
    if (p->opt.status_path == NULL) {
        write_status(p, stdout);
        return;
    }
    char tmp[PATH_MAX];
    if (snprintf(tmp, sizeof tmp, "%s.tmp.%ld", p->opt.status_path, (long)getpid()) >=
        (int)sizeof tmp) {
        usage_error("--status-file %s: path too long", p->opt.status_path);
    }
    FILE *f = fopen(tmp, "w");
    if (f == NULL) {
        (void)fprintf(stderr, "%s: status file %s: %s\n", PROG, tmp, strerror(errno));
        return;
    }
    write_status(p, f);
    const int ok = fflush(f) == 0 && fsync(fileno(f)) == 0;
    if (fclose(f) != 0 || !ok || rename(tmp, p->opt.status_path) != 0) {
        (void)fprintf(stderr, "%s: status file %s: %s\n", PROG, p->opt.status_path,
                      strerror(errno));
        (void)unlink(tmp);
    }
}

/* ---- the loop ---- */

/* What the actuator wants for the time since its last period, firmware_model's integration:
 * power (uW) * dt (us) in pJ, the sub-uJ remainder carried. */
static uint32_t actuator_need(struct port *p, uint64_t now)
{
    const uint64_t dt = now > p->last_draw_us ? now - p->last_draw_us : 0U;
    p->last_draw_us = now;
    uint64_t pj = 0U;
    if (!mul_fits(p->opt.power_uw, dt, &pj) || pj > UINT64_MAX - p->remainder_pj) {
        p->remainder_pj = 0U;
        return UINT32_MAX; /* more than any budget holds */
    }
    pj += p->remainder_pj;
    p->remainder_pj = pj % 1000000U;
    const uint64_t uj = pj / 1000000U;
    return uj > UINT32_MAX ? UINT32_MAX : (uint32_t)uj;
}

/* candump's compact form, as firmware_model's frame_text: 0CE00905#450100 */
static void frame_text(char out[FRAME_TEXT], uint32_t id, bool remote, const uint8_t *data,
                       size_t len)
{
    int at = snprintf(out, FRAME_TEXT, "%08X#%s", (unsigned)id, remote ? "R" : "");
    for (size_t i = 0U; !remote && i < len && at + 3 <= (int)FRAME_TEXT; i++) {
        at += snprintf(&out[at], FRAME_TEXT - (size_t)at, "%02X", (unsigned)data[i]);
    }
}

static void record_intrusion(struct port *p, const char *kind, const struct canergy_rx_frame *rx,
                             uint64_t now)
{
    struct intrusions *in = &p->intrusions;
    struct intrusion *e = &in->recent[in->total % INTRUSIONS_KEPT];
    if (in->total == 0U) {
        in->first_at_us = now;
    }
    in->total++;
    e->time_us = now;
    e->kind = kind;
    frame_text(e->frame, rx->id, rx->remote, rx->data, rx->len);
    if (in->total == 1U || in->total % 100U == 0U) { /* as firmware_model logs them */
        (void)fprintf(stderr, "%s: node %d: intrusion #%llu: %s (%s)\n", PROG, p->opt.node,
                      (unsigned long long)in->total, e->frame, kind);
    }
}

static void receive_one(struct port *p, const struct canergy_rx_frame *rx)
{
    const uint64_t now = now_us();
    struct canergy_out out;
    const uint8_t witness = p->node.witness;
    const int status = p->opt.auth_path != NULL
                           ? canergy_auth_node_frame(&p->auth, &p->node, rx, now, &out)
                           : canergy_node_on_frame(&p->node, rx, now, &out);
    p->witnessed += (uint8_t)(p->node.witness - witness); /* 0 or 1 per frame */
    if (status == CANERGY_DECODE_FOREIGN || status == CANERGY_RX_OTHER_NODE) {
        p->count.foreign_frames++;
    } else if (status == CANERGY_DECODE_WRONG_DIRECTION) {
        /* its own direction (MAC frames 0x8 too) with its id, as the filter passes no other
         * node's: a node never receives its own frames back, so someone speaks in its name. The
         * library counted it in the witness of its next TELEMETRY. */
        if ((rx->id & 0xFFU) == (uint32_t)p->opt.node) {
            record_intrusion(p, "a frame in its name", rx, now);
        }
    } else if (status > 0 && status <= (int)CANERGY_DECODE_OUT_OF_RANGE) {
        p->count.decode_errors++;
        p->count.reasons[status]++;
    } else if (status >= CANERGY_AUTH_MAC_BAD && status <= CANERGY_AUTH_UNAUTHENTICATED) {
        const size_t reason = (size_t)(status - CANERGY_AUTH_MAC_BAD);
        p->count.auth_failures[reason]++; /* moves nothing; an intrusion, as in Python */
        record_intrusion(p, AUTH_FAILURES[reason], rx, now);
    }
    carry_out(p, &out);
}

static void receive_all(struct port *p)
{
    for (;;) {
        struct canfd_frame cf; /* CAN_MTU bytes of it for a classic frame */
        const ssize_t n = recv(p->sock, &cf, sizeof cf, MSG_DONTWAIT);
        if (n < 0) {
            if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
                p->count.receive_errors++;
            }
            return;
        }
        if (n != (ssize_t)CAN_MTU && n != (ssize_t)CANFD_MTU) {
            p->count.receive_errors++;
            continue;
        }
        if ((cf.can_id & CAN_ERR_FLAG) != 0U) {
            p->count.error_frames++;
            continue;
        }
        p->count.frames_received++;
        const bool extended = (cf.can_id & CAN_EFF_FLAG) != 0U;
        struct canergy_rx_frame rx;
        rx.id = (uint32_t)(cf.can_id & (extended ? CAN_EFF_MASK : CAN_SFF_MASK));
        rx.data = cf.data;
        rx.len = cf.len <= CANFD_MAX_DLEN ? cf.len : CANFD_MAX_DLEN;
        rx.extended = extended;
        rx.remote = (cf.can_id & CAN_RTR_FLAG) != 0U;
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

    parse_args(argc, argv, &p.opt);
    if (p.opt.auth_path != NULL) {
        uint8_t key[CANERGY_KDF_KEY_SIZE];
        load_key(&p.opt, key);
        const int ok = canergy_auth_init(&p.auth, key, p.opt.id_base, (uint8_t)p.opt.node,
                                         p.opt.fd ? CANERGY_AUTH_FD : CANERGY_AUTH_CLASSIC,
                                         CANERGY_TO_CLIENT);
        canergy_wipe(key, sizeof key);
        if (ok != CANERGY_OK) {
            usage_error("--auth: bad node or id base");
        }
    }
    p.sock = open_can(&p.opt);
    uint8_t image[NV_IMAGE_BYTES];
    size_t image_len = 0U;
    open_nv(&p, image, &image_len);

    const struct canergy_node_config cfg = {
        .client = {.id_base = p.opt.id_base,
                   .command_timeout_us = (uint32_t)(2U * p.opt.response_timeout_us),
                   .return_retry_us = (uint32_t)(2U * p.opt.response_timeout_us),
                   .node = (uint8_t)p.opt.node},
        .telemetry_period_us = (uint32_t)p.opt.telemetry_period_us,
        .low_water_uj = p.opt.low_water_uj > UINT32_MAX ? UINT32_MAX
                                                        : (uint32_t)p.opt.low_water_uj,
        .return_above_uj = (p.opt.keep_all || p.opt.return_above_uj >= CANERGY_KEEP_ALL)
                               ? (uint32_t)CANERGY_KEEP_ALL
                               : (uint32_t)p.opt.return_above_uj,
    };
    struct canergy_out out;
    uint64_t now = now_us();
    const uint16_t nonce = random16();
    const int fallbacks = canergy_node_start(&p.node, &cfg, image, image_len, nonce, now, &out);
    if (fallbacks < 0) {
        usage_error("bad node configuration");
    }
    p.nv_fallbacks = fallbacks;
    p.joins = canergy_client_joining(&p.node.client) ? 1 : 0;
    if (p.joins && p.opt.auth_path != NULL) {
        canergy_auth_set_join(&p.auth, random16(), nonce); /* a 32-bit JOIN freshness */
    }
    carry_out(&p, &out);
    p.last_draw_us = now;
    uint64_t next_tick = now + p.opt.tick_us;
    uint64_t next_status = now;

    while (!stop_requested) {
        now = now_us();
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
            save_status(&p);
            next_status = now + p.opt.status_period_us;
        }
        const uint64_t wake = min3(canergy_node_deadline(&p.node), next_tick, next_status);
        now = now_us();
        int timeout_ms = 0;
        if (wake > now) {
            const uint64_t ms = (wake - now + 999U) / 1000U;
            timeout_ms = ms > 1000U ? 1000 : (int)ms;
        }
        struct pollfd pfd = {p.sock, POLLIN, 0};
        const int ready = poll(&pfd, 1U, timeout_ms);
        if (ready > 0 && (pfd.revents & POLLIN) != 0) {
            receive_all(&p);
        } else if (ready < 0 && errno != EINTR) {
            p.count.receive_errors++;
        }
    }
    save_status(&p);
    canergy_auth_wipe(&p.auth);
    (void)close(p.sock);
    (void)close(p.nv_fd);
    return 0;
}
