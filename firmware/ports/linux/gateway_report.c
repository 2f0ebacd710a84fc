/*
 * canergy-gateway's reports below (gateway_port.h): intrusions and refused frames, counted per
 * node, with rates, and told on stderr as `canergy gateway` tells them (its supervisor's
 * Intrusions and Refusals, src/canergy/live/supervisor/intrusions.py): a node's first intrusion
 * and then one in 100 (refused frames are counted among them quietly); the first refused frame
 * at once with its frame, then at most one line a second with what was refused since.
 */
#define _GNU_SOURCE 1

#include "gateway_port.h"

#include <stdio.h>

#define LOG_EVERY 100U            /* after a node's first intrusion, one logged in this many */
#define LOG_PERIOD_US US_PER_S    /* refusals: at most one line in this long */
#define RATE_WINDOW_US US_PER_S   /* rates: per second, over a sliding window this long */

const char *const gw_refusal_names[REFUSAL_REASONS] = {
    "MAC BAD", "freshness not the expected one", "MAC frame without its message",
    "malformed authenticated frame", "frame without a MAC", /* Python's AuthFailure */
    "freshness not the expected one (a JOIN of an earlier life: the node has its books)",
    "a frame in the supervisor's direction (not verified)"};

/* candump's compact form, as Python's frame_text: 0CE00905#450100 */
void gw_frame_text(char out[GW_FRAME_TEXT], const struct canergy_rx_frame *rx)
{
    int at = snprintf(out, GW_FRAME_TEXT, "%08X#%s", (unsigned)rx->id, rx->remote ? "R" : "");
    for (size_t i = 0U; !rx->remote && rx->data != NULL && i < rx->len &&
                        at + 3 <= (int)GW_FRAME_TEXT;
         i++) {
        at += snprintf(&out[at], GW_FRAME_TEXT - (size_t)at, "%02X", (unsigned)rx->data[i]);
    }
}

void gw_msg_text(char out[GW_MSG_TEXT], const struct canergy_msg *m)
{
    if (m->type == CANERGY_TELEMETRY) {
        (void)snprintf(out, GW_MSG_TEXT, "Telemetry(node=%u, level_mj=%lu, flags=%u, seq=%u, "
                                         "witness=%u)",
                       (unsigned)m->node, (unsigned long)m->level_mj, (unsigned)m->flags,
                       (unsigned)m->seq, (unsigned)m->witness);
    } else if (m->type == CANERGY_RETURN || m->type == CANERGY_DEBIT) {
        (void)snprintf(out, GW_MSG_TEXT, "%s(node=%u, seq=%u, amount_mj=%u)",
                       m->type == CANERGY_RETURN ? "Return" : "Debit", (unsigned)m->node,
                       (unsigned)m->seq, (unsigned)m->amount_mj);
    } else {
        (void)snprintf(out, GW_MSG_TEXT, "type 0x%X (node=%u)", (unsigned)m->type,
                       (unsigned)m->node);
    }
}

/* Python's Rate: the current window's count plus the previous one's, weighted by how much of it
 * still lies within the last second. */
static void rate_roll(struct gw_rate *r, uint64_t now)
{
    const uint64_t index = now / RATE_WINDOW_US;
    if (index != r->index) {
        r->previous = index == r->index + 1U ? r->current : 0U;
        r->current = 0U;
        r->index = index;
    }
}

double gw_rate_per_s(const struct gw_rate *r, uint64_t now)
{
    struct gw_rate at = *r;
    rate_roll(&at, now);
    const double left = 1.0 - (double)(now % RATE_WINDOW_US) / (double)RATE_WINDOW_US;
    return (double)at.previous * left + (double)at.current;
}

void gw_intrusion(struct gateway_port *g, unsigned i, const char *what, const char *kind,
                  int quiet, uint64_t now)
{
    struct below *b = &g->below[i];
    b->intrusions++;
    if (!g->intrusions_seen) {
        g->intrusions_seen = 1;
        g->intrusions_first_at = now;
    }
    if (quiet) {
        return;
    }
    b->loud++;
    if (b->loud == 1U || b->loud % LOG_EVERY == 0U) {
        (void)fprintf(stderr, "%s: intrusion #%lu for node %u below: %s (%s)\n", PROG,
                      (unsigned long)b->intrusions, (unsigned)g->opt.nodes[i], what, kind);
    }
}

void gw_refused(struct gateway_port *g, unsigned i, unsigned reason, const char *what,
                uint64_t now)
{
    struct below *b = &g->below[i];
    b->refused[reason]++;
    b->unlogged[reason]++;
    rate_roll(&b->rates[reason], now);
    b->rates[reason].current++;
    rate_roll(&g->refusal_rate, now);
    g->refusal_rate.current++;
    if (g->refused_total++ == 0U) {
        g->refused_first_at = now;
    }
    g->refused_last_at = now;
    gw_intrusion(g, i, what, gw_refusal_names[reason], 1, now);
    if (!g->refusals_logged) { /* the first one at once, with its frame */
        g->refusals_logged = 1;
        g->refusals_logged_at = now;
        b->unlogged[reason] = 0U;
        (void)fprintf(stderr,
                      "%s: refused a frame for node %u below: %s (%s); refused frames are "
                      "counted and reported (at most one line a second), never acted on\n",
                      PROG, (unsigned)g->opt.nodes[i], gw_refusal_names[reason], what);
    } else {
        gw_refusals_tick(g, now);
    }
}

void gw_refusals_tick(struct gateway_port *g, uint64_t now)
{
    if (!g->refusals_logged || now - g->refusals_logged_at < LOG_PERIOD_US) {
        return;
    }
    uint64_t count = 0U;
    for (unsigned i = 0U; i < g->opt.count; i++) {
        for (unsigned k = 0U; k < REFUSAL_REASONS; k++) {
            count += g->below[i].unlogged[k];
        }
    }
    if (count == 0U) {
        return;
    }
    (void)fprintf(stderr, "%s: refused %llu frame(s) below in the last %.1f s (%.1f/s now;", PROG,
                  (unsigned long long)count, (double)(now - g->refusals_logged_at) / 1e6,
                  gw_rate_per_s(&g->refusal_rate, now));
    for (unsigned i = 0U, n = 0U; i < g->opt.count; i++) {
        struct below *b = &g->below[i];
        for (unsigned k = 0U, r = 0U; k < REFUSAL_REASONS; k++) {
            if (b->unlogged[k] == 0U) {
                continue;
            }
            if (r++ == 0U) {
                (void)fprintf(stderr, "%s node %u: ", n++ == 0U ? "" : ";",
                              (unsigned)g->opt.nodes[i]);
            } else {
                (void)fputs(", ", stderr);
            }
            (void)fprintf(stderr, "%s %lu", gw_refusal_names[k], (unsigned long)b->unlogged[k]);
            b->unlogged[k] = 0U;
        }
    }
    (void)fprintf(stderr, "); %llu since start, none acted on\n",
                  (unsigned long long)g->refused_total);
    g->refusals_logged_at = now;
}
