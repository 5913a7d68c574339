#include "oibar/drv_inputs.h"

#include "oibar/app_events.h"
#include "oibar/app_params.h"

static volatile bool s_level[HAL_DI_COUNT];
static uint16_t s_count_ms[HAL_DI_COUNT]; /* how long raw has differed */
static float s_force_n;
static float s_plane_mm;
static bool s_force_valid;

void oibar_inputs_init(void)
{
    for (unsigned i = 0; i < (unsigned)HAL_DI_COUNT; i++) {
        s_level[i] = hal_di_read((hal_di_t)i);
        s_count_ms[i] = 0;
    }
    s_force_n = 0.0f;
    s_plane_mm = 0.0f;
    s_force_valid = false;
}

static void post_edge(hal_di_t di, bool level)
{
    oibar_sig_t sig = SIG_NONE;
    switch (di) {
    case HAL_DI_CONTACT:
        sig = level ? SIG_CONTACT : SIG_CONTACT_LOST;
        break;
    case HAL_DI_LATCH_ENGAGED:
        sig = level ? SIG_LATCH_ENGAGED : SIG_LATCH_DISENGAGED;
        break;
    case HAL_DI_CONNECTOR_MATED:
        sig = level ? SIG_CONNECTOR_MATED : SIG_CONNECTOR_LOST;
        break;
    default:
        break; /* end switches and valve sensors are read as levels */
    }
    if (sig != SIG_NONE) {
        (void)oibar_evtq_post(sig, 0u);
    }
}

void oibar_inputs_tick_isr(void)
{
    uint32_t debounce_ms = oibar_param_u32(PARAM_DEBOUNCE_MS);
    for (unsigned i = 0; i < (unsigned)HAL_DI_COUNT; i++) {
        bool raw = hal_di_read((hal_di_t)i);
        if (raw == s_level[i]) {
            s_count_ms[i] = 0;
            continue;
        }
        s_count_ms[i]++;
        if (s_count_ms[i] >= debounce_ms) {
            s_level[i] = raw;
            s_count_ms[i] = 0;
            post_edge((hal_di_t)i, raw);
        }
    }
}

bool oibar_input(hal_di_t di)
{
    return ((unsigned)di < (unsigned)HAL_DI_COUNT) ? s_level[di] : false;
}

void oibar_inputs_analog_update(void)
{
    uint16_t counts = 0;
    s_force_valid = hal_adc_read(HAL_ADC_CONTACT_FORCE, &counts);
    s_force_n = s_force_valid ? (float)counts * oibar_param_f(PARAM_FORCE_N_PER_COUNT) : 0.0f;
    if (hal_adc_read(HAL_ADC_PLANE_POS, &counts)) {
        s_plane_mm = (float)counts * oibar_param_f(PARAM_PLANE_MM_PER_COUNT);
    }
}

float oibar_contact_force_n(void) { return s_force_n; }
float oibar_plane_pos_mm(void) { return s_plane_mm; }
bool oibar_contact_force_valid(void) { return s_force_valid; }
