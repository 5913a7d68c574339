/* Contact, latch and connector sensors: debounce and edge events; the
 * event queue they post to. */
#include "fake_hal.h"
#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_inputs.h"
#include "unity.h"

void setUp(void)
{
    fake_hal_reset();
    oibar_params_init();
    oibar_evtq_init();
    oibar_faults_init();
    oibar_inputs_init();
    hal_control_tick_attach(oibar_inputs_tick_isr);
}
void tearDown(void) {}

static void test_level_must_hold_for_debounce(void)
{
    fake_hal_set_di(HAL_DI_CONTACT, true);
    fake_hal_advance_ms(9);
    TEST_ASSERT_FALSE(oibar_input(HAL_DI_CONTACT));
    fake_hal_advance_ms(1);
    TEST_ASSERT_TRUE(oibar_input(HAL_DI_CONTACT));
    oibar_evt_t e;
    TEST_ASSERT_TRUE(oibar_evtq_get(&e));
    TEST_ASSERT_EQUAL(SIG_CONTACT, e.sig);
    TEST_ASSERT_FALSE(oibar_evtq_get(&e));
}

static void test_bounce_is_filtered(void)
{
    for (unsigned i = 0; i < 50; i++) {
        fake_hal_set_di(HAL_DI_LATCH_ENGAGED, (i % 3) == 0);
        fake_hal_advance_ms(1);
    }
    oibar_evt_t e;
    TEST_ASSERT_FALSE(oibar_evtq_get(&e));
    TEST_ASSERT_FALSE(oibar_input(HAL_DI_LATCH_ENGAGED));
}

static void test_edges_of_each_sensor(void)
{
    const hal_di_t di[3] = { HAL_DI_CONTACT, HAL_DI_LATCH_ENGAGED, HAL_DI_CONNECTOR_MATED };
    const oibar_sig_t on[3] = { SIG_CONTACT, SIG_LATCH_ENGAGED, SIG_CONNECTOR_MATED };
    const oibar_sig_t off[3] = { SIG_CONTACT_LOST, SIG_LATCH_DISENGAGED, SIG_CONNECTOR_LOST };
    oibar_evt_t e;
    for (unsigned i = 0; i < 3; i++) {
        fake_hal_set_di(di[i], true);
        fake_hal_advance_ms(10);
        TEST_ASSERT_TRUE(oibar_evtq_get(&e));
        TEST_ASSERT_EQUAL(on[i], e.sig);
        fake_hal_set_di(di[i], false);
        fake_hal_advance_ms(10);
        TEST_ASSERT_TRUE(oibar_evtq_get(&e));
        TEST_ASSERT_EQUAL(off[i], e.sig);
    }
    /* End switches and valve sensors are levels only. */
    fake_hal_set_di(HAL_DI_PLANE_EXTENDED, true);
    fake_hal_advance_ms(10);
    TEST_ASSERT_TRUE(oibar_input(HAL_DI_PLANE_EXTENDED));
    TEST_ASSERT_FALSE(oibar_evtq_get(&e));
}

static void test_power_up_levels_without_events(void)
{
    fake_hal_set_di(HAL_DI_LATCH_HOME, true);
    fake_hal_set_di(HAL_DI_CONTACT, true);
    oibar_inputs_init();
    TEST_ASSERT_TRUE(oibar_input(HAL_DI_LATCH_HOME));
    TEST_ASSERT_TRUE(oibar_input(HAL_DI_CONTACT));
    oibar_evt_t e;
    TEST_ASSERT_FALSE(oibar_evtq_get(&e));
}

/* --- SAFETY_RULE_LATCH_SENSE_PAIR (issue 16 item 4) ----------------------- */
/* The latch switch is a changeover pair: NO contact (HAL_DI_LATCH_ENGAGED)
 * and NC contact (HAL_DI_LATCH_NOT_ENGAGED). */
static void set_pair(bool no_closed, bool nc_closed)
{
    fake_hal_set_di(HAL_DI_LATCH_ENGAGED, no_closed);
    fake_hal_set_di(HAL_DI_LATCH_NOT_ENGAGED, nc_closed);
}

static void drain_events(void)
{
    oibar_evt_t e;
    while (oibar_evtq_get(&e)) {
    }
}

static void engage_healthy(void)
{
    set_pair(true, false);
    fake_hal_advance_ms(10);
    TEST_ASSERT_TRUE(oibar_input(HAL_DI_LATCH_ENGAGED));
    TEST_ASSERT_TRUE(oibar_latch_sensor_plausible());
    drain_events();
}

static void test_SAFETY_RULE_LATCH_SENSE_PAIR_broken_engaged_wire_reads_disengaged_and_faults(void)
{
    engage_healthy();
    set_pair(false, false); /* the NO wire breaks: neither contact reads closed */
    fake_hal_advance_ms(10);
    TEST_ASSERT_FALSE(oibar_input(HAL_DI_LATCH_ENGAGED));
    oibar_evt_t e;
    TEST_ASSERT_TRUE(oibar_evtq_get(&e));
    TEST_ASSERT_EQUAL(SIG_LATCH_DISENGAGED, e.sig);
    /* A switch in transit shows neither contact too: the fault waits the
     * transit bound (counted from the tick that debounced the pair into
     * "neither", its first millisecond), then comes once. */
    fake_hal_advance_ms(OIBAR_LATCH_PAIR_TRANSIT_MAX_MS - 2u);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    fake_hal_advance_ms(1);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_LATCH_SENSOR, oibar_fault_take_pending());
    TEST_ASSERT_FALSE(oibar_latch_sensor_plausible());
    fake_hal_advance_ms(500);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
}

static void test_SAFETY_RULE_LATCH_SENSE_PAIR_both_contacts_closed_is_not_engaged(void)
{
    /* A short to ground on the NC wire while engaged: the old single-wire
     * scheme could not see it; the pair reads "not engaged" and faults. */
    engage_healthy();
    set_pair(true, true);
    fake_hal_advance_ms(10);
    TEST_ASSERT_FALSE(oibar_input(HAL_DI_LATCH_ENGAGED));
    fake_hal_advance_ms(OIBAR_LATCH_PAIR_TRANSIT_MAX_MS);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_LATCH_SENSOR, oibar_fault_take_pending());
}

static void test_SAFETY_RULE_LATCH_SENSE_PAIR_broken_nc_wire_found_at_rest(void)
{
    set_pair(false, false); /* latch at rest, NC wire broken */
    fake_hal_advance_ms(10 + OIBAR_LATCH_PAIR_TRANSIT_MAX_MS);
    TEST_ASSERT_FALSE(oibar_input(HAL_DI_LATCH_ENGAGED));
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_LATCH_SENSOR, oibar_fault_take_pending());
}

static void test_SAFETY_RULE_LATCH_SENSE_PAIR_transit_is_not_a_fault(void)
{
    set_pair(false, false); /* NC opened, NO not yet closed */
    fake_hal_advance_ms(OIBAR_LATCH_PAIR_TRANSIT_MAX_MS - 20u);
    set_pair(true, false);
    fake_hal_advance_ms(10);
    TEST_ASSERT_TRUE(oibar_input(HAL_DI_LATCH_ENGAGED));
    fake_hal_advance_ms(500);
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_NONE, oibar_fault_take_pending());
    TEST_ASSERT_TRUE(oibar_latch_sensor_plausible());
}

static void test_debounce_counts_elapsed_time_not_ticks(void)
{
    /* Ticks that come late (interrupts masked, a slow ISR) must not stretch
     * the debounce: the level counts once it held 10 ms of elapsed time. */
    fake_hal_set_tick_enabled(false);
    fake_hal_set_di(HAL_DI_CONTACT, true);
    fake_hal_advance_ms(1);
    oibar_inputs_tick_isr(); /* first seen: counts as the first ms */
    fake_hal_advance_ms(5);
    oibar_inputs_tick_isr(); /* 6 ms seen: not yet */
    TEST_ASSERT_FALSE(oibar_input(HAL_DI_CONTACT));
    fake_hal_advance_ms(4);
    oibar_inputs_tick_isr(); /* 10 ms seen, in three late ticks */
    TEST_ASSERT_TRUE(oibar_input(HAL_DI_CONTACT));
}

static void test_queue_fifo_overflow_counted_and_faulted(void)
{
    for (unsigned i = 0; i < OIBAR_EVT_QUEUE_LEN; i++) {
        TEST_ASSERT_TRUE(oibar_evtq_post(SIG_CONTACT, (uint16_t)i));
    }
    TEST_ASSERT_EQUAL_UINT(OIBAR_EVT_QUEUE_LEN, oibar_evtq_high_water());
    TEST_ASSERT_FALSE(oibar_evtq_post(SIG_CONTACT_LOST, 99));
    TEST_ASSERT_EQUAL_UINT32(1, oibar_evtq_overflows());
    TEST_ASSERT_EQUAL(oibar_v1_FAULT_EVENT_QUEUE_OVERFLOW, oibar_fault_take_pending());
    oibar_evt_t e;
    for (unsigned i = 0; i < OIBAR_EVT_QUEUE_LEN; i++) {
        TEST_ASSERT_TRUE(oibar_evtq_get(&e));
        TEST_ASSERT_EQUAL_UINT16(i, e.arg);
    }
    TEST_ASSERT_FALSE(oibar_evtq_get(&e));
    TEST_ASSERT_EQUAL_INT(0, fake_hal_critical_depth()); /* every enter has its exit */
}

static void test_event_log_keeps_newest(void)
{
    oibar_evlog_init();
    oibar_v1_Event ev = oibar_v1_Event_init_zero;
    for (unsigned i = 0; i < OIBAR_EVT_LOG_LEN + 5u; i++) {
        ev.arg = i;
        oibar_evlog_push(&ev);
    }
    TEST_ASSERT_EQUAL_UINT32(5, oibar_evlog_dropped());
    oibar_v1_Event out;
    TEST_ASSERT_TRUE(oibar_evlog_pop(&out));
    TEST_ASSERT_EQUAL_UINT32(5, out.arg);
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_level_must_hold_for_debounce);
    RUN_TEST(test_bounce_is_filtered);
    RUN_TEST(test_edges_of_each_sensor);
    RUN_TEST(test_power_up_levels_without_events);
    RUN_TEST(test_SAFETY_RULE_LATCH_SENSE_PAIR_broken_engaged_wire_reads_disengaged_and_faults);
    RUN_TEST(test_SAFETY_RULE_LATCH_SENSE_PAIR_both_contacts_closed_is_not_engaged);
    RUN_TEST(test_SAFETY_RULE_LATCH_SENSE_PAIR_broken_nc_wire_found_at_rest);
    RUN_TEST(test_SAFETY_RULE_LATCH_SENSE_PAIR_transit_is_not_a_fault);
    RUN_TEST(test_debounce_counts_elapsed_time_not_ticks);
    RUN_TEST(test_queue_fifo_overflow_counted_and_faulted);
    RUN_TEST(test_event_log_keeps_newest);
    return UNITY_END();
}
