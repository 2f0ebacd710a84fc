/*
 * canergy-node's and canergy-gateway's command lines (ports/linux): the usage texts, the
 * options with their defaults, and the units of firmware_model's flags ("0.5J", "250mJ",
 * "200mW", "1.5s", plain numbers in the kind's base unit), parsed exactly into micro-units. A
 * bad argument exits 2 with one line.
 */
#define _GNU_SOURCE 1

#include "args.h"
#include "gateway_port.h"

#include <errno.h>
#include <linux/can.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define MAX_DURATION_US (7ULL * 24U * 3600U * US_PER_S) /* a week, as the Python flags */
#define MAX_QUANTITY_U (1000000000ULL * 1000000ULL)     /* 1 GJ, 1 GW */

void port_usage_error(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    (void)fprintf(stderr, "%s: error: ", PROG);
    (void)vfprintf(stderr, fmt, ap);
    (void)fputc('\n', stderr);
    va_end(ap);
    exit(EXIT_USAGE);
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
int port_mul_fits(uint64_t a, uint64_t b, uint64_t *out)
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
        port_usage_error("argument %s: %.16s... is over 64 characters", flag, text);
    }
    while (*p == ' ' || *p == '\t') {
        p++;
    }
    if (*p == '-') {
        port_usage_error("argument %s: '%s' is negative", flag, text);
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
        port_usage_error("argument %s: '%s' (expected e.g. %s)", flag, text, examples);
    }
    if (*p == 'e' || *p == 'E') {
        char *end = NULL;
        errno = 0;
        const long e = strtol(p + 1, &end, 10);
        if (end == p + 1 || (p[1] == ' ') || errno != 0 || e > 200 || e < -200) {
            port_usage_error("argument %s: '%s' (expected e.g. %s)", flag, text, examples);
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
            port_usage_error("argument %s: unknown unit in '%s' (expected e.g. %s)", flag,
                             text, examples);
        }
        const char c = *p++;
        unit[nu++] = (c >= 'A' && c <= 'Z') ? (char)(c - 'A' + 'a') : c;
    }
    unit[nu] = '\0';
    while (*p == ' ' || *p == '\t') {
        p++;
    }
    if (*p != '\0') {
        port_usage_error("argument %s: '%s' (expected e.g. %s)", flag, text, examples);
    }
    uint64_t factor = 0U;
    for (const struct unit *u = units; u->name != NULL; u++) {
        if (mega && strcmp(u->name, &unit[1]) == 0) {
            port_usage_error(
                "argument %s: mega-units are not supported: '%s' (did you mean m%s?)", flag, text,
                &unit[1]);
        }
        if (strcmp(u->name, unit) == 0) {
            factor = u->factor;
        }
    }
    if (factor == 0U) {
        port_usage_error("argument %s: unknown unit '%s' in '%s' (expected e.g. %s)", flag, unit,
                         text, examples);
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
        port_usage_error("argument %s: '%s' is too large or not a whole number of micro-units",
                         flag, text);
    }
    uint64_t mant = 0U;
    for (size_t i = 0U; i < nd; i++) {
        mant = mant * 10U + (uint64_t)(digits[i] - '0');
    }
    uint64_t value = 0U;
    if (!port_mul_fits(mant, factor, &value)) {
        port_usage_error("argument %s: '%s' is too large", flag, text);
    }
    for (; exp10 > 0; exp10--) {
        if (!port_mul_fits(value, 10U, &value)) {
            port_usage_error("argument %s: '%s' is too large", flag, text);
        }
    }
    for (; exp10 < 0; exp10++) {
        if (value % 10U != 0U) {
            port_usage_error("argument %s: '%s' is not a whole number of micro-units", flag,
                             text);
        }
        value /= 10U;
    }
    if (value > max) {
        port_usage_error("argument %s: '%s' is too large", flag, text);
    }
    return value;
}

uint64_t port_parse_energy(const char *flag, const char *text)
{
    return parse_quantity(flag, text, ENERGY_UNITS, MAX_QUANTITY_U, "10J, 250mJ, 1500uJ or 2.5");
}

uint64_t port_parse_duration(const char *flag, const char *text, uint64_t max)
{
    const uint64_t us = parse_quantity(flag, text, DURATION_UNITS, MAX_DURATION_US,
                                       "50ms, 1.5s, 200us, 2min or 0.5 (seconds)");
    if (us == 0U) {
        port_usage_error("argument %s: a duration must be more than zero: '%s'", flag, text);
    }
    if (us > max) {
        port_usage_error("argument %s: '%s' is too long for this port (at most %llu s)", flag,
                         text, (unsigned long long)(max / US_PER_S));
    }
    return us;
}

uint64_t port_parse_int(const char *flag, const char *text, uint64_t low, uint64_t high)
{
    char *end = NULL;
    errno = 0;
    if (text[0] == '-' || text[0] == '\0' || strlen(text) > 32U) {
        port_usage_error("argument %s: not an integer in %llu..%llu: '%s'", flag,
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
        port_usage_error("argument %s: not an integer: '%s'", flag, text);
    }
    if (v < low || v > high) {
        port_usage_error("argument %s: %llu outside %llu..%llu", flag, v,
                         (unsigned long long)low, (unsigned long long)high);
    }
    return (uint64_t)v;
}

uint8_t port_parse_rules(const char *flag, const char *text)
{
    if (strcmp(text, "hardened") == 0) {
        return CANERGY_RULES_HARDENED;
    }
    if (strcmp(text, "witnessed") == 0) {
        return CANERGY_RULES_WITNESSED;
    }
    port_usage_error("argument %s: invalid choice: '%s' (choose from 'hardened', 'witnessed')",
                     flag, text);
    return CANERGY_RULES_HARDENED;
}

/* ---- the command line ---- */

void port_parse_args(int argc, char **argv, struct port_options *o)
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
                         "       [--rules hardened|witnessed]\n"
                         "One canergy client node on Linux SocketCAN (the C library's node\n"
                         "layer); flags as python -m firmware_model --node N. Energies 0.5J,\n"
                         "250mJ; powers 0.2W, 200mW; durations 50ms, 1.5s or plain seconds.\n"
                         "--auth: authenticated mode with this node's key file (mode 0600);\n"
                         "--fd: CAN FD (64-bit MAC; the interface needs mtu 72).\n"
                         "--rules witnessed: every draw a DEBIT the supervisor acknowledges\n"
                         "first, every start a RESUME it confirms (a record restored from an\n"
                         "older copy creates no energy); the supervisor must run them too.\n",
                         PROG);
            exit(0);
        }
        if (strcmp(flag, "--fd") == 0) {
            o->fd = 1;
            continue;
        }
        if (i + 1 >= argc) {
            port_usage_error("argument %s: expected one argument", flag);
        }
        const char *v = argv[++i];
        if (strcmp(flag, "--node") == 0) {
            o->node = (int)port_parse_int(flag, v, CANERGY_MIN_NODE, CANERGY_MAX_NODE);
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
            o->tick_us = port_parse_duration(flag, v, MAX_DURATION_US);
        } else if (strcmp(flag, "--telemetry-period") == 0) {
            o->telemetry_period_us = port_parse_duration(flag, v, UINT32_MAX);
        } else if (strcmp(flag, "--status-period") == 0) {
            o->status_period_us = port_parse_duration(flag, v, MAX_DURATION_US);
        } else if (strcmp(flag, "--response-timeout") == 0) {
            o->response_timeout_us = port_parse_duration(flag, v, UINT32_MAX / 2U);
        } else if (strcmp(flag, "--low-water") == 0) {
            o->low_water_uj = parse_quantity(flag, v, ENERGY_UNITS, MAX_QUANTITY_U,
                                             "10J, 250mJ, 1500uJ or 2.5");
        } else if (strcmp(flag, "--return-above") == 0) {
            o->return_above_uj = parse_quantity(flag, v, ENERGY_UNITS, MAX_QUANTITY_U,
                                                "10J, 250mJ, 1500uJ or 2.5");
            o->keep_all = 0;
        } else if (strcmp(flag, "--rules") == 0) {
            o->rules = port_parse_rules(flag, v);
        } else if (strcmp(flag, "--auth") == 0) {
            o->auth_path = v;
        } else if (strcmp(flag, "--id-base") == 0) {
            o->id_base = (uint32_t)port_parse_int(flag, v, 0U, CAN_EFF_MASK);
            if (!canergy_id_base_valid(o->id_base)) {
                port_usage_error(
                    "argument %s: id base 0x%08X has bits in its low 12 (mask 0x1FFFF000)", flag,
                    (unsigned)o->id_base);
            }
        } else {
            port_usage_error("unrecognized argument: %s", flag);
        }
    }
    if (o->node == 0 || o->nv_path == NULL || o->channel == NULL) {
        port_usage_error("the following arguments are required: --node, -c/--channel, --nv");
    }
    if (o->interface != NULL && strcmp(o->interface, "socketcan") != 0) {
        port_usage_error("argument -i: this port speaks socketcan only, not '%s'", o->interface);
    }
}

/* ---- canergy-gateway's command line ---- */

/* "1-5,9": ascending distinct ids into o->nodes. */
static void parse_nodes(const char *text, struct gw_options *o)
{
    uint8_t seen[CANERGY_MAX_NODE + 1U] = {0};
    char buf[512];
    if (strlen(text) >= sizeof buf) {
        port_usage_error("argument --nodes: too long");
    }
    memcpy(buf, text, strlen(text) + 1U);
    for (char *rest = NULL, *part = strtok_r(buf, ",", &rest); part != NULL;
         part = strtok_r(NULL, ",", &rest)) {
        char *dash = strchr(part, '-');
        if (dash != NULL) {
            *dash = '\0';
        }
        const uint64_t lo = port_parse_int("--nodes", part, CANERGY_MIN_NODE, CANERGY_MAX_NODE);
        const uint64_t hi = dash == NULL ? lo
                                         : port_parse_int("--nodes", dash + 1, lo, CANERGY_MAX_NODE);
        for (uint64_t n = lo; n <= hi; n++) {
            seen[n] = 1U;
        }
    }
    o->count = 0U;
    for (unsigned n = CANERGY_MIN_NODE; n <= CANERGY_MAX_NODE; n++) {
        if (seen[n] != 0U) {
            if (o->count == CANERGY_SUPERVISOR_NODES) {
                port_usage_error("argument --nodes: more than %u nodes",
                                 (unsigned)CANERGY_SUPERVISOR_NODES);
            }
            o->nodes[o->count++] = (uint8_t)n;
        }
    }
}

static void gateway_usage(void)
{
    (void)printf("usage: %s --node N --nodes 1-5 [-i socketcan] -c CHANNEL\n"
                 "       --upstream-channel CHANNEL --nv PATH [--status-file PATH]\n"
                 "       [--target E] [--min-grant E] [--return-above E]\n"
                 "       [--telemetry-period T] [--response-timeout T]\n"
                 "       [--upstream-response-timeout T] [--retries N] [--status-period T]\n"
                 "       [--stop-timeout T] [--return-hold T] [--id-base ID]\n"
                 "       [--rules hardened|witnessed] [--upstream-rules hardened|witnessed]\n"
                 "       [--upstream-auth NODE.key [--upstream-fd]] [--auth MASTER.key [--fd]]\n"
                 "A canergy gateway on Linux SocketCAN (the C library's gateway rules): node\n"
                 "--node above (--upstream-channel), supervisor of --nodes below (-c); flags\n"
                 "as canergy gateway's. Energies 0.5J, 250mJ; durations 50ms, 1.5s.\n"
                 "--rules witnessed: the nodes below draw through DEBIT and RESUME at\n"
                 "every start (the supervisor side below).\n"
                 "--upstream-rules witnessed: what goes below is a DRAW the supervisor\n"
                 "above acknowledges first, and every start waits, granting nothing below,\n"
                 "until it confirms this gateway's record (an older copy creates nothing).\n"
                 "--upstream-auth: authenticated mode above with this gateway's node key\n"
                 "file (canergy keys --master ROOT.key --nodes N; mode 0600); --upstream-fd:\n"
                 "CAN FD frames with a 64-bit MAC, otherwise each frame and a MAC frame.\n"
                 "--auth: authenticated mode below with the gateway's own master key file\n"
                 "(canergy keys -o GATEWAY.key; mode 0600): its nodes' keys are derived from\n"
                 "it (canergy keys --master GATEWAY.key --nodes 1-5); --fd: the FD layout.\n",
                 PROG);
    exit(0);
}

void port_parse_gateway_args(int argc, char **argv, struct gw_options *o)
{
    memset(o, 0, sizeof *o);
    o->min_grant_uj = MJ;
    o->telemetry_period_us = 100000U;
    o->response_timeout_us = 50000U;
    o->up_response_timeout_us = 50000U;
    o->status_period_us = 1000000U;
    o->stop_timeout_us = 5000000U;
    o->tick_us = 50000U;
    o->return_hold_us = 500000U;
    o->retries = 3U;
    o->keep_all = 1;
    o->id_base = (uint32_t)CANERGY_DEFAULT_ID_BASE;
    for (int i = 1; i < argc; i++) {
        const char *flag = argv[i];
        if (strcmp(flag, "-h") == 0 || strcmp(flag, "--help") == 0) {
            gateway_usage();
        }
        if (strcmp(flag, "--upstream-fd") == 0) {
            o->up_fd = 1;
            continue;
        }
        if (strcmp(flag, "--fd") == 0) {
            o->fd = 1;
            continue;
        }
        if (i + 1 >= argc) {
            port_usage_error("argument %s: expected one argument", flag);
        }
        const char *v = argv[++i];
        if (strcmp(flag, "--node") == 0) {
            o->node = (uint8_t)port_parse_int(flag, v, CANERGY_MIN_NODE, CANERGY_MAX_NODE);
        } else if (strcmp(flag, "--upstream-auth") == 0) {
            o->up_auth_path = v;
        } else if (strcmp(flag, "--auth") == 0) {
            o->auth_path = v;
        } else if (strcmp(flag, "--nodes") == 0) {
            parse_nodes(v, o);
        } else if (strcmp(flag, "-i") == 0 || strcmp(flag, "--interface") == 0 ||
                   strcmp(flag, "--upstream-interface") == 0) {
            if (strcmp(v, "socketcan") != 0) {
                port_usage_error("argument %s: this port speaks socketcan only, not '%s'", flag,
                                 v);
            }
        } else if (strcmp(flag, "-c") == 0 || strcmp(flag, "--channel") == 0) {
            o->down_channel = v;
        } else if (strcmp(flag, "--upstream-channel") == 0) {
            o->up_channel = v;
        } else if (strcmp(flag, "--nv") == 0) {
            o->nv_path = v;
        } else if (strcmp(flag, "--status-file") == 0) {
            o->status_path = v;
        } else if (strcmp(flag, "--target") == 0) {
            o->target_uj = port_parse_energy(flag, v);
            o->has_target = 1;
        } else if (strcmp(flag, "--min-grant") == 0) {
            o->min_grant_uj = port_parse_energy(flag, v);
        } else if (strcmp(flag, "--return-above") == 0) {
            o->return_above_uj = port_parse_energy(flag, v);
            o->keep_all = 0;
        } else if (strcmp(flag, "--telemetry-period") == 0) {
            o->telemetry_period_us = port_parse_duration(flag, v, UINT32_MAX);
        } else if (strcmp(flag, "--response-timeout") == 0) {
            o->response_timeout_us = port_parse_duration(flag, v, UINT32_MAX / 2U);
        } else if (strcmp(flag, "--upstream-response-timeout") == 0) {
            o->up_response_timeout_us = port_parse_duration(flag, v, UINT32_MAX / 4U);
        } else if (strcmp(flag, "--rules") == 0) {
            o->rules = port_parse_rules(flag, v);
        } else if (strcmp(flag, "--upstream-rules") == 0) {
            o->up_rules = port_parse_rules(flag, v);
        } else if (strcmp(flag, "--retries") == 0) {
            o->retries = (uint8_t)port_parse_int(flag, v, 0U, 255U);
        } else if (strcmp(flag, "--status-period") == 0) {
            o->status_period_us = port_parse_duration(flag, v, UINT32_MAX);
        } else if (strcmp(flag, "--return-hold") == 0) {
            o->return_hold_us = port_parse_duration(flag, v, UINT32_MAX);
        } else if (strcmp(flag, "--stop-timeout") == 0) {
            o->stop_timeout_us = port_parse_duration(flag, v, UINT32_MAX);
        } else if (strcmp(flag, "--id-base") == 0) {
            o->id_base = (uint32_t)port_parse_int(flag, v, 0U, 0x1FFFFFFFU);
            if (!canergy_id_base_valid(o->id_base)) {
                port_usage_error("argument %s: id base 0x%08X has bits in its low 12", flag,
                                 (unsigned)o->id_base);
            }
        } else {
            port_usage_error("unrecognized argument: %s", flag);
        }
    }
    if (o->node == 0U || o->count == 0U || o->down_channel == NULL || o->up_channel == NULL ||
        o->nv_path == NULL) {
        port_usage_error("the following arguments are required: --node, --nodes, -c, "
                         "--upstream-channel, --nv");
    }
    if (strcmp(o->down_channel, o->up_channel) == 0) {
        port_usage_error("-c and --upstream-channel name the same bus: a gateway joins two");
    }
    if (o->min_grant_uj < MJ) {
        port_usage_error("argument --min-grant: at least 1 mJ (one frame's unit)");
    }
    if (o->up_fd && o->up_auth_path == NULL) {
        port_usage_error("argument --upstream-fd: only with --upstream-auth (the MAC layout)");
    }
    if (o->fd && o->auth_path == NULL) {
        port_usage_error("argument --fd: only with --auth (the MAC layout)");
    }
}
