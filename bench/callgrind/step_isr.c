/*
 * Step-interrupt cost harness for `make bench` (bench/oibar_bench/firmware.py).
 *
 * Runs the firmware's own step ISR (oibar_stepper_isr, firmware/app/src/drv_stepper.c) N times
 * against the unit tests' fake HAL, the way the STM32 port's TIM2_IRQHandler calls it (through
 * the attached function pointer). Run under
 *
 *   valgrind --tool=callgrind --toggle-collect=oibar_stepper_isr step_isr MODE N
 *
 * only the ISR and what it calls are counted, so instructions / N is the cost of one interrupt.
 *
 *   MODE step    N steps of one long move (ramp up, cruise, ramp down): the common path
 *   MODE finish  N moves that each end at the first interrupt (switch reached, event posted):
 *                the longest path, once per move
 *
 * Prints one JSON line with what the bench needs to turn counts into a CPU share.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fake_hal.h"
#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/drv_stepper.h"

/* The port calls the ISR through a pointer (hal_step_timer_attach); volatile keeps the
 * compiler from inlining it into the loop, as it cannot on the board either. */
static void (*volatile s_step_irq)(void) = oibar_stepper_isr;

static const oibar_param_def_t *param(oibar_param_id_t id)
{
    const oibar_param_def_t *d = oibar_param_def((uint32_t)id);
    if (d == NULL) {
        fprintf(stderr, "step_isr: parameter %d missing from the table\n", (int)id);
        exit(2);
    }
    return d;
}

int main(int argc, char **argv)
{
    if (argc != 3 || (strcmp(argv[1], "step") != 0 && strcmp(argv[1], "finish") != 0)) {
        fprintf(stderr, "usage: %s step|finish N\n", argv[0]);
        return 2;
    }
    char *end = NULL;
    unsigned long n = strtoul(argv[2], &end, 10);
    if (end == argv[2] || *end != '\0' || n == 0ul || n > 100000000ul) {
        fprintf(stderr, "step_isr: N must be 1..100000000, not '%s'\n", argv[2]);
        return 2;
    }

    fake_hal_reset();
    fake_plant_enable(false); /* switches stay where the harness puts them */
    oibar_params_init();
    oibar_evtq_init();
    oibar_faults_init();
    oibar_stepper_init();

    /* The release move with the table's speeds; the switch never comes during `step`. */
    oibar_seek_t req = {
        .dir = 1,
        .stop_di = HAL_DI_LATCH_ENGAGED,
        .stop_level = true,
        .zero_at_stop = false,
        .budget_steps = (uint32_t)n + 1u,
        .max_speed_steps_s = oibar_param_u32(PARAM_LATCH_MAX_SPEED_STEPS_S),
        .accel_steps_s2 = oibar_param_u32(PARAM_LATCH_ACCEL_STEPS_S2),
    };
    unsigned long calls = 0ul;
    if (strcmp(argv[1], "step") == 0) {
        fake_hal_set_di(HAL_DI_LATCH_ENGAGED, false);
        if (!oibar_stepper_seek(&req)) {
            fprintf(stderr, "step_isr: seek refused\n");
            return 1;
        }
        for (unsigned long i = 0ul; i < n; i++) {
            s_step_irq();
            calls++;
        }
        if (fake_hal_step_pulses() != n || !oibar_stepper_busy()) {
            fprintf(stderr, "step_isr: %lu pulses for %lu interrupts\n", (unsigned long)fake_hal_step_pulses(), n);
            return 1;
        }
    } else {
        req.budget_steps = 1000u;
        for (unsigned long i = 0ul; i < n; i++) {
            fake_hal_set_di(HAL_DI_LATCH_ENGAGED, false);
            if (!oibar_stepper_seek(&req)) {
                fprintf(stderr, "step_isr: seek refused\n");
                return 1;
            }
            fake_hal_set_di(HAL_DI_LATCH_ENGAGED, true); /* the switch arrives */
            s_step_irq();
            calls++;
            oibar_evt_t e;
            while (oibar_evtq_get(&e)) { /* the main loop's part, not counted */
            }
            if (oibar_stepper_busy()) {
                fprintf(stderr, "step_isr: the move did not end at its switch\n");
                return 1;
            }
        }
    }
    const oibar_param_def_t *vmax = param(PARAM_LATCH_MAX_SPEED_STEPS_S);
    const oibar_param_def_t *vhome = param(PARAM_LATCH_HOME_SPEED_STEPS_S);
    printf("{\"mode\": \"%s\", \"calls\": %lu, \"ramp_entries\": %u, "
           "\"latch_max_speed_steps_s\": %g, \"latch_max_speed_steps_s_max\": %g, "
           "\"latch_home_speed_steps_s\": %g, \"latch_home_speed_steps_s_max\": %g}\n",
           argv[1], calls, oibar_stepper_ramp_len(), (double)vmax->default_value, (double)vmax->max,
           (double)vhome->default_value, (double)vhome->max);
    return 0;
}
