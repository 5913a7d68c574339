/*
 * Stepper timing. TIM2 interrupts once per step period (1 us resolution) and
 * calls the application's step ISR; TIM3 in one-pulse mode makes the STEP
 * pulse itself in hardware, so the ISR only starts it and returns.
 */
#include "oibar/hal.h"

#include "board.h"
#include "port.h"
#include "stm32f4_regs.h"

#define STEP_TICK_HZ 1000000u /* TIM2 counts microseconds */

static hal_isr_fn volatile s_step_fn; /* written by attach, read by the TIM2 ISR */

void port_step_timer_init(const clock_info_t *clk)
{
    /* TIM2: period timer, stopped until hal_step_timer_start(). */
    TIM2->CR1 = 0u;
    TIM2->DIER = 0u;
    TIM2->PSC = clk->tim_apb1_hz / STEP_TICK_HZ - 1u;
    TIM2->SR = 0u;
    nvic_enable(IRQN_TIM2, BOARD_PRIO_STEP_TIMER);

    /* TIM3 CH1 on PA6: PWM mode 2 with CCR1 = 1 and one-pulse mode gives a
     * single high pulse from count 1 to ARR, then the counter stops. */
    uint32_t ticks_per_us = clk->tim_apb1_hz / 1000000u;
    TIM3->CR1 = TIM_CR1_OPM;
    TIM3->PSC = 0u;
    TIM3->ARR = 1u + (BOARD_STEP_PULSE_NS * ticks_per_us + 999u) / 1000u;
    TIM3->CCR1 = 1u;
    TIM3->CCMR1 = TIM_CCMR1_OC1M_PWM2;
    TIM3->CCER = TIM_CCER_CC1E;
    TIM3->CNT = 0u;
    port_gpio_alternate(BOARD_STEP_PORT, BOARD_STEP_PIN, GPIO_AF_TIM3);
}

void hal_step_timer_attach(hal_isr_fn isr) { s_step_fn = isr; }

void hal_step_timer_start(uint32_t period_us)
{
    if (period_us < 2u) {
        period_us = 2u;
    }
    TIM2->CR1 = 0u;
    TIM2->ARR = period_us - 1u;
    TIM2->CNT = 0u;
    TIM2->EGR = TIM_EGR_UG; /* load PSC and ARR now; UG also raises UIF... */
    TIM2->SR = 0u;          /* ...which must not count as a step */
    TIM2->DIER = TIM_DIER_UIE;
    /* ARR not buffered (no ARPE): a period written in the ISR is the time to
     * the next interrupt, as hal.h promises. With ARPE it would load only at
     * the next update, one period late. */
    TIM2->CR1 = TIM_CR1_CEN;
}

/* hal.h: the new period runs from the last update event (the interrupt being
 * handled, when called from the ISR). Should the counter already be past the
 * new end (a much shorter period, written late), the update is forced now
 * instead of the counter running round its 32 bits. */
void hal_step_timer_set_period(uint32_t period_us)
{
    const uint32_t arr = ((period_us < 2u) ? 2u : period_us) - 1u;
    TIM2->ARR = arr;
    if (TIM2->CNT >= arr) {
        TIM2->EGR = TIM_EGR_UG; /* counter to 0 and UIF: the next step is due now */
    }
}

void hal_step_timer_stop(void)
{
    TIM2->DIER = 0u;
    TIM2->CR1 = 0u;
    TIM2->SR = 0u;
}

void hal_step_pulse(void)
{
    TIM3->CR1 = TIM_CR1_OPM | TIM_CR1_CEN;
}

void TIM2_IRQHandler(void)
{
    if ((TIM2->SR & TIM_SR_UIF) == 0u) {
        return;
    }
    TIM2->SR = ~TIM_SR_UIF; /* clear first: the write needs cycles to land */
    hal_isr_fn fn = s_step_fn;
    if (fn != 0) {
        fn();
    } else {
        hal_step_timer_stop();
    }
}
