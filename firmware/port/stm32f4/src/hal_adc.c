/*
 * ADC1: the five analog inputs, one conversion per millisecond in turn
 * (each channel refreshed every 5 ms), sequenced from the SysTick ISR: it
 * collects the conversion it started one tick earlier (a conversion takes
 * under 10 us) and starts the next. No DMA, no blocking.
 *
 * A channel is valid only when its own conversion completed (EOC) recently.
 * An ADC that stops converting, or is not there at all, makes every read
 * fail, and the application raises a sensor fault.
 */
#include "oibar/hal.h"

#include "board.h"
#include "port.h"
#include "stm32f4_regs.h"

/* Five channels at one per ms: a healthy channel is at most 5 ms old. */
#define ADC_STALE_MS 20u

static const board_adc_t k_inputs[HAL_ADC_COUNT] = BOARD_ADC_INPUTS;

static volatile uint16_t s_counts[HAL_ADC_COUNT];
static volatile uint32_t s_stamp_ms[HAL_ADC_COUNT];
static volatile uint32_t s_valid_mask; /* bit per channel: converted at least once */
static uint32_t s_current;             /* ISR only: channel being converted */
static bool s_busy;                    /* ISR only */

static void sample_time(uint32_t channel)
{
    if (channel < 10u) {
        uint32_t shift = 3u * channel;
        ADC1->SMPR2 = (ADC1->SMPR2 & ~(7u << shift)) | (ADC_SMP_144_CYCLES << shift);
    } else {
        uint32_t shift = 3u * (channel - 10u);
        ADC1->SMPR1 = (ADC1->SMPR1 & ~(7u << shift)) | (ADC_SMP_144_CYCLES << shift);
    }
}

void port_adc_init(const clock_info_t *clk)
{
    (void)clk; /* PCLK2/4 is 21 MHz at 168 MHz and 4 MHz on the RC: both in range */
    ADC_CCR = ADC_CCR_ADCPRE_DIV4;
    ADC1->CR1 = 0u;  /* 12 bits, no scan */
    ADC1->CR2 = 0u;  /* single conversion, right-aligned */
    ADC1->SQR1 = 0u; /* one conversion per start */
    for (unsigned i = 0; i < (unsigned)HAL_ADC_COUNT; i++) {
        port_gpio_analog(k_inputs[i].port, k_inputs[i].pin);
        sample_time(k_inputs[i].channel);
    }
    ADC1->CR2 = ADC_CR2_ADON;
    s_current = 0u;
    s_busy = false;
    s_valid_mask = 0u;
}

void port_adc_service_isr(uint32_t now_ms)
{
    if (s_busy) {
        if ((ADC1->SR & ADC_SR_EOC) != 0u) {
            s_counts[s_current] = (uint16_t)(ADC1->DR & HAL_ADC_MAX_COUNTS);
            s_stamp_ms[s_current] = now_ms;
            s_valid_mask |= 1u << s_current;
        } else {
            g_port_diag.adc_missed++;
        }
        s_current = (s_current + 1u) % (uint32_t)HAL_ADC_COUNT;
    }
    ADC1->SR = ~ADC_SR_OVR & ~ADC_SR_EOC; /* stale flags from a missed round */
    ADC1->SQR3 = k_inputs[s_current].channel;
    ADC1->CR2 = ADC_CR2_ADON | ADC_CR2_SWSTART;
    s_busy = true;
}

bool hal_adc_read(hal_adc_t ch, uint16_t *counts)
{
    if ((unsigned)ch >= (unsigned)HAL_ADC_COUNT || counts == 0) {
        return false;
    }
    /* Value and stamp belong together: read them without the ISR between. */
    uint32_t saved = hal_critical_enter();
    uint16_t value = s_counts[ch];
    uint32_t stamp = s_stamp_ms[ch];
    bool ever = (s_valid_mask & (1u << ch)) != 0u;
    hal_critical_exit(saved);
    if (!ever || hal_time_ms() - stamp > ADC_STALE_MS) {
        return false;
    }
    *counts = value;
    return true;
}
