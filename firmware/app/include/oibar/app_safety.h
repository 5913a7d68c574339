/*
 * SPEC section 3, one named rule per requirement. Each rule is enforced in
 * the place named in docs/firmware.md and has a test named after it.
 *
 * The valve interlock is checked twice: when a valve is asked to open
 * (oibar_safety_valves_permitted, installed as the valve driver's permit)
 * and on every main-loop pass (oibar_safety_enforce), which closes the
 * valves and raises the matching fault as soon as any precondition is lost.
 */
#ifndef OIBAR_APP_SAFETY_H
#define OIBAR_APP_SAFETY_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar.pb.h"

typedef enum {
    SAFETY_RULE_SAFE_START = 0,                 /* boot/restart: outputs safe */
    SAFETY_RULE_VALVES_ONLY_WHEN_TRANSFERRING,  /* hard-docked, in TRANSFERRING */
    SAFETY_RULE_VALVES_NEED_ARM_THEN_START,     /* explicit arm, separate start */
    SAFETY_RULE_VALVES_NEED_CONNECTOR_MATED,
    SAFETY_RULE_VALVES_NEED_LATCH_ENGAGED,
    SAFETY_RULE_VALVES_NEED_SENSORS_HEALTHY,
    SAFETY_RULE_VALVES_NEED_HOST_LINK_ALIVE,
    SAFETY_RULE_VALVES_NEED_NO_FAULT,
    SAFETY_RULE_LOST_PRECONDITION_CLOSES_VALVES,
    SAFETY_RULE_FAULT_CLOSES_VALVES_AND_REPORTS,
    SAFETY_RULE_FAULT_NEEDS_EXPLICIT_CLEAR,
    SAFETY_RULE_INVALID_COMMAND_CHANGES_NOTHING,
    SAFETY_RULE_MALFORMED_FRAME_DROPPED,        /* link layer; app never sees it */
    SAFETY_RULE_WATCHDOG_NEEDS_BOTH_LOOPS,
    SAFETY_RULE_CONTACT_FORCE_LIMIT,            /* paper: <30 N soft, <60 N hard */
    SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN,      /* couplings stay mated while fluid can flow */
    SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN,  /* a fault re-seats a half-mated plane */
    SAFETY_RULE_NO_MOTION_AFTER_RESET,          /* any reset away from home: FAULT, held */
    SAFETY_RULE_PREARM_CHECKS,                  /* ARM_TRANSFER cross-checks the sensors */
    SAFETY_RULE_LIMITS_NOT_TUNABLE,             /* no parameter in bounds disables a protection */
    SAFETY_RULE_VALVES_NEED_PLANE_MATED,        /* end switch and position sensor both at full mate */
    SAFETY_RULE_COUNT
} oibar_safety_rule_t;

#define OIBAR_SAFETY_BIT(rule) (1u << (unsigned)(rule))

void oibar_safety_init(void);
const char *oibar_safety_rule_name(oibar_safety_rule_t rule);

/* Bitmask of the valve rules that forbid an open valve right now
 * (0 = every precondition holds). */
uint32_t oibar_safety_valve_blockers(void);
bool oibar_safety_valves_permitted(void);
/* Main loop, every pass: close valves and raise a fault when a valve is
 * commanded open while a blocker exists. */
void oibar_safety_enforce(void);
/* Pre-arm checks run by ARM_TRANSFER: NACK_PREARM_SENSOR,
 * NACK_PREARM_IMPLAUSIBLE or NACK_NONE. */
oibar_v1_NackReason oibar_safety_prearm(void);
/* Main loop, once per control tick seen (now_ms: hal_time_ms()): contact
 * force limit of the current state, over elapsed time. */
void oibar_safety_force_tick(uint32_t now_ms);
/* Force limit in N for a state (0 = not monitored). */
float oibar_safety_force_limit_n(unsigned state);

#endif
