#include "oibar/drv_plane.h"

#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_inputs.h"
#include "oibar/hal.h"

static oibar_plane_motion_t s_motion;
static uint32_t s_start_ms;
static uint16_t s_move_id;
static bool s_both_reported;

/* SAFETY_RULE_PLANE_SENSE_PAIR (D9): an end is reached only when its switch
 * and the position sensor agree, within the window of app_params.h, and the
 * other end's switch is open. One broken wire (this board's reads
 * "actuated") must not make a mated plane count as retracted: SEPARATE
 * released the latch with the plane at full mate. */
static bool both_switches(void)
{
    return oibar_input(HAL_DI_PLANE_EXTENDED) && oibar_input(HAL_DI_PLANE_RETRACTED);
}

static bool at_extended(void)
{
    return oibar_input(HAL_DI_PLANE_EXTENDED) && !oibar_input(HAL_DI_PLANE_RETRACTED) &&
           oibar_plane_pos_valid() && oibar_plane_pos_mm() >= OIBAR_PLANE_MATED_MIN_MM;
}

static bool at_retracted(void)
{
    return oibar_input(HAL_DI_PLANE_RETRACTED) && !oibar_input(HAL_DI_PLANE_EXTENDED) &&
           oibar_plane_pos_valid() && oibar_plane_pos_mm() <= OIBAR_PLANE_RETRACTED_MAX_MM;
}

static void drive(bool extend, bool retract)
{
    /* Never both legs of the H-bridge: switch the old one off first. */
    if (!extend) {
        hal_do_write(HAL_DO_PLANE_EXTEND, false);
    }
    if (!retract) {
        hal_do_write(HAL_DO_PLANE_RETRACT, false);
    }
    if (extend) {
        hal_do_write(HAL_DO_PLANE_EXTEND, true);
    }
    if (retract) {
        hal_do_write(HAL_DO_PLANE_RETRACT, true);
    }
}

void oibar_plane_init(void)
{
    drive(false, false);
    s_motion = OIBAR_PLANE_STOPPED;
    s_start_ms = 0;
    s_move_id = 0;
    s_both_reported = false;
}

static void finish(oibar_sig_t sig)
{
    drive(false, false);
    s_motion = OIBAR_PLANE_STOPPED;
    (void)oibar_evtq_post(sig, s_move_id);
}

static void start(oibar_plane_motion_t motion, uint32_t now_ms)
{
    s_move_id++;
    s_start_ms = now_ms;
    s_motion = motion;
    if (motion == OIBAR_PLANE_EXTENDING) {
        if (at_extended()) {
            finish(SIG_PLANE_EXTENDED);
        } else {
            drive(true, false);
        }
    } else {
        if (at_retracted()) {
            finish(SIG_PLANE_RETRACTED);
        } else {
            drive(false, true);
        }
    }
}

void oibar_plane_extend(uint32_t now_ms) { start(OIBAR_PLANE_EXTENDING, now_ms); }
void oibar_plane_retract(uint32_t now_ms) { start(OIBAR_PLANE_RETRACTING, now_ms); }

void oibar_plane_stop(void)
{
    drive(false, false);
    s_motion = OIBAR_PLANE_STOPPED;
}

void oibar_plane_tick(uint32_t now_ms)
{
    /* Both end switches actuated (debounced) cannot be: a broken wire or a
     * short. Stop, and report it once per episode. */
    if (both_switches()) {
        oibar_plane_stop();
        if (!s_both_reported) {
            s_both_reported = true;
            oibar_fault_raise(oibar_v1_FAULT_PLANE_POSITION);
        }
        return;
    }
    s_both_reported = false;
    if (s_motion == OIBAR_PLANE_STOPPED) {
        return;
    }
    if (s_motion == OIBAR_PLANE_EXTENDING && at_extended()) {
        finish(SIG_PLANE_EXTENDED);
        return;
    }
    if (s_motion == OIBAR_PLANE_RETRACTING && at_retracted()) {
        finish(SIG_PLANE_RETRACTED);
        return;
    }
    if (now_ms - s_start_ms >= oibar_param_u32(PARAM_PLANE_MOVE_TIMEOUT_MS)) {
        oibar_plane_stop();
        oibar_fault_raise(oibar_v1_FAULT_PLANE_TIMEOUT);
    }
}

oibar_plane_motion_t oibar_plane_motion(void) { return s_motion; }
uint16_t oibar_plane_move_id(void) { return s_move_id; }

bool oibar_plane_is_extended(void) { return s_motion == OIBAR_PLANE_STOPPED && at_extended(); }
bool oibar_plane_is_retracted(void) { return s_motion == OIBAR_PLANE_STOPPED && at_retracted(); }
bool oibar_plane_sense_plausible(void) { return !both_switches() && oibar_plane_pos_valid(); }
