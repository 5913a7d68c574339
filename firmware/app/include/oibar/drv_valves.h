/*
 * Service-side (SV) and target-side (TV) valves: normally closed solenoids
 * with a position switch each. Opening asks the safety interlock first;
 * commanded and sensed state must agree within valve_mismatch_ms, else
 * FAULT_VALVE_MISMATCH.
 */
#ifndef OIBAR_DRV_VALVES_H
#define OIBAR_DRV_VALVES_H

#include <stdbool.h>
#include <stdint.h>

typedef enum { OIBAR_VALVE_SV = 0, OIBAR_VALVE_TV, OIBAR_VALVE_COUNT } oibar_valve_t;

typedef bool (*oibar_valve_permit_fn)(void);

void oibar_valves_init(void);
/* The interlock asked before any valve opens; NULL = never permitted. */
void oibar_valves_set_permit(oibar_valve_permit_fn permit);
/* Open both valves; false (and nothing opened) when the interlock says no. */
bool oibar_valves_open_both(void);
/* ISR-safe, idempotent. */
void oibar_valves_close_all(void);
bool oibar_valve_cmd_open(oibar_valve_t v);
/* Debounced position switch. */
bool oibar_valve_sensed_open(oibar_valve_t v);
bool oibar_valves_any_cmd_open(void);
bool oibar_valves_any_sensed_open(void);
/* Main loop, once per control tick seen (now_ms: hal_time_ms()):
 * commanded vs sensed check over elapsed time. */
void oibar_valves_tick(uint32_t now_ms);
/* True while a valve disagrees with its command (for clearing a fault). */
bool oibar_valves_mismatch(void);

#endif
