#include "oibar/drv_stepper.h"

#include <math.h>

#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"

/* Profile, written by the main loop before the timer starts, read by the ISR:
 * step i (0-based) is followed by
 *   s_ramp_us[i + 1]                 while accelerating (i + 1 < s_up_n),
 *   s_cruise_us                      until step s_down_at,
 *   s_ramp_us[s_up_n - 1 - j]        for j = 0 .. s_down_n - 1 (decelerating),
 *   s_creep_us                       after that, until the switch or the budget. */
static uint32_t s_ramp_us[OIBAR_STEPPER_RAMP_MAX];
static unsigned s_up_n;
static uint32_t s_cruise_us;
static uint32_t s_down_at;
static unsigned s_down_n;
static uint32_t s_creep_us;
static uint32_t s_slow_us; /* homing pull-off and re-locate: no ramp needed */

/* Move state shared with the ISR. */
typedef enum { PHASE_SEEK = 0, PHASE_PULLOFF, PHASE_LOCATE } phase_t;
static volatile bool s_busy;
static volatile int32_t s_pos;
static volatile bool s_pos_known;
static volatile uint32_t s_remaining;
static volatile uint32_t s_done;
static volatile int8_t s_dir;
static volatile uint8_t s_phase;
static volatile bool s_stop_armed;   /* the switch ends this phase */
static volatile bool s_budget_is_goal; /* the budget ends it too, successfully (pull-off) */
/* Read by the ISR, written by the main loop between moves: volatile too, so
 * the compiler keeps no copy of them across a move. */
static volatile bool s_homing;
static volatile hal_di_t s_stop_di;
static volatile bool s_stop_level;
static volatile bool s_zero_at_stop;
static volatile uint16_t s_move_id;

void oibar_stepper_init(void)
{
    hal_step_timer_stop();
    hal_do_write(HAL_DO_LATCH_ENABLE, false);
    hal_do_write(HAL_DO_LATCH_DIR, false);
    s_busy = false;
    s_pos = 0;
    s_pos_known = false;
    s_remaining = 0;
    s_done = 0;
    s_up_n = 0;
    s_down_n = 0;
    s_down_at = 0;
    s_cruise_us = 0;
    s_creep_us = 0;
    s_slow_us = 0;
    s_move_id = 0;
    hal_step_timer_attach(oibar_stepper_isr);
}

static uint32_t period_us_of(float v_steps_s) { return (uint32_t)(1.0e6f / v_steps_s); }

/* Constant acceleration from rest: after n steps v = sqrt(2 a n). The ramp
 * holds the period of each step until cruise speed, at most
 * OIBAR_STEPPER_RAMP_MAX entries and half the way to `target`; the cruise
 * speed is clamped to what the ramp reached. Deceleration mirrors the ramp
 * down to the creep speed; it ends `target / 8` steps before an `expected`
 * switch, or at `target` (the budget's end) when none is expected. */
static void plan(uint32_t target, bool expected, uint32_t vmax, uint32_t accel, uint32_t vcreep)
{
    s_cruise_us = 1000000u / vmax;
    unsigned n = 0;
    bool reached = false;
    while (n < OIBAR_STEPPER_RAMP_MAX && n < target / 2u) {
        const uint32_t period = period_us_of(sqrtf(2.0f * (float)accel * (float)(n + 1u)));
        if (period <= s_cruise_us) {
            reached = true;
            break;
        }
        s_ramp_us[n] = period;
        n++;
    }
    s_up_n = n;
    if (!reached && n > 0u) {
        s_cruise_us = s_ramp_us[n - 1u]; /* table or distance too short for vmax: clamp */
    }
    /* The first step's period: the fastest start without a ramp. */
    const uint32_t first_us = period_us_of(sqrtf(2.0f * (float)accel));
    s_creep_us = (vcreep == 0u) ? first_us : 1000000u / vcreep;
    if (s_creep_us > first_us) {
        s_creep_us = first_us; /* creeping slower than a standing start is pointless */
    }
    if (s_creep_us < s_cruise_us) {
        s_creep_us = s_cruise_us;
    }
    /* Ramp entries slower than the creep speed are not needed to slow down. */
    unsigned slow_n = 0;
    while (slow_n < n && s_ramp_us[slow_n] > s_creep_us) {
        slow_n++;
    }
    s_down_n = n - slow_n;
    const uint32_t end = expected ? target - target / 8u : target; /* creep over the last eighth */
    s_down_at = (end > n + s_down_n) ? end - s_down_n : n;
}

static void finish_isr(bool reached)
{
    hal_step_timer_stop();
    s_busy = false;
    if (reached) {
        if (s_zero_at_stop) {
            s_pos = 0;
            s_pos_known = true;
        }
        (void)oibar_evtq_post(SIG_STEPPER_DONE, s_move_id);
    } else {
        s_pos_known = false;
        oibar_fault_raise(oibar_v1_FAULT_LATCH_STALL);
    }
}

/* Homing's slow phases: constant speed, no ramp. ISR context: bounded. */
static void start_slow_isr(phase_t phase, int8_t dir, uint32_t budget, bool stop_armed)
{
    s_phase = (uint8_t)phase;
    s_dir = dir;
    hal_do_write(HAL_DO_LATCH_DIR, dir > 0);
    s_remaining = budget;
    s_done = 0;
    s_up_n = 0;
    s_down_at = UINT32_MAX;
    s_cruise_us = s_slow_us;
    s_stop_armed = stop_armed;
    s_budget_is_goal = !stop_armed;
    hal_step_timer_set_period(s_slow_us);
}

/* A phase ended: at its switch or its goal (ok), or out of budget. */
static void phase_end_isr(bool ok)
{
    if (!ok) {
        finish_isr(false);
    } else if (s_homing && s_phase == PHASE_SEEK) {
        start_slow_isr(PHASE_PULLOFF, (int8_t)-s_dir, OIBAR_STEPPER_PULLOFF_STEPS, false);
    } else if (s_phase == PHASE_PULLOFF) {
        if (hal_di_read(s_stop_di) == s_stop_level) {
            finish_isr(false); /* the switch did not clear: stuck switch or stalled motor */
        } else {
            start_slow_isr(PHASE_LOCATE, (int8_t)-s_dir, 2u * OIBAR_STEPPER_PULLOFF_STEPS, true);
        }
    } else {
        finish_isr(true);
    }
}

static bool seek(const oibar_seek_t *req, bool homing)
{
    if (req == 0 || (req->dir != 1 && req->dir != -1) || req->budget_steps == 0u ||
        req->max_speed_steps_s == 0u || req->accel_steps_s2 == 0u ||
        (unsigned)req->stop_di >= (unsigned)HAL_DI_COUNT) {
        return false;
    }
    oibar_stepper_stop();
    s_move_id++;
    s_homing = homing;
    s_phase = (uint8_t)PHASE_SEEK;
    s_dir = req->dir;
    s_stop_di = req->stop_di;
    s_stop_level = req->stop_level;
    s_zero_at_stop = req->zero_at_stop;
    s_stop_armed = true;
    s_budget_is_goal = false;
    const uint32_t expect = req->expect_steps;
    const uint32_t target = (expect == 0u || expect > req->budget_steps) ? req->budget_steps : expect;
    plan(target, target == expect, req->max_speed_steps_s, req->accel_steps_s2,
         (target == expect) ? req->creep_speed_steps_s : 0u);
    uint32_t locate = req->max_speed_steps_s / OIBAR_STEPPER_LOCATE_DIVISOR;
    s_slow_us = 1000000u / ((locate == 0u) ? 1u : locate);
    const uint32_t first_us = period_us_of(sqrtf(2.0f * (float)req->accel_steps_s2));
    if (s_slow_us < first_us) {
        s_slow_us = first_us;
    }
    s_remaining = req->budget_steps;
    s_done = 0;
    hal_do_write(HAL_DO_LATCH_DIR, req->dir > 0);
    hal_do_write(HAL_DO_LATCH_ENABLE, true);
    s_busy = true;
    if (hal_di_read(s_stop_di) == s_stop_level) {
        if (!homing) {
            finish_isr(true); /* already there: complete without a step */
            return true;
        }
        /* D7: homing that starts on its switch pulls off and re-locates as
         * GRBL does; completing at once let a welded switch (or a broken
         * wire, which reads "actuated" on this board) pass for home with the
         * latch released. A switch that does not clear is a stall. */
        start_slow_isr(PHASE_PULLOFF, (int8_t)-req->dir, OIBAR_STEPPER_PULLOFF_STEPS, false);
        hal_step_timer_start(s_slow_us);
        return true;
    }
    hal_step_timer_start(s_up_n > 0u ? s_ramp_us[0] : s_cruise_us);
    return true;
}

bool oibar_stepper_seek(const oibar_seek_t *req) { return seek(req, false); }

bool oibar_stepper_home(void)
{
    const uint32_t speed = oibar_param_u32(PARAM_LATCH_HOME_SPEED_STEPS_S);
    uint32_t budget = oibar_param_u32(PARAM_LATCH_HOME_BUDGET_STEPS);
    /* From a known position the switch is that far: slow down before it.
     * Lost steps only bring it nearer, so not finding it a quarter beyond is
     * a stall (reported as one, well before the state's timeout). */
    const uint32_t expect = (s_pos_known && s_pos > 0) ? (uint32_t)s_pos : 0u;
    if (expect > 0u) {
        const uint32_t known_budget = expect + expect / 4u + OIBAR_STEPPER_PULLOFF_STEPS;
        budget = (known_budget < budget) ? known_budget : budget;
    }
    oibar_seek_t req = {
        .dir = -1,
        .stop_di = HAL_DI_LATCH_HOME,
        .stop_level = true,
        .zero_at_stop = true,
        .budget_steps = budget,
        .max_speed_steps_s = speed,
        .accel_steps_s2 = oibar_param_u32(PARAM_LATCH_ACCEL_STEPS_S2),
        .expect_steps = expect,
        .creep_speed_steps_s = speed / 2u,
    };
    return seek(&req, true);
}

bool oibar_stepper_release_latch(void)
{
    const uint32_t budget = oibar_param_u32(PARAM_LATCH_RELEASE_BUDGET_STEPS);
    oibar_seek_t req = {
        .dir = 1,
        .stop_di = HAL_DI_LATCH_ENGAGED,
        .stop_level = false,
        .zero_at_stop = false,
        .budget_steps = budget,
        .max_speed_steps_s = oibar_param_u32(PARAM_LATCH_MAX_SPEED_STEPS_S),
        .accel_steps_s2 = oibar_param_u32(PARAM_LATCH_ACCEL_STEPS_S2),
        /* The budget is twice the cam's release travel (params.c): arrive at
         * home speed, not at full speed. */
        .expect_steps = budget / 2u,
        .creep_speed_steps_s = oibar_param_u32(PARAM_LATCH_HOME_SPEED_STEPS_S),
    };
    return seek(&req, false);
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
    s_pos_known = false; /* unpowered, the cam settles into a detent */
}

/* Bounded: no loop, no division, no float. */
void oibar_stepper_isr(void)
{
    if (!s_busy) {
        hal_step_timer_stop();
        return;
    }
    if (s_stop_armed && hal_di_read(s_stop_di) == s_stop_level) {
        phase_end_isr(true);
        return;
    }
    if (s_remaining == 0u) {
        phase_end_isr(s_budget_is_goal); /* else budget spent, switch never came: stalled */
        return;
    }
    hal_step_pulse();
    s_pos += s_dir;
    s_remaining--;
    const uint32_t done = ++s_done;
    uint32_t period;
    if (done < s_up_n) {
        period = s_ramp_us[done];                      /* accelerating */
    } else if (done < s_down_at) {
        period = s_cruise_us;
    } else if (done - s_down_at < s_down_n) {
        period = s_ramp_us[s_up_n - 1u - (done - s_down_at)]; /* decelerating */
    } else {
        period = s_creep_us;
    }
    hal_step_timer_set_period(period);
}

bool oibar_stepper_busy(void) { return s_busy; }
int32_t oibar_stepper_pos_steps(void) { return s_pos; }
bool oibar_stepper_pos_known(void) { return s_pos_known; }
uint16_t oibar_stepper_move_id(void) { return s_move_id; }
unsigned oibar_stepper_ramp_len(void) { return s_up_n; }
uint32_t oibar_stepper_ramp_period_us(unsigned i) { return (i < s_up_n) ? s_ramp_us[i] : 0u; }
uint32_t oibar_stepper_cruise_period_us(void) { return s_cruise_us; }
uint32_t oibar_stepper_decel_at_step(void) { return s_down_at; }
uint32_t oibar_stepper_creep_period_us(void) { return s_creep_us; }
