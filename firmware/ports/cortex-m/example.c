/*
 * A bare-metal canergy node for Cortex-M4 (start-up: startup.c): a main loop that wires the
 * library's node layer to the four things a board provides: a CAN controller, NV storage, a
 * microsecond clock and the actuator's energy meter. Here they are stubs (a RAM "EEPROM", a
 * software clock, a fixed meter), so the example links and runs anywhere (nothing arrives on
 * this CAN stub; a real port replaces the functions marked BOARD with its drivers).
 *
 *   make -C firmware cortex-m      arm-none-eabi-gcc -mcpu=cortex-m4 -mthumb -Os
 */
#include "canergy/node.h"

#include <string.h>

/* ---- BOARD: CAN controller (extended frames, acceptance filter id_base | node / 0x1FFFF0FF:
 * this node's frames both ways, so the node layer witnesses frames sent in its name) ---- */

#define RX_RING 8U
static struct {
    uint32_t id;
    uint8_t len;
    uint8_t data[8];
} rx_ring[RX_RING];
static volatile unsigned rx_head; /* written by the receive ISR */
static unsigned rx_tail;
static uint32_t frames_sent;

static void can_send_extended(uint32_t id, const uint8_t *data, uint8_t dlc)
{
    (void)id;
    (void)data;
    (void)dlc;
    frames_sent++; /* BOARD: put the frame in a transmit mailbox; drop it if none is free */
}

static int can_pop(struct canergy_rx_frame *f, uint8_t buf[8])
{
    if (rx_tail == rx_head) {
        return 0;
    }
    const unsigned i = rx_tail % RX_RING;
    f->id = rx_ring[i].id;
    f->len = rx_ring[i].len;
    memcpy(buf, rx_ring[i].data, 8U);
    f->data = buf;
    f->extended = true;
    f->remote = false;
    rx_tail++;
    return 1;
}

/* ---- BOARD: NV storage, two 40-byte slots in separately erasable units ---- */

static uint8_t eeprom[2U * CANERGY_NV_SLOT_SIZE];

static int nv_write(unsigned offset, const uint8_t *data, unsigned len)
{
    memcpy(&eeprom[offset], data, len); /* BOARD: program and wait until the write completes */
    return 0;
}

/* ---- BOARD: clock and meter ---- */

static uint64_t clock_us;

static uint64_t now_us(void)
{
    return clock_us; /* BOARD: a free-running timer extended to 64 bits */
}

static void sleep_until(uint64_t t)
{
    clock_us = t; /* BOARD: WFI until the timer compare or a CAN interrupt */
}

static uint32_t actuator_wants_uj(void)
{
    return 20000U; /* BOARD: the meter: energy the actuator needs for its next period */
}

/* ---- the port ---- */

static void reset_node(void)
{
    for (;;) { /* BOARD: NVIC_SystemReset() */
    }
}

static void carry_out(const struct canergy_out *out)
{
    if (out->persist &&
        nv_write(out->nv_slot * CANERGY_NV_SLOT_SIZE, out->nv_image, CANERGY_NV_SLOT_SIZE) != 0) {
        reset_node(); /* never send what a failed write stands for */
    }
    for (unsigned i = 0U; i < out->frame_count; i++) {
        can_send_extended(out->frames[i].id, out->frames[i].data, out->frames[i].dlc);
    }
}

static struct canergy_node node;

int main(void);
int main(void)
{
    const struct canergy_node_config cfg = {
        {CANERGY_DEFAULT_ID_BASE, 200000UL, 200000UL, 5U, CANERGY_RULES_HARDENED, 0U}, 1000000UL, 50000UL, 2000000UL};
    struct canergy_out out;
    const uint16_t nonce = 0x5A17U; /* BOARD: a hardware entropy source, fresh every start */
    (void)canergy_node_start(&node, &cfg, eeprom, sizeof eeprom, nonce, now_us(), &out);
    carry_out(&out);
    uint64_t next_period = now_us() + 100000U;
    for (;;) {
        struct canergy_rx_frame f;
        uint8_t buf[8];
        while (can_pop(&f, buf)) {
            (void)canergy_node_on_frame(&node, &f, now_us(), &out);
            carry_out(&out);
        }
        if (now_us() >= next_period) {
            next_period += 100000U;
            const uint32_t granted = canergy_node_draw(&node, actuator_wants_uj(), now_us(), &out);
            carry_out(&out); /* the spend is in NV ... */
            (void)granted;   /* ... before the actuator runs on it */
        }
        if (now_us() >= canergy_node_deadline(&node)) {
            canergy_node_poll(&node, now_us(), &out);
            carry_out(&out);
        }
        const uint64_t deadline = canergy_node_deadline(&node);
        sleep_until(deadline < next_period ? deadline : next_period);
    }
}
