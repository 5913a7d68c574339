/*
 * Fault latch. Raising a fault closes both valves at once (from any context,
 * including interrupts) and marks it pending; the main loop then latches the
 * flag, reports it and hands SIG_FAULT to the state machine. Pending faults
 * are kept outside the event queue so they cannot be lost to an overflow.
 */
#ifndef OIBAR_APP_FAULTS_H
#define OIBAR_APP_FAULTS_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar.pb.h"

#define OIBAR_FAULT_BIT(code) (1u << ((unsigned)(code) - 1u))
/* The highest FaultCode of the contract (proto/oibar.proto), so a new code is
 * latched, reported and walked by the tests without a second number to keep. */
#define OIBAR_FAULT_CODE_MAX ((unsigned)_oibar_v1_FaultCode_MAX)
_Static_assert((unsigned)_oibar_v1_FaultCode_MAX <= 32u, "fault_flags holds one bit per code");

void oibar_faults_init(void);
/* ISR-safe. */
void oibar_fault_raise(oibar_v1_FaultCode code);
/* Main loop: take the next pending fault, FAULT_NONE when none. */
oibar_v1_FaultCode oibar_fault_take_pending(void);
/* True while some raised fault has not been taken by the main loop yet.
 * ISR-safe; the valve driver refuses to open while one is pending. */
bool oibar_fault_any_pending(void);
/* Latched flags (Telemetry.fault_flags layout). */
uint32_t oibar_fault_flags(void);
void oibar_fault_latch(oibar_v1_FaultCode code);
void oibar_fault_clear_all(void);

#endif
