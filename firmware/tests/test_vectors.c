/*
 * Known answers in plain C, runnable wherever the library builds (host, QEMU): the CRCs'
 * check values, the frames docs/protocol.md shows, one node's life from a blank NV image to
 * a committed grant and a restart, and the state budgets. The exhaustive comparison with the
 * Python rules is in tests/test_c_*.py.
 */
#include "canergy/client.h"
#include "canergy/node.h"

#include <stdio.h>
#include <string.h>

static unsigned passed;
static unsigned failed;

static void check(int ok, const char *what)
{
    if (ok) {
        passed++;
    } else {
        failed++;
        printf("FAILED: %s\n", what);
    }
}

static int frame_is(const struct canergy_frame *f, uint32_t id, const char *hex)
{
    char text[17] = {0};
    for (unsigned i = 0U; i < f->dlc && i < 8U; i++) {
        (void)snprintf(&text[2U * i], 3U, "%02X", (unsigned)f->data[i]);
    }
    return f->id == id && strcmp(text, hex) == 0;
}

static struct canergy_msg msg(uint8_t type, uint8_t node)
{
    struct canergy_msg m;
    memset(&m, 0, sizeof m);
    m.type = type;
    m.node = node;
    return m;
}

static void test_crcs(void)
{
    const uint8_t digits[] = "123456789";
    const uint8_t crc8 = (uint8_t)(canergy_crc8(0xFFU, digits, 9U) ^ 0xFFU);
    check(crc8 == 0x4BU, "CRC-8 SAE J1850 check value");
    check(canergy_crc32(0U, digits, 9U) == 0xCBF43926UL, "CRC-32 check value");
}

static void test_documented_frames(void)
{
    struct canergy_frame f;
    struct canergy_msg m = msg(CANERGY_INTENTION, 5U);
    m.tx = 1U;
    m.amount_mj = 500U;
    check(canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &f) == CANERGY_OK &&
              frame_is(&f, 0x0CE00105UL, "290100F401000000"),
          "INTENTION as in protocol.md");
    m = msg(CANERGY_ACK, 5U);
    m.tx = 1U;
    check(canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &f) == CANERGY_OK &&
              frame_is(&f, 0x0CE00905UL, "450100"),
          "ACK as in protocol.md");
    m = msg(CANERGY_RETURN, 5U);
    m.seq = 1U;
    m.amount_mj = 120U;
    check(canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &f) == CANERGY_OK &&
              frame_is(&f, 0x0CE00C05UL, "9B01007800"),
          "RETURN as in protocol.md");
    m = msg(CANERGY_TELEMETRY, 5U);
    m.level_mj = 500U;
    m.flags = CANERGY_TELEMETRY_HALTED;
    check(canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &f) == CANERGY_OK &&
              frame_is(&f, 0x0CE00D05UL, "28F4010002"),
          "TELEMETRY as in the README");
    m = msg(CANERGY_COMMIT, 5U);
    check(canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &f) == CANERGY_ERR_ARGUMENT,
          "a zero amount does not encode");
}

static void test_decode_reasons(void)
{
    const uint8_t ack[3] = {0x45U, 0x01U, 0x00U};
    struct canergy_rx_frame rx = {0x0CE00905UL, ack, 3U, true, false};
    check(canergy_decode(CANERGY_DEFAULT_ID_BASE, &rx, CANERGY_TO_SUPERVISOR, NULL) ==
              CANERGY_DECODE_OK,
          "ACK decodes");
    check(canergy_decode(CANERGY_DEFAULT_ID_BASE, &rx, CANERGY_TO_CLIENT, NULL) ==
              CANERGY_DECODE_WRONG_DIRECTION,
          "ACK to a client is the wrong way");
    rx.len = 9U;
    check(canergy_decode(CANERGY_DEFAULT_ID_BASE, &rx, CANERGY_EITHER_WAY, NULL) ==
              CANERGY_DECODE_WRONG_DLC,
          "9 bytes is the wrong length");
    rx.extended = false;
    check(canergy_decode(CANERGY_DEFAULT_ID_BASE, &rx, CANERGY_EITHER_WAY, NULL) ==
              CANERGY_DECODE_FOREIGN,
          "an 11-bit frame is foreign");
}

/* Feed the client a supervisor message through the real codec. */
static int deliver(struct canergy_client *c, const struct canergy_msg *m, uint64_t now,
                   struct canergy_out *out)
{
    struct canergy_frame f;
    if (canergy_encode(CANERGY_DEFAULT_ID_BASE, m, &f) != CANERGY_OK) {
        return -100;
    }
    const struct canergy_rx_frame rx = {f.id, f.data, f.dlc, true, false};
    return canergy_client_on_frame(c, &rx, now, out);
}

static void test_a_node_from_blank_to_books(void)
{
    const struct canergy_client_config cfg = {CANERGY_DEFAULT_ID_BASE, 100000UL, 100000UL, 5U};
    struct canergy_client c;
    struct canergy_out out;
    uint8_t nv[2U * CANERGY_NV_SLOT_SIZE];
    memset(nv, 0, sizeof nv);

    check(canergy_client_start(&c, &cfg, nv, sizeof nv, 0xBEEFU, 0U, &out) == 0 &&
              canergy_client_joining(&c) && out.frame_count == 1U && out.persist == 0U &&
              out.frames[0].id == 0x0CE00E05UL && out.frames[0].data[1] == 0xEFU &&
              out.frames[0].data[2] == 0xBEU,
          "a blank image joins at once with JOIN(nonce), nothing to persist");
    struct canergy_msg m = msg(CANERGY_ADMIT, 5U);
    m.nonce = 0xBEEFU;
    m.tx = 40U;
    m.seq = 7U;
    check(deliver(&c, &m, 10U, &out) == CANERGY_DECODE_OK && out.persist == 1U &&
              out.nv_slot == 0U && !canergy_client_joining(&c),
          "the ADMIT for our nonce is persisted to slot 0");
    memcpy(nv, out.nv_image, CANERGY_NV_SLOT_SIZE);

    m = msg(CANERGY_INTENTION, 5U);
    m.tx = 41U;
    m.amount_mj = 500U;
    m.delivered_mj = 9999U;
    check(deliver(&c, &m, 20U, &out) == CANERGY_DECODE_OK && out.frame_count == 1U &&
              out.frames[0].id == 0x0CE00905UL && out.persist == 1U && out.nv_slot == 1U,
          "a fresh intention sets Rc = Gs (persisted to slot 1) and is acknowledged");
    memcpy(&nv[CANERGY_NV_SLOT_SIZE], out.nv_image, CANERGY_NV_SLOT_SIZE);
    check(canergy_client_deadline(&c) == 100020U, "the command timer is armed");

    m = msg(CANERGY_COMMIT, 5U);
    m.tx = 41U;
    m.amount_mj = 500U;
    check(deliver(&c, &m, 30U, &out) == CANERGY_DECODE_OK && out.persist == 1U &&
              out.nv_slot == 0U && canergy_client_usable(&c) == 500000UL &&
              (out.events & CANERGY_EV_COMMITTED) != 0U && out.frames[0].id == 0x0CE00A05UL,
          "COMMIT credits 0.5 J and answers COMMITTED");
    memcpy(nv, out.nv_image, CANERGY_NV_SLOT_SIZE);
    check(deliver(&c, &m, 31U, &out) == CANERGY_DECODE_OK && out.persist == 0U &&
              canergy_client_usable(&c) == 500000UL && out.frame_count == 1U,
          "a duplicated COMMIT is answered, not applied");

    nv[10] ^= 0x40U; /* tear the newest slot: the record before it must come back */
    struct canergy_client again;
    check(canergy_client_start(&again, &cfg, nv, sizeof nv, 1U, 40U, &out) == 1 &&
              !canergy_client_joining(&again) && again.rec.usable_uj == 0U &&
              again.held_tx == 0U && again.rec.credited_mj == 9999UL,
          "a damaged newest slot falls back to the previous record");
}

static void test_budgets(void)
{
    check(sizeof(struct canergy_client) <= 128U, "client state within 128 bytes");
    check(sizeof(struct canergy_node) <= 128U, "node state within 128 bytes");
}

int main(void)
{
    test_crcs();
    test_documented_frames();
    test_decode_reasons();
    test_a_node_from_blank_to_books();
    test_budgets();
    printf("sizeof client %u, node %u, out %u bytes\n", (unsigned)sizeof(struct canergy_client),
           (unsigned)sizeof(struct canergy_node), (unsigned)sizeof(struct canergy_out));
    printf("%u passed, %u failed\n", passed, failed);
    return failed == 0U ? 0 : 1;
}
