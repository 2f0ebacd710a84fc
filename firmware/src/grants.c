/*
 * The grant caps (canergy/grants.h), as canergy.live.supervisor.policy.
 */
#include "canergy/grants.h"

#include "canergy/codec.h"

#define US_PER_S 1000000ULL

void canergy_grant_rate_init(struct canergy_grant_rate *r, const struct canergy_grant_limits *l)
{
    const uint64_t rate = l->has_rate ? l->rate_uj_per_s : 0U;
    r->burst = l->max_grant_uj > rate ? l->max_grant_uj : rate;
    r->tokens = (int64_t)r->burst;
    r->stamp = 0U;
    r->has_stamp = false;
}

bool canergy_grant_rate_available(struct canergy_grant_rate *r,
                                  const struct canergy_grant_limits *l, uint64_t now,
                                  int64_t *tokens)
{
    if (!l->has_rate) {
        return false;
    }
    if (r->has_stamp && now > r->stamp) { /* Python's min(burst, tokens + dt * rate // 1e6) */
        const uint64_t dt = now - r->stamp;
        const uint64_t rate = l->rate_uj_per_s;
        const int64_t burst = (int64_t)r->burst;
        /* a refill of a whole burst or more fills it (tokens never go below 0) */
        if (rate != 0U && dt / US_PER_S >= r->burst / rate + 1U) {
            r->tokens = burst;
        } else {
            const uint64_t refill = dt / US_PER_S * rate + dt % US_PER_S * rate / US_PER_S;
            const int64_t sum = r->tokens + (int64_t)refill;
            r->tokens = sum < burst ? sum : burst;
        }
    }
    r->stamp = now;
    r->has_stamp = true;
    *tokens = r->tokens;
    return true;
}

void canergy_grant_rate_take(struct canergy_grant_rate *r, const struct canergy_grant_limits *l,
                             uint64_t amount_uj)
{
    if (l->has_rate) {
        r->tokens -= (int64_t)amount_uj;
    }
}

static int64_t least(int64_t a, int64_t b)
{
    return a < b ? a : b;
}

uint32_t canergy_grant_cap(const struct canergy_grant_limits *l, int64_t wanted_uj,
                           bool has_level, int64_t level_uj, int64_t usable_uj,
                           int64_t granted_total_uj, bool has_tokens, int64_t tokens)
{
    int64_t cap = least(wanted_uj, usable_uj);
    cap = least(cap, (int64_t)l->max_grant_uj);
    cap = least(cap, (int64_t)(CANERGY_AMOUNT_MAX_MJ * CANERGY_QUANTUM_UJ));
    if (has_level) {
        cap = least(cap, (int64_t)CANERGY_USABLE_MAX_UJ - level_uj);
    }
    if (l->has_max_node_level) {
        cap = least(cap, has_level ? (int64_t)l->max_node_level_uj - level_uj : 0);
    }
    if (l->has_max_total) {
        cap = least(cap, (int64_t)l->max_total_uj - granted_total_uj);
    }
    if (has_tokens) {
        cap = least(cap, tokens);
    }
    return cap <= 0 ? 0U : (uint32_t)(cap - cap % (int64_t)CANERGY_QUANTUM_UJ);
}

int64_t canergy_grant_wanted(int64_t target_uj, int64_t minimum_uj, int64_t level_uj)
{
    const int64_t short_uj = target_uj - level_uj;
    return short_uj >= minimum_uj ? short_uj : 0;
}
