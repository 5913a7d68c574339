/*
 * Pressure loop: open both valves (through the interlock), fill the target
 * tank until it reads the target pressure, close at target and post
 * SIG_TARGET_REACHED. A fill running longer than transfer_max_ms closes the
 * valves and raises FAULT_TRANSFER_TIMEOUT; one whose target-tank reading stands
 * still for fill_stall_ms while the line reads above it, or while the supply
 * tank drains, raises FAULT_FILL_STALLED (SAFETY_RULE_FILL_MUST_PROGRESS).
 * (Over-pressure is tripped by the
 * sensor driver, whatever the loop is doing.)
 */
#ifndef OIBAR_PRESSURE_LOOP_H
#define OIBAR_PRESSURE_LOOP_H

#include <stdbool.h>
#include <stdint.h>

void oibar_ploop_init(void);
/* False when the interlock refused to open the valves. */
bool oibar_ploop_start(float target_kpa, uint32_t now_ms);
void oibar_ploop_stop(void);
/* Main loop, once per ms. */
void oibar_ploop_tick(uint32_t now_ms);
bool oibar_ploop_running(void);
float oibar_ploop_target_kpa(void);

#endif
