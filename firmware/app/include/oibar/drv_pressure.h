/*
 * Pressure transducers (SV tank, TV tank, transfer line): ADC counts to kPa
 * with a per-sensor calibration, range check (open wire / short / failed
 * conversion: a single bad sample is a glitch, skipped with the last good
 * value held; a run lasting OIBAR_PRESSURE_BAD_RUN_MS ->
 * FAULT_PRESSURE_SENSOR_RANGE), rate-of-change check over 10 ms windows of
 * elapsed time (a jump no fluid can make -> FAULT_PRESSURE_SENSOR_RATE), and
 * the over-pressure trip on every healthy sensor (-> FAULT_OVERPRESSURE).
 * Each fault is raised once per episode. Times are elapsed 1 kHz ticks.
 */
#ifndef OIBAR_DRV_PRESSURE_H
#define OIBAR_DRV_PRESSURE_H

#include <stdbool.h>
#include <stdint.h>

typedef enum { OIBAR_PSENS_SV = 0, OIBAR_PSENS_TV, OIBAR_PSENS_LINE, OIBAR_PSENS_COUNT } oibar_psens_t;

#define OIBAR_PRESSURE_RATE_WINDOW_MS 10u
/* A run of bad samples is a sensor fault once it has lasted this long
 * (elapsed) and counted at least this many samples. Compile-time: the
 * tolerance of the range check is not a tunable. */
#define OIBAR_PRESSURE_BAD_RUN_MS 10u
#define OIBAR_PRESSURE_BAD_RUN_MIN_SAMPLES 2u

void oibar_pressure_init(void);
/* Main loop, once per control tick seen (now_ms: hal_time_ms()). */
void oibar_pressure_tick(uint32_t now_ms);
float oibar_pressure_kpa(oibar_psens_t s);
/* Has a value, no lasting range fault, plausible rate (a glitch in
 * progress, shorter than the bound, does not count). */
bool oibar_pressure_sensor_ok(oibar_psens_t s);
bool oibar_pressure_all_ok(void);
/* Some healthy sensor reads above overpressure_kpa, now. */
bool oibar_pressure_over(void);
/* Pure conversion, exposed for tests. */
float oibar_pressure_counts_to_kpa(oibar_psens_t s, uint16_t counts);

#endif
