/* Valves: normally closed, interlock on open, commanded vs sensed. */
#include "fake_hal.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_inputs.h"
#include "oibar/drv_valves.h"
#include "unity.h"

static bool s_permit;
static int s_permit_depth; /* critical-section depth seen by the interlock */
static bool permit(void)
{
    s_permit_depth = fake_hal_critical_depth();
    return s_permit;
}
static void loop_1ms(void) { oibar_valves_tick(hal_time_ms()); }

void setUp(void)
{
    fake_hal_reset();
    fake_plant_enable(true);
    fake_hal_advance_ms(1);
    oibar_params_init();
    oibar_faults_init();
    oibar_inputs_init();
    oibar_valves_init();
    s_permit = true;
    oibar_valves_set_permit(permit);
    hal_control_tick_attach(oibar_inputs_tick_isr);
    fake_hal_set_main_loop(loop_1ms);
}
void tearDown(void) {}

static void test_init_closes_and_no_permit_never_opens(void)
{
    hal_do_write(HAL_DO_SV_VALVE, true);
    oibar_valves_init(); /* permit hook reset too */
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_SV_VALVE));
    TEST_ASSERT_FALSE(oibar_valves_open_both());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_SV_VALVE) || fake_hal_do(HAL_DO_TV_VALVE));
}

static void test_interlock_refusal_opens_nothing(void)
{
    s_permit = false;
    TEST_ASSERT_FALSE(oibar_valves_open_both());
    TEST_ASSERT_FALSE(oibar_valves_any_cmd_open());
}

static void test_open_follow_close(void)
{
    TEST_ASSERT_TRUE(oibar_valves_open_both());
    TEST_ASSERT_TRUE(fake_hal_do(HAL_DO_SV_VALVE) && fake_hal_do(HAL_DO_TV_VALVE));
    fake_hal_advance_ms(100);
    TEST_ASSERT_TRUE(oibar_valve_sensed_open(OIBAR_VALVE_SV) && oibar_valve_sensed_open(OIBAR_VALVE_TV));
    oibar_valves_close_all();
    fake_hal_advance_ms(100);
    TEST_ASSERT_FALSE(oibar_valves_any_sensed_open());
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
}

static void test_stuck_closed_after_mismatch_time(void)
{
    fake_plant_set_valve_mode(0, FAKE_VALVE_STUCK_CLOSED);
    TEST_ASSERT_TRUE(oibar_valves_open_both());
    fake_hal_advance_ms(oibar_param_u32(PARAM_VALVE_MISMATCH_MS) - 1u);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    fake_hal_advance_ms(2);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_VALVE_MISMATCH, oibar_fault_take_pending());
    fake_hal_advance_ms(500);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending()); /* once per episode */
    TEST_ASSERT_FALSE(oibar_valves_any_cmd_open()); /* the fault closed both */
}

static void test_stuck_open_detected_while_closed(void)
{
    fake_plant_set_valve_mode(1, FAKE_VALVE_STUCK_OPEN);
    fake_hal_advance_ms(300);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_VALVE_MISMATCH, oibar_fault_take_pending());
    TEST_ASSERT_TRUE(oibar_valves_any_sensed_open());
}

/* --- SAFETY_RULE_VALVE_OPEN_ATOMIC (issue 16 item 8) ---------------------- */
static void isr_raises_fault(void) { oibar_fault_raise(oibar_v1_FAULT_OVERPRESSURE); }

static void test_SAFETY_RULE_VALVE_OPEN_ATOMIC_isr_fault_between_permit_and_coils(void)
{
    /* The interrupt is taken at the driver's first HAL access after the
     * interlock said yes. Before the fix that was the first coil write: the
     * ISR closed the (still closed) valves, then the coils went on with a
     * fault pending. */
    fake_hal_irq_at_next_window(isr_raises_fault);
    bool opened = oibar_valves_open_both();
    TEST_ASSERT_FALSE(fake_hal_irq_armed()); /* the ISR ran inside the call */
    TEST_ASSERT_FALSE(opened);
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_SV_VALVE) || fake_hal_do(HAL_DO_TV_VALVE));
    TEST_ASSERT_FALSE(oibar_valves_any_cmd_open());
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_OVERPRESSURE, oibar_fault_take_pending());
    TEST_ASSERT_EQUAL_INT(0, fake_hal_critical_depth());
}

static void test_SAFETY_RULE_VALVE_OPEN_ATOMIC_interlock_asked_with_interrupts_masked(void)
{
    s_permit_depth = 0;
    TEST_ASSERT_TRUE(oibar_valves_open_both());
    TEST_ASSERT_TRUE(s_permit_depth > 0);
    TEST_ASSERT_EQUAL_INT(0, fake_hal_critical_depth());
}

static void test_SAFETY_RULE_VALVE_OPEN_ATOMIC_pending_fault_refuses_open(void)
{
    /* Raised (by an ISR) but not yet taken by the main loop: the permit
     * would still say yes; the driver must not. */
    oibar_fault_raise(oibar_v1_FAULT_CONNECTOR_LOST);
    TEST_ASSERT_FALSE(oibar_valves_open_both());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_SV_VALVE) || fake_hal_do(HAL_DO_TV_VALVE));
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_CONNECTOR_LOST, oibar_fault_take_pending());
    TEST_ASSERT_TRUE(oibar_valves_open_both()); /* taken (and handled): no longer pending */
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_init_closes_and_no_permit_never_opens);
    RUN_TEST(test_interlock_refusal_opens_nothing);
    RUN_TEST(test_open_follow_close);
    RUN_TEST(test_stuck_closed_after_mismatch_time);
    RUN_TEST(test_stuck_open_detected_while_closed);
    RUN_TEST(test_SAFETY_RULE_VALVE_OPEN_ATOMIC_isr_fault_between_permit_and_coils);
    RUN_TEST(test_SAFETY_RULE_VALVE_OPEN_ATOMIC_interlock_asked_with_interrupts_masked);
    RUN_TEST(test_SAFETY_RULE_VALVE_OPEN_ATOMIC_pending_fault_refuses_open);
    return UNITY_END();
}
