/* Issue 59, hazards D1-D10 of the outside review (and the suspected items
 * taken): one test each, written to fail on the firmware before the fix.
 * Driven through the application on the fake HAL's plant, as a host and a
 * broken wire would drive it. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_stepper.h"
#include "unity.h"

void setUp(void) {}
void tearDown(void) {}

/* ADC counts of a healthy pressure sensor reading `kpa` (default calibration). */
static int counts_of(float kpa) { return (int)(kpa / 0.9158f + 410.0f + 0.5f); }

static bool fault_latched(oibar_v1_FaultCode code)
{
    return (oibar_fault_flags() & OIBAR_FAULT_BIT(code)) != 0u;
}

static oibar_v1_NackReason set_param(oibar_param_id_t id, float value)
{
    oibar_v1_ParamValue out;
    oibar_app_param_set((uint32_t)id, value, &out);
    return out.reason;
}

/* IDLE -> APPROACH_READY -> RECEPTION with no navigation update: the
 * capture is not confirmed, the latches pop, DOCK is refused. */
static void reception_with_dock_refused(void)
{
    bench_start();
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0.0f));
    fake_plant_set_probe(true);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_RECEPTION, 50u));
    fake_hal_advance_ms(150); /* latches pop and debounce */
    TEST_ASSERT_TRUE(hal_di_read(HAL_DI_LATCH_ENGAGED));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED, oibar_app_command(oibar_v1_CMD_DOCK, 0.0f));
}

/* For `ms`: never SOFT_DOCKED, never a valve or the plane's extend driven. */
static void never_docks_for(uint32_t ms)
{
    for (uint32_t i = 0; i < ms; i++) {
        fake_hal_advance_ms(1);
        TEST_ASSERT_NOT_EQUAL(oibar_v1_STATE_SOFT_DOCKED, oibar_app_state());
        TEST_ASSERT_FALSE(bench_any_valve_driven());
        TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    }
}

/* D1: ABORT after DOCK was refused must not do what DOCK would have done. */
static void test_D1_abort_from_reception_never_soft_docks(void)
{
    reception_with_dock_refused();
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ABORT, 0.0f));
    never_docks_for(8000u);
    /* It let the probe go instead, and is back where it started. */
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
    TEST_ASSERT_FALSE(fake_plant_probe());
    TEST_ASSERT_NOT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_HARD_DOCK, 0.0f));
}

/* D1: the same bypass through RECEPTION's latch timeout and CLEAR_FAULT. */
static void test_D1_reception_timeout_then_clear_fault_never_soft_docks(void)
{
    reception_with_dock_refused();
    fake_hal_advance_ms(oibar_param_u32(PARAM_RECEPTION_TIMEOUT_MS));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(fault_latched(oibar_v1_FAULT_LATCH_TIMEOUT));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0.0f));
    never_docks_for(5000u);
    TEST_ASSERT_NOT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_HARD_DOCK, 0.0f));
}

/* The plant's tanks moved to (sv, tv) at 1 kPa/ms, slower than the rate check. */
static void ramp_tanks(float sv_to, float tv_to)
{
    float sv = fake_plant_sv_kpa(), tv = fake_plant_tv_kpa();
    while (sv != sv_to || tv != tv_to) {
        sv = (sv < sv_to - 1.0f) ? sv + 1.0f : (sv > sv_to + 1.0f) ? sv - 1.0f : sv_to;
        tv = (tv < tv_to - 1.0f) ? tv + 1.0f : (tv > tv_to + 1.0f) ? tv - 1.0f : tv_to;
        fake_plant_set_tanks_kpa(sv, tv);
        fake_hal_advance_ms(1);
    }
    fake_hal_advance_ms(20);
}

/* D2: no START with the supply tank below the target tank. */
static void test_D2_start_refused_with_supply_below_target(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    ramp_tanks(900.0f, 1100.0f);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFER_ARMED, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED,
                      oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500.0f));
    fake_hal_advance_ms(100);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

/* D2: while open, a target tank that falls (the line and the supply with it
 * not draining: gas going back) is back-flow, not a dip to wait out. */
static void test_D2_backflow_while_open_closes_the_valves(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    uint16_t c = 0;
    TEST_ASSERT_TRUE(hal_adc_read(HAL_ADC_SV_TANK, &c));
    fake_plant_override_adc(HAL_ADC_SV_TANK, c);
    TEST_ASSERT_TRUE(hal_adc_read(HAL_ADC_TV_TANK, &c));
    float tv = ((float)c - 410.0f) * 0.9158f;
    uint32_t closed_at = 0;
    for (uint32_t ms = 0; ms < 10000u; ms += 10u) {
        tv -= 0.2f; /* 20 kPa/s back out of the target tank */
        fake_plant_override_adc(HAL_ADC_TV_TANK, counts_of(tv));
        fake_plant_override_adc(HAL_ADC_LINE, counts_of(tv - 2.0f));
        fake_hal_advance_ms(10);
        if (closed_at == 0u && !bench_any_valve_driven()) {
            closed_at = ms + 10u;
        }
    }
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_TRUE_MESSAGE(closed_at > 0u && closed_at <= 4000u, "back-flow not stopped in 4 s");
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
}

/* D3: a failed plane-position conversion is a sensor fault, not the last
 * value for ever (the valves stayed open with the plane at 29 mm). */
static void test_D3_failed_plane_position_read_is_a_sensor_fault(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    fake_hal_set_adc_fail(HAL_ADC_PLANE_POS, true);
    fake_hal_advance_ms(50);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(fault_latched(oibar_v1_FAULT_PLANE_POSITION));
    /* Nothing moves on the stale number, and the fault cannot be cleared. */
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND) || fake_hal_do(HAL_DO_PLANE_RETRACT));
    TEST_ASSERT_NOT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0.0f));
}

/* D3: and the pre-arm check does not arm on it. */
static void test_D3_no_arm_on_a_failed_plane_position_sensor(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_hal_set_adc_fail(HAL_ADC_PLANE_POS, true);
    fake_hal_advance_ms(50);
    TEST_ASSERT_NOT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0.0f));
    TEST_ASSERT_NOT_EQUAL(oibar_v1_STATE_TRANSFER_ARMED, oibar_app_state());
}

/* D4: a navigation update older than nav_max_age_ms is dropped, so 2^32 ms
 * (49.7 days) plus 100 ms later it does not read as 100 ms old. */
static void test_D4_nav_record_dropped_by_age_even_across_the_clock_wrap(void)
{
    bench_start();
    const uint32_t t0 = hal_time_ms();
    bench_nav_good();
    TEST_ASSERT_TRUE(oibar_app_capture_envelope_ok(t0 + 100u));
    fake_hal_advance_ms(oibar_param_u32(PARAM_NAV_MAX_AGE_MS) + 100u);
    TEST_ASSERT_FALSE(oibar_app_capture_envelope_ok(t0 + 100u)); /* = t0 + 2^32 + 100 */
}

/* D4: nor does navigation survive a link loss (a new session). */
static void test_D4_nav_record_dropped_on_link_loss(void)
{
    bench_start();
    bench_nav_good();
    TEST_ASSERT_TRUE(oibar_app_capture_envelope_ok(hal_time_ms()));
    oibar_app_link_state(false);
    oibar_app_link_state(true);
    TEST_ASSERT_FALSE(oibar_app_capture_envelope_ok(hal_time_ms()));
}

/* D5: the closing speed's magnitude is what the envelope bounds. */
static void test_D5_large_negative_closing_speed_is_outside_the_envelope(void)
{
    bench_start();
    oibar_v1_NavUpdate nav;
    memset(&nav, 0, sizeof nav);
    nav.closing_speed_mps = -1.0f; /* 1000 mm/s, either sign */
    nav.has_q_cam_target = true;
    nav.q_cam_target.w = 1.0f;
    nav.range_m = 0.05f;
    nav.confidence = 0.99f;
    nav.valid = true;
    oibar_app_nav_update(&nav);
    TEST_ASSERT_FALSE(oibar_app_capture_envelope_ok(hal_time_ms()));
}

/* D6: a transducer that drifts implausible while armed is caught at START. */
static void test_D6_start_transfer_rechecks_prearm(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    uint16_t c = 0;
    TEST_ASSERT_TRUE(hal_adc_read(HAL_ADC_TV_TANK, &c));
    /* The target tank's reading drifts to -150 kPa (in the sensor's valid
     * window, 1 count a ms: no rate fault), below any closed line. */
    for (int k = c; k >= counts_of(-150.0f); k--) {
        fake_plant_override_adc(HAL_ADC_TV_TANK, k);
        fake_hal_advance_ms(1);
    }
    fake_hal_advance_ms(20);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFER_ARMED, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PREARM_IMPLAUSIBLE,
                      oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500.0f));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

static bool got_sig(oibar_sig_t sig)
{
    oibar_evt_t e;
    bool seen = false;
    while (oibar_evtq_get(&e)) {
        seen = seen || e.sig == sig;
    }
    return seen;
}

/* D7: homing that starts on a switch reading "home" pulls off and
 * re-locates, so a welded switch (or a broken wire) is a stall, not home. */
static void test_D7_homing_from_a_welded_home_switch_is_a_stall(void)
{
    fake_hal_reset();
    fake_plant_enable(true);
    fake_hal_advance_ms(1);
    oibar_params_init();
    oibar_evtq_init();
    oibar_faults_init();
    oibar_stepper_init();
    fake_plant_override_di(HAL_DI_LATCH_HOME, 1); /* welded: reads home wherever the cam is */
    fake_hal_advance_ms(1);
    TEST_ASSERT_TRUE(oibar_stepper_home());
    fake_hal_advance_ms(3000);
    TEST_ASSERT_FALSE(oibar_stepper_busy());
    TEST_ASSERT_FALSE(got_sig(SIG_STEPPER_DONE));
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_LATCH_STALL, oibar_fault_take_pending());
    TEST_ASSERT_FALSE(oibar_stepper_pos_known());
}

/* D8: plane_coupling_mm = 0 is refused; at its lowest accepted value a
 * retracted plane next to a valve stuck open is not driven into the
 * couplings by FAULT's re-seat. */
static void test_D8_plane_coupling_mm_bounded_away_from_a_retracted_plane(void)
{
    bench_start();
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PARAM_OUT_OF_BOUNDS, set_param(PARAM_PLANE_COUPLING_MM, 0.0f));
    const float lowest = oibar_param_def(PARAM_PLANE_COUPLING_MM)->min;
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, set_param(PARAM_PLANE_COUPLING_MM, lowest));
    fake_plant_set_valve_mode(0, FAKE_VALVE_STUCK_OPEN);
    for (unsigned ms = 0; ms < 3000u; ms++) {
        fake_hal_advance_ms(1);
        TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    }
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(fake_plant_plane_mm() < 1.0f);
}

/* The latch never moves off home while the plane is away from retracted. */
static void latch_stays_home_while_plane_out(uint32_t ms)
{
    for (uint32_t i = 0; i < ms; i++) {
        fake_hal_advance_ms(1);
        if (fake_plant_plane_mm() > 1.0f) {
            char msg[96];
            snprintf(msg, sizeof msg, "latch at %d steps with the plane at %.1f mm",
                     (int)fake_plant_latch_steps(), (double)fake_plant_plane_mm());
            TEST_ASSERT_TRUE_MESSAGE(fake_plant_latch_steps() <= 0, msg);
            TEST_ASSERT_NOT_EQUAL_MESSAGE(oibar_v1_STATE_SOFT_DOCKED, oibar_app_state(), msg);
        }
    }
}

/* D9: one broken wire on the RETRACTED end switch (reads actuated): SEPARATE
 * must not release the latch with the plane mated. */
static void test_D9_broken_retracted_switch_wire_separate_keeps_the_latch(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_plant_override_di(HAL_DI_PLANE_RETRACTED, 1);
    fake_hal_advance_ms(30);
    (void)oibar_app_command(oibar_v1_CMD_SEPARATE, 0.0f);
    latch_stays_home_while_plane_out(15000u);
}

/* D9: ...nor ABORT report SOFT_DOCKED with the plane mated, and the
 * SEPARATE that follows release the latch. */
static void test_D9_broken_retracted_switch_wire_abort_then_separate(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_plant_override_di(HAL_DI_PLANE_RETRACTED, 1);
    fake_hal_advance_ms(30);
    (void)oibar_app_command(oibar_v1_CMD_ABORT, 0.0f);
    latch_stays_home_while_plane_out(10000u);
    (void)oibar_app_command(oibar_v1_CMD_SEPARATE, 0.0f);
    latch_stays_home_while_plane_out(15000u);
}

/* D9: both plane end switches actuated at once is a fault. */
static void test_D9_both_plane_end_switches_is_a_fault(void)
{
    bench_start();
    fake_plant_override_di(HAL_DI_PLANE_EXTENDED, 1);
    fake_hal_advance_ms(50);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(fault_latched(oibar_v1_FAULT_PLANE_POSITION));
    TEST_ASSERT_NOT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0.0f));
}

/* D10: debounce and the valve-mismatch window, each in bounds, must not
 * combine into "every healthy stroke is a stuck valve". */
static void test_D10_debounce_vs_valve_mismatch_is_cross_checked(void)
{
    bench_start();
    (void)set_param(PARAM_VALVE_MISMATCH_MS, 50.0f);
    (void)set_param(PARAM_DEBOUNCE_MS, 100.0f);
    TEST_ASSERT_TRUE(oibar_param_f(PARAM_VALVE_MISMATCH_MS) >=
                     oibar_param_f(PARAM_DEBOUNCE_MS) + 100.0f); /* stroke */
    /* Set the other way round too. */
    bench_start();
    (void)set_param(PARAM_DEBOUNCE_MS, 100.0f);
    (void)set_param(PARAM_VALVE_MISMATCH_MS, 50.0f);
    TEST_ASSERT_TRUE(oibar_param_f(PARAM_VALVE_MISMATCH_MS) >=
                     oibar_param_f(PARAM_DEBOUNCE_MS) + 100.0f); /* stroke */
}

/* D10: an abort must outlast its valve wait plus a full plane move. */
static void test_D10_abort_timeout_covers_a_full_plane_move(void)
{
    bench_start();
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PARAM_OUT_OF_BOUNDS, set_param(PARAM_ABORT_TIMEOUT_MS, 1000.0f));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PARAM_OUT_OF_BOUNDS, set_param(PARAM_PLANE_MOVE_TIMEOUT_MS, 500.0f));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PARAM_OUT_OF_BOUNDS, set_param(PARAM_PLANE_MOVE_TIMEOUT_MS, 60000.0f));
    TEST_ASSERT_EQUAL_FLOAT(12000.0f, oibar_param_f(PARAM_ABORT_TIMEOUT_MS));
}

/* Suspected item: a plane position reading beyond the potentiometer's travel
 * (short to the reference) is out of range: a sensor fault. */
static void test_S_plane_position_out_of_range_is_a_sensor_fault(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_plant_override_adc(HAL_ADC_PLANE_POS, 4095);
    fake_hal_advance_ms(50);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(fault_latched(oibar_v1_FAULT_PLANE_POSITION));
}

/* FMEA SW-EXT-STUCK: the extended end switch lost in HARD_DOCKED with the
 * position sensor still at full mate. The valves need both witnesses
 * (docs/firmware.md), so ARM can never succeed: it is FAULT_PLANE_POSITION,
 * not a refusal of every ARM for ever. The plane is not driven either way. */
static void test_S_extended_switch_lost_while_hard_docked_is_a_fault(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_hal_advance_ms(2000); /* healthy: no fault however long it rests there */
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    TEST_ASSERT_TRUE(fake_plant_plane_mm() >= OIBAR_PLANE_MATED_MIN_MM);
    fake_plant_override_di(HAL_DI_PLANE_EXTENDED, 0);
    fake_hal_advance_ms(100);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(fault_latched(oibar_v1_FAULT_PLANE_POSITION));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND) || fake_hal_do(HAL_DO_PLANE_RETRACT));
}

/* The same while armed: TRANSFER_ARMED rests on full mate too. */
static void test_S_extended_switch_lost_while_armed_is_a_fault(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    fake_plant_override_di(HAL_DI_PLANE_EXTENDED, 0);
    fake_hal_advance_ms(100);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(fault_latched(oibar_v1_FAULT_PLANE_POSITION));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

static char *read_source(const char *rel)
{
    char path[512];
    snprintf(path, sizeof path, "%s/%s", OIBAR_SOURCE_DIR, rel);
    FILE *f = fopen(path, "rb");
    TEST_ASSERT_NOT_NULL_MESSAGE(f, path);
    static char buf[65536];
    size_t n = fread(buf, 1, sizeof buf - 1u, f);
    fclose(f);
    buf[n] = '\0';
    return buf;
}

/* Suspected item: state the main loop writes and the step ISR reads is
 * volatile (a property of the source, not visible on the host). */
static void test_S_state_shared_with_the_step_isr_is_volatile(void)
{
    const char *stepper = read_source("firmware/app/src/drv_stepper.c");
    const char *const decls[] = { "static volatile bool s_homing;",
                                  "static volatile hal_di_t s_stop_di;",
                                  "static volatile bool s_stop_level;",
                                  "static volatile bool s_zero_at_stop;" };
    for (unsigned i = 0; i < sizeof decls / sizeof decls[0]; i++) {
        TEST_ASSERT_NOT_NULL_MESSAGE(strstr(stepper, decls[i]), decls[i]);
    }
    const char *step = read_source("firmware/port/stm32f4/src/hal_step.c");
    TEST_ASSERT_NOT_NULL_MESSAGE(strstr(step, "static hal_isr_fn volatile s_step_fn;"),
                                 "hal_step.c: s_step_fn");
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_D1_abort_from_reception_never_soft_docks);
    RUN_TEST(test_D1_reception_timeout_then_clear_fault_never_soft_docks);
    RUN_TEST(test_D2_start_refused_with_supply_below_target);
    RUN_TEST(test_D2_backflow_while_open_closes_the_valves);
    RUN_TEST(test_D3_failed_plane_position_read_is_a_sensor_fault);
    RUN_TEST(test_D3_no_arm_on_a_failed_plane_position_sensor);
    RUN_TEST(test_D4_nav_record_dropped_by_age_even_across_the_clock_wrap);
    RUN_TEST(test_D4_nav_record_dropped_on_link_loss);
    RUN_TEST(test_D5_large_negative_closing_speed_is_outside_the_envelope);
    RUN_TEST(test_D6_start_transfer_rechecks_prearm);
    RUN_TEST(test_D7_homing_from_a_welded_home_switch_is_a_stall);
    RUN_TEST(test_D8_plane_coupling_mm_bounded_away_from_a_retracted_plane);
    RUN_TEST(test_D9_broken_retracted_switch_wire_separate_keeps_the_latch);
    RUN_TEST(test_D9_broken_retracted_switch_wire_abort_then_separate);
    RUN_TEST(test_D9_both_plane_end_switches_is_a_fault);
    RUN_TEST(test_D10_debounce_vs_valve_mismatch_is_cross_checked);
    RUN_TEST(test_D10_abort_timeout_covers_a_full_plane_move);
    RUN_TEST(test_S_plane_position_out_of_range_is_a_sensor_fault);
    RUN_TEST(test_S_state_shared_with_the_step_isr_is_volatile);
    RUN_TEST(test_S_extended_switch_lost_while_hard_docked_is_a_fault);
    RUN_TEST(test_S_extended_switch_lost_while_armed_is_a_fault);
    return UNITY_END();
}
