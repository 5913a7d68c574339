/* Assertions as contracts. A broken contract in flight must not hang the
 * mechanism: it raises FAULT_ASSERTION (valves closed, state FAULT) and the
 * caller returns. */
#ifndef OIBAR_APP_ASSERT_H
#define OIBAR_APP_ASSERT_H

#include <stdbool.h>

void oibar_app_assert_failed(const char *file, int line);

/* Evaluates to the condition so callers can bail out: if (!OIBAR_REQUIRE(x)) return; */
#define OIBAR_REQUIRE(cond) \
    ((cond) ? true : (oibar_app_assert_failed(__FILE__, __LINE__), false))

#endif
