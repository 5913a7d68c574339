/* Seeded random-sequence property test: commands, sensor changes, hardware
 * faults and link drops in any order. Whatever happens:
 *  - no valve is ever driven open unless the machine is in
 *    STATE_TRANSFERRING with every precondition of SPEC section 3 true. The
 *    preconditions are checked three ways: the firmware's own view, the raw
 *    hardware (allowing only the debounce time; the plane's end switch and
 *    position sensor at full mate), and
 *    the command history seen by this test;
 *  - the plane is never driven back out of the coupling travel while a valve
 *    reads open (raw switch, allowing only the debounce time);
 *  - every wait is bounded: a state that waits for hardware (the ones with a
 *    timeout parameter, UNMATING on the plane's move timeout, TRANSFERRING on
 *    transfer_max_ms) is never held longer than its bound. Only the safe
 *    states that wait for the host (IDLE, SOFT_DOCKED, HARD_DOCKED, FAULT)
 *    may last. Entry times come from the firmware's own STATE_CHANGE events.
 *
 * Each run draws a fresh seed and prints it; OIBAR_PROPERTY_SEED=<n> replays
 * a run, OIBAR_PROPERTY_STEPS=<n> sets its length (default 100000; `make
 * property-long` runs 10^7). */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "oibar/app_fsm.h"
#include "oibar/app_params.h"
#include "oibar/app_safety.h"
#include "oibar/drv_inputs.h"
#include "unity.h"

#define DEFAULT_STEPS 100000u
#define DEBOUNCE_SLACK_MS 12u /* debounce_ms + the pass that acts on it */
#define COUPLING_MM 30.0f     /* plane_coupling_mm default */
#define WAIT_SLACK_MS 5u      /* a bound is acted on at the next main-loop pass */

static uint32_t s_rng;
static uint32_t s_seed;
static uint32_t s_valve_open_raw_ms, s_retract_checks, s_plane_not_mated_raw_ms;
static unsigned s_phase;          /* 0: nothing, 1: arm accepted, 2: start accepted after arm */
static bool s_link_up;
static uint32_t s_conn_false_ms, s_latch_false_ms, s_press_bad_ms;
static uint32_t s_open_ms, s_starts, s_faults_seen, s_ms;
static uint32_t s_state_hist[16];
static uint32_t s_entered_ms;       /* when the current state was entered (its STATE_CHANGE) */
static oibar_v1_State s_entered_state;
static uint32_t s_longest_wait_ms[16];

void setUp(void) {}
void tearDown(void) {}

static uint32_t rnd(void)
{
    s_rng ^= s_rng << 13;
    s_rng ^= s_rng >> 17;
    s_rng ^= s_rng << 5;
    return s_rng;
}

static uint32_t below(uint32_t n) { return rnd() % n; }

static void track_state(void)
{
    oibar_v1_State st = oibar_app_state();
    if (st != oibar_v1_STATE_TRANSFER_ARMED && st != oibar_v1_STATE_TRANSFERRING) {
        s_phase = 0;
    }
}

/* The plane's end switch and its position sensor both at full mate (raw). */
static bool plane_mated_raw(void)
{
    uint16_t c = 0;
    return hal_di_read(HAL_DI_PLANE_EXTENDED) && hal_adc_read(HAL_ADC_PLANE_POS, &c) &&
           (float)c * 0.01221f >= OIBAR_PLANE_MATED_MIN_MM;
}

static bool valve_reads_open_raw(void)
{
    return hal_di_read(HAL_DI_SV_VALVE_OPEN) || hal_di_read(HAL_DI_TV_VALVE_OPEN);
}

/* SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN, from the outside. */
static void check_no_unmate_with_valve_open(void)
{
    if (!fake_hal_do(HAL_DO_PLANE_RETRACT) || fake_plant_plane_mm() < COUPLING_MM) {
        return;
    }
    s_retract_checks++;
    char msg[160];
    snprintf(msg, sizeof msg, "seed %u ms %u state %d: plane retracting at %.2f mm, valve open %u ms",
             (unsigned)s_seed, (unsigned)s_ms, (int)oibar_app_state(), (double)fake_plant_plane_mm(),
             (unsigned)s_valve_open_raw_ms);
    TEST_ASSERT_TRUE_MESSAGE(s_valve_open_raw_ms <= DEBOUNCE_SLACK_MS, msg);
}

/* The longest the machine may stay in each state, as docs/state_table.md gives it, written here
 * rather than read from the firmware's own table so that a timeout lost there is caught. The
 * states left out wait for the host and are safe to stay in. */
static const oibar_param_id_t k_wait_bound[16] = {
    [oibar_v1_STATE_BOOT] = PARAM_BOOT_SETTLE_MS,
    [oibar_v1_STATE_APPROACH_READY] = PARAM_APPROACH_READY_TIMEOUT_MS,
    [oibar_v1_STATE_RECEPTION] = PARAM_RECEPTION_TIMEOUT_MS,
    [oibar_v1_STATE_HARD_DOCKING] = PARAM_HARD_DOCKING_TIMEOUT_MS,
    [oibar_v1_STATE_TRANSFER_ARMED] = PARAM_TRANSFER_ARMED_TIMEOUT_MS,
    [oibar_v1_STATE_TRANSFERRING] = PARAM_TRANSFER_MAX_MS,      /* the pressure loop's */
    [oibar_v1_STATE_UNMATING] = PARAM_PLANE_MOVE_TIMEOUT_MS,    /* the plane driver's */
    [oibar_v1_STATE_LATCH_RELEASE] = PARAM_LATCH_MOVE_TIMEOUT_MS,
    [oibar_v1_STATE_SEPARATING] = PARAM_SEPARATING_TIMEOUT_MS,
    [oibar_v1_STATE_LATCH_RESET] = PARAM_LATCH_MOVE_TIMEOUT_MS,
    [oibar_v1_STATE_ABORTING] = PARAM_ABORT_TIMEOUT_MS,
};

/* The longest the machine may stay in `st` (0: it waits for the host, unbounded). */
static uint32_t wait_bound_ms(oibar_v1_State st)
{
    if ((unsigned)st >= 16u || k_wait_bound[st] == (oibar_param_id_t)0) {
        return 0u;
    }
    return oibar_param_u32(k_wait_bound[st]);
}

/* Every wait bounded by a timeout (docs/firmware.md). */
static void check_bounded_wait(void)
{
    oibar_v1_Event ev;
    while (oibar_app_next_event(&ev)) {
        if (ev.id == oibar_v1_EVT_STATE_CHANGE) {
            s_entered_ms = ev.uptime_ms;
            s_entered_state = ev.to_state;
        }
    }
    const oibar_v1_State st = oibar_app_state();
    char msg[160];
    if (st != s_entered_state) { /* the message only when it fails: this runs every simulated ms */
        snprintf(msg, sizeof msg, "seed %u ms %u: state %d but the last STATE_CHANGE entered %d",
                 (unsigned)s_seed, (unsigned)s_ms, (int)st, (int)s_entered_state);
        TEST_FAIL_MESSAGE(msg);
    }
    const uint32_t held_ms = hal_time_ms() - s_entered_ms;
    if ((unsigned)st < 16u && held_ms > s_longest_wait_ms[st]) {
        s_longest_wait_ms[st] = held_ms;
    }
    const uint32_t bound = wait_bound_ms(st);
    if (bound != 0u && held_ms > bound + WAIT_SLACK_MS) {
        snprintf(msg, sizeof msg, "seed %u ms %u: %s held %u ms, its bound is %u ms", (unsigned)s_seed,
                 (unsigned)s_ms, oibar_fsm_state_name((unsigned)st), (unsigned)held_ms, (unsigned)bound);
        TEST_FAIL_MESSAGE(msg);
    }
}

static void check_invariant(void)
{
    char msg[160];
    track_state();
    check_no_unmate_with_valve_open();
    check_bounded_wait();
    if (!bench_any_valve_driven()) {
        return;
    }
    s_open_ms++;
    snprintf(msg, sizeof msg, "seed %u ms %u state %d phase %u blockers 0x%x conn %u latch %u press %u",
             (unsigned)s_seed, (unsigned)s_ms, (int)oibar_app_state(), s_phase, (unsigned)oibar_safety_valve_blockers(),
             (unsigned)s_conn_false_ms, (unsigned)s_latch_false_ms, (unsigned)s_press_bad_ms);
    TEST_ASSERT_EQUAL_INT_MESSAGE(oibar_v1_STATE_TRANSFERRING, oibar_app_state(), msg);
    TEST_ASSERT_EQUAL_UINT32_MESSAGE(0u, oibar_safety_valve_blockers(), msg);
    TEST_ASSERT_EQUAL_UINT32_MESSAGE(0u, oibar_fault_flags(), msg);
    TEST_ASSERT_EQUAL_UINT_MESSAGE(2u, s_phase, msg);
    TEST_ASSERT_TRUE_MESSAGE(s_link_up, msg);
    TEST_ASSERT_TRUE_MESSAGE(s_conn_false_ms <= DEBOUNCE_SLACK_MS, msg);
    TEST_ASSERT_TRUE_MESSAGE(s_latch_false_ms <= DEBOUNCE_SLACK_MS, msg);
    TEST_ASSERT_TRUE_MESSAGE(s_press_bad_ms <= DEBOUNCE_SLACK_MS, msg);
    TEST_ASSERT_TRUE_MESSAGE(s_plane_not_mated_raw_ms <= DEBOUNCE_SLACK_MS, msg); /* switch and pot */
}

static bool pressure_raw_ok(void)
{
    const hal_adc_t ch[3] = { HAL_ADC_SV_TANK, HAL_ADC_TV_TANK, HAL_ADC_LINE };
    for (unsigned i = 0; i < 3; i++) {
        uint16_t c = 0;
        if (!hal_adc_read(ch[i], &c) || c < 200u || c > 3900u) {
            return false;
        }
    }
    return true;
}

static void run_ms(uint32_t ms)
{
    for (uint32_t i = 0; i < ms; i++) {
        fake_hal_advance_ms(1);
        s_ms++;
        s_conn_false_ms = hal_di_read(HAL_DI_CONNECTOR_MATED) ? 0u : s_conn_false_ms + 1u;
        s_latch_false_ms = hal_di_read(HAL_DI_LATCH_ENGAGED) ? 0u : s_latch_false_ms + 1u;
        s_press_bad_ms = pressure_raw_ok() ? 0u : s_press_bad_ms + 1u;
        s_valve_open_raw_ms = valve_reads_open_raw() ? s_valve_open_raw_ms + 1u : 0u;
        s_plane_not_mated_raw_ms = plane_mated_raw() ? 0u : s_plane_not_mated_raw_ms + 1u;
        check_invariant();
    }
}

static void command(oibar_v1_CommandOpcode op, float arg)
{
    oibar_app_run_once(); /* handle what is pending, as the command would */
    check_invariant();
    oibar_v1_State before = oibar_app_state();
    oibar_v1_NackReason r = oibar_app_command(op, arg);
    if (r == oibar_v1_NACK_NONE) {
        if (op == oibar_v1_CMD_ARM_TRANSFER) {
            s_phase = 1;
        } else if (op == oibar_v1_CMD_START_TRANSFER && s_phase == 1u) {
            s_phase = 2;
            s_starts++;
        }
    } else {
        TEST_ASSERT_EQUAL_INT(before, oibar_app_state()); /* rejected: no change */
    }
    check_invariant();
}

static void clear_knobs(void)
{
    fake_plant_clear_overrides();
    fake_plant_set_valve_mode(0, FAKE_VALVE_OK);
    fake_plant_set_valve_mode(1, FAKE_VALVE_OK);
    fake_plant_set_plane_jam(false);
    fake_plant_set_stepper_stall(false);
    fake_plant_set_force_n(0.0f);
    if (!s_link_up) {
        s_link_up = true;
        oibar_app_link_state(true);
    }
}

/* The command a cooperative host would send next, so that the random walk
 * keeps reaching the transfer. */
/* Between transfers the tanks are brought back (the supply refilled, the target
 * consumed) at 1 kPa/ms, slower than any rate check: the firmware refuses a start
 * without a supply head (SAFETY_RULE_NO_BACKFLOW), and without this only the
 * first fills of a walk would open the valves. Never while transferring. */
static void restore_tanks(void)
{
    for (unsigned ms = 0; ms < 2000u && oibar_app_state() != oibar_v1_STATE_TRANSFERRING; ms++) {
        float sv = fake_plant_sv_kpa(), tv = fake_plant_tv_kpa();
        if (sv >= 1999.0f && tv <= 201.0f) {
            break;
        }
        sv = (sv < 1999.0f) ? sv + 1.0f : sv;
        tv = (tv > 201.0f) ? tv - 1.0f : tv;
        fake_plant_set_tanks_kpa(sv, tv);
        run_ms(1);
    }
}

static void guided(void)
{
    switch (oibar_app_state()) {
    case oibar_v1_STATE_IDLE:
        if (fake_plant_probe()) {
            fake_plant_set_probe(false);
        }
        command(oibar_v1_CMD_APPROACH_ARM, 0.0f);
        break;
    case oibar_v1_STATE_APPROACH_READY:
        bench_nav_good();
        fake_plant_set_probe(true);
        break;
    case oibar_v1_STATE_RECEPTION:
        bench_nav_good();
        command(oibar_v1_CMD_DOCK, 0.0f);
        break;
    case oibar_v1_STATE_SOFT_DOCKED:
        command(oibar_v1_CMD_HARD_DOCK, 0.0f);
        break;
    case oibar_v1_STATE_HARD_DOCKED:
        if (fake_plant_sv_kpa() < fake_plant_tv_kpa() + 600.0f) {
            restore_tanks();
        }
        command(below(4) == 0 ? oibar_v1_CMD_SEPARATE : oibar_v1_CMD_ARM_TRANSFER, 0.0f);
        break;
    case oibar_v1_STATE_TRANSFER_ARMED:
        command(oibar_v1_CMD_START_TRANSFER, 300.0f + (float)below(1800));
        break;
    case oibar_v1_STATE_TRANSFERRING:
        if (below(8) == 0) {
            command(oibar_v1_CMD_STOP_TRANSFER, 0.0f);
        }
        break;
    case oibar_v1_STATE_FAULT:
        clear_knobs();
        run_ms(30);
        command(oibar_v1_CMD_CLEAR_FAULT, 0.0f);
        break;
    default:
        break;
    }
}

/* The hardware stops answering (a jammed plane, a stalled stepper, a switch stuck at a level,
 * or nothing at all) and neither host nor test steps in for up to 15 s: whatever the machine
 * waits for, it must stop waiting within its bound (check_bounded_wait). */
static void stall(void)
{
    switch (below(4)) {
    case 0:
        fake_plant_set_plane_jam(true);
        break;
    case 1:
        fake_plant_set_stepper_stall(true);
        break;
    case 2:
        fake_plant_override_di((hal_di_t)below(HAL_DI_COUNT), (int)below(2));
        break;
    default:
        break;
    }
    run_ms(1000u + below(14000));
}

static uint32_t env_u32(const char *name, uint32_t fallback)
{
    const char *v = getenv(name);
    if (v == NULL || *v == '\0') {
        return fallback;
    }
    return (uint32_t)strtoul(v, NULL, 0);
}

static void test_no_valve_open_outside_a_legitimate_transfer(void)
{
    /* A fresh seed per run (time and pid), unless one is given to replay. */
    uint32_t fresh = (uint32_t)time(NULL) * 2654435761u ^ (uint32_t)getpid() * 40503u;
    s_seed = env_u32("OIBAR_PROPERTY_SEED", fresh);
    if (s_seed == 0u) {
        s_seed = 1u; /* xorshift needs a non-zero state */
    }
    const uint32_t steps = env_u32("OIBAR_PROPERTY_STEPS", DEFAULT_STEPS);
    printf("property test: seed %u, %u steps (replay: OIBAR_PROPERTY_SEED=%u)\n", (unsigned)s_seed,
           (unsigned)steps, (unsigned)s_seed);
    fflush(stdout);
    s_rng = s_seed;
    s_phase = 0;
    s_conn_false_ms = s_latch_false_ms = s_press_bad_ms = 0;
    s_valve_open_raw_ms = s_retract_checks = s_plane_not_mated_raw_ms = 0;
    s_open_ms = s_starts = s_faults_seen = s_ms = 0;
    bench_start();
    s_entered_ms = 0;
    s_entered_state = oibar_v1_STATE_UNSPECIFIED;
    memset(s_longest_wait_ms, 0, sizeof s_longest_wait_ms);
    check_bounded_wait(); /* BOOT's entry */
    s_link_up = true;
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());

    for (uint32_t step = 0; step < steps; step++) {
        uint32_t r = below(1000);
        if (r >= 800 && below(3) != 0) {
            r = 0; /* perturbations at a third of their nominal rate */
        }
        if (r >= 1u && r < 4u) { /* not 0: the perturbations put off above land there */
            stall();
        } else if (r < 450) {
            run_ms(1u + below(100));
        } else if (r < 800) {
            guided();
        } else if (r < 810) {
            command((oibar_v1_CommandOpcode)below(13), (float)below(3000) - 100.0f);
        } else if (r < 820) {
            int level = (int)below(4) - 1; /* -1 release (twice as likely), 0, 1 */
            fake_plant_override_di((hal_di_t)below(HAL_DI_COUNT), level > 1 ? -1 : level);
        } else if (r < 858) {
            fake_plant_override_adc((hal_adc_t)below(HAL_ADC_COUNT),
                                    below(3) == 0 ? (int)below(4096) : -1);
        } else if (r < 862) {
            fake_plant_set_valve_mode(below(2), (fake_valve_mode_t)below(3));
        } else if (r < 864) {
            fake_plant_set_plane_jam(below(2) == 0);
        } else if (r < 866) {
            fake_plant_set_stepper_stall(below(2) == 0);
        } else if (r < 869) {
            fake_plant_set_force_n((float)below(80));
        } else if (r < 874) {
            s_link_up = !s_link_up;
            oibar_app_link_state(s_link_up);
            check_invariant();
        } else if (r < 878) {
            fake_plant_set_probe(below(2) == 0);
        } else if (r < 881) {
            oibar_fault_raise((oibar_v1_FaultCode)(1u + below(OIBAR_FAULT_CODE_MAX)));
            check_invariant();
            s_faults_seen++;
        } else {
            clear_knobs();
        }
        s_state_hist[oibar_app_state()]++;
    }
    char msg[160];
    snprintf(msg, sizeof msg, "seed %u coverage: %u starts, %u ms with valves open, %u ms retracting "
             "in the coupling travel, %u ms simulated", (unsigned)s_seed, (unsigned)s_starts,
             (unsigned)s_open_ms, (unsigned)s_retract_checks, (unsigned)s_ms);
    TEST_MESSAGE(msg);
    for (unsigned i = 1; i < 16; i++) {
        snprintf(msg, sizeof msg, "steps ending in %s: %u (longest stay %u ms, bound %u ms)",
                 oibar_fsm_state_name(i), (unsigned)s_state_hist[i], (unsigned)s_longest_wait_ms[i],
                 (unsigned)wait_bound_ms((oibar_v1_State)i));
        TEST_MESSAGE(msg);
    }
    snprintf(msg, sizeof msg, "coverage: %u starts, %u ms with valves open, %u ms simulated",
             (unsigned)s_starts, (unsigned)s_open_ms, (unsigned)s_ms);
    /* The walk must actually exercise the transfer, or it proves nothing. */
    TEST_ASSERT_TRUE_MESSAGE(s_starts >= steps / 1000u, msg);
    TEST_ASSERT_TRUE_MESSAGE(s_open_ms >= steps / 10u, msg);
    TEST_ASSERT_TRUE_MESSAGE(s_retract_checks >= steps / 100u, msg);
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_no_valve_open_outside_a_legitimate_transfer);
    return UNITY_END();
}
