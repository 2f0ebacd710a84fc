/*
 * canergy-gateway's bus above (canergy_gateway.c: main and its loop): the frames of the
 * gateway's client role, what it hears in its name, its TELEMETRY (the level it can grant
 * below) and the RETURNs of what it holds above --return-above.
 */
#define _GNU_SOURCE 1

#include "gateway_port.h"
#include "socketcan.h"

#include <string.h>

static uint64_t least(uint64_t a, uint64_t b)
{
    return a < b ? a : b;
}

/* ---- carrying out what the library asks: both records on disk before any frame ---- */

void gw_send_up(struct gateway_port *g, const struct canergy_frame *f)
{
    if (g->opt.up_auth_path == NULL) {
        port_can_send(g->up_sock, &g->up_count, f->id, f->data, f->dlc);
        return;
    }
    struct canergy_auth_frame frames[2];
    const int n = canergy_auth_gateway_up_protect(&g->up_auth, &g->gw, f, frames);
    for (int k = 0; k < n; k++) {
        port_can_send(g->up_sock, &g->up_count, frames[k].id, frames[k].data, frames[k].len);
    }
}

void gw_up_out(struct gateway_port *g, const struct canergy_out *out)
{
    if (out->persist) {
        gw_save(g);
    }
    for (unsigned i = 0U; i < out->frame_count; i++) {
        gw_send_up(g, &out->frames[i]);
    }
}

/* ---- the bus above ---- */

/* A frame in its name above that it did not send: count it, report it at the next pass but no
 * sooner than CANERGY_WITNESS_GAP_US after the last TELEMETRY (two gateways on one id would
 * answer each other's reports with no pause), or at once when CANERGY_WITNESS_REPORT_AT went
 * unreported (the 8-bit count never moves a whole turn between reports): the node's rule. */
static void witness(struct gateway_port *g, uint64_t now)
{
    g->witnessed++;
    g->next_telemetry = least(g->next_telemetry, g->early_telemetry);
    if (g->witnessed - g->witness_reported >= CANERGY_WITNESS_REPORT_AT) {
        gw_telemetry(g, now);
    }
}

void gw_receive_up(struct gateway_port *g, uint64_t now)
{
    struct canfd_frame cf;
    struct canergy_rx_frame rx;
    while (port_can_receive(g->up_sock, &g->up_count, &cf, &rx) == 1) {
        struct canergy_out out;
        const uint64_t withdrawn = g->gw.down.withdrawn_uj;
        const int status = g->opt.up_auth_path != NULL
                               ? canergy_auth_gateway_up_frame(&g->up_auth, &g->gw, &rx, now, &out)
                               : canergy_gateway_on_up_frame(&g->gw, &rx, now, &out);
        const int behind = (out.events & CANERGY_GW_EV_FOUND_BEHIND) != 0U;
        if (behind) {
            g->found_behind++;
            g->dropped_uj += g->gw.down.withdrawn_uj - withdrawn;
        }
        gw_say_up_waiting(g, behind, g->gw.down.withdrawn_uj - withdrawn);
        if (status >= CANERGY_AUTH_MAC_BAD && status <= CANERGY_AUTH_UNAUTHENTICATED) {
            g->auth_refused++; /* --upstream-auth: refused, nothing acted on */
        } else if (status != CANERGY_AUTH_PENDING) {
            gw_count_decode(&g->up_count, status);
        }
        if (status == CANERGY_DECODE_WRONG_DIRECTION && (rx.id & 0xFFU) == g->opt.node) {
            witness(g, now); /* someone speaks in its name above */
        }
        gw_up_out(g, &out);
        if ((out.events & (CANERGY_EV_COMMITTED | CANERGY_EV_TIMEOUT_COMMIT | CANERGY_EV_CREDITED |
                           CANERGY_EV_ADMITTED)) != 0U) {
            g->next_telemetry = now; /* the level moved: report it at once */
        }
    }
}

/* The client's timer above, when due; a commit or pay-back it makes is reported at once. */
void gw_up_timer(struct gateway_port *g, uint64_t now)
{
    if (canergy_client_deadline(&g->gw.up) > now) {
        return;
    }
    struct canergy_out out;
    canergy_gateway_on_up_timer(&g->gw, now, &out);
    gw_up_out(g, &out);
    if ((out.events & (CANERGY_EV_TIMEOUT_COMMIT | CANERGY_EV_CREDITED)) != 0U) {
        g->next_telemetry = now;
    }
}

/* ---- the policy above (the library's): returns, the level reported ---- */

void gw_give_back(struct gateway_port *g, uint64_t now)
{
    const uint32_t excess = canergy_gateway_give_back_amount(g->gw.down.usable_uj,
                                                             g->opt.return_above_uj);
    struct canergy_out out;
    if (!g->opt.keep_all && excess != 0U && canergy_client_can_give_back(&g->gw.up) &&
        canergy_gateway_give_back(&g->gw, excess, now, &out) == CANERGY_OK) {
        g->returned_uj += excess;
        gw_up_out(g, &out);
    }
}

/* The gateway's level above: what it can still grant below. */
void gw_telemetry(struct gateway_port *g, uint64_t now)
{
    g->next_telemetry = now + g->opt.telemetry_period_us;
    g->early_telemetry = now + CANERGY_WITNESS_GAP_US;
    g->witness_reported = g->witnessed;
    const uint64_t mj = g->gw.down.usable_uj < 0 ? 0U : (uint64_t)g->gw.down.usable_uj / MJ;
    struct canergy_msg m;
    memset(&m, 0, sizeof m);
    m.type = CANERGY_TELEMETRY;
    m.node = g->opt.node;
    m.level_mj = mj > CANERGY_WIDE_MAX ? (uint32_t)CANERGY_WIDE_MAX : (uint32_t)mj;
    m.flags = (canergy_client_joining(&g->gw.up) ? CANERGY_TELEMETRY_JOINING : 0U) |
              (g->gw.up.rules == CANERGY_RULES_WITNESSED ? CANERGY_TELEMETRY_WITNESSED : 0U);
    m.seq = (uint16_t)(g->gw.up.rec.return_seq & 0xFFFFU);
    m.witness = (uint8_t)(g->witnessed & 0xFFU);
    struct canergy_frame f;
    if (canergy_encode(g->opt.id_base, &m, &f) == CANERGY_OK) {
        gw_send_up(g, &f);
    }
}
