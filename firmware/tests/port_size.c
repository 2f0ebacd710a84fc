/*
 * Not a port: the smallest program that uses every call a real port makes, so that `make size`
 * can link it for Cortex-M4 with --gc-sections and report what the library costs there.
 * PORT_NODE selects the node layer's API, PORT_AUTH the node layer in authenticated mode
 * (canergy/auth.h), PORT_CMAC AES-CMAC and the KDF alone, PORT_SUPERVISOR the supervisor
 * (canergy/supervisor.h), PORT_GATEWAY a gateway (canergy/gateway.h: the client above, the
 * supervisor below with its JOIN hold, canergy/joins.h), otherwise the bare client's.
 */
#include "canergy/auth.h"
#include "canergy/cmac.h"
#include "canergy/gateway.h"
#include "canergy/joins.h"
#include "canergy/node.h"
#include "canergy/supervisor.h"

void port_entry(void);

/* The rule set a node port configures: the one its build keeps (canergy/client.h). */
#ifdef CANERGY_RULES_WITNESSED_ONLY
#define PORT_RULES CANERGY_RULES_WITNESSED
#else
#define PORT_RULES CANERGY_RULES_HARDENED
#endif

#ifdef PORT_GATEWAY
void port_entry(void)
{
    static struct canergy_gateway gw;
    static struct canergy_out out;
    static struct canergy_supervisor_out down;
    static uint8_t nv[2U * CANERGY_NV_SLOT_SIZE];
    static uint8_t sup_nv[2U * CANERGY_SUPERVISOR_SLOT_SIZE];
    static const uint8_t nodes[1] = {1U};
    static const uint8_t bytes[8] = {0};
    const struct canergy_rx_frame rx = {0x0CE00101UL, bytes, 8U, true, false};
    const struct canergy_client_config up = {CANERGY_DEFAULT_ID_BASE, 100000UL, 100000UL, 9U, CANERGY_RULES_HARDENED, 0U};
    const struct canergy_supervisor_config cfg = {CANERGY_DEFAULT_ID_BASE, {50000UL, 3U, CANERGY_RULES_HARDENED, 0U}};
    volatile uint64_t sink = 0U;
    uint32_t counter = 0U;
    uint8_t slot = 0U;
    sink += (uint64_t)canergy_client_start(&gw.up, &up, nv, sizeof nv, 7U, 0U, &out);
    sink += (uint64_t)canergy_supervisor_load(&gw.down, &cfg, nodes, 1U, 0U, sup_nv,
                                              sizeof sup_nv, &counter, &slot);
    sink += (uint64_t)canergy_gateway_on_up_frame(&gw, &rx, 1U, &out);
    canergy_gateway_on_up_timer(&gw, 2U, &out);
    sink += (uint64_t)canergy_gateway_give_back(&gw, 1000U, 3U, &out);
    sink += (uint64_t)canergy_supervisor_begin(&gw.down, 1U, 1000U, 4U, &down);
    sink += (uint64_t)canergy_supervisor_on_frame(&gw.down, &rx, 5U, &down);
    sink += (uint64_t)canergy_supervisor_decide(&gw.down, 1U, true, 6U, &down);
    canergy_supervisor_on_timer(&gw.down, 7U, &down);
    sink += canergy_supervisor_image(&gw.down, counter + 1U, sup_nv);
    sink += canergy_client_deadline(&gw.up) + canergy_supervisor_deadline(&gw.down);
    sink += (uint64_t)canergy_gateway_link_gap(&gw) + out.frames[0].data[0];
    static struct canergy_joins joins; /* JOINs held below until the node's TELEMETRY */
    static struct canergy_msg msg, rules;
    struct canergy_joins_refuted refuted;
    sink += canergy_joins_route(&joins, &msg, 8U, 500000U, &rules, &refuted) + refuted.count;
    sink += canergy_joins_due_join(&joins, 1U, 9U, &rules) ? 1U : 0U;
    sink += (uint64_t)canergy_supervisor_on_msg(&gw.down, &rules, 10U, &down);
#ifdef PORT_AUTH /* authenticated on both legs: a node key above, a master key below */
    static struct canergy_auth up_auth, down_auth[1];
    static uint8_t key[16]; /* in RAM: only the library's flash is counted */
    struct canergy_auth_frame frames[2];
    struct canergy_frame verified;
    canergy_auth_node_key(key, 1U, 1U, key);
    sink += (uint64_t)canergy_auth_init(&up_auth, key, CANERGY_DEFAULT_ID_BASE, 7U,
                                        CANERGY_AUTH_CLASSIC, CANERGY_TO_CLIENT);
    sink += (uint64_t)canergy_auth_init(&down_auth[0], key, CANERGY_DEFAULT_ID_BASE, 1U,
                                        CANERGY_AUTH_CLASSIC, CANERGY_TO_SUPERVISOR);
    sink += (uint64_t)canergy_auth_gateway_up_frame(&up_auth, &gw, &rx, 8U, &out);
    sink += (uint64_t)canergy_auth_gateway_up_protect(&up_auth, &gw, &out.frames[0], frames);
    sink += (uint64_t)canergy_auth_gateway_down_frame(down_auth, &gw, &rx, &verified);
    sink += (uint64_t)canergy_auth_gateway_down_protect(down_auth, &gw, &down.frames[0], frames);
    sink += frames[0].data[0] + verified.data[0];
    static struct canergy_cmac seal; /* the NV seal: checked at start, made on each write */
    static uint8_t image[2U * CANERGY_GW_NV_SLOT_SIZE + 2U * CANERGY_NV_SEAL_SIZE];
    canergy_nv_seal_key(&seal, key, 7U, true);
    sink += canergy_nv_unseal(&seal, image, sizeof image, CANERGY_GW_NV_SLOT_SIZE, 2U,
                              &image[2U * CANERGY_GW_NV_SLOT_SIZE]);
    canergy_nv_seal(&seal, image, CANERGY_GW_NV_SLOT_SIZE, &image[2U * CANERGY_GW_NV_SLOT_SIZE]);
#endif
    (void)sink;
}
#elif defined(PORT_SUPERVISOR)
void port_entry(void)
{
    static struct canergy_supervisor sup;
    static struct canergy_supervisor_out out;
    static uint8_t nv[2U * CANERGY_SUPERVISOR_SLOT_SIZE];
    static const uint8_t nodes[1] = {1U};
    static const uint8_t bytes[8] = {0};
    const struct canergy_rx_frame rx = {0x0CE00901UL, bytes, 2U, true, false};
    const struct canergy_supervisor_config cfg = {CANERGY_DEFAULT_ID_BASE, {50000UL, 3U, CANERGY_RULES_HARDENED, 0U}};
    volatile uint64_t sink = 0U;
    uint32_t counter = 0U;
    uint8_t slot = 0U;
    sink += (uint64_t)canergy_supervisor_load(&sup, &cfg, nodes, 1U, 1000000U, nv, sizeof nv,
                                              &counter, &slot);
    sink += canergy_supervisor_image(&sup, counter + 1U, nv);
    sink += (uint64_t)canergy_supervisor_inject(&sup, 1000U);
    sink += (uint64_t)canergy_supervisor_begin(&sup, 1U, 1000U, 0U, &out);
    sink += (uint64_t)canergy_supervisor_on_frame(&sup, &rx, 1U, &out);
    sink += (uint64_t)canergy_supervisor_decide(&sup, 1U, true, 2U, &out);
    canergy_supervisor_on_timer(&sup, 3U, &out);
    canergy_supervisor_restart(&sup, 4U);
    sink += canergy_supervisor_deadline(&sup) + out.frames[0].data[0];
    (void)sink;
}
#elif defined(PORT_CMAC)
void port_entry(void)
{
    static uint8_t master[16]; /* in RAM: only the library's flash is counted */
    static uint8_t frame[8];
    static struct canergy_cmac key;
    uint8_t node_key[16];
    uint8_t mac[16];
    volatile unsigned sink = 0U;
    canergy_kdf_cmac_ctr(master, frame, 4U, frame, 1U, node_key);
    canergy_cmac_init(&key, node_key);
    canergy_wipe(node_key, sizeof node_key);
    canergy_cmac(&key, frame, sizeof frame, mac);
    sink += canergy_mac_equal(mac, frame, 4U) ? 1U : 0U;
    canergy_cmac_wipe(&key);
    (void)sink;
}
#else
void port_entry(void)
{
#ifndef PORT_AUTH /* the authenticated node reads a sealed image (below) */
    static uint8_t nv[2U * CANERGY_NV_SLOT_SIZE];
#endif
    static const uint8_t bytes[8] = {0};
    struct canergy_out out;
    const struct canergy_rx_frame rx = {0x0CE00105UL, bytes, 8U, true, false};
    const struct canergy_client_config client = {CANERGY_DEFAULT_ID_BASE, 100000UL, 100000UL, 1U, PORT_RULES, 0U};
    volatile uint64_t sink = 0U;
#if defined(PORT_NODE) || defined(PORT_AUTH)
    static struct canergy_node n;
    const struct canergy_node_config cfg = {client, 1000000UL, 0U, CANERGY_KEEP_ALL};
#ifdef PORT_AUTH
    static struct canergy_auth auth;
    static uint8_t key[16]; /* in RAM: only the library's flash is counted */
    static struct canergy_cmac seal; /* the NV seal: the image checked at start, each write's */
    static uint8_t sealed[CANERGY_NV_SEALED_SIZE];
    canergy_nv_seal_key(&seal, key, 1U, false);
    sink += canergy_nv_unseal(&seal, sealed, sizeof sealed, CANERGY_NV_SLOT_SIZE, 2U,
                              &sealed[CANERGY_NV_SEALS_AT]);
    sink += (uint64_t)canergy_node_start(&n, &cfg, sealed, sizeof sealed, 1U, 0U, &out);
    canergy_nv_seal(&seal, out.nv_image, CANERGY_NV_SLOT_SIZE, &sealed[CANERGY_NV_SEALS_AT]);
#else
    sink += (uint64_t)canergy_node_start(&n, &cfg, nv, sizeof nv, 1U, 0U, &out);
#endif
#ifdef PORT_AUTH
    struct canergy_auth_frame frames[2];
    sink += (uint64_t)canergy_auth_init(&auth, key, CANERGY_DEFAULT_ID_BASE, 1U,
                                        CANERGY_AUTH_CLASSIC, CANERGY_TO_CLIENT);
    sink += (uint64_t)canergy_auth_node_frame(&auth, &n, &rx, 1U, &out);
    sink += (uint64_t)canergy_auth_node_protect(&auth, &n, &out.frames[0], frames);
    sink += frames[0].data[0];
#else
    sink += (uint64_t)canergy_node_on_frame(&n, &rx, 1U, &out);
#endif
    canergy_node_poll(&n, 2U, &out);
    sink += canergy_node_draw(&n, 5U, 3U, &out);
    sink += canergy_node_deadline(&n);
#else
    static struct canergy_client c;
    sink += (uint64_t)canergy_client_start(&c, &client, nv, sizeof nv, 1U, 0U, &out);
    sink += (uint64_t)canergy_client_on_frame(&c, &rx, 1U, &out);
    canergy_client_on_timer(&c, 2U, &out);
    sink += (uint64_t)canergy_client_spend(&c, 5U, &out);
    sink += (uint64_t)canergy_client_give_back(&c, 1000U, 3U, &out);
    sink += canergy_client_deadline(&c);
#endif
    sink += out.nv_image[0];
    (void)sink;
}
#endif
