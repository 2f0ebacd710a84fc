/*
 * Linked only into the shared objects the Python tests load: the layout of the public structs
 * as this compiler lays them out, so the ctypes mirror in tests/test_c_binding.py can be
 * checked field by field instead of trusted.
 */
#include "canergy/auth.h"
#include "canergy/client.h"
#include "canergy/cmac.h"
#include "canergy/gateway.h"
#include "canergy/node.h"
#include "canergy/session.h"
#include "canergy/supervisor.h"
#include "canergy/witness.h"

#include <stddef.h>
#include <string.h>

long canergy_test_offset(const char *name);
long canergy_test_sizeof(const char *name);

#define FIELD(type, field) {#type "." #field, (long)offsetof(struct type, field)}

struct entry {
    const char *name;
    long value;
};

static const struct entry offsets[] = {
    FIELD(canergy_gateway_nv, up),
    FIELD(canergy_gateway_nv, down),
    FIELD(canergy_gateway_nv, counter),
    FIELD(canergy_gateway_nv, slot),
    FIELD(canergy_gateway_nv, older),
    FIELD(canergy_gateway_nv, foreign),
    FIELD(canergy_held, seq),
    FIELD(canergy_held, confirmed_at),
    FIELD(canergy_held, amount_mj),
    FIELD(canergy_held, confirmed),
    FIELD(canergy_witness, held),
    FIELD(canergy_witness, resume_held),
    FIELD(canergy_witness, resume),
    FIELD(canergy_witness, return_seq),
    FIELD(canergy_witness, confirmed_at),
    FIELD(canergy_witness, evidence_at),
    FIELD(canergy_witness, refuted),
    FIELD(canergy_witness, resynced),
    FIELD(canergy_witness, resume_nonce),
    FIELD(canergy_witness, witness),
    FIELD(canergy_witness, held_count),
    FIELD(canergy_witness, has_witness),
    FIELD(canergy_witness, has_return_seq),
    FIELD(canergy_witness, has_evidence),
    FIELD(canergy_witness, has_resume),
    FIELD(canergy_witness, has_resume_nonce),
    FIELD(canergy_witness_release, returns),
    FIELD(canergy_witness_release, resume_msg),
    FIELD(canergy_witness_release, count),
    FIELD(canergy_witness_release, resume),
    FIELD(canergy_record, spent_uj),
    FIELD(canergy_record, usable_uj),
    FIELD(canergy_record, credited_mj),
    FIELD(canergy_record, last_tx),
    FIELD(canergy_record, return_seq),
    FIELD(canergy_record, return_pending_uj),
    FIELD(canergy_record, outcome),
    FIELD(canergy_record, flags),
    FIELD(canergy_client, rec),
    FIELD(canergy_client, deadline),
    FIELD(canergy_client, return_deadline),
    FIELD(canergy_client, id_base),
    FIELD(canergy_client, command_timeout_us),
    FIELD(canergy_client, return_retry_us),
    FIELD(canergy_client, held_tx),
    FIELD(canergy_client, nv_counter),
    FIELD(canergy_client, held_amount_mj),
    FIELD(canergy_client, nonce),
    FIELD(canergy_client, node),
    FIELD(canergy_client, phase),
    FIELD(canergy_client, nv_slot),
    FIELD(canergy_client, rules),
    FIELD(canergy_client, window),
    FIELD(canergy_frame, id),
    FIELD(canergy_frame, dlc),
    FIELD(canergy_frame, data),
    FIELD(canergy_out, frames),
    FIELD(canergy_out, nv_image),
    FIELD(canergy_out, nv_counter),
    FIELD(canergy_out, events),
    FIELD(canergy_out, frame_count),
    FIELD(canergy_out, persist),
    FIELD(canergy_out, nv_slot),
    FIELD(canergy_session, delivered_uj),
    FIELD(canergy_session, returned_uj),
    FIELD(canergy_session, deadline),
    FIELD(canergy_session, tx),
    FIELD(canergy_session, returns_credited),
    FIELD(canergy_session, reserved_uj),
    FIELD(canergy_session, resume_from),
    FIELD(canergy_session, resume_to),
    FIELD(canergy_session, resume_nonce),
    FIELD(canergy_session, witness),
    FIELD(canergy_session, sync_nonce),
    FIELD(canergy_session, node),
    FIELD(canergy_session, phase),
    FIELD(canergy_session, decision),
    FIELD(canergy_session, tries),
    FIELD(canergy_session_step, msg),
    FIELD(canergy_session_step, credit_uj),
    FIELD(canergy_session_step, send),
    FIELD(canergy_session_step, resolved),
    FIELD(canergy_session_step, acknowledged),
    FIELD(canergy_session_step, admitted),
    FIELD(canergy_session_timing, response_timeout_us),
    FIELD(canergy_session_timing, retries),
    FIELD(canergy_session_timing, rules),
    FIELD(canergy_session_timing, window),
    FIELD(canergy_supervisor, usable_uj),
    FIELD(canergy_supervisor, injected_uj),
    FIELD(canergy_supervisor, withdrawn_uj),
    FIELD(canergy_supervisor, sessions),
    FIELD(canergy_supervisor, timing),
    FIELD(canergy_supervisor, id_base),
    FIELD(canergy_supervisor, start_without),
    FIELD(canergy_supervisor, count),
    FIELD(canergy_supervisor_config, id_base),
    FIELD(canergy_supervisor_config, timing),
    FIELD(canergy_gateway, up),
    FIELD(canergy_gateway, down),
    FIELD(canergy_supervisor_event, tx),
    FIELD(canergy_supervisor_event, amount_uj),
    FIELD(canergy_supervisor_event, node),
    FIELD(canergy_supervisor_event, resolved),
    FIELD(canergy_supervisor_event, flags),
    FIELD(canergy_supervisor_out, frames),
    FIELD(canergy_supervisor_out, events),
    FIELD(canergy_supervisor_out, frame_count),
    FIELD(canergy_supervisor_out, event_count),
    FIELD(canergy_supervisor_out, persist),
    FIELD(canergy_msg, delivered_mj),
    FIELD(canergy_msg, level_mj),
    FIELD(canergy_msg, tx),
    FIELD(canergy_msg, seq),
    FIELD(canergy_msg, nonce),
    FIELD(canergy_msg, amount_mj),
    FIELD(canergy_msg, type),
    FIELD(canergy_msg, node),
    FIELD(canergy_msg, flags),
    FIELD(canergy_msg, witness),
    FIELD(canergy_rx_frame, id),
    FIELD(canergy_rx_frame, data),
    FIELD(canergy_rx_frame, len),
    FIELD(canergy_rx_frame, extended),
    FIELD(canergy_rx_frame, remote),
    FIELD(canergy_client_config, id_base),
    FIELD(canergy_client_config, command_timeout_us),
    FIELD(canergy_client_config, return_retry_us),
    FIELD(canergy_client_config, node),
    FIELD(canergy_client_config, rules),
    FIELD(canergy_client_config, window),
    FIELD(canergy_nv_state, record),
    FIELD(canergy_nv_state, counter),
    FIELD(canergy_nv_state, newest_slot),
    FIELD(canergy_nv_state, books),
    FIELD(canergy_nv_state, fallbacks),
    FIELD(canergy_node_config, client),
    FIELD(canergy_node_config, telemetry_period_us),
    FIELD(canergy_node_config, low_water_uj),
    FIELD(canergy_node_config, return_above_uj),
    FIELD(canergy_node, client),
    FIELD(canergy_node, next_telemetry),
    FIELD(canergy_node, telemetry_period_us),
    FIELD(canergy_node, low_water_uj),
    FIELD(canergy_node, return_above_uj),
    FIELD(canergy_node, decode_errors),
    FIELD(canergy_node, overflow_refused),
    FIELD(canergy_node, was_low),
    FIELD(canergy_node, halted),
    FIELD(canergy_node, witness),
    FIELD(canergy_node, joined),
    FIELD(canergy_node, join_nonce),
    FIELD(canergy_node, witness_reported),
    FIELD(canergy_node, released_uj),
    FIELD(canergy_aes128, rk),
    FIELD(canergy_cmac, aes),
    FIELD(canergy_cmac, k1),
    FIELD(canergy_cmac, k2),
    FIELD(canergy_cmac_stream, x),
    FIELD(canergy_cmac_stream, n),
    FIELD(canergy_auth_frame, id),
    FIELD(canergy_auth_frame, len),
    FIELD(canergy_auth_frame, data),
    FIELD(canergy_auth, key),
    FIELD(canergy_auth, id_base),
    FIELD(canergy_auth, pending_id),
    FIELD(canergy_auth, join_fv),
    FIELD(canergy_auth, admit_fv),
    FIELD(canergy_auth, pending_data),
    FIELD(canergy_auth, pending_len),
    FIELD(canergy_auth, node),
    FIELD(canergy_auth, layout),
    FIELD(canergy_auth, receives),
};

#define SIZE(type) {#type, (long)sizeof(struct type)}

static const struct entry sizes[] = {
    SIZE(canergy_record),        SIZE(canergy_client),    SIZE(canergy_frame),
    SIZE(canergy_out),           SIZE(canergy_msg),       SIZE(canergy_rx_frame),
    SIZE(canergy_client_config), SIZE(canergy_nv_state),  SIZE(canergy_node_config),
    SIZE(canergy_node),          SIZE(canergy_aes128),    SIZE(canergy_cmac),
    SIZE(canergy_cmac_stream),   SIZE(canergy_auth_frame), SIZE(canergy_auth),
    SIZE(canergy_session),       SIZE(canergy_session_step), SIZE(canergy_session_timing),
    SIZE(canergy_supervisor),    SIZE(canergy_supervisor_config), SIZE(canergy_supervisor_out),
    SIZE(canergy_supervisor_event), SIZE(canergy_gateway),
    SIZE(canergy_held), SIZE(canergy_witness), SIZE(canergy_witness_release),
    SIZE(canergy_gateway_nv),
};

static long find(const struct entry *table, size_t n, const char *name)
{
    for (size_t i = 0U; i < n; i++) {
        if (strcmp(table[i].name, name) == 0) {
            return table[i].value;
        }
    }
    return -1;
}

long canergy_test_offset(const char *name)
{
    return find(offsets, sizeof offsets / sizeof offsets[0], name);
}

long canergy_test_sizeof(const char *name)
{
    return find(sizes, sizeof sizes / sizeof sizes[0], name);
}
