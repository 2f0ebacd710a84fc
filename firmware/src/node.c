/*
 * The node layer: telemetry, the actuator's draw and the return policy around the client, as
 * firmware_model/node.py does around canergy.core.Client (see include/canergy/node.h).
 */
#include "canergy/node.h"

#include "client_internal.h"
#include "rules.h"

#include <string.h>

#define MJ CANERGY_QUANTUM_UJ

static bool is_low(const struct canergy_node *n)
{
    return n->client.rec.usable_uj < n->low_water_uj;
}

/* The flags' two lowest bits are the booleans themselves (2 bytes of the node's flash budget). */
#if CANERGY_TELEMETRY_LOW != 1U || CANERGY_TELEMETRY_HALTED != 2U
#error "send_telemetry shifts is_low and halted into LOW and HALTED"
#endif

static void send_telemetry(struct canergy_node *n, struct canergy_out *out, uint64_t now)
{
    const uint32_t level = n->client.rec.usable_uj / MJ;
    const uint32_t fields[4] = {
        level > CANERGY_WIDE_MAX ? CANERGY_WIDE_MAX : level, /* saturating */
        (uint32_t)is_low(n) | (uint32_t)n->halted << 1U | /* LOW, HALTED: checked above */
            (n->client.phase == CANERGY_JOINING ? CANERGY_TELEMETRY_JOINING : 0U) |
            (rules_witnessed(n->client.rules) ? CANERGY_TELEMETRY_WITNESSED : 0U),
        (uint16_t)n->client.rec.return_seq, /* the number its RETURN frames carry */
        n->witness,
    }; /* TELEMETRY: level, flags, seq, witness */
    n->witness_reported = n->witness;
    n->next_telemetry = now + n->telemetry_period_us;
    n->early_telemetry = now + CANERGY_WITNESS_GAP_US;
    canergy_internal_send(&n->client, CANERGY_TELEMETRY, fields, out);
}

/* What the client's step means for the node: a new level is reported at once. */
static void after_client(struct canergy_node *n, uint64_t now, const struct canergy_out *out)
{
    const uint16_t level_moved =
        CANERGY_EV_COMMITTED | CANERGY_EV_TIMEOUT_COMMIT | CANERGY_EV_CREDITED | CANERGY_EV_ADMITTED;
    if ((out->events & level_moved) != 0U) {
        n->next_telemetry = now;
    }
}

void canergy_internal_witness(struct canergy_node *n, struct canergy_out *out, uint64_t now)
{
    n->witness = (uint8_t)(n->witness + 1U); /* modulo 256, as on the wire */
    /* due at the next poll, but no sooner than a gap after the last TELEMETRY */
    if (n->early_telemetry < n->next_telemetry) {
        n->next_telemetry = n->early_telemetry;
    }
    if ((uint8_t)(n->witness - n->witness_reported) >= CANERGY_WITNESS_REPORT_AT) {
        send_telemetry(n, out, now); /* at once: the count never moves 256 between reports */
    }
}

/* An answer to something the node never sent: a RETURN_ACK for a return number ahead of its own
 * (serial16 > 0; the step left return_seq as it was), an ADMIT not for this start's JOIN. */
static bool never_asked(const struct canergy_node *n, const struct canergy_msg *m)
{
    if (m->type == CANERGY_RETURN_ACK) {
        const uint16_t ahead = (uint16_t)(m->seq - (uint16_t)n->client.rec.return_seq);
        return ahead != 0U && ahead < 0x8000U;
    }
    return m->type == CANERGY_ADMIT && !(n->joined && m->nonce == n->join_nonce);
}

/* Periodic telemetry, and at once when the level has just fallen below the low-water mark. */
static void telemetry_due(struct canergy_node *n, uint64_t now, struct canergy_out *out)
{
    const bool low = is_low(n);
    if (now >= n->next_telemetry || (low && !n->was_low)) {
        send_telemetry(n, out, now);
    }
    n->was_low = low;
}

int canergy_node_start(struct canergy_node *n, const struct canergy_node_config *cfg,
                       const uint8_t *nv_image, size_t nv_len, uint16_t nonce, uint64_t now,
                       struct canergy_out *out)
{
    if (n == NULL || cfg == NULL || out == NULL || cfg->telemetry_period_us == 0U) {
        return CANERGY_ERR_ARGUMENT;
    }
    canergy_internal_out_clear(out);
    memset(n, 0, sizeof *n);
    const int result =
        canergy_internal_start(&n->client, &cfg->client, nv_image, nv_len, nonce, now, out);
    n->telemetry_period_us = cfg->telemetry_period_us;
    n->low_water_uj = cfg->low_water_uj;
    n->return_above_uj = cfg->return_above_uj;
    n->next_telemetry = now; /* announce the level at boot */
    /* JOINING or (witnessed) RESUMING: a start is never SYNCING */
    n->joined = n->client.phase >= CANERGY_JOINING;
    n->join_nonce = nonce;
    return result;
}

int canergy_node_on_frame(struct canergy_node *n, const struct canergy_rx_frame *frame,
                          uint64_t now, struct canergy_out *out)
{
    if (n == NULL || out == NULL) {
        return CANERGY_ERR_ARGUMENT;
    }
    canergy_internal_out_clear(out);
    struct canergy_msg m = {0}; /* read only when decoded: gcc -flto cannot tell */
#ifdef CANERGY_WITNESSED
    const uint64_t spent = n->client.rec.spent_uj;
#endif
    const int result = canergy_internal_frame(&n->client, frame, now, out, &m);
#ifdef CANERGY_WITNESSED
    /* an acknowledged DRAW is the actuator's now (spent grew by it) */
    n->released_uj += (uint32_t)(n->client.rec.spent_uj - spent);
#endif
    if ((out->events & CANERGY_EV_REFUSED) != 0U) {
        n->overflow_refused++;
    }
    /* A frame with this node's id: witnessed when it is in the node's own direction (the codec
     * checked the id block, the type and the node) or answers nothing the node sent; a decode
     * error when the codec refused it otherwise. Foreign frames and other nodes' (seen without
     * acceptance filters; never with its id) are no error of ours. */
    const bool own_id = frame != NULL && (frame->id & 0xFFU) == n->client.node;
    const bool witnessed = result == CANERGY_DECODE_WRONG_DIRECTION
                               ? own_id
                               : result == CANERGY_DECODE_OK && never_asked(n, &m);
    if (witnessed) {
        canergy_internal_witness(n, out, now);
    } else if (own_id && result != CANERGY_DECODE_OK &&
               result != CANERGY_DECODE_FOREIGN) {
        n->decode_errors++;
    }
    after_client(n, now, out);
    return result;
}

/* Each timer fires only when due (the first step of a call: out holds nothing before). */
static void timers(struct canergy_node *n, uint64_t now, struct canergy_out *out)
{
    canergy_internal_timers(&n->client, now, out);
    after_client(n, now, out);
}


/* After an actuator period, at most one debit (the debit refuses, changing nothing, when none
 * may be numbered now, one at a time, or it is 0). Witnessed: when what the actuator holds would
 * not cover the next period, a DRAW ahead, CANERGY_DRAW_AHEAD periods' worth up to whole mJ, at
 * most a frame's worth and what usable holds. Otherwise the return policy: what exceeds
 * return_above given back, in whole mJ, at most a frame's worth. A DRAW tried either leaves or
 * is refused for what refuses a give-back too (a debit pending, the books not confirmed, less
 * than 1 mJ usable), so the return policy has nothing to do after one. */
static void debit_policy(struct canergy_node *n, uint32_t wanted_uj, uint64_t now,
                         struct canergy_out *out)
{
    const uint32_t usable = n->client.rec.usable_uj;
    uint32_t over = usable > n->return_above_uj ? usable - n->return_above_uj : 0U;
    uint8_t draw = 0U;
#ifdef CANERGY_WITNESSED
    if (rules_witnessed(n->client.rules) && n->released_uj < wanted_uj) {
        draw = CANERGY_RECORD_PENDING_DRAW;
        over = usable;
    }
#else
    (void)wanted_uj;
#endif
    uint32_t amount = over - over % MJ; /* whole mJ, at most one frame's worth */
    amount = amount < CANERGY_AMOUNT_MAX_MJ * MJ ? amount : CANERGY_AMOUNT_MAX_MJ * MJ;
#ifdef CANERGY_WITNESSED
    if (draw != 0U && wanted_uj < amount / CANERGY_DRAW_AHEAD) {
        /* 32-bit only (no 64-bit division linked in): below amount, no overflow */
        const uint32_t ahead = wanted_uj * CANERGY_DRAW_AHEAD;
        amount = (uint32_t)((ahead + MJ - 1U) / MJ * MJ); /* up to whole mJ: at most amount */
    }
#endif
    (void)canergy_internal_debit(&n->client, amount, now, draw, out);
}

/* A poll (draw false: timers, telemetry) or an actuator period (timers, the draw of wanted_uj,
 * the return policy, telemetry): the microjoules the actuator may use. */
static uint32_t step(struct canergy_node *n, bool draw, uint32_t wanted_uj, uint64_t now,
                     struct canergy_out *out)
{
    if (n == NULL || out == NULL) {
        return 0U;
    }
    canergy_internal_out_clear(out);
    timers(n, now, out);
    uint32_t take = 0U;
    if (draw) {
#ifdef CANERGY_WITNESSED
        if (rules_witnessed(n->client.rules)) {
            take = wanted_uj < n->released_uj ? wanted_uj : n->released_uj;
            n->released_uj -= take;
        } else
#endif
        {
            const uint32_t usable = n->client.rec.usable_uj;
            take = wanted_uj < usable ? wanted_uj : usable;
            if (canergy_internal_spend(&n->client, take, out) != CANERGY_OK) {
                take = 0U; /* joining, or nothing to spend: refused, nothing changed */
            }
        }
        n->halted = take < wanted_uj;
        debit_policy(n, wanted_uj, now, out);
    }
    telemetry_due(n, now, out);
    return take;
}

void canergy_node_poll(struct canergy_node *n, uint64_t now, struct canergy_out *out)
{
    (void)step(n, false, 0U, now, out);
}

uint32_t canergy_node_draw(struct canergy_node *n, uint32_t wanted_uj, uint64_t now,
                           struct canergy_out *out)
{
    return step(n, true, wanted_uj, now, out);
}

uint64_t canergy_node_deadline(const struct canergy_node *n)
{
    if (n == NULL) {
        return CANERGY_NEVER;
    }
    const uint64_t client = canergy_internal_deadline(&n->client);
    return client < n->next_telemetry ? client : n->next_telemetry;
}
