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
    oibar_seek_t req = { 1, HAL_DI_LATCH_ENGAGED, true, false, 1000, 800, 4000 };
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
    oibar_seek_t req = { 1, HAL_DI_LATCH_ENGAGED, true, false, 20, 800, 4000 };
    TEST_ASSERT_TRUE(oibar_stepper_seek(&req));
    TEST_ASSERT_TRUE(oibar_stepper_ramp_len() <= 10u);
}

static void test_homing_stops_on_switch_and_zeroes(void)
{
    /* Already home: completes at once, without a step. */
    TEST_ASSERT_TRUE(oibar_stepper_home());
    TEST_ASSERT_TRUE(got(SIG_STEPPER_DONE));
    TEST_ASSERT_EQUAL_UINT32(0, fake_hal_step_pulses());
    /* Move away: release the latch (the plant releases at 600 steps). */
    fake_plant_set_probe(true);
    fake_hal_advance_ms(200);
    TEST_ASSERT_TRUE(oibar_stepper_release_latch());
    fake_hal_advance_ms(3000);
    TEST_ASSERT_TRUE(got(SIG_STEPPER_DONE));
    TEST_ASSERT_TRUE(fake_plant_latch_steps() > 0);
    TEST_ASSERT_TRUE(oibar_stepper_home());
    fake_hal_advance_ms(3000);
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
    oibar_seek_t req = { 0, HAL_DI_LATCH_HOME, true, false, 100, 800, 4000 };
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
    return UNITY_END();
}
