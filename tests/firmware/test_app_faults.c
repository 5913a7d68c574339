/* Every fault in every state ends in STATE_FAULT with the valves closed and
 * the fault reported; then the physical ways each fault arises. */
#include <stdio.h>
#include <string.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "unity.h"

void setUp(void) {}
void tearDown(void) {}

static bool reported(oibar_v1_FaultCode code)
{
    oibar_v1_Event ev;
    bool seen = false;
    while (oibar_app_next_event(&ev)) {
        seen = seen || (ev.id == oibar_v1_EVT_FAULT && ev.fault == code);
    }
    return seen;
}

static void assert_faulted(oibar_v1_FaultCode code, const char *msg)
{
    TEST_ASSERT_EQUAL_INT_MESSAGE(oibar_v1_STATE_FAULT, oibar_app_state(), msg);
    TEST_ASSERT_FALSE_MESSAGE(fake_hal_do(HAL_DO_SV_VALVE), msg);
    TEST_ASSERT_FALSE_MESSAGE(fake_hal_do(HAL_DO_TV_VALVE), msg);
    TEST_ASSERT_TRUE_MESSAGE((oibar_fault_flags() & OIBAR_FAULT_BIT(code)) != 0u, msg);
    TEST_ASSERT_TRUE_MESSAGE(reported(code), msg);
    oibar_v1_Telemetry t;
    memset(&t, 0, sizeof t);
    oibar_app_fill_telemetry(&t);
    TEST_ASSERT_TRUE_MESSAGE((t.fault_flags & OIBAR_FAULT_BIT(code)) != 0u, msg);
}

static void test_every_fault_in_every_state(void)
{
    char msg[64];
    for (unsigned st = 1; st <= 15; st++) {
        for (unsigned f = 1; f <= OIBAR_FAULT_CODE_MAX; f++) {
            snprintf(msg, sizeof msg, "state %u fault %u", st, f);
            TEST_ASSERT_TRUE_MESSAGE(bench_goto((oibar_v1_State)st), msg);
            oibar_fault_raise((oibar_v1_FaultCode)f);
            /* Valves close at the raise, before the main loop runs. */
            TEST_ASSERT_FALSE_MESSAGE(bench_any_valve_driven(), msg);
            fake_hal_advance_ms(1);
            assert_faulted((oibar_v1_FaultCode)f, msg);
            /* SAFETY_RULE_FAULT_NEEDS_EXPLICIT_CLEAR: nothing leaves FAULT by itself. */
            fake_hal_advance_ms(2000);
            TEST_ASSERT_EQUAL_INT_MESSAGE(oibar_v1_STATE_FAULT, oibar_app_state(), msg);
        }
    }
}

static void test_overpressure_trips_transfer(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_plant_override_adc(HAL_ADC_LINE, (int)(2700.0f / 0.9158f + 410.0f));
    /* a step that large also trips the rate check; both are reported */
    fake_hal_advance_ms(2);
    assert_faulted(oibar_v1_FAULT_OVERPRESSURE, "overpressure");
}

static void test_sensor_out_of_range_trips_transfer(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_hal_advance_ms(1);
    fake_plant_override_adc(HAL_ADC_TV_TANK, 50); /* open wire */
    fake_hal_advance_ms(12);
    assert_faulted(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE, "range");
}

static void test_sensor_rate_trips_transfer(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_plant_override_adc(HAL_ADC_SV_TANK, 1000); /* 2000 -> ~540 kPa at once */
    fake_hal_advance_ms(12);
    assert_faulted(oibar_v1_FAULT_PRESSURE_SENSOR_RATE, "rate");
}

static void test_stuck_closed_valve_is_mismatch(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_plant_set_valve_mode(1, FAKE_VALVE_STUCK_CLOSED);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
    fake_hal_advance_ms(150);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFERRING, oibar_app_state()); /* stroke time allowed */
    fake_hal_advance_ms(100);
    assert_faulted(oibar_v1_FAULT_VALVE_MISMATCH, "stuck closed");
}

static void test_stuck_open_valve_is_mismatch_and_blocks_clear(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_IDLE));
    fake_plant_set_valve_mode(0, FAKE_VALVE_STUCK_OPEN);
    fake_hal_advance_ms(250);
    assert_faulted(oibar_v1_FAULT_VALVE_MISMATCH, "stuck open");
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0));
}

static void test_plane_jam_is_plane_timeout(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_SOFT_DOCKED));
    fake_plant_set_plane_jam(true);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_HARD_DOCK, 0));
    fake_hal_advance_ms(8001);
    assert_faulted(oibar_v1_FAULT_PLANE_TIMEOUT, "jam");
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
}

static void test_connector_without_mating_is_plane_timeout(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_SOFT_DOCKED));
    fake_plant_override_di(HAL_DI_CONNECTOR_MATED, 0);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_HARD_DOCK, 0));
    fake_hal_advance_ms(12001);
    assert_faulted(oibar_v1_FAULT_PLANE_TIMEOUT, "no connector");
}

static void test_stepper_stall_on_reset(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_LATCH_RESET));
    fake_plant_set_stepper_stall(true);
    fake_hal_advance_ms(7000);
    assert_faulted(oibar_v1_FAULT_LATCH_STALL, "stall");
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_LATCH_ENABLE));
}

static void test_latch_release_stall(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_UNMATING));
    fake_plant_set_stepper_stall(true);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_LATCH_RELEASE, 6000));
    fake_hal_advance_ms(5000);
    assert_faulted(oibar_v1_FAULT_LATCH_STALL, "release stall");
}

static void test_probe_stuck_is_latch_timeout(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_SEPARATING));
    fake_plant_override_di(HAL_DI_CONTACT, 1);
    fake_hal_advance_ms(10001);
    assert_faulted(oibar_v1_FAULT_LATCH_TIMEOUT, "separation");
}

static void test_transfer_timeout(void)
{
    /* The tanks equalise near 1980 kPa, short of a 2300 kPa target. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 2300));
    fake_hal_advance_ms(599000);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFERRING, oibar_app_state());
    fake_hal_advance_ms(1000);
    assert_faulted(oibar_v1_FAULT_TRANSFER_TIMEOUT, "transfer timeout");
}

static void test_fill_stalled_on_a_stuck_target_sensor(void)
{
    /* SAFETY_RULE_FILL_MUST_PROGRESS through the whole application: the target tank's
     * sensor freezes 1 s into a fill, the line keeps rising with the real tank and the
     * supply tank drains; the first witness to see it (here the drain, fill_stall_ms after
     * the reading's last 5 kPa rise, <= 25 ms before the freeze) stops the fill. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
    fake_hal_advance_ms(1000);
    fake_plant_override_adc(HAL_ADC_TV_TANK, (int)(fake_plant_tv_kpa() / 0.9158f + 410.0f + 0.5f));
    fake_hal_advance_ms(2900);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFERRING, oibar_app_state());
    fake_hal_advance_ms(1000);
    assert_faulted(oibar_v1_FAULT_FILL_STALLED, "fill stalled");
    TEST_ASSERT_TRUE(fake_plant_tv_kpa() < 1500.0f);
}

static void test_link_loss_in_every_active_state(void)
{
    for (unsigned st = 1; st <= 15; st++) {
        TEST_ASSERT_TRUE(bench_goto((oibar_v1_State)st));
        oibar_app_link_state(false);
        TEST_ASSERT_FALSE(bench_any_valve_driven());
        fake_hal_advance_ms(1);
        if (st == oibar_v1_STATE_BOOT || st == oibar_v1_STATE_IDLE || st == oibar_v1_STATE_FAULT) {
            TEST_ASSERT_EQUAL(st, oibar_app_state());
        } else {
            assert_faulted(oibar_v1_FAULT_HOST_LINK_LOSS, "link loss");
        }
    }
}

static void test_connector_and_latch_loss_while_transferring(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_plant_override_di(HAL_DI_CONNECTOR_MATED, 0);
    fake_hal_advance_ms(11);
    assert_faulted(oibar_v1_FAULT_CONNECTOR_LOST, "connector");
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_plant_override_di(HAL_DI_LATCH_ENGAGED, 0);
    fake_hal_advance_ms(11);
    assert_faulted(oibar_v1_FAULT_LATCH_LOST, "latch");
}

/* SAFETY_RULE_LATCH_SENSE_PAIR through the application: a short or a broken
 * wire on the latch switch pair closes the valves and holds FAULT; the fault
 * cannot be cleared while the pair stays implausible. */
static void test_SAFETY_RULE_LATCH_SENSE_PAIR_wire_fault_while_transferring(void)
{
    const hal_di_t contact[2] = { HAL_DI_LATCH_NOT_ENGAGED, HAL_DI_LATCH_ENGAGED };
    const int level[2] = { 1, 0 }; /* NC shorted to ground; NO wire broken */
    for (unsigned k = 0; k < 2; k++) {
        TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
        TEST_ASSERT_TRUE(bench_any_valve_driven());
        fake_plant_override_di(contact[k], level[k]);
        fake_hal_advance_ms(11);
        TEST_ASSERT_FALSE(bench_any_valve_driven());
        TEST_ASSERT_EQUAL_INT(oibar_v1_STATE_FAULT, oibar_app_state());
        fake_hal_advance_ms(100);
        assert_faulted(oibar_v1_FAULT_LATCH_SENSOR, "latch pair");
        TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED,
                          oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0.0f));
        TEST_ASSERT_EQUAL_INT(oibar_v1_STATE_FAULT, oibar_app_state());
        fake_plant_clear_overrides();
    }
}

static void test_contact_overload(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_SOFT_DOCKED));
    fake_plant_set_force_n(29.0f);
    fake_hal_advance_ms(50);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_SOFT_DOCKED, oibar_app_state());
    fake_plant_set_force_n(31.0f); /* paper: soft-docking under 30 N */
    fake_hal_advance_ms(12);
    assert_faulted(oibar_v1_FAULT_CONTACT_OVERLOAD, "soft overload");
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_plant_set_force_n(55.0f);
    fake_hal_advance_ms(50);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    fake_plant_set_force_n(61.0f); /* paper: hard-docking under 60 N */
    fake_hal_advance_ms(12);
    assert_faulted(oibar_v1_FAULT_CONTACT_OVERLOAD, "hard overload");
}

static void test_event_queue_overflow_is_a_fault(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    for (unsigned i = 0; i < OIBAR_EVT_QUEUE_LEN + 3u; i++) {
        (void)oibar_evtq_post(SIG_CONTACT, 0);
    }
    TEST_ASSERT_EQUAL_UINT32(3, oibar_evtq_overflows());
    fake_hal_advance_ms(1);
    assert_faulted(oibar_v1_FAULT_EVENT_QUEUE_OVERFLOW, "overflow");
    oibar_v1_Telemetry t;
    memset(&t, 0, sizeof t);
    oibar_app_fill_telemetry(&t);
    TEST_ASSERT_EQUAL_UINT32(3, t.event_queue_overflows);
}

static void test_watchdog_reset_boots_into_fault(void)
{
    fake_hal_reset();
    fake_plant_enable(true);
    fake_hal_set_reset_cause(HAL_RESET_WATCHDOG);
    fake_hal_advance_ms(1);
    oibar_app_init();
    fake_hal_set_main_loop(oibar_app_run_once);
    oibar_app_link_state(true);
    fake_hal_advance_ms(500);
    assert_faulted(oibar_v1_FAULT_WATCHDOG_RESET, "watchdog");
    TEST_ASSERT_EQUAL(oibar_v1_RESET_WATCHDOG, oibar_app_reset_cause());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0));
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_IDLE, 3000));
}

static void test_clear_fault_recovers_through_aborting(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    oibar_fault_raise(oibar_v1_FAULT_ASSERTION);
    fake_hal_advance_ms(1);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_ABORTING, oibar_app_state());
    TEST_ASSERT_EQUAL_UINT32(0, oibar_fault_flags());
    /* still latched behind the drogue: back to soft-docked */
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_SOFT_DOCKED, 6000));
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_every_fault_in_every_state);
    RUN_TEST(test_overpressure_trips_transfer);
    RUN_TEST(test_sensor_out_of_range_trips_transfer);
    RUN_TEST(test_sensor_rate_trips_transfer);
    RUN_TEST(test_stuck_closed_valve_is_mismatch);
    RUN_TEST(test_stuck_open_valve_is_mismatch_and_blocks_clear);
    RUN_TEST(test_plane_jam_is_plane_timeout);
    RUN_TEST(test_connector_without_mating_is_plane_timeout);
    RUN_TEST(test_stepper_stall_on_reset);
    RUN_TEST(test_latch_release_stall);
    RUN_TEST(test_probe_stuck_is_latch_timeout);
    RUN_TEST(test_transfer_timeout);
    RUN_TEST(test_fill_stalled_on_a_stuck_target_sensor);
    RUN_TEST(test_link_loss_in_every_active_state);
    RUN_TEST(test_connector_and_latch_loss_while_transferring);
    RUN_TEST(test_SAFETY_RULE_LATCH_SENSE_PAIR_wire_fault_while_transferring);
    RUN_TEST(test_contact_overload);
    RUN_TEST(test_event_queue_overflow_is_a_fault);
    RUN_TEST(test_watchdog_reset_boots_into_fault);
    RUN_TEST(test_clear_fault_recovers_through_aborting);
    return UNITY_END();
}
