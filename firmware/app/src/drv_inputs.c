#include "oibar/drv_inputs.h"

#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/app_time.h"

static volatile bool s_level[HAL_DI_COUNT];
static bool s_differs[HAL_DI_COUNT];        /* raw differs from the debounced level */
static uint32_t s_differs_since_ms[HAL_DI_COUNT]; /* first tick that saw it differ */
static volatile bool s_latch_engaged;      /* the pair says engaged, plausibly */
static volatile bool s_latch_plausible;    /* exactly one contact of the pair closed */
static bool s_latch_odd;                   /* both or neither contact closed */
static uint32_t s_latch_odd_since_ms;      /* first tick that saw it */
static bool s_latch_reported;
static float s_force_n;
static float s_plane_mm;
static bool s_force_valid;
/* Plane position sensor health (D3): bounded glitch, then a fault. */
static bool s_plane_valid;
static uint32_t s_plane_bad_since_ms;
static uint32_t s_plane_bad_samples;
static bool s_plane_reported;

/* SAFETY_RULE_LATCH_SENSE_PAIR: engaged only when the NO contact is closed
 * and the NC contact open; any other combination reads "not engaged". */
static bool pair_engaged(void)
{
    return s_level[HAL_DI_LATCH_ENGAGED] && !s_level[HAL_DI_LATCH_NOT_ENGAGED];
}

static bool pair_plausible(void)
{
    return s_level[HAL_DI_LATCH_ENGAGED] != s_level[HAL_DI_LATCH_NOT_ENGAGED];
}

void oibar_inputs_init(void)
{
    uint32_t now = hal_time_ms();
    for (unsigned i = 0; i < (unsigned)HAL_DI_COUNT; i++) {
        s_level[i] = hal_di_read((hal_di_t)i);
        s_differs[i] = false;
        s_differs_since_ms[i] = now;
    }
    s_latch_engaged = pair_engaged();
    s_latch_plausible = pair_plausible();
    s_latch_odd = false;
    s_latch_odd_since_ms = now;
    s_latch_reported = false;
    s_force_n = 0.0f;
    s_plane_mm = 0.0f;
    s_force_valid = false;
    s_plane_valid = false;
    s_plane_bad_since_ms = now;
    s_plane_bad_samples = 0;
    s_plane_reported = false;
    oibar_inputs_analog_update(); /* a first reading before anything relies on it */
}

static void post_edge(hal_di_t di, bool level)
{
    oibar_sig_t sig = SIG_NONE;
    switch (di) {
    case HAL_DI_CONTACT:
        sig = level ? SIG_CONTACT : SIG_CONTACT_LOST;
        break;
    case HAL_DI_CONNECTOR_MATED:
        sig = level ? SIG_CONNECTOR_MATED : SIG_CONNECTOR_LOST;
        break;
    default:
        break; /* the latch pair is judged as a pair; the rest are levels */
    }
    if (sig != SIG_NONE) {
        (void)oibar_evtq_post(sig, 0u);
    }
}

/* The latch pair after debouncing: edges of the combined level, and the
 * plausibility check (both or neither contact closed for longer than a
 * switch transit can take is a broken wire or a short). */
static void latch_pair_update(uint32_t now_ms)
{
    bool engaged = pair_engaged();
    if (engaged != s_latch_engaged) {
        s_latch_engaged = engaged;
        (void)oibar_evtq_post(engaged ? SIG_LATCH_ENGAGED : SIG_LATCH_DISENGAGED, 0u);
    }
    if (pair_plausible()) {
        s_latch_plausible = true;
        s_latch_odd = false;
        s_latch_reported = false;
        return;
    }
    if (!s_latch_odd) {
        s_latch_odd = true;
        s_latch_odd_since_ms = now_ms;
    }
    if (oibar_held_for(now_ms, s_latch_odd_since_ms, OIBAR_LATCH_PAIR_TRANSIT_MAX_MS)) {
        s_latch_plausible = false;
        if (!s_latch_reported) {
            s_latch_reported = true; /* once per episode */
            oibar_fault_raise(oibar_v1_FAULT_LATCH_SENSOR);
        }
    }
}

void oibar_inputs_tick_isr(void)
{
    /* Elapsed time, not a count of calls: a late or missed tick does not
     * stretch the debounce. */
    uint32_t now = hal_time_ms();
    uint32_t debounce_ms = oibar_param_u32(PARAM_DEBOUNCE_MS);
    for (unsigned i = 0; i < (unsigned)HAL_DI_COUNT; i++) {
        bool raw = hal_di_read((hal_di_t)i);
        if (raw == s_level[i]) {
            s_differs[i] = false;
            continue;
        }
        if (!s_differs[i]) {
            s_differs[i] = true;
            s_differs_since_ms[i] = now;
        }
        if (oibar_held_for(now, s_differs_since_ms[i], debounce_ms)) {
            s_level[i] = raw;
            s_differs[i] = false;
            post_edge((hal_di_t)i, raw);
        }
    }
    latch_pair_update(now);
}

bool oibar_input(hal_di_t di)
{
    if (di == HAL_DI_LATCH_ENGAGED) {
        return s_latch_engaged;
    }
    return ((unsigned)di < (unsigned)HAL_DI_COUNT) ? s_level[di] : false;
}

bool oibar_latch_sensor_plausible(void) { return s_latch_plausible; }

/* D3, hal.h: a failed conversion is a sensor fault, and so is a reading
 * beyond the potentiometer's travel. As for the pressure sensors
 * (SAFETY_RULE_ADC_GLITCH_BOUNDED) one bad sample holds the last good value;
 * a run lasting OIBAR_PLANE_POS_BAD_RUN_MS over at least
 * OIBAR_PLANE_POS_BAD_RUN_MIN_SAMPLES samples makes the position invalid
 * (every interlock that reads it refuses) and raises FAULT_PLANE_POSITION,
 * once per episode. Never a stale number for ever. */
static void plane_pos_update(void)
{
    const uint32_t now = hal_time_ms();
    uint16_t counts = 0;
    float mm = 0.0f;
    bool ok = hal_adc_read(HAL_ADC_PLANE_POS, &counts);
    if (ok) {
        mm = (float)counts * oibar_param_f(PARAM_PLANE_MM_PER_COUNT);
        ok = mm <= OIBAR_PLANE_POS_MAX_MM;
    }
    if (ok) {
        s_plane_mm = mm;
        s_plane_valid = true;
        s_plane_bad_samples = 0;
        s_plane_reported = false;
        return;
    }
    if (s_plane_bad_samples == 0u) {
        s_plane_bad_since_ms = now;
    }
    if (s_plane_bad_samples < UINT32_MAX) {
        s_plane_bad_samples++;
    }
    if (s_plane_bad_samples < OIBAR_PLANE_POS_BAD_RUN_MIN_SAMPLES ||
        !oibar_held_for(now, s_plane_bad_since_ms, OIBAR_PLANE_POS_BAD_RUN_MS)) {
        return; /* a glitch so far */
    }
    s_plane_valid = false;
    if (!s_plane_reported) {
        s_plane_reported = true;
        oibar_fault_raise(oibar_v1_FAULT_PLANE_POSITION);
    }
}

void oibar_inputs_analog_update(void)
{
    uint16_t counts = 0;
    s_force_valid = hal_adc_read(HAL_ADC_CONTACT_FORCE, &counts);
    s_force_n = s_force_valid ? (float)counts * oibar_param_f(PARAM_FORCE_N_PER_COUNT) : 0.0f;
    plane_pos_update();
}

float oibar_contact_force_n(void) { return s_force_n; }
float oibar_plane_pos_mm(void) { return s_plane_mm; }
bool oibar_plane_pos_valid(void) { return s_plane_valid; }
bool oibar_contact_force_valid(void) { return s_force_valid; }
