/*
 * Fluidic-plane linear actuator: H-bridge extend/retract, an end switch at
 * each end, a timeout on every move. An end counts as reached only when its
 * switch and the position sensor agree (SAFETY_RULE_PLANE_SENSE_PAIR, windows
 * in app_params.h) and the other switch is open; both switches actuated at
 * once stops the motor and raises FAULT_PLANE_POSITION. A move that finds
 * its end already reached completes at once. Completion posts SIG_PLANE_EXTENDED/_RETRACTED
 * with the move id as argument (stale completions are recognisable); a move
 * that does not reach its switch within plane_move_timeout_ms stops the
 * motor and raises FAULT_PLANE_TIMEOUT.
 */
#ifndef OIBAR_DRV_PLANE_H
#define OIBAR_DRV_PLANE_H

#include <stdbool.h>
#include <stdint.h>

typedef enum { OIBAR_PLANE_STOPPED = 0, OIBAR_PLANE_EXTENDING, OIBAR_PLANE_RETRACTING } oibar_plane_motion_t;

void oibar_plane_init(void);
void oibar_plane_extend(uint32_t now_ms);
void oibar_plane_retract(uint32_t now_ms);
/* De-energise; the lead screw holds the plane where it is. */
void oibar_plane_stop(void);
/* Main loop, once per ms. */
void oibar_plane_tick(uint32_t now_ms);
oibar_plane_motion_t oibar_plane_motion(void);
uint16_t oibar_plane_move_id(void);
bool oibar_plane_is_extended(void);  /* at the extended switch (and sensor), not moving */
bool oibar_plane_is_retracted(void); /* at the retracted switch, not moving */
/* Position sensor valid and not both end switches actuated. */
bool oibar_plane_sense_plausible(void);

#endif
