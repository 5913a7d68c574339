/*
 * Contact, latch, connector and end-switch inputs: debounced in the 1 kHz
 * tick (a level counts once it held for debounce_ms), edges of the
 * mechanism sensors posted as events. Analog contact force and plane
 * position are converted in the main loop.
 */
#ifndef OIBAR_DRV_INPUTS_H
#define OIBAR_DRV_INPUTS_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar/hal.h"

/* Take the raw levels as the debounced ones, without events (power-up). */
void oibar_inputs_init(void);
/* 1 kHz tick (ISR context): debounce, post SIG_CONTACT/_LOST,
 * SIG_LATCH_ENGAGED/_DISENGAGED, SIG_CONNECTOR_MATED/_LOST on edges. */
void oibar_inputs_tick_isr(void);
/* Debounced level. */
bool oibar_input(hal_di_t di);

/* Main loop: convert the analog inputs. */
void oibar_inputs_analog_update(void);
float oibar_contact_force_n(void);
float oibar_plane_pos_mm(void);
bool oibar_contact_force_valid(void);

#endif
