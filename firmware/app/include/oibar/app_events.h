/*
 * Internal events (signals) and the bounded queue that carries them from the
 * interrupts (1 kHz tick, step timer) to the one state machine in the main
 * loop. Posting never blocks: a full queue drops the event, counts it and
 * raises FAULT_EVENT_QUEUE_OVERFLOW (which travels outside the queue).
 *
 * Outgoing events (oibar_v1_Event, for the host) have their own bounded log.
 */
#ifndef OIBAR_APP_EVENTS_H
#define OIBAR_APP_EVENTS_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar.pb.h"

/* Hardware facts and timer expiries. Commands are events too (see
 * app_fsm.h) but arrive synchronously from the link, not through the queue. */
typedef enum {
    SIG_NONE = 0,
    SIG_TIMEOUT,            /* the current state's timeout expired */
    SIG_CONTACT,            /* debounced probe contact made */
    SIG_CONTACT_LOST,       /* debounced probe contact gone */
    SIG_LATCH_ENGAGED,      /* soft-dock latches sensed engaged */
    SIG_LATCH_DISENGAGED,   /* soft-dock latches sensed disengaged */
    SIG_CONNECTOR_MATED,    /* electrical connector sensed mated */
    SIG_CONNECTOR_LOST,     /* electrical connector sensed unmated */
    SIG_PLANE_EXTENDED,     /* plane driver: extend move complete */
    SIG_PLANE_RETRACTED,    /* plane driver: retract move complete */
    SIG_STEPPER_DONE,       /* latch stepper reached its switch */
    SIG_TARGET_REACHED,     /* pressure loop: target pressure, valves closed */
    SIG_LINK_DOWN,          /* host link lost */
    SIG_FAULT,              /* a fault was raised; arg = oibar_v1_FaultCode */
    SIG_VALVES_CLOSED,      /* state machine: both valves read closed (ABORTING's wait) */
    SIG_VALVES_STUCK,       /* state machine: a valve still reads open after valve_mismatch_ms */
    SIG_COUNT
} oibar_sig_t;

typedef struct {
    uint16_t sig;   /* oibar_sig_t */
    uint16_t arg;
} oibar_evt_t;

#define OIBAR_EVT_QUEUE_LEN 32u

void oibar_evtq_init(void);
/* ISR-safe. Returns false (and counts the overflow) when full. */
bool oibar_evtq_post(oibar_sig_t sig, uint16_t arg);
/* Main loop only. */
bool oibar_evtq_get(oibar_evt_t *out);
uint32_t oibar_evtq_overflows(void);
unsigned oibar_evtq_depth(void);
unsigned oibar_evtq_high_water(void);
const char *oibar_sig_name(oibar_sig_t sig);

/* --- outgoing events for the host ------------------------------------- */
#define OIBAR_EVT_LOG_LEN 32u

void oibar_evlog_init(void);
/* Main loop only. When full the oldest entry is overwritten (the host
 * learns of the loss from the drop counter, Telemetry.events_lost) so the
 * newest facts survive. An entry leaves the log only once it is sent: peek,
 * send, then pop. */
void oibar_evlog_push(const oibar_v1_Event *ev);
bool oibar_evlog_peek(oibar_v1_Event *out);
bool oibar_evlog_pop(oibar_v1_Event *out);
unsigned oibar_evlog_count(void);
uint32_t oibar_evlog_dropped(void);

#endif
