/* Application wiring: init, the control tick, the main-loop pass, and the
 * requests from the host. */
#include "oibar/app.h"

#include <math.h>
#include <string.h>

#include "oibar/app_assert.h"
#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_fsm.h"
#include "oibar/app_params.h"
#include "oibar/app_pstore.h"
#include "oibar/app_safety.h"
#include "oibar/drv_inputs.h"
#include "oibar/drv_plane.h"
#include "oibar/drv_pressure.h"
#include "oibar/drv_stepper.h"
#include "oibar/drv_valves.h"
#include "oibar/hal.h"
#include "oibar/pressure_loop.h"

/* Main-loop passes handle at most this many events, so one pass stays
 * bounded even if an ISR keeps posting. */
#define MAX_EVENTS_PER_PASS (OIBAR_EVT_QUEUE_LEN + OIBAR_FAULT_CODE_MAX)

static volatile uint32_t s_ticks;        /* written by the tick ISR only */
static volatile bool s_tick_alive;       /* set by the tick, cleared by the kick */
static uint32_t s_ticks_seen;
static uint32_t s_kicks;
static bool s_link_alive;
/* CMD_END_SESSION accepted and no session since: the host's silence that
 * follows is its planned end, not a lost host (no SIG_LINK_DOWN). */
static bool s_session_ended;
static oibar_v1_ResetCause s_reset_cause;

/* Latest navigation update (host guidance). */
static bool s_nav_valid;
static uint32_t s_nav_rx_ms;
static float s_nav_closing_mm_s;
static float s_nav_misalign_deg;

static oibar_v1_ResetCause map_reset(hal_reset_cause_t c)
{
    switch (c) {
    case HAL_RESET_POWER_ON: return oibar_v1_RESET_POWER_ON;
    case HAL_RESET_PIN: return oibar_v1_RESET_PIN;
    case HAL_RESET_WATCHDOG: return oibar_v1_RESET_WATCHDOG;
    case HAL_RESET_BROWNOUT: return oibar_v1_RESET_BROWNOUT;
    case HAL_RESET_SOFTWARE: return oibar_v1_RESET_SOFTWARE;
    case HAL_RESET_LOCKUP: return oibar_v1_RESET_LOCKUP;
    case HAL_RESET_UNKNOWN:
    default: return oibar_v1_RESET_UNKNOWN;
    }
}

void oibar_app_emit(oibar_v1_EventId id, oibar_v1_Severity sev, oibar_v1_State from,
                    oibar_v1_State to, oibar_v1_FaultCode fault, oibar_v1_NackReason reason,
                    uint32_t arg)
{
    oibar_v1_Event ev;
    memset(&ev, 0, sizeof ev);
    ev.uptime_ms = hal_time_ms();
    ev.id = id;
    ev.severity = sev;
    ev.from_state = from;
    ev.to_state = to;
    ev.fault = fault;
    ev.reason = reason;
    ev.arg = arg;
    oibar_evlog_push(&ev);
}

void oibar_app_init(void)
{
    /* SAFETY_RULE_SAFE_START: every output is driven to its safe level
     * before anything else runs (the drivers' init do it), whatever the
     * reset cause. */
    oibar_valves_init();
    oibar_params_init();
    /* The newer valid stored copy replaces the defaults (app_pstore.h). */
    const oibar_pstore_load_t stored = oibar_pstore_load();
    oibar_evtq_init();
    oibar_evlog_init();
    oibar_faults_init();
    oibar_inputs_init();
    oibar_plane_init();
    oibar_stepper_init();
    oibar_pressure_init();
    oibar_ploop_init();
    oibar_safety_init();
    oibar_valves_set_permit(oibar_safety_valves_permitted);

    uint32_t cs = hal_critical_enter();
    s_ticks = 0;
    s_tick_alive = false;
    hal_critical_exit(cs);
    s_ticks_seen = 0;
    s_kicks = 0;
    s_link_alive = false;
    s_session_ended = false;
    s_nav_valid = false;
    s_nav_rx_ms = 0;
    s_nav_closing_mm_s = 0.0f;
    s_nav_misalign_deg = 0.0f;

    s_reset_cause = map_reset(hal_reset_cause());
    uint32_t now = hal_time_ms();
    oibar_app_emit(oibar_v1_EVT_BOOT, oibar_v1_SEVERITY_ACTIVITY_HI, oibar_v1_STATE_UNSPECIFIED,
                   oibar_v1_STATE_BOOT, oibar_v1_FAULT_NONE, oibar_v1_NACK_NONE,
                   (uint32_t)s_reset_cause);
    oibar_fsm_init(now);
    /* No valid stored copy: the defaults run. Never saved (blank flash) is
     * reported; copies that exist but are all invalid (CRC, version, bounds,
     * cross rules) are a fault: a calibration was lost. */
    if (stored != OIBAR_PSTORE_LOADED) {
        const bool invalid = stored == OIBAR_PSTORE_INVALID;
        oibar_app_emit(oibar_v1_EVT_PARAMS_DEFAULTED,
                       invalid ? oibar_v1_SEVERITY_WARNING_HI : oibar_v1_SEVERITY_WARNING_LO,
                       oibar_v1_STATE_BOOT, oibar_v1_STATE_BOOT, oibar_v1_FAULT_NONE,
                       oibar_v1_NACK_NONE, invalid ? 1u : 0u);
        if (invalid) {
            oibar_fault_raise(oibar_v1_FAULT_PARAMS_INVALID);
        }
    }
    /* Restart policy: nothing moves by itself after a reset. Whatever the
     * cause, BOOT's self test ends in FAULT (FAULT_RESET_AWAY_FROM_HOME) when
     * the mechanism is not at home, and FAULT waits for the host's
     * CLEAR_FAULT. A watchdog or lockup reset is also reported as its own
     * fault, even at home: the firmware itself was stuck. */
    if (s_reset_cause == oibar_v1_RESET_WATCHDOG || s_reset_cause == oibar_v1_RESET_LOCKUP) {
        oibar_fault_raise(oibar_v1_FAULT_WATCHDOG_RESET);
    }
    /* Cross-parameter rules at boot too (D10): a table that breaks one is
     * a broken contract, held in FAULT. */
    if (!oibar_params_consistent()) {
        oibar_fault_raise(oibar_v1_FAULT_ASSERTION);
    }
    hal_control_tick_attach(oibar_app_tick_1khz);
}

void oibar_app_tick_1khz(void)
{
    s_ticks = s_ticks + 1u;
    s_tick_alive = true;
    oibar_inputs_tick_isr();
}

/* Once per main-loop pass that saw at least one control tick. A pass may
 * cover several ticks (a slow pass); every duration below is therefore
 * measured as elapsed time on `now` (the 1 kHz tick clock), never as a
 * count of these calls (SAFETY_RULE_TIMES_ARE_ELAPSED). */
/* D4: the navigation record is dropped once older than nav_max_age_ms (and
 * on link loss and every new session): a 32-bit age alone would read fresh
 * again 49.7 days later. */
static void nav_age_tick(uint32_t now)
{
    if (s_nav_valid && now - s_nav_rx_ms > oibar_param_u32(PARAM_NAV_MAX_AGE_MS)) {
        s_nav_valid = false;
    }
}

static void per_ms(uint32_t now)
{
    nav_age_tick(now);
    oibar_inputs_analog_update();
    oibar_pressure_tick(now);
    oibar_valves_tick(now);
    oibar_plane_tick(now);
    oibar_ploop_tick(now);
    oibar_safety_force_tick(now);
    oibar_fsm_tick(now);
}

/* Faults first (they are never queued), then the queue, bounded. */
static void drain(uint32_t now)
{
    for (unsigned n = 0; n < MAX_EVENTS_PER_PASS; n++) {
        oibar_v1_FaultCode f = oibar_fault_take_pending();
        if (f != oibar_v1_FAULT_NONE) {
            oibar_fsm_signal(SIG_FAULT, (uint16_t)f, now);
            continue;
        }
        oibar_evt_t e;
        if (!oibar_evtq_get(&e)) {
            return;
        }
        oibar_fsm_signal((oibar_sig_t)e.sig, e.arg, now);
    }
}

void oibar_app_run_once(void)
{
    uint32_t now = hal_time_ms();
    uint32_t ticks = s_ticks;
    if (ticks != s_ticks_seen) {
        s_ticks_seen = ticks;
        per_ms(now);
    }
    drain(now);
    oibar_safety_enforce();
    drain(now); /* report what enforcement found in the same pass */

    /* SAFETY_RULE_WATCHDOG_NEEDS_BOTH_LOOPS: kicked here (main loop alive)
     * only if the tick ran since the last kick (control tick alive). */
    if (s_tick_alive) {
        s_tick_alive = false;
        hal_watchdog_kick();
        s_kicks++;
    }
}

uint32_t oibar_app_watchdog_kicks(void) { return s_kicks; }

/* CMD_SAVE_PARAMS (SAFETY_RULE_SAVE_ONLY_WHEN_SAFE): not a transition, the
 * state does not change. The sector erase blocks this main loop for up to
 * about a second (the port keeps the watchdog fed, hal.h), so only in BOOT or
 * IDLE, both valves commanded and sensed closed, the plane and the latch
 * stepper still. */
static oibar_v1_NackReason save_params(void)
{
    const oibar_v1_State st = oibar_fsm_state();
    if (st != oibar_v1_STATE_BOOT && st != oibar_v1_STATE_IDLE) {
        return oibar_v1_NACK_INVALID_IN_STATE;
    }
    if (oibar_valves_any_cmd_open() || oibar_valves_any_sensed_open() || oibar_stepper_busy() ||
        oibar_plane_motion() != OIBAR_PLANE_STOPPED) {
        return oibar_v1_NACK_PRECONDITION_FAILED;
    }
    if (!oibar_pstore_save()) {
        return oibar_v1_NACK_SAVE_FAILED;
    }
    oibar_app_emit(oibar_v1_EVT_PARAMS_SAVED, oibar_v1_SEVERITY_ACTIVITY_HI, st, st,
                   oibar_v1_FAULT_NONE, oibar_v1_NACK_NONE, oibar_pstore_seq());
    return oibar_v1_NACK_NONE;
}

oibar_v1_NackReason oibar_app_command(oibar_v1_CommandOpcode op, float target_pressure_kpa)
{
    uint32_t now = hal_time_ms();
    drain(now); /* a fault raised since the last pass wins over the command */
    oibar_v1_State before = oibar_fsm_state();
    oibar_v1_NackReason r = (op == oibar_v1_CMD_SAVE_PARAMS)
                                ? save_params()
                                : oibar_fsm_command(op, target_pressure_kpa, now);
    if (r != oibar_v1_NACK_NONE) {
        oibar_app_emit(oibar_v1_EVT_COMMAND_REJECTED, oibar_v1_SEVERITY_WARNING_LO, before, before,
                       oibar_v1_FAULT_NONE, r, (uint32_t)op);
    } else if (op == oibar_v1_CMD_END_SESSION) {
        /* Planned end: the state machine has closed the valves and held,
         * disarmed or aborted (docs/state_table.md); the silence that
         * follows is not a lost host. */
        s_session_ended = true;
    } else if (op != oibar_v1_CMD_NOOP) {
        s_session_ended = false; /* the host drives the mechanism again */
    }
    return r;
}

float oibar_app_misalignment_deg(const oibar_v1_Quat *q)
{
    /* z axis of the target expressed in the camera frame: third column of
     * the rotation matrix. Its angle to the boresight (camera z) is the
     * combined yaw/pitch error; roll about the axis does not count. */
    float n2 = q->w * q->w + q->x * q->x + q->y * q->y + q->z * q->z;
    if (!(n2 > 1e-6f) || !isfinite(n2)) {
        return 180.0f; /* not a rotation: treat as worst case */
    }
    float zz = 1.0f - 2.0f * (q->x * q->x + q->y * q->y) / n2;
    if (zz > 1.0f) {
        zz = 1.0f;
    } else if (zz < -1.0f) {
        zz = -1.0f;
    }
    float deg = acosf(zz) * (180.0f / 3.14159265f);
    /* Facing (anti-parallel) axes are as aligned as parallel ones: the
     * convention of the pose pipeline does not matter. */
    return (deg > 90.0f) ? 180.0f - deg : deg;
}

void oibar_app_nav_update(const oibar_v1_NavUpdate *nav)
{
    if (nav == NULL) {
        return;
    }
    /* Navigation contract: only an update the host marks valid, with a
     * confidence at or above nav_min_confidence and finite data, counts. */
    s_nav_valid = nav->valid && isfinite(nav->confidence) &&
                  nav->confidence >= oibar_param_f(PARAM_NAV_MIN_CONFIDENCE) &&
                  isfinite(nav->closing_speed_mps) && nav->has_q_cam_target;
    s_nav_rx_ms = hal_time_ms();
    s_nav_closing_mm_s = nav->closing_speed_mps * 1000.0f;
    s_nav_misalign_deg = nav->has_q_cam_target ? oibar_app_misalignment_deg(&nav->q_cam_target)
                                               : 180.0f;
}

bool oibar_app_capture_envelope_ok(uint32_t now_ms)
{
    if (!s_nav_valid || now_ms - s_nav_rx_ms > oibar_param_u32(PARAM_NAV_MAX_AGE_MS)) {
        return false;
    }
    /* D5: the speed's magnitude; a large negative value is no slower. */
    return fabsf(s_nav_closing_mm_s) <= oibar_param_f(PARAM_CAPTURE_MAX_CLOSING_SPEED_MM_S) &&
           s_nav_misalign_deg <= oibar_param_f(PARAM_CAPTURE_MAX_MISALIGNMENT_DEG);
}

static void fill_param(const oibar_param_def_t *d, oibar_v1_ParamValue *out)
{
    out->param_id = (uint32_t)d->id;
    out->value = oibar_param_f(d->id);
    out->min = d->min;
    out->max = d->max;
    out->default_value = d->default_value;
    strncpy(out->name, d->name, sizeof out->name - 1u);
    strncpy(out->unit, d->unit, sizeof out->unit - 1u);
}

void oibar_app_param_get(uint32_t id, oibar_v1_ParamValue *out)
{
    memset(out, 0, sizeof *out);
    out->param_id = id;
    const oibar_param_def_t *d = oibar_param_def(id);
    if (d == NULL) {
        out->reason = oibar_v1_NACK_UNKNOWN_PARAM;
        return;
    }
    fill_param(d, out);
    out->reason = oibar_v1_NACK_NONE;
}

void oibar_app_param_set(uint32_t id, float value, oibar_v1_ParamValue *out)
{
    oibar_v1_NackReason r = oibar_param_set(id, value, oibar_fsm_state());
    oibar_app_param_get(id, out); /* current value, whether or not it changed */
    if (out->reason == oibar_v1_NACK_NONE) {
        out->reason = r;
    }
    if (r == oibar_v1_NACK_NONE) {
        oibar_app_emit(oibar_v1_EVT_PARAM_CHANGED, oibar_v1_SEVERITY_ACTIVITY_HI,
                       oibar_fsm_state(), oibar_fsm_state(), oibar_v1_FAULT_NONE,
                       oibar_v1_NACK_NONE, id);
    }
}

void oibar_app_link_state(bool up)
{
    /* D4: navigation from before a loss, or from another session (the link
     * also reports a re-handshake as up), is not this approach's. */
    s_nav_valid = false;
    if (up) {
        s_session_ended = false; /* a new session (handshake): its loss faults again */
    }
    if (up == s_link_alive) {
        return;
    }
    s_link_alive = up;
    if (!up) {
        /* SAFETY_RULE_VALVES_NEED_HOST_LINK_ALIVE: close first, then tell
         * the state machine (which faults outside the safe states), unless
         * the host ended its session (CMD_END_SESSION): a planned end. */
        oibar_valves_close_all();
        if (!s_session_ended) {
            (void)oibar_evtq_post(SIG_LINK_DOWN, 0u);
        }
    }
}

bool oibar_app_host_link_alive(void) { return s_link_alive; }
bool oibar_app_session_ended(void) { return s_session_ended; }
oibar_v1_State oibar_app_state(void) { return oibar_fsm_state(); }
oibar_v1_ResetCause oibar_app_reset_cause(void) { return s_reset_cause; }

void oibar_app_fill_telemetry(oibar_v1_Telemetry *out)
{
    /* Leaves out->link / has_link to the link layer. */
    out->uptime_ms = hal_time_ms();
    out->state = oibar_fsm_state();
    out->fault_flags = oibar_fault_flags();
    out->latch_pos_steps = oibar_stepper_pos_steps();
    out->latch_engaged = oibar_input(HAL_DI_LATCH_ENGAGED);
    out->plane_pos_mm = oibar_plane_pos_mm();
    out->contact = oibar_input(HAL_DI_CONTACT);
    out->connector_mated = oibar_input(HAL_DI_CONNECTOR_MATED);
    out->sv_valve_cmd_open = oibar_valve_cmd_open(OIBAR_VALVE_SV);
    out->sv_valve_open = oibar_valve_sensed_open(OIBAR_VALVE_SV);
    out->tv_valve_cmd_open = oibar_valve_cmd_open(OIBAR_VALVE_TV);
    out->tv_valve_open = oibar_valve_sensed_open(OIBAR_VALVE_TV);
    out->sv_tank_kpa = oibar_pressure_kpa(OIBAR_PSENS_SV);
    out->tv_tank_kpa = oibar_pressure_kpa(OIBAR_PSENS_TV);
    out->line_kpa = oibar_pressure_kpa(OIBAR_PSENS_LINE);
    out->target_pressure_kpa = oibar_fsm_target_kpa();
    out->event_queue_overflows = oibar_evtq_overflows();
    out->host_link_alive = s_link_alive;
}

bool oibar_app_next_event(oibar_v1_Event *out) { return oibar_evlog_pop(out); }

void oibar_app_assert_failed(const char *file, int line)
{
    (void)file;
    (void)line;
    oibar_fault_raise(oibar_v1_FAULT_ASSERTION);
}
