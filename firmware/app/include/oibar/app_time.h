/*
 * Elapsed-time helpers. Every duration the application measures ("held for
 * debounce_ms", "mismatch for valve_mismatch_ms", ...) is a difference of the
 * 1 kHz tick clock (hal_time_ms), never a count of calls: a slow main-loop
 * pass, or a late tick, does not stretch it (issue 16 item 6,
 * SAFETY_RULE_TIMES_ARE_ELAPSED). Wrap-safe (unsigned differences).
 */
#ifndef OIBAR_APP_TIME_H
#define OIBAR_APP_TIME_H

#include <stdbool.h>
#include <stdint.h>

/* A condition first seen at `since_ms` (that sample counts as its first
 * millisecond) and still seen at `now_ms` has held for `limit_ms`. With one
 * sample per millisecond this is "the limit_ms-th consecutive sample". */
static inline bool oibar_held_for(uint32_t now_ms, uint32_t since_ms, uint32_t limit_ms)
{
    return now_ms - since_ms + 1u >= limit_ms;
}

#endif
