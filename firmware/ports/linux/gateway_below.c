/*
 * canergy-gateway's bus below (gateway_port.h): what its nodes send, through the library's
 * witness (canergy/witness.h) and JOIN hold (canergy_joins_route, canergy/joins.h) to the
 * supervisor's rules, what the rules ask carried out, and the top-ups (canergy_gateway_top_up).
 * With --auth every frame below is verified and signed under its node's key
 * (canergy_auth_gateway_down_frame and _down_protect, canergy/auth.h). Frames in the
 * supervisor's own direction for its nodes are someone else's: an intrusion (with --auth,
 * refused: the C gateway does not verify them).
 */
#define _GNU_SOURCE 1

#include "args.h"
#include "gateway_port.h"
#include "keyfile.h"
#include "socketcan.h"
#include "system.h"

#include <stdio.h>
#include <string.h>

void gw_down_keys(struct gateway_port *g)
{
    uint8_t master[CANERGY_KDF_KEY_SIZE], key[CANERGY_KDF_KEY_SIZE];
    uint32_t epoch = 0U;
    port_load_master_key("--auth", g->opt.auth_path, master, &epoch);
    if (g->opt.up_auth_path != NULL) { /* the key above derived from it: the root's master */
        static const uint8_t probe[1] = {0U};
        struct canergy_cmac derived;
        uint8_t a[CANERGY_CMAC_SIZE], b[CANERGY_CMAC_SIZE];
        canergy_auth_node_key(master, g->opt.node, epoch, key);
        canergy_cmac_init(&derived, key);
        canergy_cmac(&derived, probe, sizeof probe, a);
        canergy_cmac(&g->up_auth.key, probe, sizeof probe, b);
        canergy_cmac_wipe(&derived);
        if (canergy_mac_equal(a, b, sizeof a)) {
            port_usage_error("--auth %s: the master key --upstream-auth %s was derived from "
                             "(the supervisor above's): give the gateway a master key of its "
                             "own (canergy keys -o GATEWAY.key)",
                             g->opt.auth_path, g->opt.up_auth_path);
        }
    }
    for (unsigned i = 0U; i < g->opt.count; i++) {
        canergy_auth_node_key(master, g->opt.nodes[i], epoch, key);
        (void)canergy_auth_init(&g->down_auth[i], key, g->opt.id_base, g->opt.nodes[i],
                                g->opt.fd ? CANERGY_AUTH_FD : CANERGY_AUTH_CLASSIC,
                                CANERGY_TO_SUPERVISOR);
    }
    if (!g->sealed) { /* no key above: the NV seal's key comes from this master key */
        canergy_nv_seal_key(&g->seal, master, g->opt.node, true);
        g->sealed = 1;
    }
    canergy_wipe(key, sizeof key);
    canergy_wipe(master, sizeof master);
}

/* One frame below (with --auth: its MAC frame too, or in the FD layout). */
static void send_down(struct gateway_port *g, const struct canergy_frame *f)
{
    if (g->opt.auth_path == NULL) {
        port_can_send(g->down_sock, &g->down_count, f->id, f->data, f->dlc);
        return;
    }
    struct canergy_auth_frame frames[2];
    const int n = canergy_auth_gateway_down_protect(g->down_auth, &g->gw, f, frames);
    for (int k = 0; k < n; k++) {
        port_can_send(g->down_sock, &g->down_count, frames[k].id, frames[k].data, frames[k].len);
    }
}

static struct below *below_of(struct gateway_port *g, uint8_t node)
{
    for (unsigned i = 0U; i < g->opt.count; i++) {
        if (g->opt.nodes[i] == node) {
            return &g->below[i];
        }
    }
    return NULL;
}

void gw_down_out(struct gateway_port *g, const struct canergy_supervisor_out *out,
                 uint64_t now)
{
    if (out->persist) {
        gw_save(g);
    }
    for (unsigned i = 0U; i < out->frame_count; i++) {
        send_down(g, &out->frames[i]);
    }
    /* an acknowledged intention is committed (aborted when stopping) at once; an ended
     * transaction makes the node's level stale until it reports again */
    for (unsigned k = 0U; k < out->event_count; k++) {
        const struct canergy_supervisor_event *e = &out->events[k];
        struct below *b = below_of(g, e->node);
        if (b == NULL) {
            continue;
        }
        if (e->resolved != CANERGY_RESOLVED_NONE) {
            b->fresh = 0;
            b->committed += e->resolved == CANERGY_RESOLVED_COMMITTED ? 1U : 0U;
            b->committed_uj += e->resolved == CANERGY_RESOLVED_COMMITTED ? e->amount_uj : 0U;
            b->aborted += e->resolved == CANERGY_RESOLVED_ABORTED ? 1U : 0U;
            b->written_off += e->resolved == CANERGY_RESOLVED_WRITTEN_OFF ? 1U : 0U;
        }
        if ((e->flags & CANERGY_SUP_AHEAD) != 0U) { /* witnessed.AheadOfImage */
            const unsigned long long moved =
                (unsigned long long)e->ahead_numbers * CANERGY_AMOUNT_MAX_MJ * CANERGY_QUANTUM_UJ;
            (void)fprintf(stderr,
                          "%s: node %u below holds %u debit numbers this record never saw, with "
                          "books that cannot say what it received: the record is older than its "
                          "admission afresh; %llu uJ moved from the usable budget to its grants "
                          "(the most those numbers could draw), a loss\n",
                          PROG, (unsigned)e->node, (unsigned)e->ahead_numbers, moved);
        }
        if ((e->flags & CANERGY_SUP_ADMITTED) != 0U) {
            b->admitted++;
            b->fresh = 0;
            canergy_witness_readmitted(&b->witness); /* its return numbers start again */
        }
        struct canergy_supervisor_out decided;
        if ((e->flags & CANERGY_SUP_ACKNOWLEDGED) != 0U &&
            canergy_supervisor_decide(&g->gw.down, e->node, !g->stopping, now, &decided) ==
                CANERGY_OK) {
            gw_down_out(g, &decided, now);
        }
    }
}

static void to_rules(struct gateway_port *g, const struct canergy_msg *m, uint64_t now)
{
    struct canergy_supervisor_out out;
    (void)canergy_supervisor_on_msg(&g->gw.down, m, now, &out);
    gw_down_out(g, &out, now);
}

void gw_count_decode(struct port_counters *c, int status)
{
    if (status == CANERGY_DECODE_FOREIGN) {
        c->foreign_frames++;
    } else if (status != CANERGY_DECODE_OK && status != CANERGY_RX_OTHER_NODE) {
        c->decode_errors++;
        if (status > 0 && status <= (int)CANERGY_DECODE_OUT_OF_RANGE) {
            c->reasons[status]++;
        }
    }
}

/* The node's RETURNs (and RESUMEs) its TELEMETRY has confirmed --return-hold ago with no
 * evidence since, to the rules in order; each number missed before one as a 0 mJ RETURN. */
static void release(struct gateway_port *g, unsigned i, uint64_t now)
{
    struct below *b = &g->below[i];
    struct canergy_witness_release r;
    canergy_witness_release(&b->witness, g->gw.down.sessions[i].returns_credited, now,
                            g->opt.return_hold_us, &r);
    struct canergy_msg m;
    for (uint32_t n = 0U; canergy_witness_release_at(&r, g->opt.nodes[i], n, &m); n++) {
        if (m.type == CANERGY_RETURN && m.amount_mj == 0U) { /* a number someone else acked */
            char what[GW_MSG_TEXT];
            gw_msg_text(what, &m);
            gw_intrusion(g, i, what,
                         "return numbers acknowledged by someone else: resynchronised at 0 mJ", 0,
                         now);
        }
        to_rules(g, &m, now);
    }
}

/* The JOINs a TELEMETRY of the node with its books refused: intrusions (with --auth, refusals:
 * replays of an earlier life), as `canergy gateway` reports them. */
static void joins_refuted(struct gateway_port *g, unsigned i,
                          const struct canergy_joins_refuted *refuted, uint64_t now)
{
    for (unsigned k = 0U; k < refuted->count; k++) {
        char what[48];
        (void)snprintf(what, sizeof what, "Join(node=%u, nonce=%u)", (unsigned)g->opt.nodes[i],
                       (unsigned)refuted->nonces[k]);
        if (g->opt.auth_path != NULL) {
            gw_refused(g, i, REFUSED_OLD_JOIN, what, now);
        } else {
            gw_intrusion(g, i, what,
                         "a JOIN in its name while the node reports its books: forged or replayed",
                         0, now);
        }
    }
}

/* The message for the rules past the JOIN hold: a JOIN held, a TELEMETRY judging those held. */
static void past_joins(struct gateway_port *g, unsigned i, const struct canergy_msg *m,
                       uint64_t now)
{
    struct canergy_msg rules;
    struct canergy_joins_refuted refuted;
    const unsigned found =
        canergy_joins_route(&g->below[i].joins, m, now, JOIN_HOLD_US, &rules, &refuted);
    joins_refuted(g, i, &refuted, now);
    if ((found & (CANERGY_JOINS_PASS | CANERGY_JOINS_ADMIT)) != 0U) {
        to_rules(g, &rules, now);
    }
}

/* The client rules a node's TELEMETRY says (CANERGY_TELEMETRY_WITNESSED; without it the
 * hardened ones): other than the gateway's (--rules), it is granted nothing, told once per
 * change on stderr and counted. The flag moves no energy: a forged one only withholds the node's grants. */
static void rules_said(struct gateway_port *g, struct below *b, const struct canergy_msg *m)
{
    const int witnessed = (m->flags & CANERGY_TELEMETRY_WITNESSED) != 0U;
    const int ours = g->opt.rules == CANERGY_RULES_WITNESSED;
    const int other = witnessed != ours;
    if (other) {
        b->variant_mismatch++;
        if (!b->other_rules) {
            (void)fprintf(stderr,
                          "%s: node %u below runs the %s rules, this gateway the %s: nothing "
                          "granted to it (run both with the same rules; a node without the "
                          "rules flag in its TELEMETRY counts as hardened)\n",
                          PROG, (unsigned)m->node, witnessed ? "witnessed" : "hardened",
                          ours ? "witnessed" : "hardened");
        }
    }
    b->other_rules = other;
}

/* A message from below: a TELEMETRY's level for the top-ups; then the witness's route, and the
 * JOIN hold's. */
static void from_below(struct gateway_port *g, unsigned i, const struct canergy_msg *m,
                       uint64_t now)
{
    struct below *b = &g->below[i];
    b->heard = 1;
    b->heard_at = now;
    if (m->type == CANERGY_TELEMETRY) {
        b->level_uj = (uint64_t)m->level_mj * MJ;
        b->joining = (m->flags & CANERGY_TELEMETRY_JOINING) != 0U;
        b->fresh = 1;
        rules_said(g, b, m);
    }
    uint32_t evidence = 0U;
    const enum canergy_witness_route r =
        g->opt.auth_path != NULL /* a RETURN carries a MAC: credited at once */
            ? canergy_witness_route_keyed(&b->witness, &g->gw.down.sessions[i], m, g->opt.rules,
                                          now, &evidence)
            : canergy_witness_route(&b->witness, &g->gw.down.sessions[i], m, g->opt.rules, now,
                                    &evidence);
    if (evidence != 0U) {
        char what[GW_MSG_TEXT];
        gw_msg_text(what, m);
        gw_intrusion(g, i, what,
                     m->type == CANERGY_TELEMETRY
                         ? "evidence in its TELEMETRY: frames in its name it did not send, or "
                           "its return number went back"
                         : "no honest node sends it: beyond what its books let it hold, or "
                           "another amount under a return number held",
                     0, now);
    }
    if (r != CANERGY_WITNESS_TO_RULES) {
        release(g, i, now); /* what it held may be due now */
    }
    if (r == CANERGY_WITNESS_TO_RULES || m->type == CANERGY_TELEMETRY) {
        past_joins(g, i, m, now);
    }
}

/* A frame in the supervisor's own direction for node i below: someone else's (a second
 * supervisor, a spoofer). Without a key an intrusion; with one refused (not verified here). */
static void own_direction(struct gateway_port *g, unsigned i, const struct canergy_rx_frame *rx,
                          uint64_t now)
{
    char what[GW_FRAME_TEXT];
    gw_frame_text(what, rx);
    if (g->opt.auth_path != NULL) {
        gw_refused(g, i, REFUSED_OWN_DIRECTION, what, now);
    } else {
        gw_intrusion(g, i, what, "a frame only this supervisor sends", 0, now);
    }
}

/* The JOINs held whose hold is over, admitted. */
static void admit_due(struct gateway_port *g, uint64_t now)
{
    for (unsigned i = 0U; i < g->opt.count; i++) {
        struct canergy_msg join;
        if (canergy_joins_due_join(&g->below[i].joins, g->opt.nodes[i], now, &join)) {
            to_rules(g, &join, now);
        }
    }
}

uint64_t gw_joins_deadline(const struct gateway_port *g)
{
    uint64_t at = UINT64_MAX;
    for (unsigned i = 0U; i < g->opt.count; i++) {
        const struct canergy_joins *j = &g->below[i].joins;
        at = j->has_admitting && j->admit_at < at ? j->admit_at : at;
    }
    return at;
}

void gw_receive_down(struct gateway_port *g, uint64_t now)
{
    struct canfd_frame cf;
    struct canergy_rx_frame rx;
    while (port_can_receive(g->down_sock, &g->down_count, &cf, &rx) == 1) {
        struct canergy_msg m;
        struct canergy_frame plain;
        int status = g->opt.auth_path != NULL
                         ? canergy_auth_gateway_down_frame(g->down_auth, &g->gw, &rx, &plain)
                         : CANERGY_DECODE_OK;
        const struct below *by = below_of(g, (uint8_t)(rx.id & 0xFFU));
        const unsigned at = by == NULL ? 0U : (unsigned)(by - g->below);
        if (status >= CANERGY_AUTH_MAC_BAD && status <= CANERGY_AUTH_UNAUTHENTICATED) {
            if (by != NULL) { /* a managed node's (the only ones refused): nothing moves */
                char what[GW_FRAME_TEXT];
                gw_frame_text(what, &rx);
                gw_refused(g, at, (unsigned)(status - CANERGY_AUTH_MAC_BAD), what, now);
            }
            continue;
        }
        if (status == CANERGY_AUTH_PENDING) {
            continue; /* a classic message waits for its MAC frame, or proves nothing */
        }
        if (status == CANERGY_DECODE_OK && g->opt.auth_path != NULL) {
            rx.id = plain.id; /* the verified classic frame */
            rx.data = plain.data;
            rx.len = plain.dlc;
        }
        if (status == CANERGY_DECODE_OK) {
            status = (int)canergy_decode(g->opt.id_base, &rx, CANERGY_TO_SUPERVISOR, &m);
        }
        if (status == CANERGY_DECODE_WRONG_DIRECTION) { /* no decode error, as in Python */
            if (by != NULL) {
                own_direction(g, at, &rx, now);
            }
            continue;
        }
        gw_count_decode(&g->down_count, status);
        const struct below *b = status == CANERGY_DECODE_OK ? below_of(g, m.node) : NULL;
        if (b != NULL) {
            from_below(g, (unsigned)(b - g->below), &m, now);
        }
    }
    admit_due(g, now);
}

void gw_release_all(struct gateway_port *g, uint64_t now)
{
    for (unsigned i = 0U; i < g->opt.count; i++) {
        release(g, i, now);
    }
    gw_refusals_tick(g, now);
}

void gw_top_up(struct gateway_port *g, uint64_t now)
{
    for (unsigned i = 0U; g->opt.has_target && !g->stopping && i < g->opt.count; i++) {
        struct below *b = &g->below[i];
        const struct canergy_session *s = &g->gw.down.sessions[i];
        if (s->phase != CANERGY_S_IDLE || !b->heard || !b->fresh || b->joining ||
            b->other_rules || /* other client rules: one side would wait on the other */
            b->joins.held_count != 0U || /* JOINs wait for its TELEMETRY: a grant is lost */
            (g->opt.auth_path == NULL && /* with a key, no reason: anyone can make it count */
             canergy_witness_blocked(&b->witness, now, WITNESS_BLOCK_US))) {
            continue;
        }
        const uint32_t amount = canergy_gateway_top_up(g->opt.target_uj, g->opt.min_grant_uj,
                                                       b->level_uj, g->gw.down.usable_uj);
        struct canergy_supervisor_out out;
        const int rc = amount != 0U ? canergy_gateway_begin(&g->gw, s->node, amount, now, &out)
                                    : CANERGY_ERR_AMOUNT;
        if (rc == CANERGY_OK) {
            b->fresh = 0;
            gw_down_out(g, &out, now);
        } else if (rc == CANERGY_ERR_WINDOW && /* witnessed below: re-sync that node alone */
                   canergy_supervisor_resync(&g->gw.down, s->node, port_random16(), now, &out) ==
                       CANERGY_OK) {
            b->resyncs++;
            gw_down_out(g, &out, now);
        }
    }
}
