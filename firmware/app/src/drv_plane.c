#include "oibar/drv_plane.h"

#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_inputs.h"
#include "oibar/hal.h"

static oibar_plane_motion_t s_motion;
static uint32_t s_start_ms;
static uint16_t s_move_id;

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
        if (oibar_input(HAL_DI_PLANE_EXTENDED)) {
            finish(SIG_PLANE_EXTENDED);
        } else {
            drive(true, false);
        }
    } else {
        if (oibar_input(HAL_DI_PLANE_RETRACTED)) {
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
    if (s_motion == OIBAR_PLANE_STOPPED) {
        return;
    }
    if (s_motion == OIBAR_PLANE_EXTENDING && oibar_input(HAL_DI_PLANE_EXTENDED)) {
        finish(SIG_PLANE_EXTENDED);
        return;
    }
    if (s_motion == OIBAR_PLANE_RETRACTING && oibar_input(HAL_DI_PLANE_RETRACTED)) {
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

bool oibar_plane_is_extended(void)
{
    return s_motion == OIBAR_PLANE_STOPPED && oibar_input(HAL_DI_PLANE_EXTENDED);
}

bool oibar_plane_is_retracted(void)
{
    return s_motion == OIBAR_PLANE_STOPPED && oibar_input(HAL_DI_PLANE_RETRACTED);
}
