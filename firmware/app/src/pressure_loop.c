#include "oibar/pressure_loop.h"

#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_pressure.h"
#include "oibar/drv_valves.h"

static bool s_running;
static float s_target_kpa;
static uint32_t s_start_ms;

void oibar_ploop_init(void)
{
    s_running = false;
    s_target_kpa = 0.0f;
    s_start_ms = 0;
}

bool oibar_ploop_start(float target_kpa, uint32_t now_ms)
{
    s_target_kpa = target_kpa;
    s_start_ms = now_ms;
    s_running = oibar_valves_open_both();
    return s_running;
}

void oibar_ploop_stop(void)
{
    oibar_valves_close_all();
    s_running = false;
}

void oibar_ploop_tick(uint32_t now_ms)
{
    if (!s_running) {
        return;
    }
    if (!oibar_valves_any_cmd_open()) {
        s_running = false; /* someone (a fault, the interlock) closed them */
        return;
    }
    if (oibar_pressure_sensor_ok(OIBAR_PSENS_TV) &&
        oibar_pressure_kpa(OIBAR_PSENS_TV) >= s_target_kpa) {
        oibar_ploop_stop();
        (void)oibar_evtq_post(SIG_TARGET_REACHED, 0u);
        return;
    }
    if (now_ms - s_start_ms >= oibar_param_u32(PARAM_TRANSFER_MAX_MS)) {
        oibar_ploop_stop();
        oibar_fault_raise(oibar_v1_FAULT_TRANSFER_TIMEOUT);
    }
}

bool oibar_ploop_running(void) { return s_running; }
float oibar_ploop_target_kpa(void) { return s_target_kpa; }
