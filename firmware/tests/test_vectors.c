/*
 * Known answers in plain C, runnable wherever the library builds (host, QEMU): the CRCs'
 * check values, the frames docs/protocol.md shows, one node's life from a blank NV image to
 * a committed grant and a restart, the state budgets, and AES-128 (FIPS-197 C.1), AES-CMAC
 * (RFC 4493 section 4), the KDF (a value from Python's cryptography) and authenticated frames
 * (values from src/canergy/auth/frames.py). The exhaustive
 * comparison with the Python code is in tests/test_c_*.py.
 */
#include "canergy/auth.h"
#include "canergy/client.h"
#include "canergy/cmac.h"
#include "canergy/gateway.h"
#include "canergy/node.h"
#include "canergy/session.h"
#include "canergy/supervisor.h"

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
    m.seq = 0x1234U;
    m.witness = 3U;
    check(canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &f) == CANERGY_OK &&
              frame_is(&f, 0x0CE00D05UL, "E8F4010002341203"),
          "TELEMETRY: level, flags, return number, witness (canergy.codec's frame)");
    struct canergy_msg back;
    const struct canergy_rx_frame rx = {f.id, f.data, f.dlc, true, false};
    check(canergy_decode(CANERGY_DEFAULT_ID_BASE, &rx, CANERGY_TO_SUPERVISOR, &back) ==
              CANERGY_DECODE_OK &&
              back.level_mj == 500U && back.flags == CANERGY_TELEMETRY_HALTED &&
              back.seq == 0x1234U && back.witness == 3U &&
              canergy_data_length(CANERGY_TELEMETRY) == 8U,
          "TELEMETRY decodes back, 8 bytes");
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

/* Byte 0 of a frame of type from node 5: the CRC of its Data ID and body (codec.h). */
static void put_crc(uint8_t type, uint8_t *data, size_t len)
{
    const uint8_t data_id[2] = {5U, type};
    data[0] = (uint8_t)(canergy_crc8(canergy_crc8(0xFFU, data_id, 2U), &data[1], len - 1U) ^ 0xFFU);
}

/* A refusal writes nothing: *msg only on CANERGY_DECODE_OK, *out only on CANERGY_OK (the client
 * decodes in place and encodes in place, behind canergy_decode and canergy_encode). */
static void test_refusals_write_nothing(void)
{
    const struct canergy_msg kept = msg(CANERGY_ACK, 9U);
    struct canergy_msg m = kept;
    uint8_t commit[5] = {0U, 0x01U, 0x00U, 0x00U, 0x00U}; /* tx 1, amount 0 */
    put_crc(CANERGY_COMMIT, commit, sizeof commit);
    const struct canergy_rx_frame zero = {0x0CE00205UL, commit, sizeof commit, true, false};
    check(canergy_decode(CANERGY_DEFAULT_ID_BASE, &zero, CANERGY_TO_CLIENT, &m) ==
              CANERGY_DECODE_OUT_OF_RANGE && memcmp(&m, &kept, sizeof m) == 0,
          "a COMMIT of 0 is out of range, *msg untouched");
    uint8_t debit[8] = {0U, 0x00U, 0x00U, CANERGY_DEBIT_SYNC, 0x00U, 0x00U, 0x00U, 0x00U};
    put_crc(CANERGY_DEBIT, debit, sizeof debit);
    const struct canergy_rx_frame sync = {0x0CE00F05UL, debit, sizeof debit, true, false};
    check(canergy_decode(CANERGY_DEFAULT_ID_BASE, &sync, CANERGY_TO_SUPERVISOR, &m) ==
              CANERGY_DECODE_OUT_OF_RANGE && memcmp(&m, &kept, sizeof m) == 0,
          "a DEBIT of SYNC alone is out of range, *msg untouched");
    debit[3] = CANERGY_DEBIT_COUNTS;
    put_crc(CANERGY_DEBIT, debit, sizeof debit);
    check(canergy_decode(CANERGY_DEFAULT_ID_BASE, &sync, CANERGY_TO_SUPERVISOR, &m) ==
              CANERGY_DECODE_OK && m.type == CANERGY_DEBIT && m.flags == CANERGY_DEBIT_COUNTS,
          "a DEBIT of the counts decodes");
    struct canergy_frame f;
    memset(&f, 0xA5, sizeof f);
    const struct canergy_frame before = f;
    m = msg(CANERGY_TELEMETRY, 5U);
    m.level_mj = CANERGY_WIDE_MAX + 1U;
    check(canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &f) == CANERGY_ERR_ARGUMENT &&
              memcmp(&f, &before, sizeof f) == 0,
          "a level of 2^24 does not encode, *out untouched");
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
    const struct canergy_client_config cfg = {CANERGY_DEFAULT_ID_BASE, 100000UL, 100000UL, 5U, CANERGY_RULES_HARDENED, 0U};
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

/* Feed the node a message through the real codec (either direction). */
static int node_deliver(struct canergy_node *n, const struct canergy_msg *m, uint64_t now,
                        struct canergy_out *out)
{
    struct canergy_frame f;
    if (canergy_encode(CANERGY_DEFAULT_ID_BASE, m, &f) != CANERGY_OK) {
        return -100;
    }
    const struct canergy_rx_frame rx = {f.id, f.data, f.dlc, true, false};
    return canergy_node_on_frame(n, &rx, now, out);
}

/* The TELEMETRY the next poll sends: its return number and witness, or 0x7FFFFFFF for none. */
static long polled_telemetry(struct canergy_node *n, uint64_t now, uint8_t *witness)
{
    struct canergy_out out;
    struct canergy_msg m;
    canergy_node_poll(n, now, &out);
    for (unsigned i = 0U; i < out.frame_count; i++) {
        const struct canergy_rx_frame rx = {out.frames[i].id, out.frames[i].data,
                                            out.frames[i].dlc, true, false};
        if (canergy_decode(CANERGY_DEFAULT_ID_BASE, &rx, CANERGY_TO_SUPERVISOR, &m) ==
                CANERGY_DECODE_OK &&
            m.type == CANERGY_TELEMETRY) {
            *witness = m.witness;
            return (long)m.seq;
        }
    }
    return 0x7FFFFFFFL;
}

/* Frames in the node's name that it did not send are counted, reported at the next poll (no
 * sooner than 10 ms, CANERGY_WITNESS_GAP_US, after the last TELEMETRY), and move nothing;
 * genuine answers, their duplicates and other nodes' frames are not counted. */
static void test_node_witness(void)
{
    const struct canergy_node_config cfg = {
        {CANERGY_DEFAULT_ID_BASE, 100000UL, 100000UL, 5U, CANERGY_RULES_HARDENED, 0U}, 1000000UL, 0U, CANERGY_KEEP_ALL};
    struct canergy_node n;
    struct canergy_out out;
    uint8_t nv[2U * CANERGY_NV_SLOT_SIZE] = {0};
    uint8_t w = 0xEEU;
    (void)canergy_node_start(&n, &cfg, NULL, 0U, 0x1234U, 0U, &out);
    check(polled_telemetry(&n, 0U, &w) == 0L && w == 0U, "a new node reports witness 0");
    struct canergy_msg admit = msg(CANERGY_ADMIT, 5U);
    admit.nonce = 0x4321U;
    admit.tx = 40U;
    admit.seq = 7U;
    struct canergy_msg retack = msg(CANERGY_RETURN_ACK, 5U);
    retack.seq = 1U;
    check(node_deliver(&n, &admit, 10U, &out) == CANERGY_DECODE_OK &&
              node_deliver(&n, &retack, 11U, &out) == CANERGY_DECODE_OK && n.witness == 2U &&
              canergy_client_joining(&n.client) && canergy_node_deadline(&n) == 10000U,
          "joining: an ADMIT for another nonce, a RETURN_ACK ahead: witnessed, due 10 ms after "
          "its last report (at 0)");
    admit.nonce = 0x1234U;
    check(node_deliver(&n, &admit, 20U, &out) == CANERGY_DECODE_OK && n.witness == 2U &&
              !canergy_client_joining(&n.client) && out.persist == 1U,
          "the ADMIT for its JOIN is not witnessed");
    memcpy(&nv[out.nv_slot * CANERGY_NV_SLOT_SIZE], out.nv_image, CANERGY_NV_SLOT_SIZE);
    admit.tx = 90U;
    check(node_deliver(&n, &admit, 21U, &out) == CANERGY_DECODE_OK && n.witness == 2U &&
              out.persist == 0U && out.frame_count == 0U,
          "the same nonce once admitted (a duplicate) is not witnessed, moves nothing");
    admit.nonce = 0x1235U;
    check(node_deliver(&n, &admit, 22U, &out) == CANERGY_DECODE_OK && n.witness == 3U &&
              polled_telemetry(&n, 22U, &w) == 7L && w == 3U,
          "another nonce is; the next poll's TELEMETRY carries return number and witness");

    struct canergy_msg m = msg(CANERGY_INTENTION, 5U);
    m.tx = 41U;
    m.amount_mj = 500U;
    (void)node_deliver(&n, &m, 30U, &out);
    m = msg(CANERGY_COMMIT, 5U);
    m.tx = 41U;
    m.amount_mj = 500U;
    (void)node_deliver(&n, &m, 31U, &out);
    (void)canergy_client_give_back(&n.client, 100000UL, 32U, &out); /* RETURN number 8 */
    uint8_t books[CANERGY_NV_RECORD_SIZE];
    uint8_t after[CANERGY_NV_RECORD_SIZE];
    canergy_record_pack(&n.client.rec, books);
    retack.seq = 7U;
    check(node_deliver(&n, &retack, 40U, &out) == CANERGY_DECODE_OK && n.witness == 3U,
          "a RETURN_ACK behind its return number (a late duplicate) is not witnessed");
    retack.seq = (uint16_t)(8U + 0x7FFFU);
    check(node_deliver(&n, &retack, 41U, &out) == CANERGY_DECODE_OK && n.witness == 4U &&
              n.client.rec.return_pending_uj == 100000UL,
          "one ahead of it is, the return still pending");
    retack.seq = (uint16_t)(8U + 0x8000U);
    check(node_deliver(&n, &retack, 42U, &out) == CANERGY_DECODE_OK && n.witness == 4U,
          "half the wire away counts as behind, as unwrap() does");
    struct canergy_msg spoof = msg(CANERGY_RETURN, 5U);
    spoof.seq = 9U;
    spoof.amount_mj = 65535U;
    struct canergy_msg other = msg(CANERGY_ACK, 6U);
    const int spoofed = node_deliver(&n, &spoof, 43U, &out);
    canergy_record_pack(&n.client.rec, after);
    check(spoofed == CANERGY_DECODE_WRONG_DIRECTION && n.witness == 5U && out.persist == 0U &&
              memcmp(after, books, sizeof books) == 0 &&
              node_deliver(&n, &other, 44U, &out) == CANERGY_DECODE_WRONG_DIRECTION &&
              n.witness == 5U,
          "a RETURN in its name is witnessed and moves nothing; another node's ACK is not");
    const uint8_t garbage[12] = {0};
    struct canergy_rx_frame raw = {0x0CE00D05UL, garbage, 12U, true, false};
    const uint32_t errors = n.decode_errors;
    check(canergy_node_on_frame(&n, &raw, 45U, &out) == CANERGY_DECODE_WRONG_DIRECTION &&
              n.witness == 6U && n.decode_errors == errors,
          "any length in its own direction with its id is witnessed, not a decode error");
    raw.remote = true;
    check(canergy_node_on_frame(&n, &raw, 46U, &out) == CANERGY_DECODE_REMOTE_FRAME &&
              n.witness == 6U && n.decode_errors == errors + 1U,
          "a remote frame stays a decode error");
    retack.seq = 8U;
    check(node_deliver(&n, &retack, 50U, &out) == CANERGY_DECODE_OK && n.witness == 6U &&
              n.client.rec.return_pending_uj == 0U &&
              node_deliver(&n, &retack, 51U, &out) == CANERGY_DECODE_OK && n.witness == 6U,
          "the RETURN_ACK for its return and a duplicate of it are not witnessed");
    canergy_record_pack(&n.client.rec, books);
    for (unsigned i = 0U; i < 256U; i++) {
        (void)node_deliver(&n, &spoof, 60U, &out);
    }
    canergy_record_pack(&n.client.rec, after);
    /* the 128th was reported at once, at 60: the next report 10 ms later */
    check(n.witness == 6U && polled_telemetry(&n, 60U + 10000U, &w) == 8L && w == 6U &&
              memcmp(after, books, sizeof books) == 0,
          "the witness wraps modulo 256, the books untouched");
    admit.nonce = 0x1234U;
    (void)canergy_node_start(&n, &cfg, nv, sizeof nv, 0x1234U, 70U, &out);
    check(!canergy_client_joining(&n.client) && n.witness == 0U &&
              node_deliver(&n, &admit, 71U, &out) == CANERGY_DECODE_OK && n.witness == 1U,
          "started with books: the witness starts at 0, any ADMIT is witnessed");
}

/* One session's life (the Python table's answers): a commit, an abort, a write-off, returns
 * credited once, an admission lifting both counters. */
#ifdef CANERGY_WITNESSED
/* The client's one frame (a DEBIT) into the session, the session's answer back: the answer. */
static struct canergy_msg to_session(struct canergy_session *s, const struct canergy_out *out)
{
    const struct canergy_session_timing t = {50000U, 1U, CANERGY_RULES_WITNESSED, 0U};
    struct canergy_msg m;
    struct canergy_session_step step;
    const struct canergy_rx_frame rx = {out->frames[0].id, out->frames[0].data,
                                        out->frames[0].dlc, true, false};
    memset(&step, 0, sizeof step);
    if (out->frame_count == 1U &&
        canergy_decode(CANERGY_DEFAULT_ID_BASE, &rx, CANERGY_TO_SUPERVISOR, &m) ==
            CANERGY_DECODE_OK) {
        canergy_session_on_msg(s, &t, &m, 0U, &step);
    }
    return step.msg;
}

/* Issue 40, item 6 in C alone: 2 J on the books, 1.5 J drawn and acknowledged, the record put
 * back to the copy from before the draw: found behind, nothing left to draw. */
static void test_witnessed_older_copy(void)
{
    const struct canergy_client_config cfg = {CANERGY_DEFAULT_ID_BASE, 100000UL, 100000UL, 5U,
                                              CANERGY_RULES_WITNESSED, 0U};
    struct canergy_record rec;
    memset(&rec, 0, sizeof rec);
    rec.usable_uj = 2000000UL;
    rec.outcome = CANERGY_OUTCOME_SETTLED;
    uint8_t packed[CANERGY_NV_RECORD_SIZE];
    canergy_record_pack(&rec, packed);
    uint8_t copy[CANERGY_NV_SLOT_SIZE];
    canergy_nv_slot_encode(1U, packed, sizeof packed, copy);
    struct canergy_session s;
    canergy_session_init(&s, 5U);
    struct canergy_client c;
    struct canergy_out out;

    (void)canergy_client_start(&c, &cfg, copy, sizeof copy, 0x1111U, 0U, &out);
    check(c.phase == CANERGY_RESUMING && out.frame_count == 1U &&
              canergy_client_draw(&c, 1000U, 1U, &out) == CANERGY_ERR_PHASE,
          "witnessed: a start RESUMEs and draws nothing before its ADMIT");
    (void)canergy_client_start(&c, &cfg, copy, sizeof copy, 0x1111U, 0U, &out);
    struct canergy_msg m = to_session(&s, &out);
    check(deliver(&c, &m, 2U, &out) == CANERGY_DECODE_OK && c.phase == CANERGY_IDLE &&
              c.rec.return_seq == 1U && c.rec.usable_uj == 2000000UL,
          "witnessed: ADMIT(q + 1) confirms the books");
    check(canergy_client_draw(&c, 1500000UL, 3U, &out) == CANERGY_OK && out.persist == 1U &&
              c.rec.spent_uj == 0U,
          "witnessed: a draw is persisted and sent; the actuator waits");
    m = to_session(&s, &out);
    check(deliver(&c, &m, 4U, &out) == CANERGY_DECODE_OK && c.rec.spent_uj == 1500000UL &&
              (out.events & CANERGY_EV_RELEASED) != 0U && s.returns_credited == 2U,
          "witnessed: its acknowledgement releases it (the session holds number 2)");
    (void)canergy_client_start(&c, &cfg, copy, sizeof copy, 0x2222U, 5U, &out);
    m = to_session(&s, &out);
    check(deliver(&c, &m, 6U, &out) == CANERGY_DECODE_OK && c.phase == CANERGY_IDLE &&
              c.rec.usable_uj == 0U && c.rec.return_seq == 3U &&
              canergy_client_draw(&c, 1000U, 7U, &out) == CANERGY_ERR_AMOUNT,
          "witnessed: the older copy is found behind and holds nothing to draw");
}
#endif

static void test_session(void)
{
    const struct canergy_session_timing t = {50000U, 1U, CANERGY_RULES_HARDENED, 0U};
    struct canergy_session s;
    struct canergy_session_step step;
    struct canergy_msg m = msg(CANERGY_ACK, 5U);
    canergy_session_init(&s, 5U);

    check(canergy_session_begin(&s, &t, 1500U, 0U, &step) == CANERGY_ERR_AMOUNT,
          "whole mJ only");
    check(canergy_session_decide(&s, &t, true, 0U, &step) == CANERGY_ERR_PHASE, "decide in IDLE");
    check(canergy_session_begin(&s, &t, 2000U, 0U, &step) == CANERGY_OK && step.send &&
              step.msg.type == CANERGY_INTENTION && step.msg.tx == 1U &&
              step.msg.amount_mj == 2U && step.credit_uj == -2000,
          "begin: INTENTION(1, 2 mJ), Us -= 2 mJ");
    m.tx = 1U;
    canergy_session_on_msg(&s, &t, &m, 10U, &step);
    check(s.phase == CANERGY_S_ACKED && step.acknowledged, "ACK(1)");
    check(canergy_session_decide(&s, &t, true, 20U, &step) == CANERGY_OK &&
              step.msg.type == CANERGY_COMMIT && s.phase == CANERGY_S_WAIT_CONFIRM,
          "decide: COMMIT(1)");
    m.type = CANERGY_ABORTED;
    canergy_session_on_msg(&s, &t, &m, 30U, &step);
    check(s.phase == CANERGY_S_WAIT_CONFIRM && step.credit_uj == 0,
          "ABORTED after COMMIT: ignored");
    m.type = CANERGY_COMMITTED;
    canergy_session_on_msg(&s, &t, &m, 30U, &step);
    check(s.phase == CANERGY_S_IDLE && s.delivered_uj == 2000U &&
              step.resolved == CANERGY_RESOLVED_COMMITTED,
          "COMMITTED(1): Gs 2 mJ");

    (void)canergy_session_begin(&s, &t, 3000U, 40U, &step);
    m.type = CANERGY_ACK;
    m.tx = 2U;
    canergy_session_on_msg(&s, &t, &m, 50U, &step);
    (void)canergy_session_decide(&s, &t, false, 60U, &step);
    m.type = CANERGY_ABORTED;
    canergy_session_on_msg(&s, &t, &m, 70U, &step);
    check(step.resolved == CANERGY_RESOLVED_ABORTED && step.credit_uj == 3000 &&
              s.delivered_uj == 2000U,
          "ABORTED(2) after ABORT: Ts back to Us");

    (void)canergy_session_begin(&s, &t, 4000U, 100U, &step);
    canergy_session_timer(&s, &t, 50099U, &step);
    check(!step.send, "timer before its deadline: nothing");
    canergy_session_timer(&s, &t, 50100U, &step);
    check(step.send && step.msg.type == CANERGY_INTENTION && step.msg.tx == 3U && s.tries == 2U,
          "timer: the identical INTENTION(3)");
    canergy_session_timer(&s, &t, 100100U, &step);
    check(step.resolved == CANERGY_RESOLVED_WRITTEN_OFF && s.delivered_uj == 6000U,
          "after N re-sends: written off, Gs += Ts");

    m = msg(CANERGY_RETURN, 5U);
    m.seq = 1U;
    m.amount_mj = 7U;
    canergy_session_on_msg(&s, &t, &m, 200U, &step);
    check(step.credit_uj == 7000 && step.msg.type == CANERGY_RETURN_ACK && step.msg.seq == 1U,
          "RETURN(1, 7 mJ): credited, acknowledged");
    canergy_session_on_msg(&s, &t, &m, 210U, &step);
    check(step.credit_uj == 0 && step.send && s.returned_uj == 7000U,
          "RETURN(1) again: acknowledged, not credited");
    m.seq = 3U;
    canergy_session_on_msg(&s, &t, &m, 220U, &step);
    check(!step.send && s.returns_credited == 1U, "RETURN(3) beyond the next: ignored");

    s.returns_credited = 0x2FFFFUL; /* returns past 2^17: the admission lifts tx to them */
    (void)canergy_session_begin(&s, &t, 1000U, 300U, &step);
    m = msg(CANERGY_JOIN, 5U);
    m.nonce = 0xBEEFU;
    canergy_session_on_msg(&s, &t, &m, 310U, &step);
    check(step.resolved == CANERGY_RESOLVED_WRITTEN_OFF && s.tx == 0x20004UL &&
              step.msg.type == CANERGY_ADMIT && step.msg.nonce == 0xBEEFU &&
              step.msg.tx == 4U && step.msg.seq == 0xFFFFU,
          "JOIN: the open one written off, counters on one high half, ADMIT(n, 4, 0xFFFF)");
    check(sizeof(struct canergy_session) <= 72U, "session record within 72 bytes");
}

/* The supervisor around the sessions: Us guards a grant, frames go through the codec, a
 * change of the record asks to persist first. */
static void test_supervisor(void)
{
    const struct canergy_supervisor_config cfg = {CANERGY_DEFAULT_ID_BASE, {50000U, 3U, CANERGY_RULES_HARDENED, 0U}};
    const uint8_t nodes[2] = {3U, 5U};
    const uint8_t unsorted[2] = {5U, 3U};
    static struct canergy_supervisor sup;
    static struct canergy_supervisor_out out;
    check(canergy_supervisor_init(&sup, &cfg, unsorted, 2U, 5000U) == CANERGY_ERR_ARGUMENT,
          "nodes ascending");
    check(canergy_supervisor_init(&sup, &cfg, nodes, 2U, 5000U) == CANERGY_OK, "init");
    check(canergy_supervisor_begin(&sup, 9U, 1000U, 0U, &out) == CANERGY_ERR_ARGUMENT,
          "a node not managed here");
    check(canergy_supervisor_begin(&sup, 3U, 6000U, 0U, &out) == CANERGY_ERR_AMOUNT &&
              sup.usable_uj == 5000U && sup.sessions[0].phase == CANERGY_S_IDLE,
          "a grant beyond Us: refused, nothing changed");
    check(canergy_supervisor_begin(&sup, 3U, 2000U, 0U, &out) == CANERGY_OK && out.persist &&
              out.frame_count == 1U && out.frames[0].id == 0x0CE00103UL &&
              sup.usable_uj == 3000U,
          "begin: persist, then INTENTION to node 3; Us 3 mJ");
    const uint8_t bad_crc[3] = {0x00U, 0x01U, 0x00U}; /* ACK(3, tx 1) is 2C 01 00 */
    struct canergy_rx_frame f = {0x0CE00903UL, bad_crc, 3U, true, false};
    check(canergy_supervisor_on_frame(&sup, &f, 10U, &out) == CANERGY_DECODE_BAD_CRC &&
              sup.sessions[0].phase == CANERGY_S_WAIT_ACK && out.frame_count == 0U,
          "a frame with a bad CRC: counted, nothing happens");
    const uint8_t ack4[3] = {0xD8U, 0x01U, 0x00U}; /* ACK(4, tx 1), a valid frame */
    f.id = 0x0CE00904UL;
    f.data = ack4;
    check(canergy_supervisor_on_frame(&sup, &f, 10U, &out) == CANERGY_RX_OTHER_NODE &&
              out.frame_count == 0U,
          "ACK of node 4, not managed here: ignored");
    check(canergy_supervisor_deadline(&sup) == 50000U, "the intention's response timer");
    canergy_supervisor_on_timer(&sup, 49999U, &out);
    check(out.frame_count == 0U, "nothing due before it");
    canergy_supervisor_on_timer(&sup, 50000U, &out);
    check(out.frame_count == 1U && out.frames[0].id == 0x0CE00103UL && !out.persist,
          "due: the identical INTENTION, nothing to persist");
    check(canergy_supervisor_inject(&sup, 0U) == CANERGY_ERR_AMOUNT &&
              canergy_supervisor_inject(&sup, 500U) == CANERGY_OK && sup.usable_uj == 3500U,
          "inject");
    check(canergy_supervisor_withdraw(&sup, 0U) == CANERGY_ERR_AMOUNT &&
              canergy_supervisor_withdraw(&sup, 3501U) == CANERGY_ERR_AMOUNT &&
              canergy_supervisor_withdraw(&sup, 500U) == CANERGY_OK && sup.usable_uj == 3000U &&
              sup.withdrawn_uj == 500U && canergy_supervisor_inject(&sup, 500U) == CANERGY_OK,
          "withdraw: never more than Us, counted");
    check(sizeof(struct canergy_supervisor) <= 80U * CANERGY_SUPERVISOR_NODES,
          "supervisor state within 80 bytes per node");

    /* Its record in NV: written to slot 0 (counter 1), then 1 (counter 2); the newer wins, a
     * damaged newer one gives way to the older, none at all starts a new supervisor. */
    static uint8_t nv[2U * CANERGY_SUPERVISOR_SLOT_SIZE];
    static struct canergy_supervisor back;
    uint32_t counter = 0U;
    uint8_t slot = 0U;
    check(canergy_supervisor_load(&back, &cfg, nodes, 2U, 7U, nv, sizeof nv, &counter, &slot) ==
              0 && back.usable_uj == 7U && slot == 1U,
          "blank NV: a new supervisor, slot 0 first");
    const size_t used = canergy_supervisor_image(&sup, 1U, nv);
    check(used == 40U + 56U * 2U, "the image: 40 bytes and 56 per session");
    sup.usable_uj += 1000U;
    (void)canergy_supervisor_image(&sup, 2U, &nv[CANERGY_SUPERVISOR_SLOT_SIZE]);
    check(canergy_supervisor_load(&back, &cfg, nodes, 2U, 7U, nv, sizeof nv, &counter, &slot) ==
              1 && counter == 2U && slot == 1U && back.usable_uj == 4500U &&
              back.sessions[0].tx == 1U && back.sessions[0].phase == CANERGY_S_WAIT_ACK &&
              back.sessions[0].reserved_uj == 2000U && back.sessions[0].deadline == 0U &&
              back.injected_uj == 1000U && back.withdrawn_uj == 500U,
          "the newer slot, its open intention due at once");
    nv[CANERGY_SUPERVISOR_SLOT_SIZE + 40U] ^= 0x01U;
    check(canergy_supervisor_load(&back, &cfg, nodes, 2U, 7U, nv, sizeof nv, &counter, &slot) ==
              1 && counter == 1U && slot == 0U && back.usable_uj == 3500U,
          "a damaged newer slot: the older one");
    const uint8_t others[2] = {3U, 6U};
    check(canergy_supervisor_load(&back, &cfg, others, 2U, 7U, nv, sizeof nv, &counter, &slot) ==
              CANERGY_ERR_RECORD,
          "another node list: not this supervisor's record, and no new start over it");
    nv[4] = 1U; /* the older slot now says version 1, the newer one is damaged */
    check(canergy_supervisor_load(&back, &cfg, nodes, 2U, 7U, nv, sizeof nv, &counter, &slot) ==
              CANERGY_ERR_RECORD,
          "a record of another version: no new start over it");
}

#ifdef CANERGY_HARDENED
static const bool hardened_kept = true;
#else
static const bool hardened_kept = false;
#endif
#ifdef CANERGY_WITNESSED
static const bool witnessed_kept = true;
#else
static const bool witnessed_kept = false;
#endif

/* A build keeps the rule sets canergy/client.h says: a client, a node or a supervisor
 * configured with another is refused at start (CANERGY_ERR_ARGUMENT), never run as one kept. */
static void test_rules_kept(void)
{
    static const uint8_t nodes[1] = {5U};
    const bool sets[3] = {hardened_kept, witnessed_kept, false}; /* by enum canergy_rules */
    for (uint8_t rules = 0U; rules <= 2U; rules++) {
        const bool kept = sets[rules];
        const struct canergy_node_config cfg = {
            {CANERGY_DEFAULT_ID_BASE, 100000UL, 100000UL, 5U, rules, 0U}, 1000000UL, 0U,
            CANERGY_KEEP_ALL};
        const struct canergy_supervisor_config sup_cfg = {CANERGY_DEFAULT_ID_BASE,
                                                          {50000U, 3U, rules, 0U}};
        struct canergy_client c;
        struct canergy_node n;
        struct canergy_supervisor sup;
        struct canergy_out out;
        const int client = canergy_client_start(&c, &cfg.client, NULL, 0U, 1U, 0U, &out);
        const int node = canergy_node_start(&n, &cfg, NULL, 0U, 1U, 0U, &out);
        const int supervisor = canergy_supervisor_init(&sup, &sup_cfg, nodes, 1U, 0U);
        check(kept ? client == 0 && node == 0 && supervisor == CANERGY_OK
                   : client == CANERGY_ERR_ARGUMENT && node == CANERGY_ERR_ARGUMENT &&
                         supervisor == CANERGY_ERR_ARGUMENT,
              kept ? "a rule set the build keeps starts" : "a rule set the build lacks is refused");
    }
}

static void test_budgets(void)
{
    check(sizeof(struct canergy_client) <= 128U, "client state within 128 bytes");
    check(sizeof(struct canergy_node) <= 128U, "node state within 128 bytes");
}

/* Parse up to max bytes of hex (even length, no separators); the number of bytes. */
static size_t unhex(const char *hex, uint8_t *out, size_t max)
{
    size_t n = 0U;
    for (; n < max && hex[2U * n] != '\0'; n++) {
        unsigned byte = 0U;
        (void)sscanf(&hex[2U * n], "%2x", &byte);
        out[n] = (uint8_t)byte;
    }
    return n;
}

static int bytes_are(const uint8_t *b, size_t n, const char *hex)
{
    uint8_t want[64];
    return unhex(hex, want, sizeof want) == n && memcmp(b, want, n) == 0;
}

static const char rfc4493_key[] = "2b7e151628aed2a6abf7158809cf4f3c";
static const char rfc4493_msg[] = "6bc1bee22e409f96e93d7e117393172aae2d8a571e03ac9c9eb76fac45af8e51"
                                  "30c81c46a35ce411e5fbc1191a0a52eff69f2445df4f9b17ad2b417be66c3710";

static void test_aes128(void)
{
    struct canergy_aes128 aes;
    uint8_t key[16];
    uint8_t block[16];
    (void)unhex("000102030405060708090a0b0c0d0e0f", key, sizeof key);
    (void)unhex("00112233445566778899aabbccddeeff", block, sizeof block);
    canergy_aes128_init(&aes, key);
    canergy_aes128_encrypt(&aes, block, block);
    check(bytes_are(block, 16U, "69c4e0d86a7b0430d8cdb78070b4c55a"), "AES-128, FIPS-197 C.1");
#ifndef CANERGY_AES_PORT /* the port's context is its own */
    check(bytes_are(&aes.rk[160], 16U, "13111d7fe3944a17f307a78b4d2b30c5"),
          "AES-128 last round key, FIPS-197 C.1");
#endif
}

static bool all_zero(const void *p, size_t n)
{
    const uint8_t *b = p;
    uint8_t any = 0U;
    for (size_t i = 0U; i < n; i++) {
        any |= b[i];
    }
    return any == 0U;
}

static void test_cmac(void)
{
    static const struct {
        size_t len;
        const char *mac;
    } examples[] = {
        {0U, "bb1d6929e95937287fa37d129b756746"},
        {16U, "070a16b46b4d4144f79bdd9dd04a287c"},
        {40U, "dfa66747de9ae63030ca32611497c827"},
        {64U, "51f0bebf7e3b9d92fc49741779363cfe"},
    };
    struct canergy_cmac ctx;
    struct canergy_cmac_stream s;
    uint8_t key[16];
    uint8_t message[64];
    uint8_t mac[16];
    (void)unhex(rfc4493_key, key, sizeof key);
    (void)unhex(rfc4493_msg, message, sizeof message);
    canergy_cmac_init(&ctx, key);
    check(bytes_are(ctx.k1, 16U, "fbeed618357133667c85e08f7236a8de") &&
              bytes_are(ctx.k2, 16U, "f7ddac306ae266ccf90bc11ee46d513b"),
          "CMAC subkeys K1, K2, RFC 4493 4");
    for (size_t i = 0U; i < sizeof examples / sizeof examples[0]; i++) {
        canergy_cmac(&ctx, i == 0U ? NULL : message, examples[i].len, mac);
        check(bytes_are(mac, 16U, examples[i].mac), "CMAC, RFC 4493 examples 1-4");
    }
    /* the 64-byte example again in uneven pieces, an empty one included */
    canergy_cmac_begin(&s);
    canergy_cmac_update(&ctx, &s, message, 15U);
    canergy_cmac_update(&ctx, &s, &message[15], 0U);
    canergy_cmac_update(&ctx, &s, &message[15], 17U);
    canergy_cmac_update(&ctx, &s, &message[32], 32U);
    canergy_cmac_final(&ctx, &s, mac);
    check(bytes_are(mac, 16U, examples[3].mac) && s.n == 0U, "CMAC in pieces, stream wiped");
    canergy_cmac_wipe(&ctx);
    check(all_zero(&ctx.aes, sizeof ctx.aes) && ctx.k2[15] == 0U, "key wiped");
}

static void test_mac_equal(void)
{
    uint8_t a[16];
    uint8_t b[16];
    (void)unhex("51f0bebf7e3b9d92fc49741779363cfe", a, sizeof a);
    memcpy(b, a, sizeof b);
    check(canergy_mac_equal(a, b, 16U) && canergy_mac_equal(a, b, 4U) &&
              canergy_mac_equal(a, b, 1U),
          "equal MACs, full and truncated");
    check(!canergy_mac_equal(a, b, 0U), "a zero-length MAC never matches");
    int each = 1;
    for (size_t i = 0U; i < 16U; i++) {
        b[i] ^= 0x01U; /* one bit anywhere, first or last compared byte */
        each &= !canergy_mac_equal(a, b, 16U) && !canergy_mac_equal(a, b, i + 1U) &&
                (i == 0U || canergy_mac_equal(a, b, i));
        b[i] ^= 0x81U; /* and the top bit */
        each &= !canergy_mac_equal(a, b, i + 1U);
        b[i] ^= 0x80U;
    }
    check(each, "a difference in any compared byte is found; past n it is ignored");
}

static void test_kdf(void)
{
    static const uint8_t label[] = "canergy node key";
    static const uint8_t node[1] = {5U};
    uint8_t master[16];
    uint8_t out[16];
    (void)unhex(rfc4493_key, master, sizeof master);
    canergy_kdf_cmac_ctr(master, label, sizeof label - 1U, node, sizeof node, out);
    check(bytes_are(out, 16U, "e169cefb0c726e0e1bf3d23ae4116882"),
          "KDF as cryptography's KBKDFCMAC (label \"canergy node key\", context 05)");
    canergy_kdf_cmac_ctr(master, NULL, 0U, NULL, 0U, out);
    check(bytes_are(out, 16U, "4a10102ba6c210565f7e327e0befcae6"), "KDF, empty label and context");
}

/* Authenticated frames as src/canergy/auth/frames.py builds them (key: RFC 4493's, node 5;
 * printed once with FrameAuth(Codec(), layout, key, ..., freshness(m, last_tx, return_seq))). */
struct auth_vector {
    enum canergy_auth_layout layout;
    struct canergy_msg m;
    uint32_t last_tx;
    uint32_t return_seq;
    uint32_t id;
    const char *data;
    const char *mac_frame; /* classic: the MAC frame on 0x0CE00005 / 0x0CE00805 */
    const char *what;
};

static const struct auth_vector auth_vectors[] = {
    {CANERGY_AUTH_FD,
     {.type = CANERGY_INTENTION, .node = 5U, .tx = 2U, .amount_mj = 500U, .delivered_mj = 1000U},
     0x0001FFFFUL, 0U, 0x0CE00105UL, "860200F401E803000002000267362F45D1E04133", NULL,
     "FD INTENTION: tx 2 next to 0x1FFFF is FV 0x20002, 20 bytes"},
    {CANERGY_AUTH_FD, {.type = CANERGY_ACK, .node = 5U, .tx = 2U}, 0x0001FFFFUL, 0U,
     0x0CE00905UL, "910200000002000209021F44DA0FE551", NULL, "FD ACK: 16 bytes, FV 0x20002"},
    {CANERGY_AUTH_FD,
     {.type = CANERGY_TELEMETRY, .node = 5U, .level_mj = 500U, .flags = 2U, .seq = 0x1234U,
      .witness = 3U},
     0x00031234UL, 0U, 0x0CE00D05UL, "E8F4010002341203000312349ED47A69393B3879", NULL,
     "FD TELEMETRY: 8 data bytes, no padding, 20 bytes; FV is last_tx, 0x31234"},
    {CANERGY_AUTH_CLASSIC,
     {.type = CANERGY_TELEMETRY, .node = 5U, .level_mj = 500U, .flags = 2U, .seq = 0x1234U,
      .witness = 3U},
     0x00031234UL, 0U, 0x0CE00D05UL, "E8F4010002341203", "0D12349ED47A6939",
     "classic TELEMETRY: its MAC frame carries the FV's low half, 0x1234"},
    {CANERGY_AUTH_FD, {.type = CANERGY_JOIN, .node = 5U, .nonce = 0xBEEFU}, 0U, 0U,
     0x0CE00E05UL, "BCEFBE000000BEEFCDA616F1B0346BF5", NULL, "FD JOIN: FV is the nonce"},
    {CANERGY_AUTH_CLASSIC, {.type = CANERGY_RETURN, .node = 5U, .seq = 0xFFFFU, .amount_mj = 120U},
     0U, 0x00010002UL, 0x0CE00C05UL, "AEFFFF7800", "0C000053434A36E5",
     "classic RETURN: seq 0xFFFF next to 0x10002 is FV 0xFFFF"},
    {CANERGY_AUTH_CLASSIC, {.type = CANERGY_COMMIT, .node = 5U, .tx = 0x8000U, .amount_mj = 300U},
     0U, 0U, 0x0CE00205UL, "BE00802C01", "02FFFF3E7FAD35A0",
     "classic COMMIT: tx 0x8000 next to 0 is -32768, FV 0xFFFF8000"},
};

static int auth_frame_is(const struct canergy_auth_frame *f, uint32_t id, const char *hex)
{
    return f->id == id && bytes_are(f->data, f->len, hex);
}

/* Feed frames[0..n) to a receiver; the last result. */
static int auth_feed(struct canergy_auth *rx, const struct canergy_auth_frame *frames, int n,
                     uint32_t last_tx, uint32_t return_seq, struct canergy_frame *verified)
{
    int result = -100;
    for (int i = 0; i < n; i++) {
        const struct canergy_rx_frame f = {frames[i].id, frames[i].data, frames[i].len, true,
                                           false};
        result = canergy_auth_accept(rx, &f, last_tx, return_seq, verified);
    }
    return result;
}

static void test_auth_vector(const uint8_t key[16], const struct auth_vector *v)
{
    const bool to_supervisor = (v->m.type & CANERGY_FROM_CLIENT) != 0U;
    struct canergy_auth tx_side;
    struct canergy_auth rx_side;
    struct canergy_frame plain;
    struct canergy_frame verified;
    struct canergy_auth_frame out[2];
    (void)canergy_auth_init(&tx_side, key, CANERGY_DEFAULT_ID_BASE, 5U, v->layout,
                            to_supervisor ? CANERGY_TO_CLIENT : CANERGY_TO_SUPERVISOR);
    (void)canergy_auth_init(&rx_side, key, CANERGY_DEFAULT_ID_BASE, 5U, v->layout,
                            to_supervisor ? CANERGY_TO_SUPERVISOR : CANERGY_TO_CLIENT);
    (void)canergy_encode(CANERGY_DEFAULT_ID_BASE, &v->m, &plain);
    const int n = canergy_auth_protect(&tx_side, &plain, v->last_tx, v->return_seq, out);
    const uint32_t mac_id = CANERGY_DEFAULT_ID_BASE | (to_supervisor ? 0x800UL : 0U) | 5U;
    check(n == (v->mac_frame == NULL ? 1 : 2) && auth_frame_is(&out[0], v->id, v->data) &&
              (n == 1 || auth_frame_is(&out[1], mac_id, v->mac_frame)),
          v->what);
    check(auth_feed(&rx_side, out, n, v->last_tx, v->return_seq, &verified) == CANERGY_DECODE_OK &&
              verified.id == plain.id && verified.dlc == plain.dlc &&
              memcmp(verified.data, plain.data, plain.dlc) == 0,
          "the receiver verifies it and hands back the classic frame");
    out[n - 1].data[out[n - 1].len - 1U] ^= 0x01U; /* last MAC bit */
    check(auth_feed(&rx_side, out, n, v->last_tx, v->return_seq, &verified) ==
              CANERGY_AUTH_MAC_BAD,
          "a flipped MAC bit is MAC BAD");
    out[n - 1].data[out[n - 1].len - 1U] ^= 0x01U;
    const bool checks_fv = v->m.type != CANERGY_TELEMETRY && v->m.type != CANERGY_JOIN;
    check(!checks_fv || auth_feed(&rx_side, out, n, v->last_tx + 0x10000UL,
                                  v->return_seq + 0x10000UL, &verified) == CANERGY_AUTH_STALE,
          "a frame 65,536 counts old is stale");
}

static void test_auth_refusals(const uint8_t key[16])
{
    struct canergy_auth node;
    struct canergy_frame plain;
    struct canergy_frame verified;
    struct canergy_msg m = msg(CANERGY_COMMIT, 5U);
    m.tx = 1U;
    m.amount_mj = 300U;
    (void)canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &plain);
    const struct canergy_rx_frame bare = {plain.id, plain.data, plain.dlc, true, false};
    (void)canergy_auth_init(&node, key, CANERGY_DEFAULT_ID_BASE, 5U, CANERGY_AUTH_FD,
                            CANERGY_TO_CLIENT);
    check(canergy_auth_accept(&node, &bare, 0U, 0U, &verified) == CANERGY_AUTH_UNAUTHENTICATED,
          "FD: a classic frame is a frame without a MAC");
    uint8_t padded[20] = {0};
    memcpy(padded, plain.data, plain.dlc);
    padded[6] = 1U;
    const struct canergy_rx_frame dirty = {plain.id, padded, 20U, true, false};
    check(canergy_auth_accept(&node, &dirty, 0U, 0U, &verified) == CANERGY_DECODE_WRONG_DLC,
          "FD: padding that is not zero is the codec's wrong length");
    (void)canergy_auth_init(&node, key, CANERGY_DEFAULT_ID_BASE, 5U, CANERGY_AUTH_CLASSIC,
                            CANERGY_TO_CLIENT);
    const uint8_t trailer[8] = {CANERGY_COMMIT, 0U, 0U, 1U, 2U, 3U, 4U, 5U};
    const struct canergy_rx_frame mac_only = {0x0CE00005UL, trailer, 8U, true, false};
    const struct canergy_rx_frame short_mac = {0x0CE00005UL, trailer, 7U, true, false};
    const struct canergy_rx_frame their_mac = {0x0CE00805UL, trailer, 8U, true, false};
    check(canergy_auth_accept(&node, &mac_only, 0U, 0U, &verified) == CANERGY_AUTH_NO_DATA,
          "classic: a MAC frame without its message");
    check(canergy_auth_accept(&node, &bare, 0U, 0U, &verified) == CANERGY_AUTH_PENDING &&
              canergy_auth_accept(&node, &short_mac, 0U, 0U, &verified) ==
                  CANERGY_AUTH_MALFORMED &&
              canergy_auth_accept(&node, &mac_only, 0U, 0U, &verified) == CANERGY_AUTH_NO_DATA,
          "classic: a 7-byte MAC frame is malformed and uses up the waiting message");
    check(canergy_auth_accept(&node, &their_mac, 0U, 0U, &verified) ==
              CANERGY_DECODE_WRONG_DIRECTION,
          "classic: a node->supervisor MAC frame at a node is the wrong direction");
    canergy_auth_wipe(&node);
    check(node.key.k1[0] == 0U && node.node == 0U, "wiped");
}

/* A node joins, is admitted and granted through authenticated frames (classic layout). */
static void test_auth_node(const uint8_t key[16])
{
    const struct canergy_node_config cfg = {
        {CANERGY_DEFAULT_ID_BASE, 100000UL, 100000UL, 5U, CANERGY_RULES_HARDENED, 0U}, 1000000UL, 0U, CANERGY_KEEP_ALL};
    struct canergy_node n;
    struct canergy_auth node_auth;
    struct canergy_auth sup;
    struct canergy_out out;
    struct canergy_frame plain;
    struct canergy_frame verified;
    struct canergy_auth_frame frames[2];
    (void)canergy_auth_init(&node_auth, key, CANERGY_DEFAULT_ID_BASE, 5U, CANERGY_AUTH_CLASSIC,
                            CANERGY_TO_CLIENT);
    (void)canergy_auth_init(&sup, key, CANERGY_DEFAULT_ID_BASE, 5U, CANERGY_AUTH_CLASSIC,
                            CANERGY_TO_SUPERVISOR);
    (void)canergy_node_start(&n, &cfg, NULL, 0U, 0x1234U, 0U, &out);
    int n_frames = canergy_auth_node_protect(&node_auth, &n, &out.frames[0], frames);
    check(n_frames == 2 && auth_feed(&sup, frames, 2, 0U, 0U, &verified) == CANERGY_DECODE_OK &&
              verified.id == 0x0CE00E05UL,
          "the node's JOIN verifies at the supervisor");
    struct canergy_msg m = msg(CANERGY_ADMIT, 5U);
    m.nonce = 0x1234U;
    m.tx = 0xFFFFU;
    m.seq = 3U;
    (void)canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &plain);
    n_frames = canergy_auth_protect(&sup, &plain, 0xFFFFUL, 0U, frames); /* the sender's tx: k */
    struct canergy_rx_frame f = {frames[0].id, frames[0].data, frames[0].len, true, false};
    int first = canergy_auth_node_frame(&node_auth, &n, &f, 10U, &out);
    f = (struct canergy_rx_frame){frames[1].id, frames[1].data, frames[1].len, true, false};
    check(n_frames == 2 && first == CANERGY_AUTH_PENDING && out.frame_count == 0U &&
              canergy_auth_node_frame(&node_auth, &n, &f, 11U, &out) == CANERGY_DECODE_OK &&
              !canergy_client_joining(&n.client) && n.client.rec.last_tx == 0xFFFFUL,
          "the ADMIT counts once its MAC frame came");
    m = msg(CANERGY_INTENTION, 5U);
    m.tx = 0U; /* 0x10000 */
    m.amount_mj = 700U;
    (void)canergy_encode(CANERGY_DEFAULT_ID_BASE, &m, &plain);
    (void)canergy_auth_protect(&sup, &plain, 0x10000UL, 0U, frames);
    f = (struct canergy_rx_frame){frames[0].id, frames[0].data, frames[0].len, true, false};
    (void)canergy_auth_node_frame(&node_auth, &n, &f, 20U, &out);
    f = (struct canergy_rx_frame){frames[1].id, frames[1].data, frames[1].len, true, false};
    check(canergy_auth_node_frame(&node_auth, &n, &f, 21U, &out) == CANERGY_DECODE_OK &&
              out.frame_count == 1U && out.frames[0].id == 0x0CE00905UL,
          "an INTENTION across the 16-bit wrap verifies and is acknowledged");
    n_frames = canergy_auth_node_protect(&node_auth, &n, &out.frames[0], frames);
    check(n_frames == 2 &&
              auth_feed(&sup, frames, 2, 0x10000UL, 0U, &verified) == CANERGY_DECODE_OK &&
              auth_feed(&sup, frames, 2, 0U, 0U, &verified) == CANERGY_AUTH_STALE,
          "its ACK verifies at FV 0x10000, not at 0");
    /* frames in its name: its ACK and MAC frame replayed, a MAC frame of node 6 */
    const uint8_t witness = n.witness;
    f = (struct canergy_rx_frame){frames[0].id, frames[0].data, frames[0].len, true, false};
    const int data = canergy_auth_node_frame(&node_auth, &n, &f, 30U, &out);
    f = (struct canergy_rx_frame){frames[1].id, frames[1].data, frames[1].len, true, false};
    const int mac = canergy_auth_node_frame(&node_auth, &n, &f, 31U, &out);
    f.id = 0x0CE00806UL;
    const int theirs = canergy_auth_node_frame(&node_auth, &n, &f, 32U, &out);
    check(data == CANERGY_DECODE_WRONG_DIRECTION && mac == CANERGY_DECODE_WRONG_DIRECTION &&
              theirs == CANERGY_DECODE_WRONG_DIRECTION && n.witness == witness + 2U &&
              out.frame_count == 0U && canergy_node_deadline(&n) <= 31U, /* due */
          "authenticated: its own direction with its id, MAC frames too, is witnessed");
    canergy_auth_wipe(&node_auth);
    canergy_auth_wipe(&sup);
}

static void test_auth(bool node)
{
    uint8_t key[16];
    (void)unhex(rfc4493_key, key, sizeof key);
    for (size_t i = 0U; i < sizeof auth_vectors / sizeof auth_vectors[0]; i++) {
        test_auth_vector(key, &auth_vectors[i]);
    }
    test_auth_refusals(key);
    if (node) { /* configured with the hardened rules */
        test_auth_node(key);
    }
}

/* The answers at once: an ACK decided in the same out; one naming a transaction never begun
 * and a TELEMETRY left to the caller, nothing applied. */
static void test_supervisor_answers(void)
{
    static struct canergy_supervisor sup;
    static struct canergy_supervisor_out out;
    const struct canergy_supervisor_config cfg = {CANERGY_DEFAULT_ID_BASE, {50000U, 3U, CANERGY_RULES_HARDENED, 0U}};
    const uint8_t nodes[1] = {3U};
    struct canergy_msg m;
    check(canergy_supervisor_init(&sup, &cfg, nodes, 1U, 5000U) == CANERGY_OK &&
              canergy_supervisor_begin(&sup, 3U, 2000U, 0U, &out) == CANERGY_OK,
          "answers: an intention to node 3");
    const uint8_t ahead[3] = {0xF8U, 0x02U, 0x00U}; /* ACK(3, tx 2) */
    struct canergy_rx_frame f = {0x0CE00903UL, ahead, 3U, true, false};
    check(canergy_supervisor_on_answer(&sup, &f, 10U, false, &out, &m) == CANERGY_RX_AHEAD &&
              sup.sessions[0].phase == CANERGY_S_WAIT_ACK && out.frame_count == 0U,
          "an ACK of a transaction never begun: left to the caller, nothing applied");
    const uint8_t level[8] = {0x1BU, 0x05U, 0U, 0U, 0U, 0U, 0U, 0U}; /* TELEMETRY(3, 5 mJ) */
    f.id = 0x0CE00D03UL;
    f.data = level;
    f.len = 8U;
    check(canergy_supervisor_on_answer(&sup, &f, 10U, false, &out, &m) == CANERGY_RX_CALLER &&
              m.type == CANERGY_TELEMETRY && m.level_mj == 5U && out.frame_count == 0U,
          "a TELEMETRY: decoded for the caller");
    const uint8_t ack[3] = {0x2CU, 0x01U, 0x00U}; /* ACK(3, tx 1) */
    f.id = 0x0CE00903UL;
    f.data = ack;
    f.len = 3U;
    check(canergy_supervisor_on_answer(&sup, &f, 11U, false, &out, &m) == CANERGY_DECODE_OK &&
              out.persist && out.frame_count == 1U && out.frames[0].id == 0x0CE00203UL &&
              out.event_count == 2U && out.events[0].flags == CANERGY_SUP_ACKNOWLEDGED &&
              sup.sessions[0].phase == CANERGY_S_WAIT_CONFIRM &&
              sup.sessions[0].decision == CANERGY_DECIDE_COMMIT,
          "the ACK: committed in the same out, persisted, COMMIT to send");
}

/* The gateway rules: what the client above holds goes below at once; a give-back takes it
 * out of Us below into a RETURN above; never any energy between the two roles. */
static void test_gateway(void)
{
    static struct canergy_gateway gw;
    static struct canergy_out out;
    static struct canergy_supervisor_out sup_out;
    const struct canergy_client_config up = {CANERGY_DEFAULT_ID_BASE, 100000U, 100000U, 7U, CANERGY_RULES_HARDENED, 0U};
    const struct canergy_supervisor_config down = {CANERGY_DEFAULT_ID_BASE, {50000U, 3U, CANERGY_RULES_HARDENED, 0U}};
    const uint8_t nodes[1] = {3U};
    (void)canergy_client_start(&gw.up, &up, NULL, 0U, 1U, 0U, &out);
    gw.up.phase = CANERGY_IDLE; /* admitted (tests reach in) */
    check(canergy_supervisor_init(&gw.down, &down, nodes, 1U, 0U) == CANERGY_OK, "gateway init");
    gw.up.rec.usable_uj = 3000U; /* a commit above */
    check(canergy_gateway_forward(&gw, &out) == 3000U && out.persist && gw.up.rec.usable_uj == 0U &&
              gw.up.rec.spent_uj == 3000U && gw.down.usable_uj == 3000U &&
              canergy_gateway_link_gap(&gw) == 0,
          "forward: usable above becomes Us below, in one persisted step");
    check(canergy_gateway_forward(&gw, &out) == 0U, "nothing more to forward");
    check(canergy_supervisor_begin(&gw.down, 3U, 1000U, 0U, &sup_out) == CANERGY_OK &&
              gw.down.usable_uj == 2000U,
          "granted below from what came from above");
    check(canergy_gateway_give_back(&gw, 3000U, 0U, &out) == CANERGY_ERR_AMOUNT &&
              canergy_gateway_give_back(&gw, 1500U, 0U, &out) == CANERGY_ERR_AMOUNT &&
              out.frame_count == 0U && gw.down.usable_uj == 2000U,
          "give back: no more than Us below, whole mJ, nothing moved on a refusal");
    check(canergy_gateway_give_back(&gw, 2000U, 0U, &out) == CANERGY_OK && out.persist &&
              out.frame_count == 1U && gw.down.usable_uj == 0U && gw.down.withdrawn_uj == 2000U &&
              gw.up.rec.return_pending_uj == 2000U && gw.up.rec.spent_uj == 1000U &&
              canergy_gateway_link_gap(&gw) == 0,
          "give back: Us below withdrawn into the next RETURN above");
    check(canergy_gateway_give_back(&gw, 1000U, 0U, &out) == CANERGY_ERR_PHASE,
          "one return at a time");
}

int main(void)
{
    test_crcs();
    test_documented_frames();
    test_decode_reasons();
    test_refusals_write_nothing();
    test_rules_kept();
    test_budgets();
    if (hardened_kept) { /* configured with the hardened rules */
        test_a_node_from_blank_to_books();
        test_node_witness();
        test_session();
        test_supervisor();
        test_supervisor_answers();
        test_gateway();
    }
#ifdef CANERGY_WITNESSED
    test_witnessed_older_copy();
#endif
    test_aes128();
    test_cmac();
    test_mac_equal();
    test_kdf();
    test_auth(hardened_kept);
    printf("sizeof client %u, node %u, out %u bytes\n", (unsigned)sizeof(struct canergy_client),
           (unsigned)sizeof(struct canergy_node), (unsigned)sizeof(struct canergy_out));
    printf("%u passed, %u failed\n", passed, failed);
    return failed == 0U ? 0 : 1;
}
