/* SPEC section 3: one test per named safety rule (oibar/app_safety.h). */
#include <string.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "oibar/app_safety.h"
#include "oibar/drv_pressure.h"
#include "oibar/drv_valves.h"
#include "unity.h"

void setUp(void) {}
void tearDown(void) {}

static void test_SAFETY_RULE_SAFE_START(void)
{
    const hal_reset_cause_t causes[] = { HAL_RESET_POWER_ON, HAL_RESET_WATCHDOG,
                                         HAL_RESET_BROWNOUT, HAL_RESET_LOCKUP };
    for (unsigned i = 0; i < 4; i++) {
        fake_hal_reset();
        /* Outputs left energised by whatever ran before the reset. */
        for (unsigned o = 0; o < HAL_DO_COUNT; o++) {
            hal_do_write((hal_do_t)o, true);
        }
        fake_hal_set_reset_cause(causes[i]);
        oibar_app_init();
        for (unsigned o = 0; o < HAL_DO_COUNT; o++) {
            TEST_ASSERT_FALSE(fake_hal_do((hal_do_t)o));
        }
        TEST_ASSERT_EQUAL(oibar_v1_STATE_BOOT, oibar_app_state());
    }
    /* A restart with the mechanism docked safes it (plane back) rather
     * than calling it idle. */
    fake_hal_reset();
    fake_plant_enable(true);
    fake_plant_set_probe(true);
    fake_hal_advance_ms(200);
    oibar_app_init();
    fake_hal_set_main_loop(oibar_app_run_once);
    oibar_app_link_state(true);
    fake_hal_advance_ms(150);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_SOFT_DOCKED, oibar_app_state());
}

static void test_SAFETY_RULE_VALVES_ONLY_WHEN_TRANSFERRING(void)
{
    for (unsigned st = 1; st <= 15; st++) {
        TEST_ASSERT_TRUE(bench_goto((oibar_v1_State)st));
        bool open_ok = oibar_valves_open_both();
        TEST_ASSERT_EQUAL(st == oibar_v1_STATE_TRANSFERRING, open_ok);
        TEST_ASSERT_EQUAL(st == oibar_v1_STATE_TRANSFERRING, bench_any_valve_driven());
    }
}

/* SAFETY_RULE_VALVE_OPEN_ATOMIC: a fault raised (by an interrupt) and not
 * yet taken by the main loop blocks the interlock like a latched one. */
static void test_SAFETY_RULE_VALVE_OPEN_ATOMIC_pending_fault_blocks_interlock(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_TRUE(oibar_safety_valves_permitted());
    oibar_fault_raise(oibar_v1_FAULT_PRESSURE_SENSOR_RATE);
    TEST_ASSERT_FALSE(oibar_safety_valves_permitted());
    TEST_ASSERT_TRUE((oibar_safety_valve_blockers() &
                      OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_NO_FAULT)) != 0u);
    TEST_ASSERT_FALSE(oibar_valves_open_both());
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

static void test_SAFETY_RULE_VALVES_NEED_ARM_THEN_START(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    /* Start without arm: refused, valves closed. */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_INVALID_IN_STATE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    /* Arm alone opens nothing. */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0));
    fake_hal_advance_ms(100);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_TRUE(oibar_safety_valve_blockers() & OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_ARM_THEN_START));
    /* Arming is one-shot: after a transfer the next needs a new arm. */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 400));
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_HARD_DOCKED, 5000));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_INVALID_IN_STATE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
}

static void lose_during_transfer(hal_di_t di, oibar_v1_FaultCode want)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    fake_plant_override_di(di, 0);
    fake_hal_advance_ms(11);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(want));
}

static void test_SAFETY_RULE_VALVES_NEED_CONNECTOR_MATED(void)
{
    lose_during_transfer(HAL_DI_CONNECTOR_MATED, oibar_v1_FAULT_CONNECTOR_LOST);
}

static void test_SAFETY_RULE_VALVES_NEED_LATCH_ENGAGED(void)
{
    lose_during_transfer(HAL_DI_LATCH_ENGAGED, oibar_v1_FAULT_LATCH_LOST);
}

static void test_SAFETY_RULE_VALVES_NEED_SENSORS_HEALTHY(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_hal_set_adc_fail(HAL_ADC_LINE, true); /* conversion fails: sensor lost */
    /* Shorter than the bound it is a glitch (SAFETY_RULE_ADC_GLITCH_BOUNDED);
     * the run that reaches the bound closes the valves and faults. */
    fake_hal_advance_ms(OIBAR_PRESSURE_BAD_RUN_MS - 1u);
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    fake_hal_advance_ms(1);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    fake_hal_advance_ms(1);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE));
}

static void test_SAFETY_RULE_VALVES_NEED_HOST_LINK_ALIVE(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    oibar_app_link_state(false);
    /* The loss is handled before the start: armed -> FAULT, start refused. */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_FAULT_ACTIVE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    oibar_app_link_state(false);
    TEST_ASSERT_FALSE(bench_any_valve_driven()); /* closed in the callback itself */
    fake_hal_advance_ms(1);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(oibar_v1_FAULT_HOST_LINK_LOSS));
}

static void test_SAFETY_RULE_VALVES_NEED_NO_FAULT(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_FAULT));
    TEST_ASSERT_TRUE(oibar_safety_valve_blockers() & OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_NO_FAULT));
    TEST_ASSERT_FALSE(oibar_valves_open_both());
}

static void test_SAFETY_RULE_LOST_PRECONDITION_CLOSES_VALVES(void)
{
    /* Even if the state machine missed the edge (the signal is never
     * posted), the main-loop interlock closes the valves. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_plant_override_di(HAL_DI_CONNECTOR_MATED, 0);
    fake_hal_set_tick_enabled(false); /* no debounce, no edge event */
    fake_hal_advance_ms(5);
    TEST_ASSERT_TRUE(bench_any_valve_driven()); /* firmware has not seen it yet */
    fake_hal_set_tick_enabled(true);
    fake_hal_advance_ms(11);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

static void test_SAFETY_RULE_FAULT_CLOSES_VALVES_AND_REPORTS(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    oibar_fault_raise(oibar_v1_FAULT_OVERPRESSURE);
    TEST_ASSERT_FALSE(bench_any_valve_driven()); /* at the raise, from any context */
    fake_hal_advance_ms(1);
    oibar_v1_Event ev;
    bool reported = false;
    while (oibar_app_next_event(&ev)) {
        reported = reported || (ev.id == oibar_v1_EVT_FAULT && ev.fault == oibar_v1_FAULT_OVERPRESSURE);
    }
    TEST_ASSERT_TRUE(reported);
}

static void test_SAFETY_RULE_FAULT_NEEDS_EXPLICIT_CLEAR(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_FAULT));
    fake_hal_advance_ms(60000);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_FAULT_ACTIVE, oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0));
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_IDLE, 3000));
}

static void test_SAFETY_RULE_INVALID_COMMAND_CHANGES_NOTHING(void)
{
    /* Exhaustively in test_app_commands; here the telemetry view. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_SOFT_DOCKED));
    oibar_v1_Telemetry a, b;
    memset(&a, 0, sizeof a);
    memset(&b, 0, sizeof b);
    oibar_app_fill_telemetry(&a);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_INVALID_IN_STATE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
    oibar_app_fill_telemetry(&b);
    TEST_ASSERT_EQUAL_MEMORY(&a, &b, sizeof a);
}

static void test_SAFETY_RULE_MALFORMED_FRAME_DROPPED(void)
{
    /* The link layer drops malformed frames (its own suites); the
     * application only ever sees decoded requests, and an opcode it does
     * not know is refused without effect. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_UNKNOWN_OPCODE, oibar_app_command((oibar_v1_CommandOpcode)77, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
}

static void test_SAFETY_RULE_WATCHDOG_NEEDS_BOTH_LOOPS(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_IDLE));
    uint32_t k0 = fake_hal_watchdog_kicks();
    fake_hal_advance_ms(100);
    TEST_ASSERT_EQUAL_UINT32(k0 + 100u, fake_hal_watchdog_kicks());
    /* Control tick dead, main loop running: no kick. */
    fake_hal_set_tick_enabled(false);
    k0 = fake_hal_watchdog_kicks();
    fake_hal_advance_ms(100);
    TEST_ASSERT_EQUAL_UINT32(k0, fake_hal_watchdog_kicks());
    /* Tick alive, main loop stuck: no kick. */
    fake_hal_set_tick_enabled(true);
    fake_hal_set_main_loop(NULL);
    fake_hal_advance_ms(100);
    TEST_ASSERT_EQUAL_UINT32(k0, fake_hal_watchdog_kicks());
    /* Both back: kicks resume. */
    fake_hal_set_main_loop(oibar_app_run_once);
    fake_hal_advance_ms(10);
    TEST_ASSERT_TRUE(fake_hal_watchdog_kicks() > k0);
}

static void test_SAFETY_RULE_CONTACT_FORCE_LIMIT(void)
{
    TEST_ASSERT_EQUAL_FLOAT(30.0f, oibar_safety_force_limit_n(oibar_v1_STATE_SOFT_DOCKED));
    TEST_ASSERT_EQUAL_FLOAT(30.0f, oibar_safety_force_limit_n(oibar_v1_STATE_RECEPTION));
    TEST_ASSERT_EQUAL_FLOAT(60.0f, oibar_safety_force_limit_n(oibar_v1_STATE_HARD_DOCKING));
    TEST_ASSERT_EQUAL_FLOAT(60.0f, oibar_safety_force_limit_n(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_plant_set_force_n(70.0f);
    fake_hal_advance_ms(12);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(oibar_v1_FAULT_CONTACT_OVERLOAD));
}

static void test_SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN(void)
{
    /* A target valve stuck open right after a transfer: separating now would pull the
     * couplings apart with fluid in the line, so the command is refused and nothing moves. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_plant_set_valve_mode(1, FAKE_VALVE_STUCK_OPEN);
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 20u); /* sensed open, not yet a fault */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED, oibar_app_command(oibar_v1_CMD_SEPARATE, 0));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    TEST_ASSERT_NOT_EQUAL(oibar_v1_STATE_UNMATING, oibar_app_state());
    /* Valve closed again: separation goes ahead. */
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    fake_plant_set_valve_mode(1, FAKE_VALVE_OK);
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 20u);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_SEPARATE, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_UNMATING, oibar_app_state());
}

static void test_SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN(void)
{
    /* Unmating: the plane is on its way out when a valve fails open. The valve monitor
     * faults; the FAULT entry must drive the plane back to full mate, not stop it halfway. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 50u);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_SEPARATE, 0));
    fake_hal_advance_ms(300);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_UNMATING, oibar_app_state());
    const float half_mm = fake_plant_plane_mm();
    TEST_ASSERT_TRUE(half_mm > 1.0f && half_mm < FAKE_PLANT_TRAVEL_MM - 1.0f);
    fake_plant_set_valve_mode(0, FAKE_VALVE_STUCK_OPEN);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_FAULT, 2000));
    TEST_ASSERT_TRUE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    fake_hal_advance_ms(6000);
    TEST_ASSERT_TRUE(fake_plant_plane_mm() > FAKE_PLANT_TRAVEL_MM - 0.5f); /* re-seated */
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));                  /* and stopped */
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());

    /* A valve failing open while the plane is still short of the couplings (hard docking
     * just started): moving on would cross the venting zone, so the plane stops. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKING));
    fake_hal_advance_ms(300);
    TEST_ASSERT_TRUE(fake_plant_plane_mm() < 20.0f);
    fake_plant_set_valve_mode(0, FAKE_VALVE_STUCK_OPEN);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_FAULT, 2000));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    fake_plant_set_valve_mode(0, FAKE_VALVE_OK);

    /* The same fault with the valves healthy leaves the plane still, as before. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 50u);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_SEPARATE, 0));
    fake_hal_advance_ms(300);
    oibar_fault_raise(oibar_v1_FAULT_LATCH_STALL);
    fake_hal_advance_ms(5);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
}

static void test_rule_names_are_the_identifiers(void)
{
    TEST_ASSERT_EQUAL_STRING("SAFETY_RULE_SAFE_START", oibar_safety_rule_name(SAFETY_RULE_SAFE_START));
    TEST_ASSERT_EQUAL_STRING("SAFETY_RULE_CONTACT_FORCE_LIMIT", oibar_safety_rule_name(SAFETY_RULE_CONTACT_FORCE_LIMIT));
    for (unsigned r = 0; r < SAFETY_RULE_COUNT; r++) {
        TEST_ASSERT_EQUAL_INT(0, strncmp("SAFETY_RULE_", oibar_safety_rule_name((oibar_safety_rule_t)r), 12));
    }
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_SAFETY_RULE_SAFE_START);
    RUN_TEST(test_SAFETY_RULE_VALVES_ONLY_WHEN_TRANSFERRING);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_ARM_THEN_START);
    RUN_TEST(test_SAFETY_RULE_VALVE_OPEN_ATOMIC_pending_fault_blocks_interlock);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_CONNECTOR_MATED);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_LATCH_ENGAGED);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_SENSORS_HEALTHY);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_HOST_LINK_ALIVE);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_NO_FAULT);
    RUN_TEST(test_SAFETY_RULE_LOST_PRECONDITION_CLOSES_VALVES);
    RUN_TEST(test_SAFETY_RULE_FAULT_CLOSES_VALVES_AND_REPORTS);
    RUN_TEST(test_SAFETY_RULE_FAULT_NEEDS_EXPLICIT_CLEAR);
    RUN_TEST(test_SAFETY_RULE_INVALID_COMMAND_CHANGES_NOTHING);
    RUN_TEST(test_SAFETY_RULE_MALFORMED_FRAME_DROPPED);
    RUN_TEST(test_SAFETY_RULE_WATCHDOG_NEEDS_BOTH_LOOPS);
    RUN_TEST(test_SAFETY_RULE_CONTACT_FORCE_LIMIT);
    RUN_TEST(test_SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN);
    RUN_TEST(test_SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN);
    RUN_TEST(test_rule_names_are_the_identifiers);
    return UNITY_END();
}
