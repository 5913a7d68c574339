/* Latch stepper against the fake HAL: profile, homing, release, stall. */
#include "fake_hal.h"
#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_stepper.h"
#include "unity.h"

void setUp(void)
{
    fake_hal_reset();
    fake_plant_enable(true);
    fake_hal_advance_ms(1); /* plant drives its switches */
    oibar_params_init();
    oibar_evtq_init();
    oibar_faults_init();
    oibar_stepper_init();
}
void tearDown(void) {}

static bool got(oibar_sig_t sig)
{
    oibar_evt_t e;
    bool seen = false;
    while (oibar_evtq_get(&e)) {
        seen = seen || e.sig == sig;
    }
    return seen;
}

static void test_profile_is_trapezoidal_and_planned_up_front(void)
{
    oibar_seek_t req = { 1, HAL_DI_LATCH_ENGAGED, true, false, 1000, 800, 4000, 0, 0 };
    TEST_ASSERT_TRUE(oibar_stepper_seek(&req));
    unsigned n = oibar_stepper_ramp_len();
    TEST_ASSERT_TRUE(n > 10u && n < 200u); /* v^2/2a = 80 steps */
    for (unsigned i = 1; i < n; i++) {
        TEST_ASSERT_TRUE(oibar_stepper_ramp_period_us(i) < oibar_stepper_ramp_period_us(i - 1));
    }
    TEST_ASSERT_TRUE(oibar_stepper_ramp_period_us(n - 1) > oibar_stepper_cruise_period_us());
    TEST_ASSERT_EQUAL_UINT32(1250u, oibar_stepper_cruise_period_us());
    /* The period sequence seen by the timer: down, flat, up. */
    uint32_t prev = fake_hal_step_period_us();
    unsigned rising = 0, falling = 0;
    while (oibar_stepper_busy()) {
        fake_hal_advance_ms(1);
        uint32_t p = fake_hal_step_period_us();
        if (p < prev) falling++;
        if (p > prev) rising++;
        prev = p;
    }
    TEST_ASSERT_TRUE(falling > 0u && rising > 0u);
    TEST_ASSERT_TRUE(fake_hal_max_step_isr_per_ms() <= 1u);
}

static void test_short_move_never_reaches_cruise(void)
{
    oibar_seek_t req = { 1, HAL_DI_LATCH_ENGAGED, true, false, 20, 800, 4000, 0, 0 };
    TEST_ASSERT_TRUE(oibar_stepper_seek(&req));
    TEST_ASSERT_TRUE(oibar_stepper_ramp_len() <= 10u);
}

static void test_homing_stops_on_switch_and_zeroes(void)
{
    /* Already home: pulls off and re-locates (D7), then completes. */
    TEST_ASSERT_TRUE(oibar_stepper_home());
    fake_hal_advance_ms(2000);
    TEST_ASSERT_FALSE(oibar_stepper_busy());
    TEST_ASSERT_TRUE(got(SIG_STEPPER_DONE));
    TEST_ASSERT_EQUAL_UINT32(2u * OIBAR_STEPPER_PULLOFF_STEPS, fake_hal_step_pulses());
    TEST_ASSERT_EQUAL_INT32(0, fake_plant_latch_steps());
    /* Move away: release the latch (the plant releases at 600 steps). */
    fake_plant_set_probe(true);
    fake_hal_advance_ms(200);
    TEST_ASSERT_TRUE(oibar_stepper_release_latch());
    fake_hal_advance_ms(3000);
    TEST_ASSERT_TRUE(got(SIG_STEPPER_DONE));
    TEST_ASSERT_TRUE(fake_plant_latch_steps() > 0);
    TEST_ASSERT_TRUE(oibar_stepper_home());
    fake_hal_advance_ms(6000); /* seek, pull-off, slow re-locate */
    TEST_ASSERT_FALSE(oibar_stepper_busy());
    TEST_ASSERT_TRUE(got(SIG_STEPPER_DONE));
    TEST_ASSERT_EQUAL_INT32(0, oibar_stepper_pos_steps());
    TEST_ASSERT_EQUAL_INT32(0, fake_plant_latch_steps());
    TEST_ASSERT_TRUE(fake_hal_do(HAL_DO_LATCH_ENABLE)); /* holds until disabled */
    oibar_stepper_disable();
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_LATCH_ENABLE));
}

static void test_release_stops_when_latch_lets_go(void)
{
    fake_plant_set_probe(true);
    fake_hal_advance_ms(200); /* latches engaged */
    TEST_ASSERT_TRUE(hal_di_read(HAL_DI_LATCH_ENGAGED));
    TEST_ASSERT_TRUE(oibar_stepper_release_latch());
    fake_hal_advance_ms(3000);
    TEST_ASSERT_TRUE(got(SIG_STEPPER_DONE));
    TEST_ASSERT_TRUE(fake_plant_latch_steps() >= FAKE_PLANT_LATCH_RELEASE_STEPS);
    TEST_ASSERT_TRUE(fake_plant_latch_steps() < FAKE_PLANT_LATCH_RELEASE_STEPS + 5);
    TEST_ASSERT_EQUAL_UINT32(0, oibar_fault_take_pending());
}

static void test_stall_detected_by_step_budget(void)
{
    fake_plant_set_probe(true);
    fake_hal_advance_ms(200);
    fake_plant_set_stepper_stall(true);
    TEST_ASSERT_TRUE(oibar_stepper_release_latch());
    fake_hal_advance_ms(5000);
    TEST_ASSERT_FALSE(oibar_stepper_busy());
    TEST_ASSERT_FALSE(fake_hal_step_timer_running());
    TEST_ASSERT_EQUAL_UINT32(oibar_param_u32(PARAM_LATCH_RELEASE_BUDGET_STEPS), fake_hal_step_pulses());
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_LATCH_STALL, oibar_fault_take_pending());
    TEST_ASSERT_FALSE(got(SIG_STEPPER_DONE));
}

static void test_bad_requests_refused(void)
{
    oibar_seek_t req = { 0, HAL_DI_LATCH_HOME, true, false, 100, 800, 4000, 0, 0 };
    TEST_ASSERT_FALSE(oibar_stepper_seek(&req));
    req.dir = 1;
    req.budget_steps = 0;
    TEST_ASSERT_FALSE(oibar_stepper_seek(&req));
    req.budget_steps = 10;
    req.max_speed_steps_s = 0;
    TEST_ASSERT_FALSE(oibar_stepper_seek(&req));
    TEST_ASSERT_FALSE(oibar_stepper_seek(NULL));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_LATCH_ENABLE));
}

static void test_stop_is_immediate(void)
{
    fake_plant_set_probe(true);
    fake_hal_advance_ms(200);
    TEST_ASSERT_TRUE(oibar_stepper_release_latch());
    fake_hal_advance_ms(100);
    oibar_stepper_stop();
    uint32_t p = fake_hal_step_pulses();
    fake_hal_advance_ms(100);
    TEST_ASSERT_EQUAL_UINT32(p, fake_hal_step_pulses());
}

/* Issue 16 item 7: at 100 steps/s^2 the 256-step table reaches only ~226
 * steps/s, far below 5000 steps/s. The cruise speed is clamped to the last
 * ramp entry: no period ever drops below it (the old ISR jumped from the
 * table's 4.4 ms to a 0.2 ms cruise period: a stall on real hardware). */
static void test_speed_the_ramp_table_cannot_reach_is_clamped(void)
{
    oibar_seek_t req = { 1, HAL_DI_LATCH_ENGAGED, true, false, 20000, 5000, 100, 0, 0 };
    TEST_ASSERT_TRUE(oibar_stepper_seek(&req));
    TEST_ASSERT_EQUAL_UINT(OIBAR_STEPPER_RAMP_MAX, oibar_stepper_ramp_len());
    const uint32_t fastest = oibar_stepper_ramp_period_us(OIBAR_STEPPER_RAMP_MAX - 1u);
    TEST_ASSERT_TRUE(oibar_stepper_cruise_period_us() >= fastest);
    uint32_t prev = fake_hal_step_period_us();
    for (unsigned ms = 0; ms < 4000u && oibar_stepper_busy(); ms++) {
        fake_hal_advance_ms(1);
        const uint32_t p = fake_hal_step_period_us();
        TEST_ASSERT_TRUE_MESSAGE(p >= fastest, "faster than the ramp ever reached");
        TEST_ASSERT_TRUE_MESSAGE(p <= prev, "slowed down while accelerating");
        prev = p;
    }
}

/* Run until the move ends; the step period in force when it ended. */
static uint32_t run_to_end(uint32_t max_ms)
{
    uint32_t last = fake_hal_step_period_us();
    for (uint32_t ms = 0; ms < max_ms && oibar_stepper_busy(); ms++) {
        last = fake_hal_step_period_us();
        fake_hal_advance_ms(1);
    }
    TEST_ASSERT_FALSE_MESSAGE(oibar_stepper_busy(), "move did not end");
    return last;
}

/* The release seek slows down before the latch is expected to let go: it
 * reaches the switch at home speed, not at full speed. */
static void test_release_reaches_its_switch_slowed_down(void)
{
    fake_plant_set_probe(true);
    fake_hal_advance_ms(200);
    TEST_ASSERT_TRUE(oibar_stepper_release_latch());
    const uint32_t at_switch_us = run_to_end(5000);
    TEST_ASSERT_TRUE(got(SIG_STEPPER_DONE));
    TEST_ASSERT_TRUE(at_switch_us >= 1000000u / oibar_param_u32(PARAM_LATCH_HOME_SPEED_STEPS_S));
    TEST_ASSERT_TRUE(oibar_stepper_decel_at_step() < FAKE_PLANT_LATCH_RELEASE_STEPS);
}

/* GRBL's homing: seek the switch, pull off it, re-locate it slowly, zero. */
static void test_homing_seeks_pulls_off_and_relocates_slowly(void)
{
    fake_plant_set_probe(true);
    fake_hal_advance_ms(200);
    TEST_ASSERT_TRUE(oibar_stepper_release_latch());
    (void)run_to_end(5000);
    (void)got(SIG_STEPPER_DONE);
    const int32_t from = fake_plant_latch_steps();
    TEST_ASSERT_TRUE(from > 0);
    const uint32_t pulses0 = fake_hal_step_pulses();
    const uint32_t dir_writes0 = fake_hal_do_writes(HAL_DO_LATCH_DIR);
    TEST_ASSERT_TRUE(oibar_stepper_home());
    const uint32_t at_switch_us = run_to_end(10000);
    TEST_ASSERT_TRUE(got(SIG_STEPPER_DONE));
    TEST_ASSERT_EQUAL_UINT32(0, oibar_fault_take_pending());
    /* seek `from` steps, pull off, come back the same way */
    TEST_ASSERT_EQUAL_UINT32((uint32_t)from + 2u * OIBAR_STEPPER_PULLOFF_STEPS, fake_hal_step_pulses() - pulses0);
    TEST_ASSERT_TRUE(fake_hal_do_writes(HAL_DO_LATCH_DIR) - dir_writes0 >= 3u);
    TEST_ASSERT_EQUAL_INT32(0, fake_plant_latch_steps());
    TEST_ASSERT_EQUAL_INT32(0, oibar_stepper_pos_steps());
    TEST_ASSERT_TRUE(oibar_stepper_pos_known());
    /* the re-locate is slow */
    TEST_ASSERT_TRUE(at_switch_us >= OIBAR_STEPPER_LOCATE_DIVISOR * 1000000u /
                                         oibar_param_u32(PARAM_LATCH_HOME_SPEED_STEPS_S));
    TEST_ASSERT_TRUE(fake_hal_max_step_isr_per_ms() <= 1u);
}

/* A home switch that does not clear on the pull-off is a stall, not a home. */
static void test_pulloff_that_does_not_clear_the_switch_is_a_stall(void)
{
    fake_plant_set_probe(true);
    fake_hal_advance_ms(200);
    TEST_ASSERT_TRUE(oibar_stepper_release_latch());
    (void)run_to_end(5000);
    (void)got(SIG_STEPPER_DONE);
    TEST_ASSERT_TRUE(oibar_stepper_home());
    fake_hal_advance_ms(300);
    fake_plant_override_di(HAL_DI_LATCH_HOME, 1); /* welded switch */
    (void)run_to_end(10000);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_LATCH_STALL, oibar_fault_take_pending());
    TEST_ASSERT_FALSE(got(SIG_STEPPER_DONE));
    TEST_ASSERT_FALSE(oibar_stepper_pos_known());
}

/* hal.h's contract, as the fake HAL keeps it (and the STM32F4 port now does,
 * with TIM2's ARR unbuffered): a period set in the step ISR is the time to
 * the next call, not one period later. */
static uint32_t s_isr_at_ms[4];
static unsigned s_isr_calls;
static void period_probe_isr(void)
{
    if (s_isr_calls < 4u) {
        s_isr_at_ms[s_isr_calls] = hal_time_ms();
    }
    s_isr_calls++;
    hal_step_timer_set_period(s_isr_calls == 1u ? 3000u : 1000u);
}

static void test_hal_step_period_set_in_isr_applies_to_the_next_interval(void)
{
    s_isr_calls = 0;
    hal_step_timer_attach(period_probe_isr);
    const uint32_t t0 = hal_time_ms();
    hal_step_timer_start(1000u);
    fake_hal_advance_ms(10);
    hal_step_timer_stop();
    TEST_ASSERT_TRUE(s_isr_calls >= 4u);
    TEST_ASSERT_EQUAL_UINT32(3u, s_isr_at_ms[1] - s_isr_at_ms[0]);
    TEST_ASSERT_EQUAL_UINT32(1u, s_isr_at_ms[2] - s_isr_at_ms[1]);
    TEST_ASSERT_TRUE(s_isr_at_ms[0] > t0);
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_profile_is_trapezoidal_and_planned_up_front);
    RUN_TEST(test_short_move_never_reaches_cruise);
    RUN_TEST(test_homing_stops_on_switch_and_zeroes);
    RUN_TEST(test_release_stops_when_latch_lets_go);
    RUN_TEST(test_stall_detected_by_step_budget);
    RUN_TEST(test_bad_requests_refused);
    RUN_TEST(test_stop_is_immediate);
    RUN_TEST(test_speed_the_ramp_table_cannot_reach_is_clamped);
    RUN_TEST(test_release_reaches_its_switch_slowed_down);
    RUN_TEST(test_homing_seeks_pulls_off_and_relocates_slowly);
    RUN_TEST(test_pulloff_that_does_not_clear_the_switch_is_a_stall);
    RUN_TEST(test_hal_step_period_set_in_isr_applies_to_the_next_interval);
    return UNITY_END();
}
