#include "oibar/drv_stepper.h"

#include <math.h>

#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"

/* Profile, written by the main loop before the timer starts, read by the ISR. */
static uint32_t s_ramp_us[OIBAR_STEPPER_RAMP_MAX];
static unsigned s_ramp_n;
static uint32_t s_cruise_us;

/* Move state shared with the ISR. */
static volatile bool s_busy;
static volatile int32_t s_pos;
static volatile uint32_t s_remaining;
static volatile uint32_t s_done;
static int8_t s_dir;
static hal_di_t s_stop_di;
static bool s_stop_level;
static bool s_zero_at_stop;
static volatile uint16_t s_move_id;

void oibar_stepper_init(void)
{
    hal_step_timer_stop();
    hal_do_write(HAL_DO_LATCH_ENABLE, false);
    hal_do_write(HAL_DO_LATCH_DIR, false);
    s_busy = false;
    s_pos = 0;
    s_remaining = 0;
    s_done = 0;
    s_ramp_n = 0;
    s_cruise_us = 0;
    s_move_id = 0;
    hal_step_timer_attach(oibar_stepper_isr);
}

/* Constant acceleration from rest: after n steps v = sqrt(2 a n). The ramp
 * holds the period of each step until cruise speed. */
static void plan(uint32_t budget, uint32_t vmax, uint32_t accel)
{
    s_cruise_us = 1000000u / vmax;
    unsigned n = 0;
    while (n < OIBAR_STEPPER_RAMP_MAX && n < budget / 2u) {
        float v = sqrtf(2.0f * (float)accel * (float)(n + 1u));
        uint32_t period = (uint32_t)(1.0e6f / v);
        if (period <= s_cruise_us) {
            break;
        }
        s_ramp_us[n] = period;
        n++;
    }
    s_ramp_n = n;
}

static void finish_isr(bool reached)
{
    hal_step_timer_stop();
    s_busy = false;
    if (reached) {
        if (s_zero_at_stop) {
            s_pos = 0;
        }
        (void)oibar_evtq_post(SIG_STEPPER_DONE, s_move_id);
    } else {
        oibar_fault_raise(oibar_v1_FAULT_LATCH_STALL);
    }
}

bool oibar_stepper_seek(const oibar_seek_t *req)
{
    if (req == 0 || (req->dir != 1 && req->dir != -1) || req->budget_steps == 0u ||
        req->max_speed_steps_s == 0u || req->accel_steps_s2 == 0u ||
        (unsigned)req->stop_di >= (unsigned)HAL_DI_COUNT) {
        return false;
    }
    oibar_stepper_stop();
    s_move_id++;
    s_dir = req->dir;
    s_stop_di = req->stop_di;
    s_stop_level = req->stop_level;
    s_zero_at_stop = req->zero_at_stop;
    plan(req->budget_steps, req->max_speed_steps_s, req->accel_steps_s2);
    s_remaining = req->budget_steps;
    s_done = 0;
    hal_do_write(HAL_DO_LATCH_DIR, req->dir > 0);
    hal_do_write(HAL_DO_LATCH_ENABLE, true);
    s_busy = true;
    if (hal_di_read(s_stop_di) == s_stop_level) {
        finish_isr(true); /* already there: complete without a step */
        return true;
    }
    hal_step_timer_start(s_ramp_n > 0u ? s_ramp_us[0] : s_cruise_us);
    return true;
}

bool oibar_stepper_home(void)
{
    oibar_seek_t req = {
        .dir = -1,
        .stop_di = HAL_DI_LATCH_HOME,
        .stop_level = true,
        .zero_at_stop = true,
        .budget_steps = oibar_param_u32(PARAM_LATCH_HOME_BUDGET_STEPS),
        .max_speed_steps_s = oibar_param_u32(PARAM_LATCH_HOME_SPEED_STEPS_S),
        .accel_steps_s2 = oibar_param_u32(PARAM_LATCH_ACCEL_STEPS_S2),
    };
    return oibar_stepper_seek(&req);
}

bool oibar_stepper_release_latch(void)
{
    oibar_seek_t req = {
        .dir = 1,
        .stop_di = HAL_DI_LATCH_ENGAGED,
        .stop_level = false,
        .zero_at_stop = false,
        .budget_steps = oibar_param_u32(PARAM_LATCH_RELEASE_BUDGET_STEPS),
        .max_speed_steps_s = oibar_param_u32(PARAM_LATCH_MAX_SPEED_STEPS_S),
        .accel_steps_s2 = oibar_param_u32(PARAM_LATCH_ACCEL_STEPS_S2),
    };
    return oibar_stepper_seek(&req);
}

void oibar_stepper_stop(void)
{
    hal_step_timer_stop();
    s_busy = false;
}

void oibar_stepper_disable(void)
{
    oibar_stepper_stop();
    hal_do_write(HAL_DO_LATCH_ENABLE, false);
}

/* Bounded: no loop, no division, no float. */
void oibar_stepper_isr(void)
{
    if (!s_busy) {
        hal_step_timer_stop();
        return;
    }
    if (hal_di_read(s_stop_di) == s_stop_level) {
        finish_isr(true);
        return;
    }
    if (s_remaining == 0u) {
        finish_isr(false); /* budget spent, switch never came: stalled */
        return;
    }
    hal_step_pulse();
    s_pos += s_dir;
    s_remaining--;
    s_done++;
    uint32_t period;
    if (s_done < s_ramp_n) {
        period = s_ramp_us[s_done];           /* accelerating */
    } else if (s_remaining < s_ramp_n) {
        period = s_ramp_us[s_remaining];      /* decelerating */
    } else {
        period = s_cruise_us;
    }
    hal_step_timer_set_period(period);
}

bool oibar_stepper_busy(void) { return s_busy; }
int32_t oibar_stepper_pos_steps(void) { return s_pos; }
uint16_t oibar_stepper_move_id(void) { return s_move_id; }
unsigned oibar_stepper_ramp_len(void) { return s_ramp_n; }
uint32_t oibar_stepper_ramp_period_us(unsigned i) { return (i < s_ramp_n) ? s_ramp_us[i] : 0u; }
uint32_t oibar_stepper_cruise_period_us(void) { return s_cruise_us; }
