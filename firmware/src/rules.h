/*
 * Library-internal: the rule sets this build keeps (canergy/client.h). With one set kept both
 * answers are constants, so the other set's code folds away.
 */
#ifndef CANERGY_RULES_H
#define CANERGY_RULES_H

#include "canergy/client.h"

/* Whether this build has rules (enum canergy_rules): a configuration naming another set is
 * refused at start, never run as the set kept. */
static inline bool rules_kept(uint32_t rules)
{
#if defined(CANERGY_WITNESSED) && defined(CANERGY_HARDENED)
    return rules <= CANERGY_RULES_WITNESSED;
#elif defined(CANERGY_WITNESSED)
    return rules == CANERGY_RULES_WITNESSED;
#else
    return rules == CANERGY_RULES_HARDENED;
#endif
}

/* Whether rules (a set rules_kept took) are the witnessed ones. */
static inline bool rules_witnessed(uint32_t rules)
{
#if defined(CANERGY_WITNESSED) && defined(CANERGY_HARDENED)
    return rules == CANERGY_RULES_WITNESSED;
#elif defined(CANERGY_WITNESSED)
    (void)rules;
    return true;
#else
    (void)rules;
    return false;
#endif
}

#endif /* CANERGY_RULES_H */
