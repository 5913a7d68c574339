/*
 * Parameter table, F Prime style: every tunable number of the mechanism in one
 * place, with a unit, a default and bounds. Values are settable over the link
 * only while the mechanism is safe (STATE_BOOT, STATE_IDLE or STATE_FAULT).
 */
#ifndef OIBAR_APP_PARAMS_H
#define OIBAR_APP_PARAMS_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar.pb.h"

/* Ids are part of the host contract: append only, never renumber. */
typedef enum {
    PARAM_CAPTURE_MAX_CLOSING_SPEED_MM_S = 1,
    PARAM_CAPTURE_MAX_MISALIGNMENT_DEG,
    PARAM_SOFT_DOCK_MAX_FORCE_N,
    PARAM_HARD_DOCK_MAX_FORCE_N,
    PARAM_NAV_MAX_AGE_MS,
    PARAM_DEBOUNCE_MS,
    PARAM_BOOT_SETTLE_MS,
    PARAM_APPROACH_READY_TIMEOUT_MS,
    PARAM_RECEPTION_TIMEOUT_MS,
    PARAM_PLANE_MOVE_TIMEOUT_MS,
    PARAM_HARD_DOCKING_TIMEOUT_MS,
    PARAM_TRANSFER_ARMED_TIMEOUT_MS,
    PARAM_SEPARATING_TIMEOUT_MS,
    PARAM_LATCH_MOVE_TIMEOUT_MS,
    PARAM_LATCH_RELEASE_BUDGET_STEPS,
    PARAM_LATCH_HOME_BUDGET_STEPS,
    PARAM_LATCH_MAX_SPEED_STEPS_S,
    PARAM_LATCH_ACCEL_STEPS_S2,
    PARAM_LATCH_HOME_SPEED_STEPS_S,
    PARAM_VALVE_MISMATCH_MS,
    PARAM_PRESS_ZERO_COUNTS,
    PARAM_PRESS_SV_KPA_PER_COUNT,
    PARAM_PRESS_TV_KPA_PER_COUNT,
    PARAM_PRESS_LINE_KPA_PER_COUNT,
    PARAM_PRESS_VALID_MIN_COUNTS,
    PARAM_PRESS_VALID_MAX_COUNTS,
    PARAM_PRESS_MAX_RATE_KPA_S,
    PARAM_OVERPRESSURE_KPA,
    PARAM_TARGET_MIN_KPA,
    PARAM_TARGET_MAX_KPA,
    PARAM_TRANSFER_MAX_MS,
    PARAM_PLANE_MM_PER_COUNT,
    PARAM_FORCE_N_PER_COUNT,
    PARAM_ABORT_TIMEOUT_MS,
    PARAM_PLANE_COUPLING_MM,
    PARAM_NAV_MIN_CONFIDENCE,
    PARAM_FILL_STALL_MS,
    PARAM_ID_END /* one past the last id */
} oibar_param_id_t;

/* Ratings the safety limits are bounded against: compile-time, not tunable. */
#define OIBAR_TANK_RATING_KPA 3000.0f      /* tanks and line (assumption) */
#define OIBAR_OVERPRESSURE_MAX_KPA 2700.0f /* trip at most 90 % of the rating */
/* Pre-arm plausibility (ARM_TRANSFER): a reading below -tolerance, or a line
 * above the higher tank by more than it, means a calibration or sensor error. */
#define OIBAR_PREARM_TOLERANCE_KPA 100.0f
/* Plane position sensor reading below which the plane cannot be at full mate,
 * whatever its end switch says: 40 mm travel, calibration within +-5 %. */
#define OIBAR_PLANE_MATED_MIN_MM 37.5f
/* Fill progress (SAFETY_RULE_FILL_MUST_PROGRESS): while the line reads at least
 * the lead above the target tank, gas flows into it, so its reading must rise by
 * the minimum within fill_stall_ms. Both well above the sensors' ~1 kPa count. */
#define OIBAR_FILL_LINE_LEAD_KPA 100.0f
#define OIBAR_FILL_MIN_RISE_KPA 5.0f
/* The second witness of the same rule: the supply tank falling this much over
 * fill_stall_ms means gas left it, so the target tank's reading must have risen
 * (whatever the line sensor reads). Above the sensors' noise (~1 kPa a count,
 * a few counts peak to peak), well below a real fill's drain over 3 s. */
#define OIBAR_FILL_MIN_DRAIN_KPA 15.0f

/* Lower bound of plane_coupling_mm: the couplings' poppets cannot touch
 * before the alignment pins are well inside their cavities (assumption: not
 * in the first half of the 40 mm travel). */
#define OIBAR_PLANE_COUPLING_MIN_MM 20.0f
/* Cross-parameter rules (oibar_params_consistent). Assumptions: a healthy
 * valve strokes within 100 ms (valve_mismatch_ms's comment); the plane's
 * full 40 mm travel takes 4 s at 10 mm/s. */
#define OIBAR_VALVE_STROKE_MAX_MS 100.0f
#define OIBAR_PLANE_FULL_TRAVEL_MS 4000.0f
/* Flow direction (SAFETY_RULE_NO_BACKFLOW): START_TRANSFER needs the supply
 * tank this far above the target tank (the sensors' calibration tolerance,
 * so a reading error cannot fake a head); while open, a supply read below the
 * target by as much, or a target tank falling this far from its highest
 * reading of the transfer, is gas flowing backwards. The fall bound is above
 * the dip of a target tank refilling an emptier line as the valves open. */
#define OIBAR_FLOW_MIN_HEAD_KPA 100.0f
#define OIBAR_BACKFLOW_DROP_KPA 50.0f
/* Plane position plausibility (SAFETY_RULE_PLANE_SENSE_PAIR): the retracted
 * end switch counts only with the position sensor at or below this (40 mm
 * travel; the switch trips within 0.2 mm of the end), the extended one only
 * at or above OIBAR_PLANE_MATED_MIN_MM. A reading above
 * OIBAR_PLANE_POS_MAX_MM is out of range (the potentiometer spans 50 mm). */
#define OIBAR_PLANE_RETRACTED_MAX_MM 2.5f
#define OIBAR_PLANE_POS_MAX_MM 44.0f

#define OIBAR_PARAM_COUNT ((unsigned)PARAM_ID_END - 1u)

typedef struct {
    oibar_param_id_t id;
    const char *name;   /* snake_case, unit suffix included */
    const char *unit;
    float default_value;
    float min;
    float max;
    bool integer;       /* value must be a whole number */
} oibar_param_def_t;

/* Restore every default. */
void oibar_params_init(void);
/* The current table passes the cross-parameter rules (checked on every set,
 * and at boot by oibar_app_init, which faults when it does not). */
bool oibar_params_consistent(void);

/* Definition by id, NULL when unknown. */
const oibar_param_def_t *oibar_param_def(uint32_t id);
/* Definition by table index 0 .. OIBAR_PARAM_COUNT-1. */
const oibar_param_def_t *oibar_param_def_at(unsigned index);

/* Current values; the id must be valid (contract). */
float oibar_param_f(oibar_param_id_t id);
uint32_t oibar_param_u32(oibar_param_id_t id);

/* Set a value: NACK_UNKNOWN_PARAM, NACK_PARAM_OUT_OF_BOUNDS (also for a
 * fraction on an integer parameter, NaN, or a value in its own bounds that
 * breaks a cross-parameter rule), NACK_PARAM_LOCKED when `state`
 * is not a safe state, else NACK_NONE. */
oibar_v1_NackReason oibar_param_set(uint32_t id, float value, oibar_v1_State state);

/* True in the states where parameters may change. */
bool oibar_params_settable_in(oibar_v1_State state);

/* The whole table, in id order (index = id - 1), for the parameter store. */
void oibar_params_snapshot(float out[OIBAR_PARAM_COUNT]);
/* Replace the whole table if every value is in its bounds (a whole number
 * where the parameter is an integer, never NaN) and the table passes the
 * cross-parameter rules; otherwise change nothing and return false. The
 * parameter store loads a copy from flash only through this. */
bool oibar_params_apply(const float in[OIBAR_PARAM_COUNT]);

#endif
