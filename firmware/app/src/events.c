/* Bounded event queue (ISR producers, one main-loop consumer) and the
 * outgoing event log. */
#include "oibar/app_events.h"

#include <stddef.h>
#include <string.h>

#include "oibar/app_faults.h"
#include "oibar/hal.h"

static oibar_evt_t s_q[OIBAR_EVT_QUEUE_LEN];
static volatile unsigned s_head;   /* next write */
static volatile unsigned s_tail;   /* next read */
static volatile unsigned s_count;
static volatile unsigned s_high_water;
static volatile uint32_t s_overflows;

void oibar_evtq_init(void)
{
    uint32_t cs = hal_critical_enter();
    s_head = 0;
    s_tail = 0;
    s_count = 0;
    s_high_water = 0;
    s_overflows = 0;
    hal_critical_exit(cs);
}

bool oibar_evtq_post(oibar_sig_t sig, uint16_t arg)
{
    bool ok;
    uint32_t cs = hal_critical_enter();
    if (s_count >= OIBAR_EVT_QUEUE_LEN) {
        s_overflows++;
        ok = false;
    } else {
        s_q[s_head].sig = (uint16_t)sig;
        s_q[s_head].arg = arg;
        s_head = (s_head + 1u) % OIBAR_EVT_QUEUE_LEN;
        s_count++;
        if (s_count > s_high_water) {
            s_high_water = s_count;
        }
        ok = true;
    }
    hal_critical_exit(cs);
    if (!ok) {
        /* A lost fact is a fault: the machine no longer knows the hardware. */
        oibar_fault_raise(oibar_v1_FAULT_EVENT_QUEUE_OVERFLOW);
    }
    return ok;
}

bool oibar_evtq_get(oibar_evt_t *out)
{
    bool ok = false;
    uint32_t cs = hal_critical_enter();
    if (s_count > 0u) {
        *out = s_q[s_tail];
        s_tail = (s_tail + 1u) % OIBAR_EVT_QUEUE_LEN;
        s_count--;
        ok = true;
    }
    hal_critical_exit(cs);
    return ok;
}

uint32_t oibar_evtq_overflows(void) { return s_overflows; }
unsigned oibar_evtq_depth(void) { return s_count; }
unsigned oibar_evtq_high_water(void) { return s_high_water; }

const char *oibar_sig_name(oibar_sig_t sig)
{
    static const char *const names[SIG_COUNT] = {
        "SIG_NONE", "SIG_TIMEOUT", "SIG_CONTACT", "SIG_CONTACT_LOST",
        "SIG_LATCH_ENGAGED", "SIG_LATCH_DISENGAGED", "SIG_CONNECTOR_MATED",
        "SIG_CONNECTOR_LOST", "SIG_PLANE_EXTENDED", "SIG_PLANE_RETRACTED",
        "SIG_STEPPER_DONE", "SIG_TARGET_REACHED", "SIG_LINK_DOWN", "SIG_FAULT",
        "SIG_VALVES_CLOSED", "SIG_VALVES_STUCK",
    };
    return ((unsigned)sig < (unsigned)SIG_COUNT) ? names[sig] : "?";
}

/* --- outgoing log ---------------------------------------------------- */
static oibar_v1_Event s_log[OIBAR_EVT_LOG_LEN];
static unsigned s_log_head;
static unsigned s_log_count;
static uint32_t s_log_dropped;

void oibar_evlog_init(void)
{
    memset(s_log, 0, sizeof s_log);
    s_log_head = 0;
    s_log_count = 0;
    s_log_dropped = 0;
}

void oibar_evlog_push(const oibar_v1_Event *ev)
{
    if (s_log_count == OIBAR_EVT_LOG_LEN) {
        s_log_head = (s_log_head + 1u) % OIBAR_EVT_LOG_LEN; /* drop oldest */
        s_log_count--;
        s_log_dropped++;
    }
    s_log[(s_log_head + s_log_count) % OIBAR_EVT_LOG_LEN] = *ev;
    s_log_count++;
}

bool oibar_evlog_peek(oibar_v1_Event *out)
{
    if (s_log_count == 0u) {
        return false;
    }
    *out = s_log[s_log_head];
    return true;
}

unsigned oibar_evlog_count(void) { return s_log_count; }

bool oibar_evlog_pop(oibar_v1_Event *out)
{
    if (s_log_count == 0u) {
        return false;
    }
    *out = s_log[s_log_head];
    s_log_head = (s_log_head + 1u) % OIBAR_EVT_LOG_LEN;
    s_log_count--;
    return true;
}

uint32_t oibar_evlog_dropped(void) { return s_log_dropped; }
