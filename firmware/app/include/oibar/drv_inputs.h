/*
 * Contact, latch, connector and end-switch inputs: debounced in the 1 kHz
 * tick (a level counts once it held for debounce_ms of elapsed time), edges
 * of the mechanism sensors posted as events. Analog contact force and plane
 * position are converted in the main loop.
 *
 * The latch switch is a changeover pair (HAL_DI_LATCH_ENGAGED = NO contact,
 * HAL_DI_LATCH_NOT_ENGAGED = NC contact). oibar_input(HAL_DI_LATCH_ENGAGED)
 * is the pair's verdict: engaged only with NO closed and NC open. Both or
 * neither closed for longer than OIBAR_LATCH_PAIR_TRANSIT_MAX_MS raises
 * FAULT_LATCH_SENSOR (a broken wire or a short), once per episode.
 */
#ifndef OIBAR_DRV_INPUTS_H
#define OIBAR_DRV_INPUTS_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar/hal.h"

/* Longest time a healthy changeover switch shows neither contact (its
 * transit), after debouncing. Compile-time: not a tunable. */
#define OIBAR_LATCH_PAIR_TRANSIT_MAX_MS 100u

/* Plane position sensor: a run of failed (or out of range) conversions this
 * long (elapsed) and this many samples is a sensor fault (D3). Compile-time,
 * the same tolerance as the pressure sensors'. */
#define OIBAR_PLANE_POS_BAD_RUN_MS 10u
#define OIBAR_PLANE_POS_BAD_RUN_MIN_SAMPLES 2u

/* Take the raw levels as the debounced ones, without events (power-up). */
void oibar_inputs_init(void);
/* 1 kHz tick (ISR context): debounce, post SIG_CONTACT/_LOST,
 * SIG_LATCH_ENGAGED/_DISENGAGED, SIG_CONNECTOR_MATED/_LOST on edges. */
void oibar_inputs_tick_isr(void);
/* Debounced level (HAL_DI_LATCH_ENGAGED: the pair's verdict, see above). */
bool oibar_input(hal_di_t di);
/* False while the latch pair has been implausible for longer than the
 * transit time (the FAULT_LATCH_SENSOR condition). */
bool oibar_latch_sensor_plausible(void);

/* Main loop: convert the analog inputs. */
void oibar_inputs_analog_update(void);
float oibar_contact_force_n(void);
float oibar_plane_pos_mm(void);
/* False until a first good reading, and after a run of bad ones (then
 * FAULT_PLANE_POSITION was raised): oibar_plane_pos_mm() is not to be used. */
bool oibar_plane_pos_valid(void);
bool oibar_contact_force_valid(void);

#endif
