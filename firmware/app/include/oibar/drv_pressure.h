/*
 * Pressure transducers (SV tank, TV tank, transfer line): ADC counts to kPa
 * with a per-sensor calibration, range check (open wire / short / failed
 * conversion persisting debounce_ms -> FAULT_PRESSURE_SENSOR_RANGE),
 * rate-of-change check over 10 ms windows (a jump no fluid can make ->
 * FAULT_PRESSURE_SENSOR_RATE), and the over-pressure trip on every healthy
 * sensor (-> FAULT_OVERPRESSURE). Each fault is raised once per episode.
 */
#ifndef OIBAR_DRV_PRESSURE_H
#define OIBAR_DRV_PRESSURE_H

#include <stdbool.h>
#include <stdint.h>

typedef enum { OIBAR_PSENS_SV = 0, OIBAR_PSENS_TV, OIBAR_PSENS_LINE, OIBAR_PSENS_COUNT } oibar_psens_t;

#define OIBAR_PRESSURE_RATE_WINDOW_MS 10u

void oibar_pressure_init(void);
/* Main loop, once per ms. */
void oibar_pressure_tick(void);
float oibar_pressure_kpa(oibar_psens_t s);
/* In range and plausible rate, now. */
bool oibar_pressure_sensor_ok(oibar_psens_t s);
bool oibar_pressure_all_ok(void);
/* Some healthy sensor reads above overpressure_kpa, now. */
bool oibar_pressure_over(void);
/* Pure conversion, exposed for tests. */
float oibar_pressure_counts_to_kpa(oibar_psens_t s, uint16_t counts);

#endif
