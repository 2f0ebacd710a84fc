/*
 * The grant caps (src/canergy/live/supervisor/policy.py's capped_grant, RateLimiter and
 * TopUp.wanted), sans-IO: how much one grant may be now under the safety limits, the budget,
 * what the node's record holds above its reported level, and the rate limiter's tokens.
 * tests/test_ccore_tables.py runs both side by side; the compiled core's grant desk sizes its
 * grants here (canergy.ccore.grants).
 */
#ifndef CANERGY_GRANTS_H
#define CANERGY_GRANTS_H

#include <stdbool.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Python's Limits: µJ; a has_ flag false is Python's None. */
struct canergy_grant_limits {
    uint64_t max_grant_uj;     /* 1 mJ .. 65.535 J */
    uint64_t max_node_level_uj; /* has_max_node_level */
    uint64_t max_total_uj;      /* has_max_total: over this run, all nodes together */
    uint64_t rate_uj_per_s;     /* has_rate: a token bucket over all nodes */
    bool has_max_node_level;
    bool has_max_total;
    bool has_rate;
};

/* Python's RateLimiter: burst = max(max_grant, rate), full at start. */
struct canergy_grant_rate {
    int64_t tokens;
    uint64_t burst;
    uint64_t stamp; /* has_stamp */
    bool has_stamp;
};

void canergy_grant_rate_init(struct canergy_grant_rate *r, const struct canergy_grant_limits *l);

/* The tokens now (refilled since the last look); false without a rate (Python's None). */
bool canergy_grant_rate_available(struct canergy_grant_rate *r,
                                  const struct canergy_grant_limits *l, uint64_t now,
                                  int64_t *tokens);

/* A grant of amount_uj began. */
void canergy_grant_rate_take(struct canergy_grant_rate *r, const struct canergy_grant_limits *l,
                             uint64_t amount_uj);

/* The largest grant <= wanted_uj every cap allows, whole mJ (0: none): usable_uj, max_grant,
 * one frame's amount, what the record holds above level_uj (has_level), max_node_level (an
 * unknown level: 0), max_total less granted_total_uj, the tokens (has_tokens). */
uint32_t canergy_grant_cap(const struct canergy_grant_limits *l, int64_t wanted_uj,
                           bool has_level, int64_t level_uj, int64_t usable_uj,
                           int64_t granted_total_uj, bool has_tokens, int64_t tokens);

/* TopUp(target_uj, minimum_uj).wanted(level_uj): the shortfall when at least minimum_uj. */
int64_t canergy_grant_wanted(int64_t target_uj, int64_t minimum_uj, int64_t level_uj);

#ifdef __cplusplus
}
#endif

#endif
