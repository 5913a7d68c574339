/* The whole SPEC section 2 sequence on the plant model, and its timeouts. */
#include <string.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_params.h"
#include "oibar/app_faults.h"
#include "oibar/drv_stepper.h"
#include "unity.h"

void setUp(void) { bench_start(); }
void tearDown(void) {}

static bool saw_event(oibar_v1_EventId id, oibar_v1_FaultCode fault)
{
    oibar_v1_Event ev;
    bool seen = false;
    while (oibar_app_next_event(&ev)) {
        if (ev.id == id && (fault == oibar_v1_FAULT_NONE || ev.fault == fault)) {
            seen = true;
        }
    }
    return seen;
}

static void test_boot_reaches_idle_with_everything_safe(void)
{
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
    for (unsigned i = 0; i < HAL_DO_COUNT; i++) {
        TEST_ASSERT_FALSE(fake_hal_do((hal_do_t)i));
    }
}

static void test_full_refuelling_sequence(void)
{
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_APPROACH_READY, oibar_app_state());
    bench_nav_good();
    fake_plant_set_probe(true);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_RECEPTION, 50));
    fake_hal_advance_ms(150);
    bench_nav_good();
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_DOCK, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_SOFT_DOCKED, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_HARD_DOCK, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKING, oibar_app_state());
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_HARD_DOCKED, 6000));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFERRING, oibar_app_state());
    TEST_ASSERT_TRUE(fake_hal_do(HAL_DO_SV_VALVE));
    TEST_ASSERT_TRUE(fake_hal_do(HAL_DO_TV_VALVE));
    (void)saw_event(oibar_v1_EVT_UNSPECIFIED, oibar_v1_FAULT_NONE); /* flush */
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_HARD_DOCKED, 10000));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_TRUE(fake_plant_tv_kpa() >= 1495.0f); /* ADC quantisation */
    TEST_ASSERT_TRUE(saw_event(oibar_v1_EVT_TRANSFER_COMPLETE, oibar_v1_FAULT_NONE));
    /* The valves take their stroke time to read closed; separating before that is refused
     * (SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN), so a host waits for closed valves first. */
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 50u);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_SEPARATE, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_UNMATING, oibar_app_state());
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_LATCH_RELEASE, 6000));
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_SEPARATING, 3000));
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_LATCH_RESET, 2000));
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_IDLE, 4000));
    TEST_ASSERT_EQUAL_INT32(0, fake_plant_latch_steps());
    TEST_ASSERT_FALSE(fake_plant_probe());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_LATCH_ENABLE));
    TEST_ASSERT_EQUAL_UINT32(0, oibar_fault_flags());
    /* Ready for the next refuelling (once the home switch has debounced). */
    fake_hal_advance_ms(20);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0));
}

static void test_every_state_reachable_by_bench(void)
{
    for (unsigned s = 1; s <= 15; s++) {
        TEST_ASSERT_TRUE_MESSAGE(bench_goto((oibar_v1_State)s), "state not reached");
    }
}

static void test_abort_from_hard_docked_returns_to_soft_docked(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ABORT, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_ABORTING, oibar_app_state());
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_SOFT_DOCKED, 6000));
    TEST_ASSERT_TRUE(fake_plant_plane_mm() < 0.1f);
}

static void test_abort_from_approach_ready_goes_home(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_APPROACH_READY));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ABORT, 0));
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_IDLE, 3000));
}

static void test_probe_bounce_returns_to_approach_ready(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_RECEPTION));
    fake_plant_set_probe(false);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_APPROACH_READY, 50));
}

static void test_reception_timeout_is_latch_timeout_fault(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_RECEPTION));
    fake_hal_advance_ms(30000);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(oibar_v1_FAULT_LATCH_TIMEOUT));
}

static void test_approach_ready_timeout_disarms(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_APPROACH_READY));
    fake_hal_advance_ms(600000);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
}

static void test_armed_timeout_disarms(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    fake_hal_advance_ms(60000);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_INVALID_IN_STATE,
                      oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
}

static void test_dock_refused_outside_capture_envelope(void)
{
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0));
    oibar_v1_NavUpdate nav;
    memset(&nav, 0, sizeof nav);
    nav.closing_speed_mps = 0.080f; /* 80 mm/s: faster than the paper's 50 */
    nav.has_q_cam_target = true;
    nav.q_cam_target.w = 1.0f;
    oibar_app_nav_update(&nav);
    fake_plant_set_probe(true);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_RECEPTION, 50));
    fake_hal_advance_ms(150);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED, oibar_app_command(oibar_v1_CMD_DOCK, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_RECEPTION, oibar_app_state());
}

/* Issue 16, item 12: the navigation contract. Data inside the envelope is
 * not enough: the update must be marked valid, with a confidence of at least
 * nav_min_confidence; anything else counts as no navigation at all. */
static void dock_with_nav(bool valid, float confidence, oibar_v1_NackReason want)
{
    bench_start();
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0));
    oibar_v1_NavUpdate nav;
    memset(&nav, 0, sizeof nav);
    nav.closing_speed_mps = 0.010f; /* inside the envelope */
    nav.has_q_cam_target = true;
    nav.q_cam_target.w = 1.0f;
    nav.valid = valid;
    nav.confidence = confidence;
    oibar_app_nav_update(&nav);
    fake_plant_set_probe(true);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_RECEPTION, 50));
    fake_hal_advance_ms(150);
    TEST_ASSERT_EQUAL(want, oibar_app_command(oibar_v1_CMD_DOCK, 0));
}

static void test_dock_needs_a_valid_confident_nav_update(void)
{
    const float min_conf = oibar_param_f(PARAM_NAV_MIN_CONFIDENCE);
    TEST_ASSERT_TRUE(min_conf > 0.0f);
    dock_with_nav(false, 0.99f, oibar_v1_NACK_PRECONDITION_FAILED); /* an old host, or not initialised */
    dock_with_nav(true, min_conf * 0.5f, oibar_v1_NACK_PRECONDITION_FAILED);
    dock_with_nav(true, 0.0f, oibar_v1_NACK_PRECONDITION_FAILED);
    dock_with_nav(true, min_conf, oibar_v1_NACK_NONE);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_SOFT_DOCKED, oibar_app_state());
}

static void test_misalignment_from_quaternion(void)
{
    oibar_v1_Quat q = { 1.0f, 0.0f, 0.0f, 0.0f };
    TEST_ASSERT_FLOAT_WITHIN(0.01f, 0.0f, oibar_app_misalignment_deg(&q));
    /* 12 deg pitch: rotation about x by 12 deg. */
    q.w = 0.99452190f; q.x = 0.10452846f;
    TEST_ASSERT_FLOAT_WITHIN(0.05f, 12.0f, oibar_app_misalignment_deg(&q));
    /* Facing convention: 180 deg about y is aligned. */
    q.w = 0.0f; q.x = 0.0f; q.y = 1.0f;
    TEST_ASSERT_FLOAT_WITHIN(0.05f, 0.0f, oibar_app_misalignment_deg(&q));
    /* Pure roll about the docking axis does not count. */
    q.w = 0.70710678f; q.y = 0.0f; q.z = 0.70710678f;
    TEST_ASSERT_FLOAT_WITHIN(0.05f, 0.0f, oibar_app_misalignment_deg(&q));
    q.w = 0.0f; q.z = 0.0f;
    TEST_ASSERT_FLOAT_WITHIN(0.05f, 180.0f, oibar_app_misalignment_deg(&q));
}

static void test_telemetry_reflects_the_mechanism(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    oibar_v1_Telemetry t;
    memset(&t, 0, sizeof t);
    oibar_app_fill_telemetry(&t);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFERRING, t.state);
    TEST_ASSERT_TRUE(t.sv_valve_cmd_open && t.tv_valve_cmd_open);
    TEST_ASSERT_TRUE(t.sv_valve_open && t.tv_valve_open);
    TEST_ASSERT_TRUE(t.connector_mated && t.latch_engaged && t.contact);
    TEST_ASSERT_FLOAT_WITHIN(0.5f, 40.0f, t.plane_pos_mm);
    TEST_ASSERT_FLOAT_WITHIN(0.1f, 1500.0f, t.target_pressure_kpa);
    TEST_ASSERT_TRUE(t.tv_tank_kpa > 200.0f);
    TEST_ASSERT_TRUE(t.host_link_alive);
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_boot_reaches_idle_with_everything_safe);
    RUN_TEST(test_full_refuelling_sequence);
    RUN_TEST(test_every_state_reachable_by_bench);
    RUN_TEST(test_abort_from_hard_docked_returns_to_soft_docked);
    RUN_TEST(test_abort_from_approach_ready_goes_home);
    RUN_TEST(test_probe_bounce_returns_to_approach_ready);
    RUN_TEST(test_reception_timeout_is_latch_timeout_fault);
    RUN_TEST(test_approach_ready_timeout_disarms);
    RUN_TEST(test_armed_timeout_disarms);
    RUN_TEST(test_dock_refused_outside_capture_envelope);
    RUN_TEST(test_dock_needs_a_valid_confident_nav_update);
    RUN_TEST(test_misalignment_from_quaternion);
    RUN_TEST(test_telemetry_reflects_the_mechanism);
    return UNITY_END();
}
