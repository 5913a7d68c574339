/* Docking state machine: the transition table, the guards, the actions and
 * one entry handler per state. */
#include "oibar/app_fsm.h"

#include <math.h>
#include <stddef.h>

#include "oibar/app.h"
#include "oibar/app_assert.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/app_safety.h"
#include "oibar/drv_inputs.h"
#include "oibar/drv_plane.h"
#include "oibar/drv_pressure.h"
#include "oibar/drv_stepper.h"
#include "oibar/drv_valves.h"
#include "oibar/pressure_loop.h"

/* Short names for the table. */
#define S(x) ((uint8_t)oibar_v1_STATE_##x)
#define C(x) OIBAR_FSM_EV_CMD(oibar_v1_CMD_##x)
#define E(x) ((uint8_t)SIG_##x)
#define G(x) ((uint8_t)GUARD_##x)
#define A(x) ((uint8_t)ACT_##x)
#define ANY ((uint8_t)OIBAR_FSM_ANY)
#define SUPER(x) ((uint8_t)OIBAR_FSM_SUPER_##x)
#define STAY ((uint8_t)OIBAR_FSM_STAY)

/* The table. docs/state_table.md is the same table, row for row, in this
 * order (test_app_state_table checks it). An event is looked up in the
 * current state's rows, then in its superstates' (innermost first), then in
 * the ANY rows; the first level with a row for the event handles it. */
static const oibar_fsm_row_t k_table[] = {
    /* state              event                  guard                 next               action */
    { S(BOOT),            E(TIMEOUT),            G(AT_HOME),           S(IDLE),           A(NONE) },
    { S(BOOT),            E(TIMEOUT),            G(NOT_AT_HOME),       S(FAULT),          A(FAULT_RESET_AWAY_FROM_HOME) },
    { S(BOOT),            C(ABORT),              G(NONE),              STAY,              A(NONE) },
    { S(BOOT),            E(LINK_DOWN),          G(NONE),              STAY,              A(NONE) },

    { S(IDLE),            C(APPROACH_ARM),       G(READY_FOR_APPROACH), S(APPROACH_READY), A(NONE) },
    { S(IDLE),            C(ABORT),              G(NONE),              STAY,              A(NONE) },
    { S(IDLE),            E(LINK_DOWN),          G(NONE),              STAY,              A(NONE) },

    { S(APPROACH_READY),  E(CONTACT),            G(NONE),              S(RECEPTION),      A(RECORD_CAPTURE) },
    { S(APPROACH_READY),  E(TIMEOUT),            G(NONE),              S(IDLE),           A(NONE) },
    { S(APPROACH_READY),  C(END_SESSION),        G(NONE),              S(IDLE),           A(NONE) },

    { S(RECEPTION),       C(DOCK),               G(CAPTURE_CONFIRMED), S(SOFT_DOCKED),    A(NONE) },
    { S(RECEPTION),       E(CONTACT_LOST),       G(LATCH_NOT_ENGAGED), S(APPROACH_READY), A(NONE) },
    { S(RECEPTION),       E(TIMEOUT),            G(NONE),              S(FAULT),          A(FAULT_LATCH_TIMEOUT) },

    { S(SOFT_DOCKED),     C(HARD_DOCK),          G(SOFT_DOCK_HELD),    S(HARD_DOCKING),   A(NONE) },
    { S(SOFT_DOCKED),     C(SEPARATE),           G(VALVES_CLOSED),     S(UNMATING),       A(NONE) },
    { S(SOFT_DOCKED),     C(END_SESSION),        G(NONE),              STAY,              A(NONE) },

    { S(HARD_DOCKING),    E(PLANE_EXTENDED),     G(CONNECTOR_MATED),   S(HARD_DOCKED),    A(NONE) },
    { S(HARD_DOCKING),    E(CONNECTOR_MATED),    G(PLANE_EXTENDED),    S(HARD_DOCKED),    A(NONE) },
    { S(HARD_DOCKING),    E(TIMEOUT),            G(NONE),              S(FAULT),          A(FAULT_PLANE_TIMEOUT) },
    { S(HARD_DOCKING),    C(SEPARATE),           G(VALVES_CLOSED),     S(UNMATING),       A(NONE) },

    { S(HARD_DOCKED),     C(ARM_TRANSFER),       G(TRANSFER_READY),    S(TRANSFER_ARMED), A(ARM) },
    { S(HARD_DOCKED),     C(SEPARATE),           G(VALVES_CLOSED),     S(UNMATING),       A(NONE) },
    { S(HARD_DOCKED),     C(END_SESSION),        G(NONE),              STAY,              A(NONE) },

    { S(TRANSFER_ARMED),  C(START_TRANSFER),     G(START_OK),          S(TRANSFERRING),   A(START_TRANSFER) },
    { S(TRANSFER_ARMED),  C(DISARM_TRANSFER),    G(NONE),              S(HARD_DOCKED),    A(NONE) },
    { S(TRANSFER_ARMED),  E(TIMEOUT),            G(NONE),              S(HARD_DOCKED),    A(NONE) },
    { S(TRANSFER_ARMED),  C(END_SESSION),        G(NONE),              S(HARD_DOCKED),    A(NONE) },

    { S(TRANSFERRING),    E(TARGET_REACHED),     G(NONE),              S(HARD_DOCKED),    A(REPORT_TRANSFER_COMPLETE) },
    { S(TRANSFERRING),    C(STOP_TRANSFER),      G(NONE),              S(HARD_DOCKED),    A(NONE) },
    { S(TRANSFERRING),    C(END_SESSION),        G(NONE),              S(HARD_DOCKED),    A(NONE) },

    { S(UNMATING),        E(PLANE_RETRACTED),    G(NONE),              S(LATCH_RELEASE),  A(NONE) },

    { S(LATCH_RELEASE),   E(STEPPER_DONE),       G(NONE),              S(SEPARATING),     A(NONE) },
    { S(LATCH_RELEASE),   E(TIMEOUT),            G(NONE),              S(FAULT),          A(FAULT_LATCH_TIMEOUT) },

    { S(SEPARATING),      E(CONTACT_LOST),       G(NONE),              S(LATCH_RESET),    A(NONE) },
    { S(SEPARATING),      E(TIMEOUT),            G(NONE),              S(FAULT),          A(FAULT_LATCH_TIMEOUT) },

    { S(LATCH_RESET),     E(STEPPER_DONE),       G(NONE),              S(IDLE),           A(NONE) },
    { S(LATCH_RESET),     E(TIMEOUT),            G(NONE),              S(FAULT),          A(FAULT_LATCH_TIMEOUT) },

    { S(ABORTING),        E(VALVES_CLOSED),      G(NONE),              STAY,              A(RETRACT_PLANE) },
    { S(ABORTING),        E(VALVES_STUCK),       G(NONE),              S(FAULT),          A(FAULT_VALVE_MISMATCH) },
    { S(ABORTING),        E(PLANE_RETRACTED),    G(SOFT_DOCK_CONFIRMED), S(SOFT_DOCKED),  A(NONE) },
    { S(ABORTING),        E(PLANE_RETRACTED),    G(LATCH_NOT_ENGAGED), S(LATCH_RESET),    A(NONE) },
    { S(ABORTING),        E(PLANE_RETRACTED),    G(LATCH_ENGAGED),     S(LATCH_RELEASE),  A(NONE) },
    { S(ABORTING),        E(TIMEOUT),            G(NONE),              S(FAULT),          A(FAULT_PLANE_TIMEOUT) },
    { S(ABORTING),        C(ABORT),              G(NONE),              STAY,              A(NONE) },

    { S(FAULT),           C(CLEAR_FAULT),        G(FAULT_CAUSES_GONE), S(ABORTING),       A(CLEAR_FAULTS) },
    { S(FAULT),           C(ABORT),              G(NONE),              STAY,              A(NONE) },
    { S(FAULT),           E(FAULT),              G(NONE),              STAY,              A(LATCH_FAULT) },
    { S(FAULT),           E(LINK_DOWN),          G(NONE),              STAY,              A(NONE) },

    /* Superstates (QP/C style): a row here applies to every state inside. */
    { SUPER(ACTIVE),      C(ABORT),              G(NONE),              S(ABORTING),       A(NONE) },
    { SUPER(ACTIVE),      C(END_SESSION),        G(NONE),              S(ABORTING),       A(NONE) },
    { SUPER(DOCKED),      E(LATCH_DISENGAGED),   G(NONE),              S(FAULT),          A(FAULT_LATCH_LOST) },
    { SUPER(MATED),       E(CONNECTOR_LOST),     G(NONE),              S(FAULT),          A(FAULT_CONNECTOR_LOST) },

    { ANY,                C(NOOP),               G(NONE),              STAY,              A(NONE) },
    { ANY,                C(END_SESSION),        G(NONE),              STAY,              A(NONE) },
    { ANY,                E(FAULT),              G(NONE),              S(FAULT),          A(LATCH_FAULT) },
    { ANY,                E(LINK_DOWN),          G(NONE),              S(FAULT),          A(FAULT_HOST_LINK_LOSS) },
};

#define TABLE_ROWS (sizeof k_table / sizeof k_table[0])

const oibar_fsm_row_t *oibar_fsm_table(unsigned *rows)
{
    if (rows != NULL) {
        *rows = (unsigned)TABLE_ROWS;
    }
    return k_table;
}

/* --- names --------------------------------------------------------------- */
static const char *const k_state_names[OIBAR_FSM_NODE_LAST + 1u] = {
    "ANY", "STATE_BOOT", "STATE_IDLE", "STATE_APPROACH_READY", "STATE_RECEPTION",
    "STATE_SOFT_DOCKED", "STATE_HARD_DOCKING", "STATE_HARD_DOCKED", "STATE_TRANSFER_ARMED",
    "STATE_TRANSFERRING", "STATE_UNMATING", "STATE_LATCH_RELEASE", "STATE_SEPARATING",
    "STATE_LATCH_RESET", "STATE_ABORTING", "STATE_FAULT", "ACTIVE", "DOCKED", "MATED",
};

/* Each node's superstate (ANY: none). ACTIVE: every state where the mechanism
 * is doing something on the host's behalf (ABORT safes it); DOCKED: the
 * soft-dock latch holds the target (losing it is a fault); MATED: the plane and
 * the connector are mated (losing the connector is a fault). */
static const uint8_t k_parent[OIBAR_FSM_NODE_LAST + 1u] = {
    [oibar_v1_STATE_APPROACH_READY] = OIBAR_FSM_SUPER_ACTIVE,
    [oibar_v1_STATE_RECEPTION] = OIBAR_FSM_SUPER_ACTIVE,
    [oibar_v1_STATE_SOFT_DOCKED] = OIBAR_FSM_SUPER_DOCKED,
    [oibar_v1_STATE_HARD_DOCKING] = OIBAR_FSM_SUPER_DOCKED,
    [oibar_v1_STATE_HARD_DOCKED] = OIBAR_FSM_SUPER_MATED,
    [oibar_v1_STATE_TRANSFER_ARMED] = OIBAR_FSM_SUPER_MATED,
    [oibar_v1_STATE_TRANSFERRING] = OIBAR_FSM_SUPER_MATED,
    [oibar_v1_STATE_UNMATING] = OIBAR_FSM_SUPER_DOCKED,
    [oibar_v1_STATE_LATCH_RELEASE] = OIBAR_FSM_SUPER_ACTIVE,
    [oibar_v1_STATE_SEPARATING] = OIBAR_FSM_SUPER_ACTIVE,
    [oibar_v1_STATE_LATCH_RESET] = OIBAR_FSM_SUPER_ACTIVE,
    [OIBAR_FSM_SUPER_DOCKED] = OIBAR_FSM_SUPER_ACTIVE,
    [OIBAR_FSM_SUPER_MATED] = OIBAR_FSM_SUPER_DOCKED,
};

unsigned oibar_fsm_parent(unsigned node)
{
    return (node <= OIBAR_FSM_NODE_LAST) ? k_parent[node] : OIBAR_FSM_ANY;
}
static const char *const k_cmd_names[OIBAR_CMD_LAST + 1u] = {
    "CMD_UNSPECIFIED", "CMD_NOOP", "CMD_APPROACH_ARM", "CMD_DOCK", "CMD_HARD_DOCK",
    "CMD_ARM_TRANSFER", "CMD_START_TRANSFER", "CMD_STOP_TRANSFER", "CMD_SEPARATE",
    "CMD_ABORT", "CMD_CLEAR_FAULT", "CMD_DISARM_TRANSFER", "CMD_END_SESSION",
};
static const char *const k_guard_names[GUARD_COUNT] = {
    "-", "at_home", "not_at_home", "ready_for_approach", "capture_confirmed",
    "soft_dock_held", "connector_mated", "plane_extended", "latch_engaged",
    "latch_not_engaged", "transfer_ready", "start_ok", "fault_causes_gone", "valves_closed",
    "soft_dock_confirmed",
};
static const char *const k_action_names[ACT_COUNT] = {
    "-", "record_capture", "arm", "start_transfer", "report_transfer_complete",
    "latch_fault", "fault_latch_timeout", "fault_plane_timeout", "fault_connector_lost",
    "fault_latch_lost", "fault_host_link_loss", "clear_faults", "retract_plane",
    "fault_valve_mismatch", "fault_reset_away_from_home",
};

const char *oibar_fsm_state_name(unsigned state)
{
    return (state <= OIBAR_FSM_NODE_LAST) ? k_state_names[state] : "?";
}

const char *oibar_fsm_next_name(unsigned next)
{
    return (next == OIBAR_FSM_STAY) ? "-" : oibar_fsm_state_name(next);
}

const char *oibar_fsm_event_name(unsigned event)
{
    if (event < (unsigned)SIG_COUNT) {
        return oibar_sig_name((oibar_sig_t)event);
    }
    if (event >= OIBAR_FSM_EV_CMD_BASE && event <= OIBAR_FSM_EV_CMD_BASE + OIBAR_CMD_LAST) {
        return k_cmd_names[event - OIBAR_FSM_EV_CMD_BASE];
    }
    return "?";
}

const char *oibar_fsm_guard_name(unsigned guard)
{
    return (guard < (unsigned)GUARD_COUNT) ? k_guard_names[guard] : "?";
}

const char *oibar_fsm_action_name(unsigned action)
{
    return (action < (unsigned)ACT_COUNT) ? k_action_names[action] : "?";
}

/* --- machine state ----------------------------------------------------- */
static oibar_v1_State s_state;
static uint32_t s_deadline_ms;
static bool s_timer_armed;
static bool s_armed;        /* ARM_TRANSFER accepted, not yet left */
static bool s_started;      /* START_TRANSFER accepted in the armed state */
static float s_target_kpa;
static bool s_capture_ok;
static float s_cmd_target_kpa; /* argument of the command being dispatched */
static uint16_t s_sig_arg;      /* argument of the signal being dispatched */
static bool s_valve_wait;       /* ABORTING: plane held until the valves read closed */
static bool s_mate_lost;        /* a mated state without full mate (oibar_fsm_tick) */
static uint32_t s_mate_lost_since_ms;
/* D1: RECEPTION entered and DOCK (capture_confirmed) not yet accepted. An
 * abort or a fault recovery must not land in SOFT_DOCKED past that refusal:
 * with the latches popped it releases the probe instead. */
static bool s_dock_unconfirmed;
static uint32_t s_valve_wait_since_ms;

oibar_v1_State oibar_fsm_state(void) { return s_state; }
bool oibar_fsm_transfer_armed(void) { return s_armed; }
bool oibar_fsm_transfer_started(void) { return s_started; }
float oibar_fsm_target_kpa(void) { return s_target_kpa; }
bool oibar_fsm_capture_ok(void) { return s_capture_ok; }

/* --- guards: NACK_NONE when the guard holds ----------------------------- */
static bool at_home(void)
{
    return oibar_plane_is_retracted() && oibar_input(HAL_DI_LATCH_HOME) &&
           !oibar_input(HAL_DI_CONTACT) && !oibar_input(HAL_DI_LATCH_ENGAGED);
}

static bool transfer_ready(void)
{
    return oibar_input(HAL_DI_CONNECTOR_MATED) && oibar_input(HAL_DI_LATCH_ENGAGED) &&
           oibar_plane_is_extended() && oibar_pressure_all_ok() && !oibar_pressure_over() &&
           oibar_app_host_link_alive() && !oibar_valves_any_sensed_open() &&
           oibar_fault_flags() == 0u;
}

static oibar_v1_NackReason pre(bool ok)
{
    return ok ? oibar_v1_NACK_NONE : oibar_v1_NACK_PRECONDITION_FAILED;
}

static oibar_v1_NackReason guard(oibar_guard_t g)
{
    switch (g) {
    case GUARD_NONE:
        return oibar_v1_NACK_NONE;
    case GUARD_AT_HOME:
        return pre(at_home());
    case GUARD_NOT_AT_HOME:
        return pre(!at_home());
    case GUARD_READY_FOR_APPROACH:
        return pre(at_home() && oibar_pressure_all_ok() && oibar_fault_flags() == 0u &&
                   !oibar_valves_any_sensed_open());
    case GUARD_CAPTURE_CONFIRMED:
        return pre(s_capture_ok && oibar_input(HAL_DI_CONTACT) &&
                   oibar_input(HAL_DI_LATCH_ENGAGED));
    case GUARD_SOFT_DOCK_HELD:
        /* The plane must not carry the couplings into their venting travel while a valve
         * reads open (before the valve monitor has called it a fault). */
        return pre(oibar_input(HAL_DI_CONTACT) && oibar_input(HAL_DI_LATCH_ENGAGED) &&
                   oibar_plane_is_retracted() && oibar_pressure_all_ok() &&
                   !oibar_valves_any_sensed_open() && !oibar_valves_mismatch());
    case GUARD_CONNECTOR_MATED:
        return pre(oibar_input(HAL_DI_CONNECTOR_MATED));
    case GUARD_PLANE_EXTENDED:
        return pre(oibar_plane_is_extended());
    case GUARD_LATCH_ENGAGED:
        return pre(oibar_input(HAL_DI_LATCH_ENGAGED));
    case GUARD_LATCH_NOT_ENGAGED:
        return pre(!oibar_input(HAL_DI_LATCH_ENGAGED));
    case GUARD_SOFT_DOCK_CONFIRMED:
        return pre(oibar_input(HAL_DI_LATCH_ENGAGED) && !s_dock_unconfirmed);
    case GUARD_TRANSFER_READY: {
        /* SAFETY_RULE_PREARM_CHECKS: the reason names the failed check. */
        oibar_v1_NackReason r = oibar_safety_prearm();
        return (r != oibar_v1_NACK_NONE) ? r : pre(transfer_ready());
    }
    case GUARD_START_OK: {
        float t = s_cmd_target_kpa;
        /* The argument first: a bad target is the host's error whatever
         * the hardware says. The target must stay below the trip point. */
        if (!isfinite(t) || t < oibar_param_f(PARAM_TARGET_MIN_KPA) ||
            t > oibar_param_f(PARAM_TARGET_MAX_KPA) || t >= oibar_param_f(PARAM_OVERPRESSURE_KPA)) {
            return oibar_v1_NACK_BAD_ARGUMENT;
        }
        /* D6: the pre-arm checks again, right before the valves open (the
         * armed state lasts up to armed_timeout_ms). */
        oibar_v1_NackReason r = oibar_safety_prearm();
        if (r != oibar_v1_NACK_NONE) {
            return r;
        }
        /* D2, SAFETY_RULE_NO_BACKFLOW: gas must flow from the supply to the
         * target tank; with the supply lower the fill runs backwards. */
        const bool head = oibar_pressure_kpa(OIBAR_PSENS_SV) >=
                          oibar_pressure_kpa(OIBAR_PSENS_TV) + OIBAR_FLOW_MIN_HEAD_KPA;
        return pre(s_armed && transfer_ready() && head);
    }
    case GUARD_FAULT_CAUSES_GONE:
        return pre(oibar_pressure_all_ok() && !oibar_pressure_over() && !oibar_valves_mismatch() &&
                   !oibar_valves_any_sensed_open() && oibar_app_host_link_alive() &&
                   oibar_latch_sensor_plausible() && oibar_plane_sense_plausible());
    case GUARD_VALVES_CLOSED:
        /* SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN: the valve monitor needs its
         * debounce time to call a stuck valve a fault; until then a valve that
         * still reads open must keep the fluid couplings mated, or fuel vents.
         * Every CMD_SEPARATE row carries it: HARD_DOCKING's did not, and the
         * property test retracted a plane at 34.7 mm with a valve open. */
        return pre(!oibar_valves_any_sensed_open() && !oibar_valves_mismatch());
    case GUARD_COUNT:
    default:
        break;
    }
    (void)OIBAR_REQUIRE(false);
    return oibar_v1_NACK_PRECONDITION_FAILED;
}

/* --- actions ------------------------------------------------------------ */
static void fault_now(oibar_v1_FaultCode code)
{
    oibar_valves_close_all(); /* SAFETY_RULE_FAULT_CLOSES_VALVES_AND_REPORTS */
    oibar_fault_latch(code);
    oibar_app_emit(oibar_v1_EVT_FAULT, oibar_v1_SEVERITY_WARNING_HI, s_state, s_state, code,
                   oibar_v1_NACK_NONE, 0u);
}

static void action(oibar_action_t a, uint32_t now_ms)
{
    switch (a) {
    case ACT_NONE:
        break;
    case ACT_RECORD_CAPTURE:
        s_capture_ok = oibar_app_capture_envelope_ok(now_ms);
        break;
    case ACT_ARM:
        s_armed = true;
        break;
    case ACT_START_TRANSFER:
        s_target_kpa = s_cmd_target_kpa;
        s_started = true;
        break;
    case ACT_REPORT_TRANSFER_COMPLETE:
        oibar_app_emit(oibar_v1_EVT_TRANSFER_COMPLETE, oibar_v1_SEVERITY_ACTIVITY_HI, s_state,
                       s_state, oibar_v1_FAULT_NONE, oibar_v1_NACK_NONE,
                       (uint32_t)oibar_pressure_kpa(OIBAR_PSENS_TV));
        break;
    case ACT_LATCH_FAULT:
        fault_now((oibar_v1_FaultCode)s_sig_arg);
        break;
    case ACT_FAULT_LATCH_TIMEOUT:
        fault_now(oibar_v1_FAULT_LATCH_TIMEOUT);
        break;
    case ACT_FAULT_PLANE_TIMEOUT:
        fault_now(oibar_v1_FAULT_PLANE_TIMEOUT);
        break;
    case ACT_FAULT_CONNECTOR_LOST:
        fault_now(oibar_v1_FAULT_CONNECTOR_LOST);
        break;
    case ACT_FAULT_LATCH_LOST:
        fault_now(oibar_v1_FAULT_LATCH_LOST);
        break;
    case ACT_FAULT_HOST_LINK_LOSS:
        fault_now(oibar_v1_FAULT_HOST_LINK_LOSS);
        break;
    case ACT_RETRACT_PLANE:
        oibar_plane_retract(now_ms);
        break;
    case ACT_FAULT_VALVE_MISMATCH:
        fault_now(oibar_v1_FAULT_VALVE_MISMATCH);
        break;
    case ACT_FAULT_RESET_AWAY_FROM_HOME:
        fault_now(oibar_v1_FAULT_RESET_AWAY_FROM_HOME);
        break;
    case ACT_CLEAR_FAULTS:
        oibar_fault_clear_all();
        oibar_app_emit(oibar_v1_EVT_FAULT_CLEARED, oibar_v1_SEVERITY_ACTIVITY_HI, s_state,
                       s_state, oibar_v1_FAULT_NONE, oibar_v1_NACK_NONE, 0u);
        break;
    case ACT_COUNT:
    default:
        (void)OIBAR_REQUIRE(false);
        break;
    }
}

/* --- one entry handler per state (the diagram's boxes) ------------------ */
typedef void (*entry_fn)(uint32_t now_ms);

/* Nothing energised; the self test runs for boot_settle_ms. */
static void entry_boot(uint32_t now_ms)
{
    (void)now_ms;
    oibar_plane_stop();
    oibar_stepper_disable();
}

/* Safe: valves closed (by enter()), plane and stepper de-energised. */
static void entry_idle(uint32_t now_ms)
{
    (void)now_ms;
    oibar_plane_stop();
    oibar_stepper_disable();
}

/* Latch at home, springs free to pop: wait for the probe. */
static void entry_approach_ready(uint32_t now_ms)
{
    (void)now_ms;
    s_capture_ok = false;
}

/* Probe in the drogue: wait for the latches and the host's confirmation. */
static void entry_reception(uint32_t now_ms) { (void)now_ms; }

/* Latched behind the cavity; plane retracted. */
static void entry_soft_docked(uint32_t now_ms)
{
    (void)now_ms;
    oibar_plane_stop();
    oibar_stepper_disable();
}

static void entry_hard_docking(uint32_t now_ms) { oibar_plane_extend(now_ms); }

/* Plane mated; the lead screw holds it, the motor is off. */
static void entry_hard_docked(uint32_t now_ms)
{
    (void)now_ms;
    oibar_plane_stop();
}

static void entry_transfer_armed(uint32_t now_ms) { (void)now_ms; }

static void entry_transferring(uint32_t now_ms)
{
    if (!oibar_ploop_start(s_target_kpa, now_ms) && !oibar_fault_any_pending()) {
        /* The guard said yes and the interlock says no: a broken contract
         * (unless an interrupt raised a fault in between: the valve driver
         * refuses then, SAFETY_RULE_VALVE_OPEN_ATOMIC, and that fault is
         * the one to report). */
        oibar_fault_raise(oibar_v1_FAULT_ASSERTION);
    }
}

static void entry_unmating(uint32_t now_ms) { oibar_plane_retract(now_ms); }

static void entry_latch_release(uint32_t now_ms)
{
    (void)now_ms;
    (void)oibar_stepper_release_latch();
}

/* The stepper keeps the latch released (holding torque) while the
 * spring-damper pushes the probe out. */
static void entry_separating(uint32_t now_ms)
{
    (void)now_ms;
    if (!oibar_input(HAL_DI_CONTACT)) {
        (void)oibar_evtq_post(SIG_CONTACT_LOST, 0u); /* already out */
    }
}

static void entry_latch_reset(uint32_t now_ms)
{
    (void)now_ms;
    (void)oibar_stepper_home();
}

/* Safing: valves closed (by enter()), stepper off, plane back -- but
 * SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN: while any valve reads open (wherever
 * the position sensor says the plane is) the plane holds until both read
 * closed (SIG_VALVES_CLOSED, then the retract_plane action). A valve still reading open after valve_mismatch_ms
 * (SIG_VALVES_STUCK) is a fault, with the plane held where it is. */
static void entry_aborting(uint32_t now_ms)
{
    oibar_stepper_disable();
    if (oibar_valves_any_sensed_open()) {
        oibar_plane_stop();
        s_valve_wait = true;
        s_valve_wait_since_ms = now_ms;
    } else {
        oibar_plane_retract(now_ms);
    }
}

/* Safe and still: valves closed, nothing driven -- except a plane that would
 * otherwise stop half-mated next to a valve that reads open.
 * SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN: the couplings seal at full mate
 * and self-seal when apart (below plane_coupling_mm), but vent in between; a
 * valve stuck open while unmating must not leave them there, so the plane
 * re-seats (extends to its switch, bounded by the plane move timeout). Below
 * the coupling travel, stopping is the safe choice: moving on would cross the
 * venting zone. Found by the HIL fault matrix (valve_stuck_open@unmating). */
static void entry_fault(uint32_t now_ms)
{
    oibar_stepper_disable();
    /* D3/D9: never moved on a stale or implausible position (a failed
     * sensor, both end switches): it stops where it is. */
    const bool half_mated = oibar_plane_sense_plausible() && !oibar_plane_is_extended() &&
                            oibar_plane_pos_mm() >= oibar_param_f(PARAM_PLANE_COUPLING_MM);
    if (oibar_valves_any_sensed_open() && half_mated) {
        oibar_plane_extend(now_ms);
    } else {
        oibar_plane_stop();
    }
}

typedef struct {
    entry_fn entry;
    oibar_param_id_t timeout_param; /* 0: the state waits for nobody's hardware */
} state_desc_t;

static const state_desc_t k_states[OIBAR_STATE_LAST + 1u] = {
    [oibar_v1_STATE_UNSPECIFIED] = { NULL, (oibar_param_id_t)0 },
    [oibar_v1_STATE_BOOT] = { entry_boot, PARAM_BOOT_SETTLE_MS },
    [oibar_v1_STATE_IDLE] = { entry_idle, (oibar_param_id_t)0 },
    [oibar_v1_STATE_APPROACH_READY] = { entry_approach_ready, PARAM_APPROACH_READY_TIMEOUT_MS },
    [oibar_v1_STATE_RECEPTION] = { entry_reception, PARAM_RECEPTION_TIMEOUT_MS },
    [oibar_v1_STATE_SOFT_DOCKED] = { entry_soft_docked, (oibar_param_id_t)0 },
    [oibar_v1_STATE_HARD_DOCKING] = { entry_hard_docking, PARAM_HARD_DOCKING_TIMEOUT_MS },
    [oibar_v1_STATE_HARD_DOCKED] = { entry_hard_docked, (oibar_param_id_t)0 },
    [oibar_v1_STATE_TRANSFER_ARMED] = { entry_transfer_armed, PARAM_TRANSFER_ARMED_TIMEOUT_MS },
    /* TRANSFERRING: the pressure loop's transfer_max_ms is the timeout. */
    [oibar_v1_STATE_TRANSFERRING] = { entry_transferring, (oibar_param_id_t)0 },
    /* UNMATING: the plane driver's plane_move_timeout_ms is the timeout. */
    [oibar_v1_STATE_UNMATING] = { entry_unmating, (oibar_param_id_t)0 },
    [oibar_v1_STATE_LATCH_RELEASE] = { entry_latch_release, PARAM_LATCH_MOVE_TIMEOUT_MS },
    [oibar_v1_STATE_SEPARATING] = { entry_separating, PARAM_SEPARATING_TIMEOUT_MS },
    [oibar_v1_STATE_LATCH_RESET] = { entry_latch_reset, PARAM_LATCH_MOVE_TIMEOUT_MS },
    [oibar_v1_STATE_ABORTING] = { entry_aborting, PARAM_ABORT_TIMEOUT_MS },
    [oibar_v1_STATE_FAULT] = { entry_fault, (oibar_param_id_t)0 },
};

unsigned oibar_fsm_state_timeout_param(unsigned state)
{
    return (state >= OIBAR_STATE_FIRST && state <= OIBAR_STATE_LAST)
               ? (unsigned)k_states[state].timeout_param
               : 0u;
}

static void enter(oibar_v1_State next, uint32_t now_ms)
{
    oibar_v1_State from = s_state;
    s_state = next;
    if (next != oibar_v1_STATE_TRANSFER_ARMED && next != oibar_v1_STATE_TRANSFERRING) {
        s_armed = false; /* SAFETY_RULE_VALVES_NEED_ARM_THEN_START: arming is one-shot */
    }
    if (next != oibar_v1_STATE_TRANSFERRING) {
        s_started = false;
        oibar_ploop_stop(); /* valves open in TRANSFERRING only */
    }
    s_timer_armed = false;
    s_valve_wait = false;
    s_mate_lost = false;
    if (next == oibar_v1_STATE_RECEPTION) {
        s_dock_unconfirmed = true;
    } else if (next == oibar_v1_STATE_SOFT_DOCKED || next == oibar_v1_STATE_IDLE ||
               next == oibar_v1_STATE_APPROACH_READY || next == oibar_v1_STATE_LATCH_RELEASE ||
               next == oibar_v1_STATE_LATCH_RESET) {
        s_dock_unconfirmed = false; /* docked by DOCK, or the probe let go */
    }
    const state_desc_t *d = &k_states[next];
    if (d->timeout_param != (oibar_param_id_t)0) {
        s_deadline_ms = now_ms + oibar_param_u32(d->timeout_param);
        s_timer_armed = true;
    }
    oibar_app_emit(oibar_v1_EVT_STATE_CHANGE, oibar_v1_SEVERITY_ACTIVITY_LO, from, next,
                   oibar_v1_FAULT_NONE, oibar_v1_NACK_NONE, 0u);
    d->entry(now_ms);
}

void oibar_fsm_init(uint32_t now_ms)
{
    s_state = oibar_v1_STATE_UNSPECIFIED;
    s_armed = false;
    s_started = false;
    s_target_kpa = 0.0f;
    s_capture_ok = false;
    s_cmd_target_kpa = 0.0f;
    s_sig_arg = 0;
    s_valve_wait = false;
    s_valve_wait_since_ms = 0;
    s_mate_lost = false;
    s_mate_lost_since_ms = 0;
    s_dock_unconfirmed = false;
    enter(oibar_v1_STATE_BOOT, now_ms);
}

/* Find and run the row for `event`. Returns NACK_NONE when a row ran;
 * otherwise the first failing guard's reason, or NACK_UNKNOWN_MESSAGE as a
 * private marker for "no row at all". */
#define NO_ROW oibar_v1_NACK_UNKNOWN_MESSAGE

static oibar_v1_NackReason dispatch(uint8_t event, uint32_t now_ms)
{
    oibar_v1_NackReason first_fail = NO_ROW;
    const oibar_fsm_row_t *hit = NULL;
    /* The state, its superstates outwards, then ANY: the first level with a
     * row for the event decides (bounded: the hierarchy has no cycles). */
    unsigned level = (unsigned)s_state;
    for (unsigned depth = 0; depth <= OIBAR_FSM_NODE_LAST && hit == NULL && first_fail == NO_ROW;
         depth++) {
        for (unsigned i = 0; i < TABLE_ROWS; i++) {
            const oibar_fsm_row_t *r = &k_table[i];
            if (r->state != level || r->event != event) {
                continue;
            }
            oibar_v1_NackReason g = guard((oibar_guard_t)r->guard);
            if (g == oibar_v1_NACK_NONE) {
                hit = r;
                break;
            }
            if (first_fail == NO_ROW) {
                first_fail = g;
            }
        }
        if (level == OIBAR_FSM_ANY) {
            break;
        }
        level = oibar_fsm_parent(level);
    }
    if (hit == NULL) {
        return first_fail;
    }
    action((oibar_action_t)hit->action, now_ms);
    if (hit->next != STAY) {
        enter((oibar_v1_State)hit->next, now_ms);
    }
    return oibar_v1_NACK_NONE;
}

void oibar_fsm_signal(oibar_sig_t sig, uint16_t arg, uint32_t now_ms)
{
    /* Completions of an earlier move are stale: only the current one counts. */
    if ((sig == SIG_PLANE_EXTENDED || sig == SIG_PLANE_RETRACTED) && arg != oibar_plane_move_id()) {
        return;
    }
    if (sig == SIG_STEPPER_DONE && arg != oibar_stepper_move_id()) {
        return;
    }
    s_sig_arg = arg;
    (void)dispatch((uint8_t)sig, now_ms);
}

oibar_v1_NackReason oibar_fsm_command(oibar_v1_CommandOpcode op, float target_kpa, uint32_t now_ms)
{
    if ((unsigned)op < OIBAR_CMD_FIRST || (unsigned)op > OIBAR_CMD_LAST) {
        return oibar_v1_NACK_UNKNOWN_OPCODE;
    }
    s_cmd_target_kpa = target_kpa;
    oibar_v1_NackReason r = dispatch(OIBAR_FSM_EV_CMD(op), now_ms);
    if (r == NO_ROW) {
        r = (s_state == oibar_v1_STATE_FAULT) ? oibar_v1_NACK_FAULT_ACTIVE
                                               : oibar_v1_NACK_INVALID_IN_STATE;
    }
    return r;
}

/* FMEA SW-EXT-STUCK: HARD_DOCKED and TRANSFER_ARMED rest on full mate, which
 * HARD_DOCKING established with both witnesses (the extended end switch and
 * the position sensor at OIBAR_PLANE_MATED_MIN_MM, drv_plane.c), and nothing
 * drives the plane there. A witness that stops reading full mate (a switch
 * lost while the sensor reads mated, or the reverse) is a failed sensor or a
 * plane that moved: the valves' precondition (docs/firmware.md) can no longer
 * be shown, so it is FAULT_PLANE_POSITION, not a silent refusal of every ARM.
 * TRANSFERRING has the valve interlock (safety.c), which closes the valves
 * and raises the same fault at once. Held for OIBAR_PLANE_MATE_LOST_MS past
 * the switch's debounce so one sensor sample at the threshold is no fault. */
#define OIBAR_PLANE_MATE_LOST_MS 20u
static void mated_plane_check(uint32_t now_ms)
{
    const bool mated_state =
        s_state == oibar_v1_STATE_HARD_DOCKED || s_state == oibar_v1_STATE_TRANSFER_ARMED;
    if (!mated_state || oibar_plane_motion() != OIBAR_PLANE_STOPPED || oibar_plane_is_extended()) {
        s_mate_lost = false;
        return;
    }
    if (!s_mate_lost) {
        s_mate_lost = true;
        s_mate_lost_since_ms = now_ms;
    } else if (now_ms - s_mate_lost_since_ms >= OIBAR_PLANE_MATE_LOST_MS) {
        s_mate_lost = false;
        oibar_fault_raise(oibar_v1_FAULT_PLANE_POSITION);
    }
}

void oibar_fsm_tick(uint32_t now_ms)
{
    mated_plane_check(now_ms);
    if (s_valve_wait) {
        if (!oibar_valves_any_sensed_open()) {
            s_valve_wait = false;
            s_sig_arg = 0;
            (void)dispatch((uint8_t)SIG_VALVES_CLOSED, now_ms);
        } else if (now_ms - s_valve_wait_since_ms >= oibar_param_u32(PARAM_VALVE_MISMATCH_MS)) {
            s_valve_wait = false;
            s_sig_arg = 0;
            (void)dispatch((uint8_t)SIG_VALVES_STUCK, now_ms);
        }
    }
    if (s_timer_armed && (int32_t)(now_ms - s_deadline_ms) >= 0) {
        s_timer_armed = false;
        s_sig_arg = 0;
        (void)dispatch((uint8_t)SIG_TIMEOUT, now_ms);
    }
}
