/*
 * HAL core for the STM32F405: init order, the 1 kHz SysTick time base,
 * critical sections, the independent watchdog, the reset cause and the
 * fatal-error reset.
 */
#include "oibar/hal.h"

#include "board.h"
#include "port.h"
#include "stm32f4_regs.h"

/* The watchdog timeout is HAL_WATCHDOG_TIMEOUT_MS (oibar/hal.h), the number
 * the simulated MCU uses too. */
#define LSI_HZ 32000u /* RM0090: 17..47 kHz; the nominal value sets the timeout */
#define IWDG_WAIT_LOOPS 100000u

volatile port_diag_t g_port_diag;
/* Survives a software reset: not zeroed by the start-up code. */
__attribute__((section(".noinit"))) port_reset_note_t g_reset_note;

static volatile uint32_t s_time_ms;
static hal_isr_fn s_tick_fn;
static hal_reset_cause_t s_reset_cause;

void hal_init(void)
{
    uint32_t saved = hal_critical_enter();
    port_reset_cause_capture();
    clock_info_t clk;
    clock_init(&clk);
    RCC->AHB1ENR |= RCC_AHB1ENR_GPIOAEN | RCC_AHB1ENR_GPIOBEN | RCC_AHB1ENR_GPIOCEN;
    RCC->APB1ENR |= RCC_APB1ENR_TIM2EN | RCC_APB1ENR_TIM3EN;
    RCC->APB2ENR |= RCC_APB2ENR_USART1EN | RCC_APB2ENR_ADC1EN;
    (void)RCC->APB2ENR; /* clocks on before the first peripheral access */
    port_gpio_init();   /* outputs safe before anything else */
    port_adc_init(&clk);
    port_uart_init(&clk);
    port_step_timer_init(&clk);
    port_watchdog_init();
    port_systick_init(&clk);
    hal_critical_exit(saved);
}

/* --- time base ---------------------------------------------------------- */
void port_systick_init(const clock_info_t *clk)
{
    SYSTICK->CTRL = 0u;
    SYSTICK->LOAD = clk->hclk_hz / 1000u - 1u;
    SYSTICK->VAL = 0u;
    SCB->SHPR[SCB_SHPR_IDX_SYSTICK] = (uint8_t)(BOARD_PRIO_SYSTICK << (8u - NVIC_PRIO_BITS));
    SYSTICK->CTRL = SYSTICK_CTRL_CLKSOURCE_CPU | SYSTICK_CTRL_TICKINT | SYSTICK_CTRL_ENABLE;
}

/* 1 kHz: count the millisecond, let the application capture its inputs,
 * keep the ADC scan and the USART going. Nothing here waits. */
void SysTick_Handler(void)
{
    uint32_t now = s_time_ms + 1u;
    s_time_ms = now;
    port_stack_guard_check(); /* a written guard word: outputs safe, reset */
    port_adc_service_isr(now);
#if defined(OIBAR_QEMU) && OIBAR_QEMU
    port_uart_service_kick(); /* emulator image only (hal_uart.c) */
#endif
    hal_isr_fn fn = s_tick_fn;
    if (fn != 0) {
        fn();
    }
}

uint32_t hal_time_ms(void) { return s_time_ms; }

void hal_control_tick_attach(hal_isr_fn tick) { s_tick_fn = tick; }

/* --- critical sections -------------------------------------------------- */
uint32_t hal_critical_enter(void)
{
    uint32_t primask;
    __asm volatile("mrs %0, primask\n cpsid i" : "=r"(primask)::"memory");
    return primask;
}

void hal_critical_exit(uint32_t saved)
{
    /* Only the outermost exit (interrupts were on when it entered) re-enables. */
    if ((saved & 1u) == 0u) {
        __asm volatile("cpsie i" ::: "memory");
    }
}

/* --- watchdog ----------------------------------------------------------- */
static void iwdg_wait_idle(void)
{
    for (uint32_t n = 0; n < IWDG_WAIT_LOOPS && (IWDG->SR & (IWDG_SR_PVU | IWDG_SR_RVU)) != 0u;
         n++) {
    }
}

void port_watchdog_init(void)
{
    /* Started once and never stopped (nothing can stop the IWDG). LSI/32 =
     * 1 ms per count. It pauses while a debugger halts the core, so a
     * breakpoint does not reset the board (no effect when running). */
    DBGMCU_APB1_FZ |= DBGMCU_APB1_FZ_DBG_IWDG_STOP;
    IWDG->KR = IWDG_KEY_START;
    IWDG->KR = IWDG_KEY_UNLOCK;
    iwdg_wait_idle();
    IWDG->PR = IWDG_PR_DIV32;
    IWDG->RLR = HAL_WATCHDOG_TIMEOUT_MS * (LSI_HZ / 32u) / 1000u;
    iwdg_wait_idle(); /* bounded: on a board without LSI the values simply never load */
    IWDG->KR = IWDG_KEY_RELOAD;
}

void hal_watchdog_kick(void) { IWDG->KR = IWDG_KEY_RELOAD; }

/* --- reset cause (RCC_CSR, RM0090 section 7.3.21) ----------------------- */
void port_reset_cause_capture(void)
{
    uint32_t csr = RCC->CSR;
    bool noted = g_reset_note.magic == PORT_RESET_NOTE_MAGIC;
    hal_reset_cause_t cause;
    /* A power-on also sets PIN and BOR; a watchdog or software reset also
     * sets PIN: test the specific flags first. */
    if ((csr & (RCC_CSR_IWDGRSTF | RCC_CSR_WWDGRSTF)) != 0u) {
        cause = HAL_RESET_WATCHDOG;
    } else if ((csr & RCC_CSR_SFTRSTF) != 0u) {
        /* Our fatal-error path (hard fault, failed assertion, stray
         * interrupt) resets by software after noting why: report it like a
         * lockup, so the application waits in FAULT for the host. */
        cause = noted ? HAL_RESET_LOCKUP : HAL_RESET_SOFTWARE;
    } else if ((csr & RCC_CSR_PORRSTF) != 0u) {
        cause = HAL_RESET_POWER_ON;
    } else if ((csr & RCC_CSR_BORRSTF) != 0u) {
        cause = HAL_RESET_BROWNOUT;
    } else if ((csr & RCC_CSR_PINRSTF) != 0u) {
        cause = HAL_RESET_PIN;
    } else {
        /* No flag at all: low-power reset, or an RCC model that reads 0. */
        cause = HAL_RESET_UNKNOWN;
    }
    s_reset_cause = cause;
    RCC->CSR |= RCC_CSR_RMVF; /* the next reset reports only itself */
    g_reset_note.magic = 0u;
}

hal_reset_cause_t hal_reset_cause(void) { return s_reset_cause; }

/* --- fatal errors ------------------------------------------------------- */
__attribute__((noreturn)) void port_fatal_reset(uint32_t reason, uint32_t pc)
{
    __asm volatile("cpsid i" ::: "memory");
    port_outputs_safe(); /* valves closed, actuators off, before anything else */
    g_reset_note.magic = PORT_RESET_NOTE_MAGIC;
    g_reset_note.reason = reason;
    g_reset_note.cfsr = SCB->CFSR;
    g_reset_note.pc = pc;
    cpu_dsb();
    SCB->AIRCR = SCB_AIRCR_VECTKEY | SCB_AIRCR_SYSRESETREQ;
    cpu_dsb();
    for (;;) {
        /* the reset takes a few cycles; the watchdog backs it up */
    }
}
