/* The STM32F405 board's pin map (firmware/port/stm32f4/include/board.h),
 * checked on the host: wiring rules that make a broken wire fail safe. */
#include <stdint.h>

#include "../../firmware/port/stm32f4/include/board.h"
#include "unity.h"

static const board_pin_t k_di[HAL_DI_COUNT] = BOARD_DI_PINS;
static const board_pin_t k_do[HAL_DO_COUNT] = BOARD_DO_PINS;
static const board_adc_t k_adc[HAL_ADC_COUNT] = BOARD_ADC_INPUTS;

void setUp(void) {}
void tearDown(void) {}

/* SAFETY_RULE_LATCH_SENSE_PAIR: both latch contacts close to ground and are
 * read active low against the pull-up, so a broken wire reads "contact
 * open" on its pin; the old single normally-closed wire read "engaged". */
static void test_SAFETY_RULE_LATCH_SENSE_PAIR_broken_wire_reads_open(void)
{
    TEST_ASSERT_NOT_NULL(k_di[HAL_DI_LATCH_ENGAGED].port);
    TEST_ASSERT_NOT_NULL(k_di[HAL_DI_LATCH_NOT_ENGAGED].port);
    TEST_ASSERT_TRUE(k_di[HAL_DI_LATCH_ENGAGED].active_low);
    TEST_ASSERT_TRUE(k_di[HAL_DI_LATCH_NOT_ENGAGED].active_low);
    /* the connector sense loop, the other valve precondition, likewise */
    TEST_ASSERT_TRUE(k_di[HAL_DI_CONNECTOR_MATED].active_low);
}

static uint32_t key(const gpio_regs_t *port, unsigned pin)
{
    return (uint32_t)(((uintptr_t)port - (uintptr_t)GPIOA) / 0x400u) * 16u + pin;
}

static void test_every_signal_has_its_own_pin(void)
{
    uint32_t used[3] = { 0 }; /* ports A, B, C: bit per pin */
    unsigned n = 0;
    uint32_t keys[HAL_DI_COUNT + HAL_DO_COUNT + HAL_ADC_COUNT + 4u];
    for (unsigned i = 0; i < HAL_DI_COUNT; i++) {
        TEST_ASSERT_NOT_NULL_MESSAGE(k_di[i].port, "digital input without a pin");
        keys[n++] = key(k_di[i].port, k_di[i].pin);
    }
    for (unsigned i = 0; i < HAL_DO_COUNT; i++) {
        TEST_ASSERT_NOT_NULL_MESSAGE(k_do[i].port, "digital output without a pin");
        keys[n++] = key(k_do[i].port, k_do[i].pin);
    }
    for (unsigned i = 0; i < HAL_ADC_COUNT; i++) {
        keys[n++] = key(k_adc[i].port, k_adc[i].pin);
    }
    keys[n++] = key(BOARD_STEP_PORT, BOARD_STEP_PIN);
    keys[n++] = key(GPIOA, 9u);  /* USART1 TX */
    keys[n++] = key(GPIOA, 10u); /* USART1 RX */
    for (unsigned i = 0; i < n; i++) {
        TEST_ASSERT_TRUE_MESSAGE(keys[i] < 48u, "only ports A-C are clocked");
        uint32_t bit = 1u << (keys[i] % 16u);
        TEST_ASSERT_FALSE_MESSAGE(used[keys[i] / 16u] & bit, "two signals on one pin");
        used[keys[i] / 16u] |= bit;
    }
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_SAFETY_RULE_LATCH_SENSE_PAIR_broken_wire_reads_open);
    RUN_TEST(test_every_signal_has_its_own_pin);
    return UNITY_END();
}
