/* SAFETY_RULE_TIMES_ARE_ELAPSED (issue 16 item 6): every time the
 * application measures is elapsed time on the 1 kHz tick clock, so a slow
 * main loop (several ticks per pass) still trips at the stated time instead
 * of stretching it by the number of ticks per pass. */
#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_pressure.h"
#include "unity.h"

#define TICKS_PER_PASS 4u

void setUp(void) {}
void tearDown(void) {}

/* The main loop gets round once every TICKS_PER_PASS ticks. */
static void slow_pass(void)
{
    if (hal_time_ms() % TICKS_PER_PASS == 0u) {
        oibar_app_run_once();
    }
}

/* Run until `code` is latched; the elapsed ms, or UINT32_MAX after max_ms. */
static uint32_t ms_until_fault(oibar_v1_FaultCode code, uint32_t max_ms)
{
    uint32_t t0 = hal_time_ms();
    while (hal_time_ms() - t0 < max_ms) {
        fake_hal_advance_ms(1);
        if ((oibar_fault_flags() & OIBAR_FAULT_BIT(code)) != 0u) {
            return hal_time_ms() - t0;
        }
    }
    return UINT32_MAX;
}

static void test_SAFETY_RULE_TIMES_ARE_ELAPSED_force_limit_in_a_slow_loop(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_SOFT_DOCKED));
    fake_hal_set_main_loop(slow_pass);
    fake_plant_set_force_n(31.0f); /* over the 30 N soft-dock limit */
    uint32_t debounce = oibar_param_u32(PARAM_DEBOUNCE_MS);
    uint32_t t = ms_until_fault(oibar_v1_FAULT_CONTACT_OVERLOAD, 10u * debounce);
    TEST_ASSERT_TRUE_MESSAGE(t >= debounce - 1u, "tripped early");
    TEST_ASSERT_TRUE_MESSAGE(t <= debounce + 2u * TICKS_PER_PASS, "stretched by the slow loop");
}

static void test_SAFETY_RULE_TIMES_ARE_ELAPSED_valve_mismatch_in_a_slow_loop(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    fake_plant_set_valve_mode(1, FAKE_VALVE_STUCK_CLOSED);
    fake_hal_set_main_loop(slow_pass);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500.0f));
    uint32_t limit = oibar_param_u32(PARAM_VALVE_MISMATCH_MS);
    uint32_t t = ms_until_fault(oibar_v1_FAULT_VALVE_MISMATCH, 10u * limit);
    TEST_ASSERT_TRUE_MESSAGE(t >= limit - 1u, "tripped early");
    TEST_ASSERT_TRUE_MESSAGE(t <= limit + 2u * TICKS_PER_PASS, "stretched by the slow loop");
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

static void test_SAFETY_RULE_TIMES_ARE_ELAPSED_sensor_range_in_a_slow_loop(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_hal_set_main_loop(slow_pass);
    fake_plant_override_adc(HAL_ADC_LINE, 0); /* open wire, for good */
    uint32_t t = ms_until_fault(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE, 200u);
    TEST_ASSERT_TRUE_MESSAGE(t <= OIBAR_PRESSURE_BAD_RUN_MS + 2u * TICKS_PER_PASS,
                             "stretched by the slow loop");
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

static void test_SAFETY_RULE_TIMES_ARE_ELAPSED_fill_rate_is_not_a_jump_in_a_slow_loop(void)
{
    /* The rate window is 10 ms of elapsed time: a slow loop must not turn
     * a legal fill into a "jump" by stretching the window. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    fake_hal_set_main_loop(slow_pass);
    /* Opening the valves slews the line at 1000 kPa/s (half the plausible
     * rate) towards the tank pressure. */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500.0f));
    fake_hal_advance_ms(1000);
    TEST_ASSERT_EQUAL_UINT32(0u, oibar_fault_flags());
    TEST_ASSERT_EQUAL_INT(oibar_v1_STATE_TRANSFERRING, oibar_app_state());
}

/* SAFETY_RULE_ADC_GLITCH_BOUNDED through the application: one bad sample
 * mid-transfer neither closes the valves nor latches a fault. */
static void test_SAFETY_RULE_ADC_GLITCH_BOUNDED_one_sample_mid_transfer(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_plant_override_adc(HAL_ADC_TV_TANK, 0);
    fake_hal_advance_ms(1);
    fake_plant_clear_overrides();
    fake_hal_advance_ms(50);
    TEST_ASSERT_EQUAL_INT(oibar_v1_STATE_TRANSFERRING, oibar_app_state());
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    TEST_ASSERT_EQUAL_UINT32(0u, oibar_fault_flags());
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_SAFETY_RULE_TIMES_ARE_ELAPSED_force_limit_in_a_slow_loop);
    RUN_TEST(test_SAFETY_RULE_TIMES_ARE_ELAPSED_valve_mismatch_in_a_slow_loop);
    RUN_TEST(test_SAFETY_RULE_TIMES_ARE_ELAPSED_sensor_range_in_a_slow_loop);
    RUN_TEST(test_SAFETY_RULE_TIMES_ARE_ELAPSED_fill_rate_is_not_a_jump_in_a_slow_loop);
    RUN_TEST(test_SAFETY_RULE_ADC_GLITCH_BOUNDED_one_sample_mid_transfer);
    return UNITY_END();
}
