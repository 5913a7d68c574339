/* SPEC section 3 safety rules that are checked at run time. The others are
 * structural (named where they are implemented; see docs/firmware.md). */
#include "oibar/app_safety.h"

#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "oibar/app_fsm.h"
#include "oibar/app_params.h"
#include "oibar/app_time.h"
#include "oibar/drv_inputs.h"
#include "oibar/drv_plane.h"
#include "oibar/drv_pressure.h"
#include "oibar/drv_valves.h"

static const char *const k_names[SAFETY_RULE_COUNT] = {
    "SAFETY_RULE_SAFE_START",
    "SAFETY_RULE_VALVES_ONLY_WHEN_TRANSFERRING",
    "SAFETY_RULE_VALVES_NEED_ARM_THEN_START",
    "SAFETY_RULE_VALVES_NEED_CONNECTOR_MATED",
    "SAFETY_RULE_VALVES_NEED_LATCH_ENGAGED",
    "SAFETY_RULE_VALVES_NEED_SENSORS_HEALTHY",
    "SAFETY_RULE_VALVES_NEED_HOST_LINK_ALIVE",
    "SAFETY_RULE_VALVES_NEED_NO_FAULT",
    "SAFETY_RULE_LOST_PRECONDITION_CLOSES_VALVES",
    "SAFETY_RULE_FAULT_CLOSES_VALVES_AND_REPORTS",
    "SAFETY_RULE_FAULT_NEEDS_EXPLICIT_CLEAR",
    "SAFETY_RULE_INVALID_COMMAND_CHANGES_NOTHING",
    "SAFETY_RULE_MALFORMED_FRAME_DROPPED",
    "SAFETY_RULE_WATCHDOG_NEEDS_BOTH_LOOPS",
    "SAFETY_RULE_CONTACT_FORCE_LIMIT",
    "SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN",
    "SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN",
    "SAFETY_RULE_NO_MOTION_AFTER_RESET",
    "SAFETY_RULE_PREARM_CHECKS",
    "SAFETY_RULE_LIMITS_NOT_TUNABLE",
    "SAFETY_RULE_VALVES_NEED_PLANE_MATED",
};

const char *oibar_safety_rule_name(oibar_safety_rule_t rule)
{
    return ((unsigned)rule < (unsigned)SAFETY_RULE_COUNT) ? k_names[rule] : "?";
}

uint32_t oibar_safety_valve_blockers(void)
{
    uint32_t b = 0;
    if (oibar_fsm_state() != oibar_v1_STATE_TRANSFERRING) {
        b |= OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_ONLY_WHEN_TRANSFERRING);
    }
    if (!oibar_fsm_transfer_armed() || !oibar_fsm_transfer_started()) {
        b |= OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_ARM_THEN_START);
    }
    if (!oibar_input(HAL_DI_CONNECTOR_MATED)) {
        b |= OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_CONNECTOR_MATED);
    }
    if (!oibar_input(HAL_DI_LATCH_ENGAGED)) {
        b |= OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_LATCH_ENGAGED);
    }
    /* The end switch alone is one stuck contact away from "mated": the
     * position sensor must agree (found by the property test). */
    if (!oibar_plane_is_extended() || !oibar_plane_pos_valid() ||
        oibar_plane_pos_mm() < OIBAR_PLANE_MATED_MIN_MM) {
        b |= OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_PLANE_MATED);
    }
    if (!oibar_pressure_all_ok() || oibar_pressure_over()) {
        b |= OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_SENSORS_HEALTHY);
    }
    if (!oibar_app_host_link_alive()) {
        b |= OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_HOST_LINK_ALIVE);
    }
    if (oibar_fault_flags() != 0u || oibar_fault_any_pending()) { /* raised counts, not only latched */
        b |= OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_NO_FAULT);
    }
    return b;
}

bool oibar_safety_valves_permitted(void) { return oibar_safety_valve_blockers() == 0u; }

/* SAFETY_RULE_LOST_PRECONDITION_CLOSES_VALVES: whatever the state machine
 * believes, an open valve without every precondition is closed now, and the
 * loss is reported as the fault that names it. */
static void enforce_plane(void);

void oibar_safety_enforce(void)
{
    enforce_plane();
    if (!oibar_valves_any_cmd_open()) {
        return;
    }
    uint32_t b = oibar_safety_valve_blockers();
    if (b == 0u) {
        return;
    }
    oibar_valves_close_all();
    oibar_v1_FaultCode code = oibar_v1_FAULT_ASSERTION; /* state/arm: a broken contract */
    if (b & OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_CONNECTOR_MATED)) {
        code = oibar_v1_FAULT_CONNECTOR_LOST;
    } else if (b & OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_LATCH_ENGAGED)) {
        code = oibar_v1_FAULT_LATCH_LOST;
    } else if (b & OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_PLANE_MATED)) {
        code = oibar_v1_FAULT_PLANE_POSITION;
    } else if (b & OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_SENSORS_HEALTHY)) {
        code = oibar_pressure_over() ? oibar_v1_FAULT_OVERPRESSURE
                                     : oibar_v1_FAULT_PRESSURE_SENSOR_RANGE;
    } else if (b & OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_HOST_LINK_ALIVE)) {
        code = oibar_v1_FAULT_HOST_LINK_LOSS;
    } else if (b & OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_NO_FAULT)) {
        return; /* the latched fault is already being handled */
    }
    oibar_fault_raise(code);
}

/* SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN, at run time: whatever the state
 * machine commanded, the plane is never driven back while a valve reads
 * open. Wherever the position sensor says the plane is: it may be wrong
 * (the property test found a plane retracting at 36 mm with its sensor read
 * low), and stopping is never the unsafe choice below the coupling travel.
 * The motor stops at once and the valve that disagrees with its (closed)
 * command is reported; FAULT then re-seats a half-mated plane
 * (SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN). */
static void enforce_plane(void)
{
    if (oibar_plane_motion() != OIBAR_PLANE_RETRACTING || !oibar_valves_any_sensed_open()) {
        return;
    }
    oibar_plane_stop();
    oibar_fault_raise(oibar_v1_FAULT_VALVE_MISMATCH);
}

/* Pre-arm checks (ARM_TRANSFER), PX4 style: the sensors the transfer relies
 * on are healthy and their readings agree with the physics of a closed
 * line. With both valves closed the line holds what the last transfer left
 * in it: never more than the higher tank, never below zero. A reading
 * outside that (beyond OIBAR_PREARM_TOLERANCE_KPA) means a wrong
 * calibration or a failing sensor. Likewise a plane whose end switch reads
 * extended must read at least OIBAR_PLANE_MATED_MIN_MM on its position
 * sensor. */
oibar_v1_NackReason oibar_safety_prearm(void)
{
    for (unsigned i = 0; i < (unsigned)OIBAR_PSENS_COUNT; i++) {
        if (!oibar_pressure_sensor_ok((oibar_psens_t)i)) {
            return oibar_v1_NACK_PREARM_SENSOR;
        }
    }
    /* D3: the position sensor is one of the sensors the transfer relies on. */
    if (!oibar_plane_pos_valid()) {
        return oibar_v1_NACK_PREARM_SENSOR;
    }
    const float tol = OIBAR_PREARM_TOLERANCE_KPA;
    const float sv = oibar_pressure_kpa(OIBAR_PSENS_SV);
    const float tv = oibar_pressure_kpa(OIBAR_PSENS_TV);
    const float line = oibar_pressure_kpa(OIBAR_PSENS_LINE);
    const float highest = (sv > tv) ? sv : tv;
    if (!(sv >= -tol && tv >= -tol && line >= -tol && line <= highest + tol)) {
        return oibar_v1_NACK_PREARM_IMPLAUSIBLE; /* also NaN */
    }
    /* The plane's end switch says mated; its position sensor must agree. */
    if (oibar_input(HAL_DI_PLANE_EXTENDED) && !(oibar_plane_pos_mm() >= OIBAR_PLANE_MATED_MIN_MM)) {
        return oibar_v1_NACK_PREARM_IMPLAUSIBLE;
    }
    if (!oibar_plane_sense_plausible()) {
        return oibar_v1_NACK_PREARM_IMPLAUSIBLE; /* both end switches (D9) */
    }
    return oibar_v1_NACK_NONE;
}

float oibar_safety_force_limit_n(unsigned state)
{
    switch (state) {
    case oibar_v1_STATE_FAULT:
    case oibar_v1_STATE_UNSPECIFIED:
        return 0.0f; /* already safe; nothing more to do */
    case oibar_v1_STATE_APPROACH_READY:
    case oibar_v1_STATE_RECEPTION:
    case oibar_v1_STATE_SOFT_DOCKED:
        return oibar_param_f(PARAM_SOFT_DOCK_MAX_FORCE_N);
    default:
        return oibar_param_f(PARAM_HARD_DOCK_MAX_FORCE_N);
    }
}

/* SAFETY_RULE_CONTACT_FORCE_LIMIT: over the limit for debounce_ms of
 * elapsed time (not main-loop passes). */
static bool s_over;
static uint32_t s_over_since_ms;
static bool s_force_reported;

void oibar_safety_init(void)
{
    s_over = false;
    s_over_since_ms = 0;
    s_force_reported = false;
}

void oibar_safety_force_tick(uint32_t now_ms)
{
    float limit = oibar_safety_force_limit_n((unsigned)oibar_fsm_state());
    bool over = limit > 0.0f && oibar_contact_force_valid() && oibar_contact_force_n() > limit;
    if (!over) {
        s_over = false;
        s_force_reported = false;
        return;
    }
    if (!s_over) {
        s_over = true;
        s_over_since_ms = now_ms;
    }
    if (oibar_held_for(now_ms, s_over_since_ms, oibar_param_u32(PARAM_DEBOUNCE_MS)) &&
        !s_force_reported) {
        s_force_reported = true;
        oibar_fault_raise(oibar_v1_FAULT_CONTACT_OVERLOAD);
    }
}
