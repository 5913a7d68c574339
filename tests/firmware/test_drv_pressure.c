/* Pressure sensors (conversion, range, rate, over-pressure) and the loop. */
#include "fake_hal.h"
#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_inputs.h"
#include "oibar/drv_pressure.h"
#include "oibar/drv_valves.h"
#include "oibar/pressure_loop.h"
#include "unity.h"

static bool permit(void) { return true; }
static void loop_1ms(void)
{
    oibar_pressure_tick();
    oibar_valves_tick();
    oibar_ploop_tick(hal_time_ms());
}

void setUp(void)
{
    fake_hal_reset();
    oibar_params_init();
    oibar_evtq_init();
    oibar_faults_init();
    oibar_inputs_init();
    oibar_valves_init();
    oibar_valves_set_permit(permit);
    oibar_pressure_init();
    oibar_ploop_init();
    for (unsigned c = 0; c < 3; c++) {
        fake_hal_set_adc((hal_adc_t)c, 1000);
    }
    hal_control_tick_attach(oibar_inputs_tick_isr);
    fake_hal_set_main_loop(loop_1ms);
}
void tearDown(void) {}

static void test_conversion_with_calibration(void)
{
    TEST_ASSERT_FLOAT_WITHIN(0.01f, 0.0f, oibar_pressure_counts_to_kpa(OIBAR_PSENS_SV, 410));
    TEST_ASSERT_FLOAT_WITHIN(1.0f, 3000.0f, oibar_pressure_counts_to_kpa(OIBAR_PSENS_SV, 3686));
    oibar_v1_NackReason r = oibar_param_set(PARAM_PRESS_TV_KPA_PER_COUNT, 1.0f, oibar_v1_STATE_IDLE);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, r);
    TEST_ASSERT_FLOAT_WITHIN(0.01f, 590.0f, oibar_pressure_counts_to_kpa(OIBAR_PSENS_TV, 1000));
    fake_hal_advance_ms(1);
    TEST_ASSERT_FLOAT_WITHIN(0.01f, 590.0f, oibar_pressure_kpa(OIBAR_PSENS_TV));
    TEST_ASSERT_TRUE(oibar_pressure_all_ok());
}

static void test_range_fault_after_debounce(void)
{
    fake_hal_advance_ms(20);
    fake_hal_set_adc(HAL_ADC_LINE, 100); /* open wire */
    fake_hal_advance_ms(1);
    TEST_ASSERT_FALSE(oibar_pressure_sensor_ok(OIBAR_PSENS_LINE)); /* unhealthy at once */
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending()); /* fault after debounce */
    fake_hal_advance_ms(10);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE, oibar_fault_take_pending());
    fake_hal_set_adc(HAL_ADC_LINE, 4000); /* short */
    fake_hal_advance_ms(20);
    TEST_ASSERT_FALSE(oibar_pressure_sensor_ok(OIBAR_PSENS_LINE));
    fake_hal_set_adc(HAL_ADC_LINE, 1000);
    fake_hal_advance_ms(2);
    TEST_ASSERT_TRUE(oibar_pressure_sensor_ok(OIBAR_PSENS_LINE));
}

static void test_failed_conversion_is_range_fault(void)
{
    fake_hal_advance_ms(20);
    fake_hal_set_adc_fail(HAL_ADC_SV_TANK, true);
    fake_hal_advance_ms(11);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE, oibar_fault_take_pending());
}

static void test_rate_fault_on_jump_not_on_fill(void)
{
    fake_hal_advance_ms(20);
    /* A steady 200 kPa/s ramp is fine. */
    for (unsigned i = 0; i < 500; i++) {
        fake_hal_set_adc(HAL_ADC_TV_TANK, (uint16_t)(1000u + i / 5u));
        fake_hal_advance_ms(1);
    }
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    fake_hal_set_adc(HAL_ADC_TV_TANK, 2500);
    fake_hal_advance_ms(10);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_PRESSURE_SENSOR_RATE, oibar_fault_take_pending());
    TEST_ASSERT_FALSE(oibar_pressure_all_ok());
}

static void test_overpressure_trip(void)
{
    /* Ramp slowly above 2600 kPa so only the trip fires. */
    uint16_t c = 1000;
    while (oibar_pressure_kpa(OIBAR_PSENS_LINE) <= 2600.0f) {
        c++;
        fake_hal_set_adc(HAL_ADC_LINE, c);
        fake_hal_advance_ms(2);
        TEST_ASSERT_TRUE(c < 3900);
    }
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_OVERPRESSURE, oibar_fault_take_pending());
    TEST_ASSERT_TRUE(oibar_pressure_over());
}

static void test_loop_fills_to_target_and_closes(void)
{
    fake_plant_enable(true);
    fake_hal_advance_ms(50);
    TEST_ASSERT_TRUE(oibar_ploop_start(800.0f, hal_time_ms()));
    TEST_ASSERT_TRUE(fake_hal_do(HAL_DO_SV_VALVE) && fake_hal_do(HAL_DO_TV_VALVE));
    fake_hal_advance_ms(4000);
    oibar_evt_t e;
    TEST_ASSERT_TRUE(oibar_evtq_get(&e));
    TEST_ASSERT_EQUAL(SIG_TARGET_REACHED, e.sig);
    TEST_ASSERT_FALSE(oibar_ploop_running());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_SV_VALVE) || fake_hal_do(HAL_DO_TV_VALVE));
    /* the valves' 30 ms stroke lets a few more kPa through */
    TEST_ASSERT_FLOAT_WITHIN(10.0f, 800.0f, fake_plant_tv_kpa());
}

static void test_loop_max_transfer_time(void)
{
    fake_plant_enable(true);
    fake_hal_advance_ms(50);
    oibar_v1_NackReason r = oibar_param_set(PARAM_TRANSFER_MAX_MS, 2000.0f, oibar_v1_STATE_IDLE);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, r);
    TEST_ASSERT_TRUE(oibar_ploop_start(2300.0f, hal_time_ms()));
    fake_hal_advance_ms(2001);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_TRANSFER_TIMEOUT, oibar_fault_take_pending());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_SV_VALVE) || fake_hal_do(HAL_DO_TV_VALVE));
}

static void test_loop_refused_by_interlock(void)
{
    oibar_valves_set_permit(NULL);
    TEST_ASSERT_FALSE(oibar_ploop_start(800.0f, hal_time_ms()));
    TEST_ASSERT_FALSE(oibar_ploop_running());
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_conversion_with_calibration);
    RUN_TEST(test_range_fault_after_debounce);
    RUN_TEST(test_failed_conversion_is_range_fault);
    RUN_TEST(test_rate_fault_on_jump_not_on_fill);
    RUN_TEST(test_overpressure_trip);
    RUN_TEST(test_loop_fills_to_target_and_closes);
    RUN_TEST(test_loop_max_transfer_time);
    RUN_TEST(test_loop_refused_by_interlock);
    return UNITY_END();
}
