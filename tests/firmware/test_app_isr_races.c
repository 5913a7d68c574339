/* SAFETY_RULE_VALVE_OPEN_ATOMIC through the application: a fault raised by
 * an interrupt at every possible point of CMD_START_TRANSFER (every HAL call
 * made with interrupts enabled, one run per point) never leaves a valve
 * driven with the fault pending, and ends in FAULT with that fault and no
 * other (in particular no FAULT_ASSERTION "broken contract"). */
#include <stdio.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "unity.h"

void setUp(void) {}
void tearDown(void) {}

static void isr_overpressure(void) { oibar_fault_raise(oibar_v1_FAULT_OVERPRESSURE); }

static void test_SAFETY_RULE_VALVE_OPEN_ATOMIC_fault_at_every_point_of_start_transfer(void)
{
    char msg[64];
    unsigned points = 0;
    for (uint32_t n = 1; n < 10000u; n++) {
        snprintf(msg, sizeof msg, "interrupt at HAL call %u", (unsigned)n);
        TEST_ASSERT_TRUE_MESSAGE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED), msg);
        fake_hal_irq_at_window(n, isr_overpressure);
        (void)oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500.0f);
        if (fake_hal_irq_armed()) {
            fake_hal_irq_at_window(0u, NULL); /* the command made fewer HAL calls: done */
            break;
        }
        points++;
        /* Whatever the point: never a coil on while the fault is pending. */
        TEST_ASSERT_FALSE_MESSAGE(bench_any_valve_driven() && oibar_fault_any_pending(), msg);
        fake_hal_advance_ms(1);
        TEST_ASSERT_EQUAL_INT_MESSAGE(oibar_v1_STATE_FAULT, oibar_app_state(), msg);
        TEST_ASSERT_FALSE_MESSAGE(bench_any_valve_driven(), msg);
        TEST_ASSERT_EQUAL_UINT32_MESSAGE(OIBAR_FAULT_BIT(oibar_v1_FAULT_OVERPRESSURE),
                                         oibar_fault_flags(), msg);
    }
    TEST_ASSERT_TRUE(points > 3u); /* the command was really interleaved */
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_SAFETY_RULE_VALVE_OPEN_ATOMIC_fault_at_every_point_of_start_transfer);
    return UNITY_END();
}
