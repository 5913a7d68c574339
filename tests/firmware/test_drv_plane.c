/* Fluidic-plane actuator against the fake HAL. */
#include "fake_hal.h"
#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_inputs.h"
#include "oibar/drv_plane.h"
#include "unity.h"

/* As the application's pass: the position sensor is read before the plane
 * driver looks at it (an end counts only with switch and sensor agreeing). */
static void loop_1ms(void)
{
    oibar_inputs_analog_update();
    oibar_plane_tick(hal_time_ms());
}

void setUp(void)
{
    fake_hal_reset();
    fake_plant_enable(true);
    fake_hal_advance_ms(1);
    oibar_params_init();
    oibar_evtq_init();
    oibar_faults_init();
    oibar_inputs_init();
    oibar_plane_init();
    hal_control_tick_attach(oibar_inputs_tick_isr);
    fake_hal_set_main_loop(loop_1ms);
}
void tearDown(void) {}

static bool got(oibar_sig_t sig, uint16_t id)
{
    oibar_evt_t e;
    bool seen = false;
    while (oibar_evtq_get(&e)) {
        seen = seen || (e.sig == sig && e.arg == id);
    }
    return seen;
}

static void test_extend_then_retract(void)
{
    oibar_plane_extend(hal_time_ms());
    TEST_ASSERT_TRUE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    fake_hal_advance_ms(4200);
    TEST_ASSERT_TRUE(got(SIG_PLANE_EXTENDED, oibar_plane_move_id()));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    TEST_ASSERT_TRUE(oibar_plane_is_extended());
    oibar_plane_retract(hal_time_ms());
    TEST_ASSERT_TRUE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    fake_hal_advance_ms(4200);
    TEST_ASSERT_TRUE(got(SIG_PLANE_RETRACTED, oibar_plane_move_id()));
    TEST_ASSERT_TRUE(oibar_plane_is_retracted());
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
}

static void test_move_to_where_it_is_completes_at_once(void)
{
    oibar_plane_retract(hal_time_ms());
    TEST_ASSERT_TRUE(got(SIG_PLANE_RETRACTED, oibar_plane_move_id()));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
}

static void test_jam_times_out_and_stops(void)
{
    fake_plant_set_plane_jam(true);
    oibar_plane_extend(hal_time_ms());
    fake_hal_advance_ms(oibar_param_u32(PARAM_PLANE_MOVE_TIMEOUT_MS) - 2u);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    fake_hal_advance_ms(3);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_PLANE_TIMEOUT, oibar_fault_take_pending());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    TEST_ASSERT_EQUAL(OIBAR_PLANE_STOPPED, oibar_plane_motion());
}

static void test_reversal_never_drives_both_legs(void)
{
    oibar_plane_extend(hal_time_ms());
    fake_hal_advance_ms(500);
    uint16_t first = oibar_plane_move_id();
    oibar_plane_retract(hal_time_ms());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND) && fake_hal_do(HAL_DO_PLANE_RETRACT));
    fake_hal_advance_ms(1000);
    TEST_ASSERT_TRUE(got(SIG_PLANE_RETRACTED, oibar_plane_move_id()));
    TEST_ASSERT_NOT_EQUAL(first, oibar_plane_move_id()); /* stale completions recognisable */
}

static void test_position_from_potentiometer(void)
{
    oibar_plane_extend(hal_time_ms());
    fake_hal_advance_ms(2000);
    oibar_inputs_analog_update();
    TEST_ASSERT_FLOAT_WITHIN(0.2f, fake_plant_plane_mm(), oibar_plane_pos_mm());
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_extend_then_retract);
    RUN_TEST(test_move_to_where_it_is_completes_at_once);
    RUN_TEST(test_jam_times_out_and_stops);
    RUN_TEST(test_reversal_never_drives_both_legs);
    RUN_TEST(test_position_from_potentiometer);
    return UNITY_END();
}
