/*
 * Fake HAL for the firmware unit tests: scriptable inputs, recorded outputs,
 * simulated time, fault knobs, and an optional plant model (valves, plane,
 * latch stepper, probe, tanks) that answers the outputs the way the
 * mechanism would, so the state machine can be driven end to end.
 *
 * Time only moves in fake_hal_advance_ms(): each simulated millisecond runs
 * the plant, the step-timer interrupts due, the 1 kHz control tick, then the
 * main-loop hook (usually oibar_app_run_once).
 */
#ifndef FAKE_HAL_H
#define FAKE_HAL_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "oibar/hal.h"

/* Everything back to power-on: time 0, inputs false, outputs false, ADC at
 * mid-scale, no ISRs attached, plant off, knobs cleared. */
void fake_hal_reset(void);

/* --- raw inputs/outputs (plant off) ----------------------------------- */
/* Setting HAL_DI_LATCH_ENGAGED also sets HAL_DI_LATCH_NOT_ENGAGED to the
 * opposite (a healthy changeover switch); set HAL_DI_LATCH_NOT_ENGAGED
 * afterwards to model a broken wire or a short. */
void fake_hal_set_di(hal_di_t di, bool level);
bool fake_hal_do(hal_do_t out);
uint32_t fake_hal_do_writes(hal_do_t out);
void fake_hal_set_adc(hal_adc_t ch, uint16_t counts);
void fake_hal_set_adc_fail(hal_adc_t ch, bool fail);
void fake_hal_set_reset_cause(hal_reset_cause_t cause);

/* --- time and interrupts --------------------------------------------- */
void fake_hal_set_main_loop(void (*fn)(void));
void fake_hal_advance_ms(uint32_t ms);
/* Fault knob: the control tick interrupt stops firing. */
void fake_hal_set_tick_enabled(bool on);
uint32_t fake_hal_watchdog_kicks(void);
uint32_t fake_hal_step_pulses(void);
bool fake_hal_step_timer_running(void);
uint32_t fake_hal_step_period_us(void);
int fake_hal_critical_depth(void);
/* Arm an "interrupt": `isr` runs once, at the first HAL call made outside
 * every critical section (hal_critical_enter runs it before masking). Used
 * to place an ISR between two statements of the code under test. */
void fake_hal_irq_at_next_window(void (*isr)(void));
/* The same at the n-th such call (1 = the next); NULL disarms. */
void fake_hal_irq_at_window(uint32_t n, void (*isr)(void));
bool fake_hal_irq_armed(void);
/* Longest step ISR burst seen in one ms (to check the ISR stays bounded). */
uint32_t fake_hal_max_step_isr_per_ms(void);

/* --- UART ------------------------------------------------------------- */
size_t fake_hal_uart_tx_len(void);
const uint8_t *fake_hal_uart_tx_data(void);
void fake_hal_uart_tx_clear(void);
/* What hal_uart_errors() reports (0 and 0 after fake_hal_reset). */
void fake_hal_uart_set_errors(uint32_t rx_errors, uint32_t rx_overruns);
void fake_hal_uart_rx_inject(const uint8_t *bytes, size_t len);

/* --- parameter flash (hal_flash_*) ------------------------------------ */
/* Two in-memory sectors of HAL_FLASH_SECTOR_BYTES that keep flash semantics
 * (erased = 0xFF, programming ANDs bits in). fake_hal_reset() blanks them;
 * fake_hal_power_cycle() keeps them (a reboot of the same board). */
uint8_t *fake_flash_sector(unsigned sector); /* raw bytes, for tests to corrupt */
void fake_flash_blank(void);
/* Erase operations and programmed words since the last reset. */
uint32_t fake_flash_ops(void);
/* Power cut: `ops` more erase/word-program operations complete, the next one
 * is cut half way (an erase leaves the sector's second half unerased and the
 * first half erased; a word keeps some of its old bits), and every later one
 * fails (no power) until fake_hal_power_cycle(). -1 disarms. */
void fake_flash_cut_after(int32_t ops);
/* Fail every erase or program (a flash error) while on. */
void fake_flash_set_fail(bool fail);
/* Word programs report success but write nothing (a flash that fails silently) while on. */
void fake_flash_set_silent_drop(bool drop);
/* Everything as fake_hal_reset() except the flash contents. */
void fake_hal_power_cycle(void);

/* --- plant model ------------------------------------------------------ */
#define FAKE_PLANT_TRAVEL_MM 40.0f
#define FAKE_PLANT_LATCH_RELEASE_STEPS 600
#define FAKE_PLANT_VALVE_STROKE_MS 30u

typedef enum { FAKE_VALVE_OK = 0, FAKE_VALVE_STUCK_CLOSED, FAKE_VALVE_STUCK_OPEN } fake_valve_mode_t;

void fake_plant_enable(bool on);
/* The target's drogue pushes the probe in (true) or it is pulled out. */
void fake_plant_set_probe(bool inserted);
bool fake_plant_probe(void);
void fake_plant_set_valve_mode(unsigned valve /* 0 SV, 1 TV */, fake_valve_mode_t mode);
/* Valve stroke time, both valves (FAKE_PLANT_VALVE_STROKE_MS after reset). */
void fake_plant_set_valve_stroke_ms(uint32_t ms);
void fake_plant_set_plane_jam(bool jam);
void fake_plant_set_stepper_stall(bool stall);
void fake_plant_set_tanks_kpa(float sv_kpa, float tv_kpa);
void fake_plant_set_force_n(float force_n);
/* Force a digital input (level 0/1) whatever the plant says; -1 releases. */
void fake_plant_override_di(hal_di_t di, int level);
/* Force ADC counts whatever the plant says; -1 releases. */
void fake_plant_override_adc(hal_adc_t ch, int counts);
void fake_plant_clear_overrides(void);
float fake_plant_plane_mm(void);
int32_t fake_plant_latch_steps(void);
float fake_plant_tv_kpa(void);
float fake_plant_sv_kpa(void);
bool fake_plant_valve_open(unsigned valve);


/* --- bench: the whole application on the plant ------------------------- */
/* These drive oibar_app (app.h) through the plant; only suites that test
 * the application call them. */
#include "oibar.pb.h"

/* Reset, plant on, app init, host link up, run until STATE_IDLE. */
void bench_start(void);
/* Run until the state is `st` (checked every ms); false after max_ms. */
bool bench_wait_state(oibar_v1_State st, uint32_t max_ms);
/* A navigation update inside the capture envelope (10 mm/s, aligned). */
void bench_nav_good(void);
/* Drive the nominal sequence from power-on into `st`; true when reached. */
bool bench_goto(oibar_v1_State st);
/* Valve coils as driven (true = some valve commanded open). */
bool bench_any_valve_driven(void);
#endif
