/*
 * CANERGY_ASSERT(x): an invariant the library relies on (after libcanard's CANARD_ASSERT). Off
 * unless CANERGY_ASSERTS is defined; the sanitizer builds of the tests define it, so a broken
 * invariant aborts there. A port may define CANERGY_ASSERT itself before including canergy's
 * headers, e.g. to its own fault handler.
 */
#ifndef CANERGY_ASSERT_H
#define CANERGY_ASSERT_H

#ifndef CANERGY_ASSERT
#ifdef CANERGY_ASSERTS
#include <assert.h>
#define CANERGY_ASSERT(x) assert(x)
#else
#define CANERGY_ASSERT(x) ((void)0)
#endif
#endif

#endif /* CANERGY_ASSERT_H */
