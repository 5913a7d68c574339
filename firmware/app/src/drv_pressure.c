#include "oibar/drv_pressure.h"

#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/hal.h"

typedef struct {
    float kpa;
    float window_start_kpa;
    uint32_t window_ms;
    uint32_t bad_range_ms;
    bool range_bad;      /* out of range long enough */
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

static void update(oibar_psens_t which)
{
    sensor_t *s = &s_sens[which];
    uint16_t counts = 0;
    bool read_ok = hal_adc_read(k_chan[which], &counts);
    bool in_range = read_ok && counts >= oibar_param_u32(PARAM_PRESS_VALID_MIN_COUNTS) &&
                    counts <= oibar_param_u32(PARAM_PRESS_VALID_MAX_COUNTS);

    if (!in_range) {
        /* A single glitch is tolerated; a lasting one is a broken sensor. */
        s->bad_range_ms++;
        if (s->bad_range_ms >= oibar_param_u32(PARAM_DEBOUNCE_MS) && !s->range_bad) {
            s->range_bad = true;
            oibar_fault_raise(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE);
        }
        s->have_value = false; /* restart the rate window after recovery */
        s->over = false;
        return;
    }
    s->bad_range_ms = 0;
    s->range_bad = false;
    s->kpa = oibar_pressure_counts_to_kpa(which, counts);

    if (!s->have_value) {
        s->have_value = true;
        s->window_start_kpa = s->kpa;
        s->window_ms = 0;
    } else if (++s->window_ms >= OIBAR_PRESSURE_RATE_WINDOW_MS) {
        float delta = s->kpa - s->window_start_kpa;
        if (delta < 0.0f) {
            delta = -delta;
        }
        float limit = oibar_param_f(PARAM_PRESS_MAX_RATE_KPA_S) *
                      ((float)OIBAR_PRESSURE_RATE_WINDOW_MS / 1000.0f);
        bool bad = delta > limit;
        if (bad && !s->rate_bad) {
            oibar_fault_raise(oibar_v1_FAULT_PRESSURE_SENSOR_RATE);
        }
        s->rate_bad = bad;
        s->window_start_kpa = s->kpa;
        s->window_ms = 0;
    }

    bool over = s->kpa > oibar_param_f(PARAM_OVERPRESSURE_KPA);
    if (over && !s->over) {
        oibar_fault_raise(oibar_v1_FAULT_OVERPRESSURE);
    }
    s->over = over;
}

void oibar_pressure_tick(void)
{
    for (unsigned i = 0; i < (unsigned)OIBAR_PSENS_COUNT; i++) {
        update((oibar_psens_t)i);
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
    return p->have_value && p->bad_range_ms == 0u && !p->rate_bad;
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
