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
    oibar_pressure_tick(hal_time_ms());
    oibar_valves_tick(hal_time_ms());
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
    fake_hal_advance_ms(OIBAR_PRESSURE_BAD_RUN_MS - 1u);
    TEST_ASSERT_TRUE(oibar_pressure_sensor_ok(OIBAR_PSENS_LINE)); /* a glitch so far */
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    fake_hal_advance_ms(1);
    TEST_ASSERT_FALSE(oibar_pressure_sensor_ok(OIBAR_PSENS_LINE));
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE, oibar_fault_take_pending());
    fake_hal_set_adc(HAL_ADC_LINE, 4000); /* short */
    fake_hal_advance_ms(20);
    TEST_ASSERT_FALSE(oibar_pressure_sensor_ok(OIBAR_PSENS_LINE));
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending()); /* same episode */
    fake_hal_set_adc(HAL_ADC_LINE, 1000);
    fake_hal_advance_ms(2);
    TEST_ASSERT_TRUE(oibar_pressure_sensor_ok(OIBAR_PSENS_LINE));
}

static void test_failed_conversion_is_range_fault(void)
{
    fake_hal_advance_ms(20);
    fake_hal_set_adc_fail(HAL_ADC_SV_TANK, true);
    fake_hal_advance_ms(OIBAR_PRESSURE_BAD_RUN_MS);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE, oibar_fault_take_pending());
}

/* --- SAFETY_RULE_ADC_GLITCH_BOUNDED (issue 16 item 9) --------------------- */
static void test_SAFETY_RULE_ADC_GLITCH_BOUNDED_one_bad_sample_does_not_trip(void)
{
    fake_hal_advance_ms(20);
    const float before = oibar_pressure_kpa(OIBAR_PSENS_TV);
    const hal_adc_t ch[2] = { HAL_ADC_TV_TANK, HAL_ADC_TV_TANK };
    for (unsigned k = 0; k < 2; k++) {
        if (k == 0) {
            fake_hal_set_adc(ch[k], 0); /* one conversion out of range */
        } else {
            fake_hal_set_adc_fail(ch[k], true); /* one conversion failed */
        }
        fake_hal_advance_ms(1);
        TEST_ASSERT_TRUE(oibar_pressure_sensor_ok(OIBAR_PSENS_TV));
        TEST_ASSERT_TRUE(oibar_pressure_all_ok());
        TEST_ASSERT_FLOAT_WITHIN(0.01f, before, oibar_pressure_kpa(OIBAR_PSENS_TV)); /* held */
        fake_hal_set_adc(ch[k], 1000);
        fake_hal_set_adc_fail(ch[k], false);
        fake_hal_advance_ms(50);
    }
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    TEST_ASSERT_TRUE(oibar_pressure_all_ok());
}

static void test_SAFETY_RULE_ADC_GLITCH_BOUNDED_a_run_trips_within_the_bound(void)
{
    fake_hal_advance_ms(20);
    /* Runs shorter than the bound, again and again: never a fault. */
    for (unsigned i = 0; i < 20; i++) {
        fake_hal_set_adc(HAL_ADC_SV_TANK, 0);
        fake_hal_advance_ms(OIBAR_PRESSURE_BAD_RUN_MS - 1u);
        fake_hal_set_adc(HAL_ADC_SV_TANK, 1000);
        fake_hal_advance_ms(1);
    }
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    /* A run of the bound: trips on its last sample. */
    fake_hal_set_adc(HAL_ADC_SV_TANK, 0);
    fake_hal_advance_ms(OIBAR_PRESSURE_BAD_RUN_MS);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE, oibar_fault_take_pending());
    TEST_ASSERT_FALSE(oibar_pressure_all_ok());
}

static void slow_loop_pass(void)
{
    /* A main loop that gets round only every third tick. */
    if (hal_time_ms() % 3u == 0u) {
        loop_1ms();
    }
}

static void test_SAFETY_RULE_ADC_GLITCH_BOUNDED_slow_loop_still_trips_on_time(void)
{
    fake_hal_set_main_loop(slow_loop_pass);
    fake_hal_advance_ms(30);
    /* One bad sample in a slow loop is still one glitch. */
    fake_hal_set_adc(HAL_ADC_LINE, 0);
    fake_hal_advance_ms(3);
    fake_hal_set_adc(HAL_ADC_LINE, 1000);
    fake_hal_advance_ms(30);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    /* A lasting one trips at the first pass at or after the bound in
     * elapsed time (counting passes it would take three times as long). */
    fake_hal_set_adc(HAL_ADC_LINE, 0);
    uint32_t t0 = hal_time_ms();
    oibar_v1_FaultCode f = oibar_v1_FAULT_NONE;
    while (f == oibar_v1_FAULT_NONE && hal_time_ms() - t0 < 100u) {
        fake_hal_advance_ms(1);
        f = oibar_fault_take_pending();
    }
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE, f);
    TEST_ASSERT_TRUE(hal_time_ms() - t0 <= OIBAR_PRESSURE_BAD_RUN_MS + 3u);
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

/* ADC counts of a healthy sensor reading `kpa` (default calibration). */
static int counts_of(float kpa) { return (int)(kpa / 0.9158f + 410.0f + 0.5f); }

/* A fill towards 1500 kPa started, then the target tank's reading frozen 0.5 s into it. */
static void fill_then_freeze_target(void)
{
    fake_hal_advance_ms(50);
    TEST_ASSERT_TRUE(oibar_ploop_start(1500.0f, hal_time_ms()));
    fake_hal_advance_ms(500);
    fake_plant_override_adc(HAL_ADC_TV_TANK, counts_of(fake_plant_tv_kpa()));
}

/* FAULT_FILL_STALLED raised now, valves closed, the real tank short of the target. */
static void assert_stalled_short_of_target(void)
{
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_FILL_STALLED, oibar_fault_take_pending());
    TEST_ASSERT_FALSE(oibar_ploop_running());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_SV_VALVE) || fake_hal_do(HAL_DO_TV_VALVE));
    TEST_ASSERT_TRUE(fake_plant_tv_kpa() < 1500.0f);
}

/* SAFETY_RULE_FILL_MUST_PROGRESS: the target tank's sensor sticks in range mid-fill. The
 * line goes on rising with the real tank, so it reads ever further above the frozen value;
 * fill_stall_ms after it leads by OIBAR_FILL_LINE_LEAD_KPA the loop closes the valves with
 * FAULT_FILL_STALLED, before the tank reaches the target the frozen sensor would never see
 * (without the rule the fill runs on to the fake's ~1830 kPa equalisation). */
static void test_SAFETY_RULE_FILL_MUST_PROGRESS_stuck_target_sensor_stops_the_fill(void)
{
    fake_plant_enable(true);
    /* The supply tank's reading held flat, so the line is the only witness here. */
    fake_plant_override_adc(HAL_ADC_SV_TANK, counts_of(2000.0f));
    fill_then_freeze_target();
    /* At 200 kPa/s the line leads the frozen reading by 100 kPa after 0.5 s; then 3 s. */
    fake_hal_advance_ms(3000);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    TEST_ASSERT_TRUE(oibar_ploop_running());
    fake_hal_advance_ms(1000);
    assert_stalled_short_of_target();
}

/* The same rule does not trip a fill that rises, however far the line leads (here 1900 kPa
 * against a tank going from 200 to 1500 kPa in 6.5 s, more than twice fill_stall_ms). */
static void test_SAFETY_RULE_FILL_MUST_PROGRESS_a_rising_tank_is_no_stall(void)
{
    fake_plant_enable(true);
    fake_plant_override_adc(HAL_ADC_LINE, (int)(1900.0f / 0.9158f + 410.0f));
    fake_hal_advance_ms(50);
    TEST_ASSERT_TRUE(oibar_ploop_start(1500.0f, hal_time_ms()));
    fake_hal_advance_ms(8000);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    oibar_evt_t e;
    TEST_ASSERT_TRUE(oibar_evtq_get(&e));
    TEST_ASSERT_EQUAL(SIG_TARGET_REACHED, e.sig);
    TEST_ASSERT_FLOAT_WITHIN(10.0f, 1500.0f, fake_plant_tv_kpa());
}

/* The same rule with the line sensor failed low (here reading 150 kPa, below the target tank):
 * no lead is seen, but the supply tank drains (20 kPa/s in the fake) while the frozen target
 * reading stands still, so fill_stall_ms after its last rise the loop closes the valves. Without
 * the supply witness this double fault filled on to the fake's ~1830 kPa equalisation. */
static void test_SAFETY_RULE_FILL_MUST_PROGRESS_line_failed_low_the_supply_drain_witnesses(void)
{
    fake_plant_enable(true);
    fake_plant_override_adc(HAL_ADC_LINE, counts_of(150.0f));
    fill_then_freeze_target();
    fake_hal_advance_ms(2900); /* the window started at the last 5 kPa rise, <= 25 ms ago */
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    TEST_ASSERT_TRUE(oibar_ploop_running());
    fake_hal_advance_ms(200);
    assert_stalled_short_of_target();
}

/* ...and a supply that does not drain (equalised tanks, or a supply reading gone flat) is no
 * stall by that witness: the window starts again, and transfer_max_ms ends the fill. */
static void test_SAFETY_RULE_FILL_MUST_PROGRESS_no_drain_no_stall(void)
{
    fake_plant_enable(true);
    fake_plant_override_adc(HAL_ADC_LINE, counts_of(150.0f));
    fake_plant_override_adc(HAL_ADC_SV_TANK, counts_of(2000.0f));
    fill_then_freeze_target();
    fake_hal_advance_ms(9000); /* three windows */
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    TEST_ASSERT_TRUE(oibar_ploop_running());
}

/* A target tank fuller than the line flows back into it as the valves open: its reading falls
 * while the supply drains into the line, then rises as the line fills past it. Read here as 20 kPa
 * down over 1 s, then up at 10 kPa/s: the window starts again at the fall, so the rise from the
 * bottom is progress (counted from the reading before the fall it would take 2.5 s more, and the
 * supply witness would trip at 3 s). */
static void test_SAFETY_RULE_FILL_MUST_PROGRESS_backflow_as_the_valves_open_is_no_stall(void)
{
    fake_plant_enable(true);
    fake_plant_override_adc(HAL_ADC_LINE, counts_of(150.0f));
    fake_plant_override_adc(HAL_ADC_TV_TANK, counts_of(1000.0f));
    fake_hal_advance_ms(50);
    TEST_ASSERT_TRUE(oibar_ploop_start(1500.0f, hal_time_ms()));
    float tv_kpa = 1000.0f;
    for (unsigned ms = 0; ms < 4500u; ms += 50u) {
        tv_kpa += (ms < 1000u) ? -1.0f : 0.5f;
        fake_plant_override_adc(HAL_ADC_TV_TANK, counts_of(tv_kpa));
        fake_hal_advance_ms(50);
    }
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    TEST_ASSERT_TRUE(oibar_ploop_running());
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
    RUN_TEST(test_SAFETY_RULE_ADC_GLITCH_BOUNDED_one_bad_sample_does_not_trip);
    RUN_TEST(test_SAFETY_RULE_ADC_GLITCH_BOUNDED_a_run_trips_within_the_bound);
    RUN_TEST(test_SAFETY_RULE_ADC_GLITCH_BOUNDED_slow_loop_still_trips_on_time);
    RUN_TEST(test_rate_fault_on_jump_not_on_fill);
    RUN_TEST(test_overpressure_trip);
    RUN_TEST(test_loop_fills_to_target_and_closes);
    RUN_TEST(test_loop_max_transfer_time);
    RUN_TEST(test_SAFETY_RULE_FILL_MUST_PROGRESS_stuck_target_sensor_stops_the_fill);
    RUN_TEST(test_SAFETY_RULE_FILL_MUST_PROGRESS_a_rising_tank_is_no_stall);
    RUN_TEST(test_SAFETY_RULE_FILL_MUST_PROGRESS_line_failed_low_the_supply_drain_witnesses);
    RUN_TEST(test_SAFETY_RULE_FILL_MUST_PROGRESS_no_drain_no_stall);
    RUN_TEST(test_SAFETY_RULE_FILL_MUST_PROGRESS_backflow_as_the_valves_open_is_no_stall);
    RUN_TEST(test_loop_refused_by_interlock);
    return UNITY_END();
}
