#include "oibar/pressure_loop.h"

#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/app_time.h"
#include "oibar/drv_pressure.h"
#include "oibar/drv_valves.h"

static bool s_running;
static float s_target_kpa;
static uint32_t s_start_ms;
static float s_ref_tv_kpa; /* target-tank reading the fill must rise above */
static uint32_t s_ref_ms;  /* since when it has not, with the line leading */
/* The supply-tank witness's window: the tank readings at its start. */
static float s_win_tv_kpa;
static float s_win_sv_kpa;
static uint32_t s_win_ms;
static float s_tv_peak_kpa; /* highest target-tank reading of this transfer */

static void win_restart(uint32_t now_ms)
{
    s_win_tv_kpa = oibar_pressure_kpa(OIBAR_PSENS_TV);
    s_win_sv_kpa = oibar_pressure_kpa(OIBAR_PSENS_SV);
    s_win_ms = now_ms;
}

void oibar_ploop_init(void)
{
    s_running = false;
    s_target_kpa = 0.0f;
    s_start_ms = 0;
    s_ref_tv_kpa = 0.0f;
    s_ref_ms = 0;
    s_win_tv_kpa = 0.0f;
    s_win_sv_kpa = 0.0f;
    s_win_ms = 0;
    s_tv_peak_kpa = 0.0f;
}

bool oibar_ploop_start(float target_kpa, uint32_t now_ms)
{
    s_target_kpa = target_kpa;
    s_start_ms = now_ms;
    s_ref_tv_kpa = oibar_pressure_kpa(OIBAR_PSENS_TV);
    s_ref_ms = now_ms;
    s_tv_peak_kpa = s_ref_tv_kpa;
    win_restart(now_ms);
    /* SAFETY_RULE_NO_BACKFLOW: never opened towards the supply (the state
     * machine's START guard checks it too). */
    if (oibar_pressure_kpa(OIBAR_PSENS_SV) < s_ref_tv_kpa + OIBAR_FLOW_MIN_HEAD_KPA) {
        s_running = false;
        return false;
    }
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
        return;
    }
    /* SAFETY_RULE_NO_BACKFLOW (D2): a supply reading below the target tank,
     * or a target tank falling OIBAR_BACKFLOW_DROP_KPA below its highest
     * reading of this transfer, is gas flowing backwards: close and fault
     * (FAULT_FILL_STALLED: the fill does not progress, it regresses). The
     * progress windows below would only restart on such a fall. */
    const float tv_now = oibar_pressure_kpa(OIBAR_PSENS_TV);
    if (tv_now > s_tv_peak_kpa) {
        s_tv_peak_kpa = tv_now;
    }
    if (oibar_pressure_kpa(OIBAR_PSENS_SV) < tv_now - OIBAR_FLOW_MIN_HEAD_KPA ||
        tv_now < s_tv_peak_kpa - OIBAR_BACKFLOW_DROP_KPA) {
        oibar_ploop_stop();
        oibar_fault_raise(oibar_v1_FAULT_FILL_STALLED);
        return;
    }
    /* SAFETY_RULE_FILL_MUST_PROGRESS: with the line above the target tank, gas
     * flows into it; a reading that does not rise is a sensor stuck in range (or
     * a blocked path), and filling on it would overfill the tank unseen until the
     * over-pressure trip. Equalised tanks (no lead) are left to transfer_max_ms. */
    float tv_kpa = oibar_pressure_kpa(OIBAR_PSENS_TV);
    float lead_kpa = oibar_pressure_kpa(OIBAR_PSENS_LINE) - tv_kpa;
    if (tv_kpa >= s_ref_tv_kpa + OIBAR_FILL_MIN_RISE_KPA || lead_kpa < OIBAR_FILL_LINE_LEAD_KPA) {
        s_ref_tv_kpa = tv_kpa;
        s_ref_ms = now_ms;
    } else if (oibar_held_for(now_ms, s_ref_ms, oibar_param_u32(PARAM_FILL_STALL_MS))) {
        oibar_ploop_stop();
        oibar_fault_raise(oibar_v1_FAULT_FILL_STALLED);
        return;
    }
    /* The same rule, witnessed by the supply tank: a line sensor failed low (or
     * stuck below the target tank) hides the lead, but gas leaving the supply
     * tank must arrive in the target tank. Over each fill_stall_ms window with no
     * rise, a supply drain of OIBAR_FILL_MIN_DRAIN_KPA is a stall; no drain is
     * equalised tanks, and the window starts again. A target reading that falls
     * as much (gas flowing back into an emptier line as the valves open) restarts
     * it; a few counts of noise do not. */
    if (tv_kpa >= s_win_tv_kpa + OIBAR_FILL_MIN_RISE_KPA ||
        tv_kpa <= s_win_tv_kpa - OIBAR_FILL_MIN_RISE_KPA) {
        win_restart(now_ms);
    } else if (oibar_held_for(now_ms, s_win_ms, oibar_param_u32(PARAM_FILL_STALL_MS))) {
        if (s_win_sv_kpa - oibar_pressure_kpa(OIBAR_PSENS_SV) >= OIBAR_FILL_MIN_DRAIN_KPA) {
            oibar_ploop_stop();
            oibar_fault_raise(oibar_v1_FAULT_FILL_STALLED);
            return;
        }
        win_restart(now_ms);
    }
}

bool oibar_ploop_running(void) { return s_running; }
float oibar_ploop_target_kpa(void) { return s_target_kpa; }
