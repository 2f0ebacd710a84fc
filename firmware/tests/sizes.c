/*
 * Not linked anywhere: `make size` compiles it for the target and reads the sizes of these
 * objects back with nm, which is the state a node needs there (and an AES-CMAC key).
 */
#include "canergy/auth.h"
#include "canergy/cmac.h"
#include "canergy/gateway.h"
#include "canergy/node.h"
#include "canergy/supervisor.h"

extern char canergy_client_bytes[sizeof(struct canergy_client)];
extern char canergy_node_bytes[sizeof(struct canergy_node)];
char canergy_client_bytes[sizeof(struct canergy_client)];
char canergy_node_bytes[sizeof(struct canergy_node)];
extern char canergy_cmac_bytes[sizeof(struct canergy_cmac)];
char canergy_cmac_bytes[sizeof(struct canergy_cmac)];
extern char canergy_auth_bytes[sizeof(struct canergy_auth)];
char canergy_auth_bytes[sizeof(struct canergy_auth)];
extern char canergy_supervisor_bytes[sizeof(struct canergy_supervisor)];
char canergy_supervisor_bytes[sizeof(struct canergy_supervisor)];
extern char canergy_session_bytes[sizeof(struct canergy_session)];
char canergy_session_bytes[sizeof(struct canergy_session)];
extern char canergy_gateway_bytes[sizeof(struct canergy_gateway)];
char canergy_gateway_bytes[sizeof(struct canergy_gateway)];
extern char canergy_supervisor_out_bytes[sizeof(struct canergy_supervisor_out)];
char canergy_supervisor_out_bytes[sizeof(struct canergy_supervisor_out)];
