/*
 * A bare-metal canergy gateway for Cortex-M4 (start-up: startup.c), the Linux canergy-gateway's
 * loop on a board: node GW_NODE of the bus above, supervisor of nodes 1..NODES below, one NV
 * record for both roles (canergy_gateway_nv_*), each fresh RETURN below held until the node's
 * TELEMETRY confirms it (canergy/witness.h), each JOIN until the node's TELEMETRY judges it
 * (canergy_joins_route, canergy/joins.h), every node topped up to TARGET_UJ
 * (canergy_gateway_top_up), Us beyond RETURN_ABOVE_UJ given back above. What a board provides
 * (two CAN controllers, NV storage, a microsecond clock) is stubbed here so that it links and
 * runs anywhere; a real port replaces the functions marked BOARD with its drivers.
 *
 *   make -C firmware cortex-m      arm-none-eabi-gcc -mcpu=cortex-m4 -mthumb -Os
 */
#include "canergy/gateway.h"
#include "canergy/joins.h"
#include "canergy/witness.h"

#include <string.h>

#define GW_NODE 9U
#define NODES 4U /* CANERGY_SUPERVISOR_NODES of this build */
#define TARGET_UJ 2000000U
#define MIN_GRANT_UJ 100000U
#define RETURN_ABOVE_UJ 20000000U
#define HOLD_US 500000U
#define JOIN_HOLD_US 500000U
#define BLOCK_US 10000000U
#define TICK_US 50000U
#define TELEMETRY_US 100000U

/* ---- BOARD: two CAN controllers (extended frames; above: this gateway's id, both ways;
 * below: every node's) ---- */

enum bus { ABOVE, BELOW };
static uint32_t frames_sent[2];

static void can_send(enum bus bus, const struct canergy_frame *f)
{
    frames_sent[bus]++; /* BOARD: a transmit mailbox of that controller */
    (void)f;
}

static int can_pop(enum bus bus, struct canergy_rx_frame *f, uint8_t buf[8])
{
    (void)bus; /* BOARD: that controller's receive ring, filled by its ISR */
    (void)f;
    (void)buf;
    return 0;
}

/* ---- BOARD: NV storage, two slots in separately erasable units; clock ---- */

static uint8_t nv[2U * CANERGY_GW_NV_SLOT_SIZE];

static int nv_write(unsigned offset, const uint8_t *data, unsigned len)
{
    memcpy(&nv[offset], data, len); /* BOARD: program and wait until the write completes */
    return 0;
}

static uint64_t clock_us;

static uint64_t now_us(void)
{
    return clock_us; /* BOARD: a free-running timer extended to 64 bits */
}

static void sleep_until(uint64_t t)
{
    clock_us = t; /* BOARD: WFI until the timer compare or a CAN interrupt */
}

/* ---- the port ---- */

static struct canergy_gateway gw;
static struct canergy_witness witness[NODES];
static struct canergy_joins joins[NODES]; /* each node's JOINs held */
static uint64_t level_uj[NODES];
static uint8_t fresh[NODES]; /* a level reported since the node's last transaction ended */
static uint32_t intrusions;
static uint32_t nv_counter;
static uint8_t nv_slot = 1U; /* slot of the newest record: slot 0 is written first */

static void save(void)
{
    static uint8_t slot[CANERGY_GW_NV_SLOT_SIZE];
    const uint8_t next = (uint8_t)(1U - nv_slot);
    canergy_gateway_nv_encode(&gw, nv_counter + 1U, slot);
    if (nv_write(next * CANERGY_GW_NV_SLOT_SIZE, slot, sizeof slot) != 0) {
        for (;;) { /* BOARD: NVIC_SystemReset(): never send what a failed write stands for */
        }
    }
    nv_slot = next;
    nv_counter++;
}

static void up_out(const struct canergy_out *out)
{
    if (out->persist) {
        save();
    }
    for (unsigned i = 0U; i < out->frame_count; i++) {
        can_send(ABOVE, &out->frames[i]);
    }
}

static void down_out(const struct canergy_supervisor_out *out, uint64_t now)
{
    if (out->persist) {
        save();
    }
    for (unsigned i = 0U; i < out->frame_count; i++) {
        can_send(BELOW, &out->frames[i]);
    }
    for (unsigned k = 0U; k < out->event_count; k++) {
        const struct canergy_supervisor_event *e = &out->events[k];
        const unsigned i = (unsigned)e->node - 1U;
        if (e->resolved != CANERGY_RESOLVED_NONE || (e->flags & CANERGY_SUP_ADMITTED) != 0U) {
            fresh[i] = 0U;
        }
        if ((e->flags & CANERGY_SUP_ADMITTED) != 0U) {
            canergy_witness_readmitted(&witness[i]);
        }
        struct canergy_supervisor_out decided;
        if ((e->flags & CANERGY_SUP_ACKNOWLEDGED) != 0U &&
            canergy_supervisor_decide(&gw.down, e->node, true, now, &decided) == CANERGY_OK) {
            down_out(&decided, now);
        }
    }
}

static void to_rules(const struct canergy_msg *m, uint64_t now)
{
    struct canergy_supervisor_out out;
    (void)canergy_supervisor_on_msg(&gw.down, m, now, &out);
    down_out(&out, now);
}

/* What the witness releases of node i, to the rules in order (missed numbers as 0 mJ). */
static void release(unsigned i, uint64_t now)
{
    struct canergy_witness_release r;
    canergy_witness_release(&witness[i], gw.down.sessions[i].returns_credited, now, HOLD_US, &r);
    struct canergy_msg m;
    for (uint32_t n = 0U; canergy_witness_release_at(&r, (uint8_t)(i + 1U), n, &m); n++) {
        to_rules(&m, now);
    }
}

static void from_below(const struct canergy_rx_frame *f, uint64_t now)
{
    struct canergy_msg m;
    if (canergy_decode(CANERGY_DEFAULT_ID_BASE, f, CANERGY_TO_SUPERVISOR, &m) !=
            CANERGY_DECODE_OK ||
        m.node < 1U || m.node > NODES) {
        return;
    }
    const unsigned i = (unsigned)m.node - 1U;
    if (m.type == CANERGY_TELEMETRY) {
        level_uj[i] = (uint64_t)m.level_mj * 1000U;
        fresh[i] = (m.flags & CANERGY_TELEMETRY_JOINING) == 0U;
    }
    const enum canergy_witness_route r = canergy_witness_route(
        &witness[i], &gw.down.sessions[i], &m, CANERGY_RULES_HARDENED, now, &intrusions);
    if (r != CANERGY_WITNESS_TO_RULES) {
        release(i, now);
    }
    if (r == CANERGY_WITNESS_TO_RULES || m.type == CANERGY_TELEMETRY) { /* the JOIN hold's turn */
        struct canergy_msg rules;
        struct canergy_joins_refuted refuted;
        const unsigned found =
            canergy_joins_route(&joins[i], &m, now, JOIN_HOLD_US, &rules, &refuted);
        intrusions += refuted.count; /* JOINs in its name while it reports its books */
        if ((found & (CANERGY_JOINS_PASS | CANERGY_JOINS_ADMIT)) != 0U) {
            to_rules(&rules, now);
        }
    }
}

static void tick(uint64_t now)
{
    for (unsigned i = 0U; i < NODES; i++) {
        release(i, now);
        struct canergy_msg join;
        if (canergy_joins_due_join(&joins[i], (uint8_t)(i + 1U), now, &join)) {
            to_rules(&join, now); /* confirmed, and nobody objected within the hold */
        }
        const uint32_t amount =
            canergy_gateway_top_up(TARGET_UJ, MIN_GRANT_UJ, level_uj[i], gw.down.usable_uj);
        struct canergy_supervisor_out out;
        if (fresh[i] != 0U && gw.down.sessions[i].phase == CANERGY_S_IDLE && amount != 0U &&
            joins[i].held_count == 0U &&
            !canergy_witness_blocked(&witness[i], now, BLOCK_US) &&
            canergy_gateway_begin(&gw, (uint8_t)(i + 1U), amount, now, &out) == CANERGY_OK) {
            fresh[i] = 0U;
            down_out(&out, now);
        }
    }
    const uint32_t back = canergy_gateway_give_back_amount(gw.down.usable_uj, RETURN_ABOVE_UJ);
    struct canergy_out out;
    if (back != 0U && canergy_gateway_give_back(&gw, back, now, &out) == CANERGY_OK) {
        up_out(&out);
    }
}

static void telemetry(void)
{
    struct canergy_msg m;
    memset(&m, 0, sizeof m);
    m.type = CANERGY_TELEMETRY;
    m.node = GW_NODE;
    const uint64_t mj = gw.down.usable_uj < 0 ? 0U : (uint64_t)gw.down.usable_uj / 1000U;
    m.level_mj = mj > CANERGY_WIDE_MAX ? (uint32_t)CANERGY_WIDE_MAX : (uint32_t)mj;
    m.flags = canergy_client_joining(&gw.up) ? CANERGY_TELEMETRY_JOINING : 0U;
    m.seq = (uint16_t)gw.up.rec.return_seq;
    struct canergy_frame f;
    if (canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &f) == CANERGY_OK) {
        can_send(ABOVE, &f);
    }
}

/* Both roles from the newest slot (none: JOIN above, new below). */
static void start(uint64_t now)
{
    static const uint8_t nodes[NODES] = {1U, 2U, 3U, 4U};
    const struct canergy_client_config up = {CANERGY_DEFAULT_ID_BASE, 100000UL, 100000UL,
                                             GW_NODE, CANERGY_RULES_HARDENED, 0U};
    const struct canergy_supervisor_config down = {CANERGY_DEFAULT_ID_BASE,
                                                   {50000UL, 3U, CANERGY_RULES_HARDENED, 0U}};
    const uint16_t nonce = 0x5A17U; /* BOARD: a hardware entropy source, fresh every start */
    struct canergy_gateway_nv books;
    struct canergy_out out;
    uint32_t counter = 0U;
    uint8_t slot = 0U;
    if (canergy_gateway_nv_load(nv, sizeof nv, &books) == CANERGY_OK && books.slot >= 0) {
        uint8_t client_nv[CANERGY_NV_SLOTS * CANERGY_NV_SLOT_SIZE] = {0};
        uint8_t rec[CANERGY_NV_RECORD_SIZE];
        canergy_record_pack(&books.up, rec);
        canergy_nv_slot_encode(books.counter, rec, sizeof rec, client_nv);
        (void)canergy_client_start(&gw.up, &up, client_nv, sizeof client_nv, nonce, now, &out);
        if (canergy_supervisor_load(&gw.down, &down, nodes, NODES, 0U, books.down,
                                    CANERGY_SUPERVISOR_SLOT_SIZE, &counter, &slot) == 1) {
            nv_counter = books.counter;
            nv_slot = (uint8_t)books.slot;
            struct canergy_supervisor_out sout;
            canergy_supervisor_start(&gw.down, (uint16_t)(nonce + 1U), now, &sout);
            down_out(&sout, now);
            up_out(&out);
            return;
        }
    }
    (void)canergy_client_start(&gw.up, &up, NULL, 0U, nonce, now, &out); /* JOIN above */
    (void)canergy_supervisor_init(&gw.down, &down, nodes, NODES, 0U);
    up_out(&out);
}

int main(void);
int main(void)
{
    for (unsigned i = 0U; i < NODES; i++) {
        canergy_witness_init(&witness[i]);
    }
    start(now_us());
    uint64_t next_tick = now_us(), next_telemetry = now_us();
    for (;;) {
        struct canergy_rx_frame f;
        uint8_t buf[8];
        while (can_pop(ABOVE, &f, buf)) {
            struct canergy_out out;
            (void)canergy_gateway_on_up_frame(&gw, &f, now_us(), &out);
            up_out(&out);
        }
        while (can_pop(BELOW, &f, buf)) {
            from_below(&f, now_us());
        }
        const uint64_t now = now_us();
        if (canergy_client_deadline(&gw.up) <= now) {
            struct canergy_out out;
            canergy_gateway_on_up_timer(&gw, now, &out);
            up_out(&out);
        }
        if (canergy_supervisor_deadline(&gw.down) <= now) {
            struct canergy_supervisor_out out;
            canergy_supervisor_on_timer(&gw.down, now, &out);
            down_out(&out, now);
        }
        if (now >= next_tick) {
            next_tick = now + TICK_US;
            tick(now);
        }
        if (now >= next_telemetry) {
            next_telemetry = now + TELEMETRY_US;
            telemetry();
        }
        uint64_t wake = next_tick < next_telemetry ? next_tick : next_telemetry;
        wake = canergy_client_deadline(&gw.up) < wake ? canergy_client_deadline(&gw.up) : wake;
        const uint64_t sup = canergy_supervisor_deadline(&gw.down);
        sleep_until(sup < wake ? sup : wake);
    }
}
