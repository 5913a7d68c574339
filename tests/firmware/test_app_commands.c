/* Every state x every command: accepted -> the expected next state;
 * rejected -> the expected reason and nothing changed. The expectations are
 * written here independently of the code's table (which test_app_state_table
 * ties to the doc). */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "unity.h"

void setUp(void) {}
void tearDown(void) {}

typedef struct {
    oibar_v1_NackReason reason;
    oibar_v1_State next; /* when accepted; 0 = unchanged */
} expect_t;

#define N_CMD 13 /* opcodes 0 .. 12 */
#define OK(s) { oibar_v1_NACK_NONE, oibar_v1_STATE_##s }
#define STAYS { oibar_v1_NACK_NONE, oibar_v1_STATE_UNSPECIFIED }
#define INV { oibar_v1_NACK_INVALID_IN_STATE, oibar_v1_STATE_UNSPECIFIED }
#define PRE { oibar_v1_NACK_PRECONDITION_FAILED, oibar_v1_STATE_UNSPECIFIED }
#define FLT { oibar_v1_NACK_FAULT_ACTIVE, oibar_v1_STATE_UNSPECIFIED }
#define UNK { oibar_v1_NACK_UNKNOWN_OPCODE, oibar_v1_STATE_UNSPECIFIED }

/* Columns: UNSPECIFIED NOOP APPROACH_ARM DOCK HARD_DOCK ARM_TRANSFER
 *          START_TRANSFER STOP_TRANSFER SEPARATE ABORT CLEAR_FAULT DISARM END_SESSION */
static const expect_t k_expect[16][N_CMD] = {
    [oibar_v1_STATE_BOOT] = { UNK, STAYS, INV, INV, INV, INV, INV, INV, INV, STAYS, INV, INV, STAYS },
    [oibar_v1_STATE_IDLE] = { UNK, STAYS, OK(APPROACH_READY), INV, INV, INV, INV, INV, INV, STAYS, INV, INV, STAYS },
    [oibar_v1_STATE_APPROACH_READY] = { UNK, STAYS, INV, INV, INV, INV, INV, INV, INV, OK(ABORTING), INV, INV, OK(IDLE) },
    /* Just after contact the latches have not popped yet. */
    [oibar_v1_STATE_RECEPTION] = { UNK, STAYS, INV, PRE, INV, INV, INV, INV, INV, OK(ABORTING), INV, INV, OK(ABORTING) },
    [oibar_v1_STATE_SOFT_DOCKED] = { UNK, STAYS, INV, INV, OK(HARD_DOCKING), INV, INV, INV, OK(UNMATING), OK(ABORTING), INV, INV, STAYS },
    [oibar_v1_STATE_HARD_DOCKING] = { UNK, STAYS, INV, INV, INV, INV, INV, INV, OK(UNMATING), OK(ABORTING), INV, INV, OK(ABORTING) },
    [oibar_v1_STATE_HARD_DOCKED] = { UNK, STAYS, INV, INV, INV, OK(TRANSFER_ARMED), INV, INV, OK(UNMATING), OK(ABORTING), INV, INV, STAYS },
    [oibar_v1_STATE_TRANSFER_ARMED] = { UNK, STAYS, INV, INV, INV, INV, OK(TRANSFERRING), INV, INV, OK(ABORTING), INV, OK(HARD_DOCKED), OK(HARD_DOCKED) },
    [oibar_v1_STATE_TRANSFERRING] = { UNK, STAYS, INV, INV, INV, INV, INV, OK(HARD_DOCKED), INV, OK(ABORTING), INV, INV, OK(HARD_DOCKED) },
    [oibar_v1_STATE_UNMATING] = { UNK, STAYS, INV, INV, INV, INV, INV, INV, INV, OK(ABORTING), INV, INV, OK(ABORTING) },
    [oibar_v1_STATE_LATCH_RELEASE] = { UNK, STAYS, INV, INV, INV, INV, INV, INV, INV, OK(ABORTING), INV, INV, OK(ABORTING) },
    [oibar_v1_STATE_SEPARATING] = { UNK, STAYS, INV, INV, INV, INV, INV, INV, INV, OK(ABORTING), INV, INV, OK(ABORTING) },
    [oibar_v1_STATE_LATCH_RESET] = { UNK, STAYS, INV, INV, INV, INV, INV, INV, INV, OK(ABORTING), INV, INV, OK(ABORTING) },
    [oibar_v1_STATE_ABORTING] = { UNK, STAYS, INV, INV, INV, INV, INV, INV, INV, STAYS, INV, INV, STAYS },
    [oibar_v1_STATE_FAULT] = { UNK, STAYS, FLT, FLT, FLT, FLT, FLT, FLT, FLT, STAYS, OK(ABORTING), FLT, STAYS },
};

static bool last_event_is_rejection(oibar_v1_CommandOpcode op, oibar_v1_NackReason r)
{
    oibar_v1_Event ev, last;
    bool any = false;
    while (oibar_app_next_event(&ev)) {
        last = ev;
        any = true;
    }
    return any && last.id == oibar_v1_EVT_COMMAND_REJECTED && last.reason == r &&
           last.arg == (uint32_t)op;
}

static void check(oibar_v1_State st, unsigned op)
{
    char msg[128];
    snprintf(msg, sizeof msg, "state %d opcode %u", (int)st, op);
    TEST_ASSERT_TRUE_MESSAGE(bench_goto(st), msg);
    bool outs[HAL_DO_COUNT];
    for (unsigned i = 0; i < HAL_DO_COUNT; i++) {
        outs[i] = fake_hal_do((hal_do_t)i);
    }
    uint32_t flags = oibar_fault_flags();
    oibar_v1_Event ev;
    while (oibar_app_next_event(&ev)) {
    }
    const expect_t *e = &k_expect[st][op];
    oibar_v1_NackReason r = oibar_app_command((oibar_v1_CommandOpcode)op, 1500.0f);
    TEST_ASSERT_EQUAL_INT_MESSAGE(e->reason, r, msg);
    if (r == oibar_v1_NACK_NONE) {
        oibar_v1_State want = (e->next == oibar_v1_STATE_UNSPECIFIED) ? st : e->next;
        TEST_ASSERT_EQUAL_INT_MESSAGE(want, oibar_app_state(), msg);
        return;
    }
    /* SAFETY_RULE_INVALID_COMMAND_CHANGES_NOTHING */
    TEST_ASSERT_EQUAL_INT_MESSAGE(st, oibar_app_state(), msg);
    for (unsigned i = 0; i < HAL_DO_COUNT; i++) {
        TEST_ASSERT_EQUAL_MESSAGE(outs[i], fake_hal_do((hal_do_t)i), msg);
    }
    TEST_ASSERT_EQUAL_UINT32_MESSAGE(flags, oibar_fault_flags(), msg);
    TEST_ASSERT_TRUE_MESSAGE(last_event_is_rejection((oibar_v1_CommandOpcode)op, r), msg);
}

static void test_every_state_every_command(void)
{
    for (unsigned st = 1; st <= 15; st++) {
        for (unsigned op = 0; op < N_CMD; op++) {
            check((oibar_v1_State)st, op);
        }
    }
}

static void test_unknown_opcodes_rejected_everywhere(void)
{
    for (unsigned st = 1; st <= 15; st++) {
        TEST_ASSERT_TRUE(bench_goto((oibar_v1_State)st));
        TEST_ASSERT_EQUAL(oibar_v1_NACK_UNKNOWN_OPCODE, oibar_app_command((oibar_v1_CommandOpcode)200, 0));
        TEST_ASSERT_EQUAL(oibar_v1_NACK_UNKNOWN_OPCODE, oibar_app_command((oibar_v1_CommandOpcode)255, 0));
        TEST_ASSERT_EQUAL(st, oibar_app_state());
    }
}

static void test_start_transfer_argument_bounds(void)
{
    const float bad[] = { -1.0f, 0.0f, 99.0f, 2401.0f, 2600.0f, 1e9f, NAN, INFINITY };
    for (unsigned i = 0; i < sizeof bad / sizeof bad[0]; i++) {
        TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
        TEST_ASSERT_EQUAL(oibar_v1_NACK_BAD_ARGUMENT, oibar_app_command(oibar_v1_CMD_START_TRANSFER, bad[i]));
        TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFER_ARMED, oibar_app_state());
        TEST_ASSERT_FALSE(bench_any_valve_driven());
    }
}

static void test_preconditions_refuse_with_reason(void)
{
    /* Arm while a valve reads open: refused. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_plant_override_di(HAL_DI_SV_VALVE_OPEN, 1); /* a valve reads open */
    fake_hal_advance_ms(20);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0));
    /* Approach arm with the probe already in contact: refused. */
    bench_start();
    fake_plant_set_probe(true);
    fake_hal_advance_ms(20);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED, oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
    /* Clearing a fault whose cause remains: refused. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_IDLE));
    fake_plant_override_adc(HAL_ADC_TV_TANK, 4095);
    fake_hal_advance_ms(30);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0));
    fake_plant_override_adc(HAL_ADC_TV_TANK, -1);
    fake_hal_advance_ms(30);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0));
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_IDLE, 3000));
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_every_state_every_command);
    RUN_TEST(test_unknown_opcodes_rejected_everywhere);
    RUN_TEST(test_start_transfer_argument_bounds);
    RUN_TEST(test_preconditions_refuse_with_reason);
    return UNITY_END();
}
