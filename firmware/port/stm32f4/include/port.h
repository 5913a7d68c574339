/*
 * Internals shared by the STM32F4 port's files. The application never sees
 * this header: it talks to oibar/hal.h only.
 */
#ifndef OIBAR_PORT_H
#define OIBAR_PORT_H

#include <stdbool.h>
#include <stdint.h>

#include "stm32f4_regs.h"

/* Where the system clock came from after clock_init(). */
typedef enum {
    CLOCK_SRC_HSE_PLL = 0, /* crystal through the PLL: the normal case */
    CLOCK_SRC_HSI_PLL,     /* crystal did not start: internal RC through the PLL */
    CLOCK_SRC_HSI,         /* PLL did not lock or the switch failed: 16 MHz RC */
    CLOCK_SRC_UNVERIFIED   /* RCC reports nothing (not even the running HSI) */
} clock_source_t;

typedef struct {
    clock_source_t source;
    uint32_t hclk_hz;     /* core, SysTick */
    uint32_t pclk2_hz;    /* USART1, ADC */
    uint32_t tim_apb1_hz; /* TIM2..TIM5 kernel clock */
} clock_info_t;

/* Bring the core to 168 MHz; every wait is bounded, failures fall back. */
void clock_init(clock_info_t *out);
/* Program the brown-out reset to level 3 (2.70 V) if it is not; true when set. */
bool clock_bor_level3(void);
const clock_info_t *clock_info(void);

/* Per-module init, called by hal_init() in this order. */
void port_reset_cause_capture(void);
void port_gpio_init(void);
void port_adc_init(const clock_info_t *clk);
void port_uart_init(const clock_info_t *clk);
void port_step_timer_init(const clock_info_t *clk);
void port_watchdog_init(void);
void port_systick_init(const clock_info_t *clk);

/* Pin set-up for the peripheral files. */
void port_gpio_alternate(gpio_regs_t *port, uint32_t pin, uint32_t af);
void port_gpio_analog(gpio_regs_t *port, uint32_t pin);

/* Called from the SysTick ISR: collect the finished conversion, start the next. */
void port_adc_service_isr(uint32_t now_ms);
/* Called from the SysTick ISR: have the USART handler look at the line. */
void port_uart_service_kick(void);
/* Drive every output to its safe (de-energised) level; usable from a fault handler. */
void port_outputs_safe(void);

/* Counters for diagnosis (the UART's receive errors are in telemetry,
 * hal_uart_errors(); the rest is visible with a debugger). */
typedef struct {
    uint32_t uart_rx_errors;   /* framing/noise/parity */
    uint32_t uart_rx_overruns; /* a byte arrived before the previous was read */
    uint32_t uart_tx_refused;  /* writes refused because the queue was full */
    uint32_t adc_missed;       /* conversions not finished by the next tick */
} port_diag_t;
extern volatile port_diag_t g_port_diag;

/* Why the previous run ended, kept across a software reset in .noinit. */
#define PORT_RESET_NOTE_MAGIC 0x0BA2F417u
typedef struct {
    uint32_t magic;
    uint32_t reason; /* PORT_NOTE_* */
    uint32_t cfsr;   /* SCB->CFSR at the fault */
    uint32_t pc;     /* stacked PC at the fault, when known */
} port_reset_note_t;
#define PORT_NOTE_HARDFAULT 1u
#define PORT_NOTE_ASSERT 2u
#define PORT_NOTE_UNEXPECTED_IRQ 3u
#define PORT_NOTE_CLOCK_FAILURE 4u /* the HSE failed in flight (clock security NMI) */
#define PORT_NOTE_STACK_OVERFLOW 5u /* the stack guard below the main stack was written */
extern port_reset_note_t g_reset_note;

/* Interrupt handlers, named in the vector table (startup.c). */
void NMI_Handler(void); /* clock security (clock.c) */
void SysTick_Handler(void);
void TIM2_IRQHandler(void);
void USART1_IRQHandler(void);

/* Run-time stack guard (startup.c): PORT_STACK_GUARD_WORDS words at the
 * bottom of the stack region (.stack_guard in stm32f405.ld, between the
 * static data and the lowest address the main stack may reach) hold
 * PORT_STACK_CANARY from the reset on; the 1 kHz tick checks them and a
 * changed word is a stack overflow: outputs safe, note, reset. */
#define PORT_STACK_GUARD_WORDS 8u
#define PORT_STACK_CANARY 0x5AC4C0DEu
void port_stack_guard_fill(void);
void port_stack_guard_check(void);

/* Safe the outputs, note why, and reset the chip. */
__attribute__((noreturn)) void port_fatal_reset(uint32_t reason, uint32_t pc);

#endif /* OIBAR_PORT_H */
