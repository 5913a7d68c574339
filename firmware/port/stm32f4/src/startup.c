/*
 * Start-up for the STM32F405: the vector table, the reset handler (FPU on,
 * .data copied, .bss zeroed, then main) and the fault handlers.
 *
 * Any fault or an interrupt nobody enabled is a firmware bug: the outputs go
 * to their safe level first, the cause is noted in .noinit RAM, and the chip
 * resets (the next boot reports RESET_LOCKUP or RESET_SOFTWARE and the
 * application starts in FAULT; see hal_reset_cause()). The NMI (clock
 * security, clock.c) and a written stack guard (port_stack_guard_check, from
 * the tick) end the same way.
 */
#include <stdint.h>
#include <string.h>

#include "port.h"
#include "stm32f4_regs.h"

/* Symbols from stm32f405.ld. */
extern uint32_t _estack;
extern uint32_t _sidata[], _sdata[], _edata[], _sbss[], _ebss[];
extern uint32_t _sstack_guard[]; /* PORT_STACK_GUARD_WORDS words (asserted by the linker script) */

int main(void);

void Reset_Handler(void);
void Default_Handler(void);
void HardFault_Handler(void);

typedef union {
    void (*handler)(void);
    uint32_t *stack_top;
} vector_t;

#define D Default_Handler

/* Cortex-M4 system vectors, then the 82 STM32F405 interrupts (RM0090
 * table 61). Unused slots point at Default_Handler, never at 0. */
__attribute__((section(".isr_vector"), used)) const vector_t g_vectors[16u + IRQN_COUNT] = {
    { .stack_top = &_estack },
    { Reset_Handler },
    { NMI_Handler },       /* NMI: clock security (clock.c) */
    { HardFault_Handler },
    { HardFault_Handler }, /* MemManage (disabled: escalates to HardFault) */
    { HardFault_Handler }, /* BusFault */
    { HardFault_Handler }, /* UsageFault */
    { 0 }, { 0 }, { 0 }, { 0 }, /* reserved */
    { D },                 /* SVCall */
    { D },                 /* DebugMonitor */
    { 0 },                 /* reserved */
    { D },                 /* PendSV */
    { SysTick_Handler },
    /* IRQ 0..27 */
    { D }, { D }, { D }, { D }, { D }, { D }, { D }, { D },
    { D }, { D }, { D }, { D }, { D }, { D }, { D }, { D },
    { D }, { D }, { D }, { D }, { D }, { D }, { D }, { D },
    { D }, { D }, { D }, { D },
    /* IRQ 28: TIM2, step pulses */
    { TIM2_IRQHandler },
    /* IRQ 29..36 */
    { D }, { D }, { D }, { D }, { D }, { D }, { D }, { D },
    /* IRQ 37: USART1, link to the companion computer */
    { USART1_IRQHandler },
    /* IRQ 38..81 */
    { D }, { D }, { D }, { D }, { D }, { D }, { D }, { D },
    { D }, { D }, { D }, { D }, { D }, { D }, { D }, { D },
    { D }, { D }, { D }, { D }, { D }, { D }, { D }, { D },
    { D }, { D }, { D }, { D }, { D }, { D }, { D }, { D },
    { D }, { D }, { D }, { D }, { D }, { D }, { D }, { D },
    { D }, { D }, { D }, { D },
};

#undef D

__attribute__((noreturn)) void Reset_Handler(void)
{
    /* FPU first: the C code below may already use its registers. */
    SCB_CPACR |= SCB_CPACR_FPU_FULL;
    cpu_dsb();
    cpu_isb();

    /* Word counts from the addresses: the linker script aligns all four. */
    uint32_t data_words = ((uint32_t)(uintptr_t)_edata - (uint32_t)(uintptr_t)_sdata) / 4u;
    uint32_t bss_words = ((uint32_t)(uintptr_t)_ebss - (uint32_t)(uintptr_t)_sbss) / 4u;
    for (uint32_t i = 0; i < data_words; i++) {
        _sdata[i] = _sidata[i];
    }
    for (uint32_t i = 0; i < bss_words; i++) {
        _sbss[i] = 0u;
    }
    port_stack_guard_fill();
    SCB->VTOR = (uint32_t)(uintptr_t)g_vectors;
    cpu_dsb();

    (void)main();
    port_fatal_reset(PORT_NOTE_ASSERT, 0u); /* main never returns */
}

/* The guard is written once here, before main, and never again by the
 * firmware: only a stack that ran past its lowest address changes it. */
void port_stack_guard_fill(void)
{
    for (uint32_t i = 0; i < PORT_STACK_GUARD_WORDS; i++) {
        _sstack_guard[i] = PORT_STACK_CANARY;
    }
}

/* From the 1 kHz tick. noinline: the image test finds the call in the tick. */
__attribute__((noinline)) void port_stack_guard_check(void)
{
    const volatile uint32_t *guard = _sstack_guard;
    for (uint32_t i = 0; i < PORT_STACK_GUARD_WORDS; i++) {
        if (guard[i] != PORT_STACK_CANARY) {
            port_fatal_reset(PORT_NOTE_STACK_OVERFLOW, (uint32_t)(uintptr_t)&guard[i]);
        }
    }
}

void Default_Handler(void)
{
    port_fatal_reset(PORT_NOTE_UNEXPECTED_IRQ, 0u);
}

/* The stacked PC tells where it happened; pick the stack that was in use. */
__attribute__((naked)) void HardFault_Handler(void)
{
    __asm volatile(
        "tst lr, #4\n"
        "ite eq\n"
        "mrseq r0, msp\n"
        "mrsne r0, psp\n"
        "b hardfault_report\n");
}

__attribute__((used, noreturn)) void hardfault_report(const uint32_t *frame);
__attribute__((used, noreturn)) void hardfault_report(const uint32_t *frame)
{
    port_fatal_reset(PORT_NOTE_HARDFAULT, frame[6]);
}
