/*
 * The board: which pin carries which signal, with its polarity, and the
 * clock plan. docs/hardware.md is the wiring guide that matches this file;
 * change both together.
 */
#ifndef OIBAR_BOARD_H
#define OIBAR_BOARD_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar/hal.h"
#include "stm32f4_regs.h"

/* --- clocks -------------------------------------------------------------- */
/* Crystal on the board (override with -DBOARD_HSE_HZ=...). PLLM divides it
 * down to a 1 MHz VCO input, so any whole-MHz crystal from 2 to 26 MHz works. */
#ifndef BOARD_HSE_HZ
#define BOARD_HSE_HZ 8000000u
#endif
#define BOARD_HSI_HZ 16000000u
#define BOARD_SYSCLK_TARGET_HZ 168000000u

/* --- serial link to the companion computer ------------------------------- */
/* USART1: PA9 TX, PA10 RX (AF7). On QEMU's netduinoplus2 USART1 is the
 * first `-serial` device. */
#define BOARD_LINK_BAUD 115200u

/* --- digital pins -------------------------------------------------------- */
typedef struct {
    gpio_regs_t *port;
    uint8_t pin;
    bool active_low; /* true: the named condition holds when the pin reads 0 */
} board_pin_t;

/* Indexed by hal_di_t. Switches are normally closed to ground with the
 * internal pull-up, so "actuated" (and a broken wire) reads high. The
 * connector sense loop is closed to ground through the mated connector, so
 * "mated" reads low and a broken wire reads "not mated". The latch switch
 * is a changeover (SPDT, common to ground) on two pins, both active low:
 * PC7 its NO contact (closed = engaged), PC10 its NC contact (closed = not
 * engaged). A broken wire then reads "not engaged" on its pin, and the pair
 * reads "neither" or "both", which the application faults on. */
#define BOARD_DI_PINS                                         \
    {                                                         \
        [HAL_DI_CONTACT] = { GPIOC, 6u, false },              \
        [HAL_DI_LATCH_ENGAGED] = { GPIOC, 7u, true },         \
        [HAL_DI_LATCH_HOME] = { GPIOC, 8u, false },           \
        [HAL_DI_PLANE_EXTENDED] = { GPIOC, 9u, false },       \
        [HAL_DI_PLANE_RETRACTED] = { GPIOB, 12u, false },     \
        [HAL_DI_CONNECTOR_MATED] = { GPIOB, 13u, true },      \
        [HAL_DI_SV_VALVE_OPEN] = { GPIOB, 14u, false },       \
        [HAL_DI_TV_VALVE_OPEN] = { GPIOB, 15u, false },       \
        [HAL_DI_LATCH_NOT_ENGAGED] = { GPIOC, 10u, true },    \
    }

/* Indexed by hal_do_t. The stepper driver's enable input is active low
 * (nENBL on DRV8825 / A4988 class drivers); everything else is a logic-high
 * gate drive (MOSFET or H-bridge input). */
#define BOARD_DO_PINS                                         \
    {                                                         \
        [HAL_DO_LATCH_DIR] = { GPIOB, 0u, false },            \
        [HAL_DO_LATCH_ENABLE] = { GPIOB, 1u, true },          \
        [HAL_DO_PLANE_EXTEND] = { GPIOB, 6u, false },         \
        [HAL_DO_PLANE_RETRACT] = { GPIOB, 7u, false },        \
        [HAL_DO_SV_VALVE] = { GPIOB, 8u, false },             \
        [HAL_DO_TV_VALVE] = { GPIOB, 9u, false },             \
    }

/* STEP: PA6 = TIM3_CH1 (AF2), one hardware pulse per hal_step_pulse(). */
#define BOARD_STEP_PORT GPIOA
#define BOARD_STEP_PIN 6u
#define BOARD_STEP_PULSE_NS 3000u /* >= 1.9 us high time of DRV8825-class drivers */

/* --- analog inputs, indexed by hal_adc_t: ADC1 channel and pin ----------- */
typedef struct {
    gpio_regs_t *port;
    uint8_t pin;
    uint8_t channel;
} board_adc_t;

#define BOARD_ADC_INPUTS                                      \
    {                                                         \
        [HAL_ADC_SV_TANK] = { GPIOA, 0u, 0u },                \
        [HAL_ADC_TV_TANK] = { GPIOA, 1u, 1u },                \
        [HAL_ADC_LINE] = { GPIOA, 4u, 4u },                   \
        [HAL_ADC_PLANE_POS] = { GPIOC, 0u, 10u },             \
        [HAL_ADC_CONTACT_FORCE] = { GPIOC, 1u, 11u },         \
    }

/* --- interrupt priorities (0 = most urgent, 15 = least) ------------------ */
#define BOARD_PRIO_STEP_TIMER 1u /* step timing jitter is what the motor feels */
#define BOARD_PRIO_USART 2u      /* 87 us per byte at 115200 baud */
#define BOARD_PRIO_SYSTICK 3u    /* 1 kHz control tick, ADC sequencing */

#endif /* OIBAR_BOARD_H */
