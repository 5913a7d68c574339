#include "oibar/drv_valves.h"

#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/app_time.h"
#include "oibar/drv_inputs.h"
#include "oibar/hal.h"

static const hal_do_t k_coil[OIBAR_VALVE_COUNT] = { HAL_DO_SV_VALVE, HAL_DO_TV_VALVE };
static const hal_di_t k_sense[OIBAR_VALVE_COUNT] = { HAL_DI_SV_VALVE_OPEN, HAL_DI_TV_VALVE_OPEN };

static volatile bool s_cmd_open[OIBAR_VALVE_COUNT];
static bool s_mismatch[OIBAR_VALVE_COUNT];
static uint32_t s_mismatch_since_ms[OIBAR_VALVE_COUNT]; /* first tick that saw it */
static bool s_reported[OIBAR_VALVE_COUNT];
static oibar_valve_permit_fn s_permit;

void oibar_valves_init(void)
{
    oibar_valves_close_all();
    for (unsigned v = 0; v < (unsigned)OIBAR_VALVE_COUNT; v++) {
        s_mismatch[v] = false;
        s_mismatch_since_ms[v] = 0;
        s_reported[v] = false;
    }
    s_permit = 0;
}

void oibar_valves_set_permit(oibar_valve_permit_fn permit) { s_permit = permit; }

/* SAFETY_RULE_VALVE_OPEN_ATOMIC: the interlock is asked and the coils are
 * driven in one critical section, and a fault raised but not yet taken by
 * the main loop refuses the opening. A fault raised from an interrupt thus
 * either lands before the check (and is seen) or after the coils are on
 * (and its oibar_fault_raise closes them): never in between. */
bool oibar_valves_open_both(void)
{
    bool opened = false;
    uint32_t cs = hal_critical_enter();
    if (s_permit != 0 && !oibar_fault_any_pending() && s_permit()) {
        for (unsigned v = 0; v < (unsigned)OIBAR_VALVE_COUNT; v++) {
            s_cmd_open[v] = true;
            hal_do_write(k_coil[v], true);
        }
        opened = true;
    }
    hal_critical_exit(cs);
    return opened;
}

void oibar_valves_close_all(void)
{
    for (unsigned v = 0; v < (unsigned)OIBAR_VALVE_COUNT; v++) {
        hal_do_write(k_coil[v], false);
        s_cmd_open[v] = false;
    }
}

bool oibar_valve_cmd_open(oibar_valve_t v)
{
    return ((unsigned)v < (unsigned)OIBAR_VALVE_COUNT) ? s_cmd_open[v] : false;
}

bool oibar_valve_sensed_open(oibar_valve_t v)
{
    return ((unsigned)v < (unsigned)OIBAR_VALVE_COUNT) ? oibar_input(k_sense[v]) : false;
}

bool oibar_valves_any_cmd_open(void)
{
    return s_cmd_open[OIBAR_VALVE_SV] || s_cmd_open[OIBAR_VALVE_TV];
}

bool oibar_valves_any_sensed_open(void)
{
    return oibar_valve_sensed_open(OIBAR_VALVE_SV) || oibar_valve_sensed_open(OIBAR_VALVE_TV);
}

void oibar_valves_tick(uint32_t now_ms)
{
    uint32_t limit_ms = oibar_param_u32(PARAM_VALVE_MISMATCH_MS);
    for (unsigned v = 0; v < (unsigned)OIBAR_VALVE_COUNT; v++) {
        if (s_cmd_open[v] == oibar_valve_sensed_open((oibar_valve_t)v)) {
            s_mismatch[v] = false;
            s_reported[v] = false;
            continue;
        }
        /* A valve needs its stroke time to follow; only a lasting
         * disagreement (elapsed time, not main-loop passes) is a stuck
         * valve. */
        if (!s_mismatch[v]) {
            s_mismatch[v] = true;
            s_mismatch_since_ms[v] = now_ms;
        }
        if (oibar_held_for(now_ms, s_mismatch_since_ms[v], limit_ms) && !s_reported[v]) {
            s_reported[v] = true; /* once per episode */
            oibar_fault_raise(oibar_v1_FAULT_VALVE_MISMATCH);
        }
    }
}

bool oibar_valves_mismatch(void)
{
    for (unsigned v = 0; v < (unsigned)OIBAR_VALVE_COUNT; v++) {
        if (s_cmd_open[v] != oibar_valve_sensed_open((oibar_valve_t)v)) {
            return true;
        }
    }
    return false;
}
