/*
 * OIBAR docking-and-refuelling application: the entry points a port (or a
 * test) drives, and the requests the link glue forwards.
 *
 *   hal_init(); oibar_app_init();           // once, attaches the ISRs
 *   for (;;) { oibar_app_run_once(); ... }  // main loop, never blocks
 *
 * The 1 kHz control tick calls oibar_app_tick_1khz() (attached by init);
 * the step timer calls oibar_stepper_isr() (attached by the stepper).
 */
#ifndef OIBAR_APP_H
#define OIBAR_APP_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar.pb.h"

void oibar_app_init(void);
/* Control tick, ISR context: captures inputs, posts events. */
void oibar_app_tick_1khz(void);
/* One main-loop pass: drivers, events, safety, watchdog. */
void oibar_app_run_once(void);

/* --- requests from the host (main-loop context) ------------------------ */
/* Returns the nack reason (NACK_NONE = accepted); state after: oibar_app_state(). */
oibar_v1_NackReason oibar_app_command(oibar_v1_CommandOpcode op, float target_pressure_kpa);
void oibar_app_nav_update(const oibar_v1_NavUpdate *nav);
/* Fill `out` for a get/set; out->reason says whether it worked. */
void oibar_app_param_get(uint32_t id, oibar_v1_ParamValue *out);
void oibar_app_param_set(uint32_t id, float value, oibar_v1_ParamValue *out);
void oibar_app_link_state(bool up);
void oibar_app_fill_telemetry(oibar_v1_Telemetry *out);
/* Next event for the host; false when none. */
bool oibar_app_next_event(oibar_v1_Event *out);

oibar_v1_State oibar_app_state(void);
bool oibar_app_host_link_alive(void);
/* CMD_END_SESSION accepted since the last handshake (and no other command
 * but NOOP after it): a link loss now is the host's planned end, no fault. */
bool oibar_app_session_ended(void);
oibar_v1_ResetCause oibar_app_reset_cause(void);
/* Capture envelope (paper: <= 50 mm/s, <= 10 deg) from the latest fresh
 * navigation update. */
bool oibar_app_capture_envelope_ok(uint32_t now_ms);
/* Misalignment in degrees between the camera boresight and the target's
 * docking axis, from q_cam_target (facing or aligned axes both count as 0). */
float oibar_app_misalignment_deg(const oibar_v1_Quat *q);
/* Emit an event to the host log (stamps uptime). */
void oibar_app_emit(oibar_v1_EventId id, oibar_v1_Severity sev, oibar_v1_State from,
                    oibar_v1_State to, oibar_v1_FaultCode fault, oibar_v1_NackReason reason,
                    uint32_t arg);
uint32_t oibar_app_watchdog_kicks(void);

#endif
