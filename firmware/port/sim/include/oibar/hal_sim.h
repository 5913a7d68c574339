/*
 * The simulated MCU's side doors into its HAL: what the lockstep loop (main.c)
 * uses to play the board's hardware. The application never calls these; it
 * sees only oibar/hal.h.
 */
#ifndef OIBAR_HAL_SIM_H
#define OIBAR_HAL_SIM_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "oibar/hal.h"

/* Power-on or reset: outputs off, timers stopped, uptime 0, the given cause.
 * Sensor inputs are physics and survive a reset; so do the cumulative
 * counters (steps, kicks). */
void hal_sim_reset(hal_reset_cause_t cause);

/* Latest sensor values from the plant (hold until the next call). */
void hal_sim_set_inputs(uint32_t di_bits, const uint16_t *adc_counts, size_t n_adc,
                        uint32_t adc_fail_bits);

/* One millisecond of simulated time: the step-timer interrupts that fall in
 * it, then the 1 kHz control tick. */
void hal_sim_advance_1ms(void);

uint32_t hal_sim_do_bits(void);
bool hal_sim_step_timer_running(void);
/* Step pulses since the previous call, split by the DIR output at the pulse. */
void hal_sim_take_steps(uint32_t *fwd, uint32_t *rev);
uint32_t hal_sim_steps_total(void);

/* Independent watchdog: expires when not kicked for `timeout_ms`. */
void hal_sim_set_watchdog_timeout_ms(uint32_t timeout_ms);
bool hal_sim_watchdog_expired(void);
uint32_t hal_sim_watchdog_kicks(void);

/* UART: where transmitted bytes go, and the receive "interrupt". */
typedef size_t (*hal_sim_tx_fn)(const uint8_t *data, size_t len);
void hal_sim_set_uart_tx(hal_sim_tx_fn tx);
void hal_sim_uart_rx_byte(uint8_t byte);

/* Keep the parameter flash (hal_flash_*) in this image file: created blank
 * (0xFF) when missing or empty, loaded when it holds the two sectors, every
 * erase and program written through. False (and a message) when it cannot be
 * opened or has another size. Without it the flash lives in memory only. */
bool hal_sim_flash_attach(const char *path);

#endif /* OIBAR_HAL_SIM_H */
