/*
 * The docking state machine. One transition table (state x event -> guard,
 * next state, action) drives it; docs/state_table.md holds the same table
 * and a test keeps the two identical. Each state has one entry handler
 * (its entry actions) and at most one timeout parameter.
 *
 * Rules the table does not spell out (also stated in the doc):
 *  - rows for the current state are tried in order, the first whose guard
 *    holds wins; only when the state has no row for the event are the rows
 *    of its superstate tried (ACTIVE, DOCKED, MATED: QP/C-style hierarchical
 *    states, see oibar_fsm_parent), then the superstate's superstate, and
 *    last the ANY rows;
 *  - a command with no row is rejected with NACK_INVALID_IN_STATE
 *    (NACK_FAULT_ACTIVE in STATE_FAULT); a command whose guards all fail is
 *    rejected with the first guard's reason; a rejected command changes
 *    nothing;
 *  - a signal with no row, or whose guards all fail, is ignored.
 */
#ifndef OIBAR_APP_FSM_H
#define OIBAR_APP_FSM_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar.pb.h"
#include "oibar/app_events.h"

#define OIBAR_FSM_ANY 0u   /* state column: every state */
#define OIBAR_FSM_STAY 0u  /* next column: no transition (internal) */
#define OIBAR_STATE_FIRST 1u
#define OIBAR_STATE_LAST 15u
/* Superstates: table nodes that are never the current state. */
#define OIBAR_FSM_SUPER_ACTIVE 16u
#define OIBAR_FSM_SUPER_DOCKED 17u
#define OIBAR_FSM_SUPER_MATED 18u
#define OIBAR_FSM_NODE_LAST 18u
#define OIBAR_CMD_FIRST 1u
#define OIBAR_CMD_LAST 12u
/* Table event ids: signals keep their value, commands are offset. */
#define OIBAR_FSM_EV_CMD_BASE 32u
#define OIBAR_FSM_EV_CMD(op) ((uint8_t)(OIBAR_FSM_EV_CMD_BASE + (unsigned)(op)))
#define OIBAR_FSM_EV_LIMIT (OIBAR_FSM_EV_CMD_BASE + OIBAR_CMD_LAST + 1u)

typedef enum {
    GUARD_NONE = 0,
    GUARD_AT_HOME,
    GUARD_NOT_AT_HOME,
    GUARD_READY_FOR_APPROACH,
    GUARD_CAPTURE_CONFIRMED,
    GUARD_SOFT_DOCK_HELD,
    GUARD_CONNECTOR_MATED,
    GUARD_PLANE_EXTENDED,
    GUARD_LATCH_ENGAGED,
    GUARD_LATCH_NOT_ENGAGED,
    GUARD_TRANSFER_READY,
    GUARD_START_OK,
    GUARD_FAULT_CAUSES_GONE,
    GUARD_VALVES_CLOSED,
    GUARD_SOFT_DOCK_CONFIRMED,
    GUARD_COUNT
} oibar_guard_t;

typedef enum {
    ACT_NONE = 0,
    ACT_RECORD_CAPTURE,
    ACT_ARM,
    ACT_START_TRANSFER,
    ACT_REPORT_TRANSFER_COMPLETE,
    ACT_LATCH_FAULT,
    ACT_FAULT_LATCH_TIMEOUT,
    ACT_FAULT_PLANE_TIMEOUT,
    ACT_FAULT_CONNECTOR_LOST,
    ACT_FAULT_LATCH_LOST,
    ACT_FAULT_HOST_LINK_LOSS,
    ACT_CLEAR_FAULTS,
    ACT_RETRACT_PLANE,
    ACT_FAULT_VALVE_MISMATCH,
    ACT_FAULT_RESET_AWAY_FROM_HOME,
    ACT_COUNT
} oibar_action_t;

typedef struct {
    uint8_t state;   /* oibar_v1_State, a superstate or OIBAR_FSM_ANY */
    uint8_t event;   /* oibar_sig_t or OIBAR_FSM_EV_CMD(opcode) */
    uint8_t guard;   /* oibar_guard_t */
    uint8_t next;    /* oibar_v1_State or OIBAR_FSM_STAY */
    uint8_t action;  /* oibar_action_t */
} oibar_fsm_row_t;

const oibar_fsm_row_t *oibar_fsm_table(unsigned *rows);

/* Names as written in docs/state_table.md. */
const char *oibar_fsm_state_name(unsigned state);   /* "STATE_IDLE", 0 -> "ANY" */
const char *oibar_fsm_next_name(unsigned next);     /* 0 -> "-" */
const char *oibar_fsm_event_name(unsigned event);   /* "SIG_CONTACT", "CMD_DOCK" */
const char *oibar_fsm_guard_name(unsigned guard);   /* GUARD_NONE -> "-" */
const char *oibar_fsm_action_name(unsigned action); /* ACT_NONE -> "-" */
/* Superstate of a state or superstate (OIBAR_FSM_ANY: none). */
unsigned oibar_fsm_parent(unsigned node);
/* Timeout parameter of a state (0 when it has none). */
unsigned oibar_fsm_state_timeout_param(unsigned state);

/* Enter STATE_BOOT. */
void oibar_fsm_init(uint32_t now_ms);
oibar_v1_State oibar_fsm_state(void);
/* Main loop. */
void oibar_fsm_signal(oibar_sig_t sig, uint16_t arg, uint32_t now_ms);
oibar_v1_NackReason oibar_fsm_command(oibar_v1_CommandOpcode op, float target_kpa, uint32_t now_ms);
/* Main loop, once per ms: the state timeout. */
void oibar_fsm_tick(uint32_t now_ms);

/* Arm-then-start bookkeeping, read by the safety interlock. */
bool oibar_fsm_transfer_armed(void);
bool oibar_fsm_transfer_started(void);
float oibar_fsm_target_kpa(void);
/* Capture conditions recorded at probe contact. */
bool oibar_fsm_capture_ok(void);

#endif
