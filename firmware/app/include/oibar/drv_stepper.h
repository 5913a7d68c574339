/*
 * Latch stepper: step/dir/enable. Every move is a "seek": run towards a
 * switch (home, or the latch-engaged sensor going off) with a trapezoidal
 * speed profile, stop when the switch reads the wanted level, and give up
 * after a step budget (stall detection for an open-loop motor: a stalled
 * motor never reaches its switch). The profile is planned here, in the main
 * loop; the step interrupt only looks periods up (short and bounded, GRBL
 * style).
 *
 * Profile (docs/firmware.md): accelerate along the ramp table, cruise,
 * decelerate to the creep speed before the switch is expected, creep on until
 * it trips. The table holds OIBAR_STEPPER_RAMP_MAX steps; a speed the table
 * cannot reach at the given acceleration is clamped to the fastest entry, so
 * the motor never jumps to a speed it was not ramped to.
 *
 * Homing is GRBL's: seek the home switch, pull off it by
 * OIBAR_STEPPER_PULLOFF_STEPS, then re-locate it at the slow speed (no
 * faster than the ramp's first step, so no ramp is needed) and zero there.
 * A switch that does not clear on the pull-off is a stall. Homing that
 * starts on the switch does the same (pull off, re-locate): only a switch
 * seen to clear and trip again counts as home.
 *
 * Completion posts SIG_STEPPER_DONE (arg = move id); an exhausted budget
 * stops the motor and raises FAULT_LATCH_STALL.
 */
#ifndef OIBAR_DRV_STEPPER_H
#define OIBAR_DRV_STEPPER_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar/hal.h"

#define OIBAR_STEPPER_RAMP_MAX 256u
/* Homing: steps off the home switch before the slow re-locate. */
#define OIBAR_STEPPER_PULLOFF_STEPS 40u
/* Homing: the re-locate runs at home speed / this (and no faster than the
 * ramp's first step). */
#define OIBAR_STEPPER_LOCATE_DIVISOR 4u

typedef struct {
    int8_t dir;              /* +1 towards release, -1 towards home */
    hal_di_t stop_di;        /* switch that ends the move */
    bool stop_level;         /* ... when it reads this level */
    bool zero_at_stop;       /* homing: position := 0 at the switch */
    uint32_t budget_steps;   /* give up (stall) after this many steps */
    uint32_t max_speed_steps_s;
    uint32_t accel_steps_s2;
    uint32_t expect_steps;        /* where the switch should trip; 0: plan to stop at the budget */
    uint32_t creep_speed_steps_s; /* speed on reaching expect_steps; 0: the ramp's first step */
} oibar_seek_t;

void oibar_stepper_init(void);
/* Plan and start a seek. Returns false (nothing moves) for a bad request. */
bool oibar_stepper_seek(const oibar_seek_t *req);
/* Home with the parameter table's speeds and budget. */
bool oibar_stepper_home(void);
/* Release the soft-dock latch (seek until the latch sensor reads off). */
bool oibar_stepper_release_latch(void);
/* Stop at once, keep holding torque. ISR-safe. */
void oibar_stepper_stop(void);
/* Stop and de-energise. */
void oibar_stepper_disable(void);
/* Step timer interrupt. */
void oibar_stepper_isr(void);

bool oibar_stepper_busy(void);
int32_t oibar_stepper_pos_steps(void);
uint16_t oibar_stepper_move_id(void);
/* Profile inspection for tests: number of ramp entries and entry i. */
unsigned oibar_stepper_ramp_len(void);
uint32_t oibar_stepper_ramp_period_us(unsigned i);
uint32_t oibar_stepper_cruise_period_us(void);
/* Step at which deceleration starts, and the creep period after it. */
uint32_t oibar_stepper_decel_at_step(void);
uint32_t oibar_stepper_creep_period_us(void);
/* True once a homing run has zeroed the position (and the motor stayed
 * energised since). */
bool oibar_stepper_pos_known(void);

#endif
