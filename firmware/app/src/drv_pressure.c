#include "oibar/drv_pressure.h"

#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/app_time.h"
#include "oibar/hal.h"

typedef struct {
    float kpa;             /* latest good reading (held through a short glitch) */
    float window_start_kpa;
    uint32_t window_start_ms;
    uint32_t bad_since_ms; /* first sample of the current run of bad samples */
    uint32_t bad_samples;  /* samples in that run (saturates) */
    bool range_bad;        /* the run outlasted the bound: sensor fault */
    bool rate_bad;
    bool have_value;
    bool over;
} sensor_t;

static const hal_adc_t k_chan[OIBAR_PSENS_COUNT] = { HAL_ADC_SV_TANK, HAL_ADC_TV_TANK, HAL_ADC_LINE };
static const oibar_param_id_t k_gain[OIBAR_PSENS_COUNT] = {
    PARAM_PRESS_SV_KPA_PER_COUNT, PARAM_PRESS_TV_KPA_PER_COUNT, PARAM_PRESS_LINE_KPA_PER_COUNT
};

static sensor_t s_sens[OIBAR_PSENS_COUNT];

void oibar_pressure_init(void)
{
    for (unsigned i = 0; i < (unsigned)OIBAR_PSENS_COUNT; i++) {
        s_sens[i] = (sensor_t){ 0 };
    }
}

float oibar_pressure_counts_to_kpa(oibar_psens_t s, uint16_t counts)
{
    float zero = oibar_param_f(PARAM_PRESS_ZERO_COUNTS);
    return ((float)counts - zero) * oibar_param_f(k_gain[s]);
}

/* SAFETY_RULE_ADC_GLITCH_BOUNDED: one bad conversion (out of range, or a
 * failed/stale read) is a glitch: skipped, the last good value held, nothing
 * raised. A run of bad samples that lasts OIBAR_PRESSURE_BAD_RUN_MS of
 * elapsed time, over at least OIBAR_PRESSURE_BAD_RUN_MIN_SAMPLES samples, is
 * a broken sensor: unhealthy and FAULT_PRESSURE_SENSOR_RANGE, once. */
static void bad_sample(sensor_t *s, uint32_t now_ms)
{
    if (s->bad_samples == 0u) {
        s->bad_since_ms = now_ms;
    }
    if (s->bad_samples < UINT32_MAX) {
        s->bad_samples++;
    }
    if (s->range_bad || s->bad_samples < OIBAR_PRESSURE_BAD_RUN_MIN_SAMPLES ||
        !oibar_held_for(now_ms, s->bad_since_ms, OIBAR_PRESSURE_BAD_RUN_MS)) {
        return; /* a glitch so far: hold the last good value */
    }
    s->range_bad = true;
    s->have_value = false; /* restart the rate window after recovery */
    s->over = false;       /* a broken sensor cannot say; its fault closes the valves */
    oibar_fault_raise(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE);
}

static void update(oibar_psens_t which, uint32_t now_ms)
{
    sensor_t *s = &s_sens[which];
    uint16_t counts = 0;
    bool read_ok = hal_adc_read(k_chan[which], &counts);
    bool in_range = read_ok && counts >= oibar_param_u32(PARAM_PRESS_VALID_MIN_COUNTS) &&
                    counts <= oibar_param_u32(PARAM_PRESS_VALID_MAX_COUNTS);

    if (!in_range) {
        bad_sample(s, now_ms);
        return;
    }
    s->bad_samples = 0u;
    s->range_bad = false;
    s->kpa = oibar_pressure_counts_to_kpa(which, counts);

    /* Rate over windows of elapsed time (not of samples): the limit scales
     * with the time the window really took. */
    if (!s->have_value) {
        s->have_value = true;
        s->window_start_kpa = s->kpa;
        s->window_start_ms = now_ms;
    } else if (now_ms - s->window_start_ms >= OIBAR_PRESSURE_RATE_WINDOW_MS) {
        float delta = s->kpa - s->window_start_kpa;
        if (delta < 0.0f) {
            delta = -delta;
        }
        float limit = oibar_param_f(PARAM_PRESS_MAX_RATE_KPA_S) *
                      ((float)(now_ms - s->window_start_ms) / 1000.0f);
        bool bad = delta > limit;
        if (bad && !s->rate_bad) {
            oibar_fault_raise(oibar_v1_FAULT_PRESSURE_SENSOR_RATE);
        }
        s->rate_bad = bad;
        s->window_start_kpa = s->kpa;
        s->window_start_ms = now_ms;
    }

    bool over = s->kpa > oibar_param_f(PARAM_OVERPRESSURE_KPA);
    if (over && !s->over) {
        oibar_fault_raise(oibar_v1_FAULT_OVERPRESSURE);
    }
    s->over = over;
}

void oibar_pressure_tick(uint32_t now_ms)
{
    for (unsigned i = 0; i < (unsigned)OIBAR_PSENS_COUNT; i++) {
        update((oibar_psens_t)i, now_ms);
    }
}

float oibar_pressure_kpa(oibar_psens_t s)
{
    return ((unsigned)s < (unsigned)OIBAR_PSENS_COUNT) ? s_sens[s].kpa : 0.0f;
}

bool oibar_pressure_sensor_ok(oibar_psens_t s)
{
    if ((unsigned)s >= (unsigned)OIBAR_PSENS_COUNT) {
        return false;
    }
    const sensor_t *p = &s_sens[s];
    return p->have_value && !p->range_bad && !p->rate_bad;
}

bool oibar_pressure_all_ok(void)
{
    for (unsigned i = 0; i < (unsigned)OIBAR_PSENS_COUNT; i++) {
        if (!oibar_pressure_sensor_ok((oibar_psens_t)i)) {
            return false;
        }
    }
    return true;
}

bool oibar_pressure_over(void)
{
    for (unsigned i = 0; i < (unsigned)OIBAR_PSENS_COUNT; i++) {
        if (s_sens[i].over) {
            return true;
        }
    }
    return false;
}
