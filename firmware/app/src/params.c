/* Parameter table. Every number below marked "assumption" is ours: SPEC gives
 * only the capture envelope and contact forces from the paper; travel,
 * speeds, pressures, sensor ranges and timeouts are design choices to be
 * confirmed on hardware. */
#include "oibar/app_params.h"

#include <math.h>
#include <stddef.h>

#include "oibar/app_assert.h"

#define P_INT(id_, name_, unit_, def_, min_, max_) \
    { (id_), (name_), (unit_), (float)(def_), (float)(min_), (float)(max_), true }
#define P_REAL(id_, name_, unit_, def_, min_, max_) \
    { (id_), (name_), (unit_), (float)(def_), (float)(min_), (float)(max_), false }

/* Safety limits (the force limits, the over-pressure trip, the sensor
 * calibration and validity window, the valve mismatch time, the coupling
 * travel) are parameters only so that a unit can be calibrated: their bounds
 * keep a margin to the rating or the physical fault they protect against, so
 * no value in bounds switches a protection off (docs/firmware.md, "Safety
 * limits"). The ratings they are measured against are compile-time constants
 * in app_params.h.
 *
 * Ordered by id: s_defs[i].id == i + 1 (checked by a test). */
static const oibar_param_def_t s_defs[OIBAR_PARAM_COUNT] = {
    /* Paper: capture works up to 50 mm/s closing speed. */
    P_REAL(PARAM_CAPTURE_MAX_CLOSING_SPEED_MM_S, "capture_max_speed_mm_s", "mm/s", 50, 0, 50),
    /* Paper: combined yaw and pitch misalignment up to 10 deg. */
    P_REAL(PARAM_CAPTURE_MAX_MISALIGNMENT_DEG, "capture_max_misalign_deg", "deg", 10, 0, 10),
    /* Paper: soft-docking contact force under half the hard-docking one. */
    /* Safety limit: never 0 (0 would read as "no limit"); at most the paper's value. */
    P_REAL(PARAM_SOFT_DOCK_MAX_FORCE_N, "soft_dock_max_force_n", "N", 30, 10, 30),
    /* Paper: hard-docking contact force under 60 N. */
    /* Safety limit: above the 20 N mating force, at most the paper's value. */
    P_REAL(PARAM_HARD_DOCK_MAX_FORCE_N, "hard_dock_max_force_n", "N", 60, 30, 60),
    /* Assumption: navigation updates arrive every 100 ms; 5 missed = stale. */
    P_INT(PARAM_NAV_MAX_AGE_MS, "nav_max_age_ms", "ms", 500, 100, 5000),
    /* Assumption: switch bounce of microswitches settles within 10 ms. */
    P_INT(PARAM_DEBOUNCE_MS, "debounce_ms", "ms", 10, 1, 100),
    /* Assumption: inputs and ADC settle within 100 ms of power-up. */
    P_INT(PARAM_BOOT_SETTLE_MS, "boot_settle_ms", "ms", 100, 20, 2000),
    /* Assumption: contact must come within 10 min of arming for reception. */
    P_INT(PARAM_APPROACH_READY_TIMEOUT_MS, "approach_timeout_ms", "ms", 600000, 1000, 3600000),
    /* Assumption: latches engage and the host confirms within 30 s of contact. */
    P_INT(PARAM_RECEPTION_TIMEOUT_MS, "reception_timeout_ms", "ms", 30000, 1000, 300000),
    /* Assumption: 40 mm plane travel at 10 mm/s = 4 s, doubled. */
    P_INT(PARAM_PLANE_MOVE_TIMEOUT_MS, "plane_move_timeout_ms", "ms", 8000, 500, 60000),
    /* Assumption: plane move plus connector mating, with margin. */
    P_INT(PARAM_HARD_DOCKING_TIMEOUT_MS, "hard_docking_timeout_ms", "ms", 12000, 1000, 120000),
    /* Assumption: an arm step not followed by a start within 60 s lapses. */
    P_INT(PARAM_TRANSFER_ARMED_TIMEOUT_MS, "armed_timeout_ms", "ms", 60000, 1000, 600000),
    /* Assumption: spring-damper pre-load extracts the probe within 10 s. */
    P_INT(PARAM_SEPARATING_TIMEOUT_MS, "separating_timeout_ms", "ms", 10000, 1000, 60000),
    /* Assumption: longer than the home budget at home speed (2400 steps at
     * 400 steps/s = 6 s), so a stall is reported as a stall, not a timeout. */
    P_INT(PARAM_LATCH_MOVE_TIMEOUT_MS, "latch_move_timeout_ms", "ms", 8000, 500, 60000),
    /* Assumption: the latch releases about 600 steps from home; 2x budget. */
    P_INT(PARAM_LATCH_RELEASE_BUDGET_STEPS, "latch_rel_budget_steps", "steps", 1200, 10, 20000),
    /* Assumption: homing from the far end of travel, 2x margin. */
    P_INT(PARAM_LATCH_HOME_BUDGET_STEPS, "latch_home_budget_steps", "steps", 2400, 10, 40000),
    /* Assumption: stepper cruise speed. */
    P_INT(PARAM_LATCH_MAX_SPEED_STEPS_S, "latch_max_speed_steps_s", "steps/s", 800, 50, 5000),
    /* Assumption: stepper acceleration for the trapezoidal profile. */
    P_INT(PARAM_LATCH_ACCEL_STEPS_S2, "latch_accel_steps_s2", "steps/s2", 4000, 100, 50000),
    /* Assumption: slower homing speed so the switch is not overrun. */
    P_INT(PARAM_LATCH_HOME_SPEED_STEPS_S, "latch_home_speed_steps_s", "steps/s", 400, 50, 2000),
    /* Assumption: solenoid valve stroke under 100 ms; 2x before a mismatch. */
    /* Safety limit: also bounds how long an abort holds the plane mated
     * waiting for the valves to read closed. */
    P_INT(PARAM_VALVE_MISMATCH_MS, "valve_mismatch_ms", "ms", 200, 50, 500),
    /* Assumption: 0.5-4.5 V ratiometric transducers; 0.5 V = 410 counts. */
    /* Safety limit (calibration): +-40 counts (+-37 kPa) around 0.5 V. */
    P_INT(PARAM_PRESS_ZERO_COUNTS, "press_zero_counts", "counts", 410, 370, 450),
    /* Assumption: 0..3000 kPa over 3276 counts (calibration per sensor).
     * Safety limit (calibration): +-10 % of nominal, so a gain cannot scale
     * an over-pressure below the trip. */
    P_REAL(PARAM_PRESS_SV_KPA_PER_COUNT, "press_sv_kpa_per_count", "kPa/cnt", 0.9158, 0.82, 1.01),
    P_REAL(PARAM_PRESS_TV_KPA_PER_COUNT, "press_tv_kpa_per_count", "kPa/cnt", 0.9158, 0.82, 1.01),
    P_REAL(PARAM_PRESS_LINE_KPA_PER_COUNT, "press_line_kpa_per_count", "kPa/cnt", 0.9158, 0.82, 1.01),
    /* Assumption: below 0.25 V = open wire, above 4.75 V = short.
     * Safety limit: the window keeps a margin to 0 counts (open wire) and
     * 4095 (short), and contains the rated pressure's counts (3686). */
    P_INT(PARAM_PRESS_VALID_MIN_COUNTS, "press_min_counts", "counts", 200, 100, 300),
    P_INT(PARAM_PRESS_VALID_MAX_COUNTS, "press_max_counts", "counts", 3900, 3750, 4000),
    /* Assumption: no real fill changes pressure faster than 2000 kPa/s. */
    /* Safety limit: a sensor jump faster than this is a sensor fault. */
    P_REAL(PARAM_PRESS_MAX_RATE_KPA_S, "press_max_rate_kpa_s", "kPa/s", 2000, 500, 5000),
    /* Assumption: tanks and line rated 3000 kPa (OIBAR_TANK_RATING_KPA); trip
     * at 2600 kPa. Safety limit: at most 90 % of the rating. */
    P_REAL(PARAM_OVERPRESSURE_KPA, "overpressure_kpa", "kPa", 2600, 100,
           OIBAR_OVERPRESSURE_MAX_KPA),
    /* Assumption: accepted range of CMD_START_TRANSFER target pressure (and
     * always below the trip, checked by START_TRANSFER). */
    P_REAL(PARAM_TARGET_MIN_KPA, "target_min_kpa", "kPa", 100, 0, OIBAR_OVERPRESSURE_MAX_KPA),
    P_REAL(PARAM_TARGET_MAX_KPA, "target_max_kpa", "kPa", 2400, 0, OIBAR_OVERPRESSURE_MAX_KPA),
    /* Assumption: a fill never takes longer than 10 min. */
    P_INT(PARAM_TRANSFER_MAX_MS, "transfer_max_ms", "ms", 600000, 1000, 3600000),
    /* Assumption: 50 mm potentiometer over the full ADC range. Safety limit
     * (calibration): +-5 %, so full mate (40 mm) always reads above
     * OIBAR_PLANE_MATED_MIN_MM and a plane short of it cannot read as mated. */
    P_REAL(PARAM_PLANE_MM_PER_COUNT, "plane_mm_per_count", "mm/cnt", 0.01221, 0.0116, 0.0128),
    /* Assumption: load cell amplifier 0..204 N over the full ADC range.
     * Safety limit (calibration): +-20 % of nominal, so a gain cannot hide
     * an overload. */
    P_REAL(PARAM_FORCE_N_PER_COUNT, "force_n_per_count", "N/cnt", 0.05, 0.04, 0.06),
    /* Assumption: abort retracts the plane (plane timeout) plus margin. */
    P_INT(PARAM_ABORT_TIMEOUT_MS, "abort_timeout_ms", "ms", 12000, 1000, 120000),
    /* Assumption: plane travel (mm from retracted) from which the fluid couplings' poppets
     * are pushed open; below it they are apart and self-sealed, at full travel sealed. */
    /* Safety limit: at most 35 mm, so the re-seat and the abort's valve wait
     * cannot be tuned away (smaller is the cautious side), and at least
     * OIBAR_PLANE_COUPLING_MIN_MM: at 0 FAULT's re-seat drove a retracted
     * plane through the whole coupling travel with a valve reading open. */
    P_REAL(PARAM_PLANE_COUPLING_MM, "plane_coupling_mm", "mm", 30, OIBAR_PLANE_COUPLING_MIN_MM, 35),
    /* Assumption: the host's confidence (0..1) below which a navigation
     * update is not used for DOCK's capture check; never 0. */
    P_REAL(PARAM_NAV_MIN_CONFIDENCE, "nav_min_confidence", "1", 0.5, 0.2, 1),
    /* Assumption: with the line OIBAR_FILL_LINE_LEAD_KPA above the target tank, the
     * tank rises OIBAR_FILL_MIN_RISE_KPA in ~1.2 s (rig: 0.84 L/s into 20 L); 3 s is
     * 2.5x that, and the MCU acts before the host's own 5 s fill-stall abort.
     * Safety limit: at most 30 s, so it cannot be tuned into transfer_max_ms. */
    P_INT(PARAM_FILL_STALL_MS, "fill_stall_ms", "ms", 3000, 500, 30000),
};

static float s_values[OIBAR_PARAM_COUNT];

#define V(v, id) ((v)[(unsigned)(id) - 1u])

/* Cross-parameter rules (D10): values each in bounds can still combine into a
 * protection that never works or one that trips on every healthy run. Checked
 * on a candidate table, so a set that would break one is refused whole. */
static bool cross_ok(const float *v)
{
    /* A healthy valve stroke plus the debounce of its position switch must
     * fit in the mismatch window (debounce 100 ms with a 50 ms window made
     * every healthy stroke a stuck valve). */
    if (V(v, PARAM_VALVE_MISMATCH_MS) < V(v, PARAM_DEBOUNCE_MS) + OIBAR_VALVE_STROKE_MAX_MS) {
        return false;
    }
    /* The plane's own timeout must cover a full travel, and an abort (which
     * may first wait valve_mismatch_ms for the valves, then move the plane
     * its whole travel) must outlast both: the plane's fault names the cause. */
    if (V(v, PARAM_PLANE_MOVE_TIMEOUT_MS) < OIBAR_PLANE_FULL_TRAVEL_MS ||
        V(v, PARAM_ABORT_TIMEOUT_MS) < V(v, PARAM_VALVE_MISMATCH_MS) + V(v, PARAM_PLANE_MOVE_TIMEOUT_MS) ||
        V(v, PARAM_HARD_DOCKING_TIMEOUT_MS) < V(v, PARAM_PLANE_MOVE_TIMEOUT_MS)) {
        return false;
    }
    /* The latch state timeout covers the homing budget at home speed, so a
     * stall is reported as a stall, not as a timeout. */
    if (V(v, PARAM_LATCH_MOVE_TIMEOUT_MS) * V(v, PARAM_LATCH_HOME_SPEED_STEPS_S) <
        1000.0f * V(v, PARAM_LATCH_HOME_BUDGET_STEPS)) {
        return false;
    }
    /* The target range is not empty and stays below the trip. */
    if (V(v, PARAM_TARGET_MIN_KPA) > V(v, PARAM_TARGET_MAX_KPA) ||
        V(v, PARAM_TARGET_MAX_KPA) >= V(v, PARAM_OVERPRESSURE_KPA)) {
        return false;
    }
    return true;
}

bool oibar_params_consistent(void) { return cross_ok(s_values); }

static bool value_ok(const oibar_param_def_t *def, float value)
{
    if (!(value >= def->min && value <= def->max)) { /* also rejects NaN */
        return false;
    }
    return !def->integer || floorf(value) == value;
}

void oibar_params_snapshot(float out[OIBAR_PARAM_COUNT])
{
    for (unsigned i = 0; i < OIBAR_PARAM_COUNT; i++) {
        out[i] = s_values[i];
    }
}

bool oibar_params_apply(const float in[OIBAR_PARAM_COUNT])
{
    for (unsigned i = 0; i < OIBAR_PARAM_COUNT; i++) {
        if (!value_ok(&s_defs[i], in[i])) {
            return false;
        }
    }
    if (!cross_ok(in)) {
        return false;
    }
    for (unsigned i = 0; i < OIBAR_PARAM_COUNT; i++) {
        s_values[i] = in[i];
    }
    return true;
}

void oibar_params_init(void)
{
    for (unsigned i = 0; i < OIBAR_PARAM_COUNT; i++) {
        s_values[i] = s_defs[i].default_value;
    }
}

const oibar_param_def_t *oibar_param_def(uint32_t id)
{
    if (id == 0u || id >= (uint32_t)PARAM_ID_END) {
        return NULL;
    }
    return &s_defs[id - 1u];
}

const oibar_param_def_t *oibar_param_def_at(unsigned index)
{
    return (index < OIBAR_PARAM_COUNT) ? &s_defs[index] : NULL;
}

float oibar_param_f(oibar_param_id_t id)
{
    if (!OIBAR_REQUIRE(id > 0 && id < PARAM_ID_END)) {
        return 0.0f;
    }
    return s_values[(unsigned)id - 1u];
}

uint32_t oibar_param_u32(oibar_param_id_t id)
{
    float v = oibar_param_f(id);
    return (v <= 0.0f) ? 0u : (uint32_t)v;
}

bool oibar_params_settable_in(oibar_v1_State state)
{
    return state == oibar_v1_STATE_BOOT || state == oibar_v1_STATE_IDLE ||
           state == oibar_v1_STATE_FAULT;
}

oibar_v1_NackReason oibar_param_set(uint32_t id, float value, oibar_v1_State state)
{
    const oibar_param_def_t *def = oibar_param_def(id);
    if (def == NULL) {
        return oibar_v1_NACK_UNKNOWN_PARAM;
    }
    /* The locked check comes before the bounds check: a host probing a
     * moving mechanism learns first that it must not. */
    if (!oibar_params_settable_in(state)) {
        return oibar_v1_NACK_PARAM_LOCKED;
    }
    if (!value_ok(def, value)) { /* bounds, NaN, a fraction on an integer */
        return oibar_v1_NACK_PARAM_OUT_OF_BOUNDS;
    }
    float candidate[OIBAR_PARAM_COUNT];
    for (unsigned i = 0; i < OIBAR_PARAM_COUNT; i++) {
        candidate[i] = s_values[i];
    }
    candidate[id - 1u] = value;
    if (!cross_ok(candidate)) {
        return oibar_v1_NACK_PARAM_OUT_OF_BOUNDS; /* in its own bounds, not with the others */
    }
    s_values[id - 1u] = value;
    return oibar_v1_NACK_NONE;
}
