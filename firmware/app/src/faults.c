/* Fault latch: pending bits (ISR-safe), latched flags (main loop). */
#include "oibar/app_faults.h"

#include "oibar/drv_valves.h"
#include "oibar/hal.h"

static volatile uint32_t s_pending;
static uint32_t s_latched;

void oibar_faults_init(void)
{
    uint32_t cs = hal_critical_enter();
    s_pending = 0;
    s_latched = 0;
    hal_critical_exit(cs);
}

void oibar_fault_raise(oibar_v1_FaultCode code)
{
    if (code == oibar_v1_FAULT_NONE || (unsigned)code > OIBAR_FAULT_CODE_MAX) {
        code = oibar_v1_FAULT_ASSERTION;
    }
    /* SAFETY_RULE_FAULT_CLOSES_VALVES: first act, then tell. */
    oibar_valves_close_all();
    uint32_t cs = hal_critical_enter();
    s_pending |= OIBAR_FAULT_BIT(code);
    hal_critical_exit(cs);
}

oibar_v1_FaultCode oibar_fault_take_pending(void)
{
    oibar_v1_FaultCode code = oibar_v1_FAULT_NONE;
    uint32_t cs = hal_critical_enter();
    for (unsigned c = 1; c <= OIBAR_FAULT_CODE_MAX; c++) {
        if ((s_pending & OIBAR_FAULT_BIT(c)) != 0u) {
            s_pending &= ~OIBAR_FAULT_BIT(c);
            code = (oibar_v1_FaultCode)c;
            break;
        }
    }
    hal_critical_exit(cs);
    return code;
}

bool oibar_fault_any_pending(void) { return s_pending != 0u; }

uint32_t oibar_fault_flags(void) { return s_latched; }

void oibar_fault_latch(oibar_v1_FaultCode code)
{
    if (code != oibar_v1_FAULT_NONE && (unsigned)code <= OIBAR_FAULT_CODE_MAX) {
        s_latched |= OIBAR_FAULT_BIT(code);
    }
}

void oibar_fault_clear_all(void) { s_latched = 0; }
