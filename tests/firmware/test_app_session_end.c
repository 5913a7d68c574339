/* CMD_END_SESSION (issue 60 item 4): the host's planned end. In every state
 * the valves are closed, a transfer stops, mated states hold, moving unmated
 * states take the abort path (never past a guard: D1), and once accepted the
 * host link going quiet is not FAULT_HOST_LINK_LOSS. An unplanned loss, or a
 * loss after the host took the mechanism up again, still faults. */
#include <string.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_events.h"
#include "oibar/app_faults.h"
#include "oibar/app_link.h"
#include "oibar/frame.h"
#include "oibar/link.h"
#include "unity.h"

#define LINK_FAULT_BIT (1u << (oibar_v1_FAULT_HOST_LINK_LOSS - 1u))

void setUp(void) {}
void tearDown(void) {}

static bool saw_fault_event(void)
{
    oibar_v1_Event ev;
    bool fault = false;
    while (oibar_app_next_event(&ev)) {
        fault = fault || ev.id == oibar_v1_EVT_FAULT;
    }
    return fault;
}

static void drain_events(void) { (void)saw_fault_event(); }

/* Host silent from now on: the link layer reports the loss (as link.c does
 * after link_timeout_ms); `ms` more milliseconds run. */
static void host_goes_quiet(uint32_t ms)
{
    oibar_app_link_state(false);
    fake_hal_advance_ms(ms);
}

/* --- what END_SESSION does in each state --------------------------------- */

static void test_transferring_stops_the_transfer_and_holds_mated(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFERRING, oibar_app_state());
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    const float plane_mm = fake_plant_plane_mm();
    drain_events();
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_END_SESSION, 0.0f));
    /* Valves first: closed when the command returns. */
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    host_goes_quiet(3000);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    TEST_ASSERT_EQUAL_UINT32(0u, oibar_fault_flags());
    TEST_ASSERT_FALSE(saw_fault_event());
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_FLOAT_WITHIN(0.5f, plane_mm, fake_plant_plane_mm()); /* held where it is */
}

static void test_transfer_armed_disarms_and_holds(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_END_SESSION, 0.0f));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    host_goes_quiet(3000);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    TEST_ASSERT_EQUAL_UINT32(0u, oibar_fault_flags());
    /* Arming is one-shot: START now is refused. */
    TEST_ASSERT_NOT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500.0f));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

static void test_docked_states_hold(void)
{
    const oibar_v1_State held[] = { oibar_v1_STATE_SOFT_DOCKED, oibar_v1_STATE_HARD_DOCKED };
    for (unsigned i = 0; i < sizeof held / sizeof held[0]; i++) {
        TEST_ASSERT_TRUE(bench_goto(held[i]));
        TEST_ASSERT_EQUAL(held[i], oibar_app_state());
        const float plane_mm = fake_plant_plane_mm();
        const int32_t latch = fake_plant_latch_steps();
        TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_END_SESSION, 0.0f));
        host_goes_quiet(5000);
        TEST_ASSERT_EQUAL(held[i], oibar_app_state());
        TEST_ASSERT_EQUAL_UINT32(0u, oibar_fault_flags());
        TEST_ASSERT_FLOAT_WITHIN(0.5f, plane_mm, fake_plant_plane_mm());
        TEST_ASSERT_EQUAL_INT32(latch, fake_plant_latch_steps());
    }
}

static void test_approach_ready_disarms_to_idle(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_APPROACH_READY));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_END_SESSION, 0.0f));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
    host_goes_quiet(2000);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
    TEST_ASSERT_EQUAL_UINT32(0u, oibar_fault_flags());
}

/* Moving and not mated: the abort path. From HARD_DOCKING the plane comes
 * back and the latched, confirmed dock holds (SOFT_DOCKED). */
static void test_hard_docking_retracts_to_soft_docked(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKING));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKING, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_END_SESSION, 0.0f));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_ABORTING, oibar_app_state());
    host_goes_quiet(0);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_SOFT_DOCKED, 10000u));
    fake_hal_advance_ms(2000);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_SOFT_DOCKED, oibar_app_state());
    TEST_ASSERT_EQUAL_UINT32(0u, oibar_fault_flags());
}

/* D1: from RECEPTION without an accepted DOCK, the planned end never lands
 * in SOFT_DOCKED past the refused capture guard: it releases the probe and
 * homes, like ABORT, and without a host. */
static void test_reception_unconfirmed_releases_and_homes(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_RECEPTION));
    fake_hal_advance_ms(150); /* latches pop and debounce */
    TEST_ASSERT_EQUAL(oibar_v1_STATE_RECEPTION, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_END_SESSION, 0.0f));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_ABORTING, oibar_app_state());
    host_goes_quiet(0);
    bool soft_docked = false;
    for (unsigned t = 0; t < 20000u && oibar_app_state() != oibar_v1_STATE_IDLE; t++) {
        if (oibar_app_state() == oibar_v1_STATE_SEPARATING) {
            fake_plant_set_probe(false); /* the spring pushes the probe out */
        }
        soft_docked = soft_docked || oibar_app_state() == oibar_v1_STATE_SOFT_DOCKED;
        fake_hal_advance_ms(1);
    }
    TEST_ASSERT_FALSE(soft_docked);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
    TEST_ASSERT_EQUAL_UINT32(0u, oibar_fault_flags());
}

/* Safe states stay as they are; a latched fault stays latched. */
static void test_safe_states_accept_and_stay(void)
{
    const oibar_v1_State safe[] = { oibar_v1_STATE_IDLE, oibar_v1_STATE_FAULT };
    for (unsigned i = 0; i < sizeof safe / sizeof safe[0]; i++) {
        TEST_ASSERT_TRUE(bench_goto(safe[i]));
        const uint32_t flags = oibar_fault_flags();
        TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_END_SESSION, 0.0f));
        TEST_ASSERT_EQUAL(safe[i], oibar_app_state());
        host_goes_quiet(2000);
        TEST_ASSERT_EQUAL(safe[i], oibar_app_state());
        TEST_ASSERT_EQUAL_UINT32(flags, oibar_fault_flags());
    }
}

/* --- an unplanned loss still faults ------------------------------------- */

static void test_loss_without_end_session_still_faults(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    host_goes_quiet(20);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE((oibar_fault_flags() & LINK_FAULT_BIT) != 0u);
}

static void test_a_command_after_end_session_takes_the_session_up_again(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_IDLE));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_END_SESSION, 0.0f));
    TEST_ASSERT_TRUE(oibar_app_session_ended());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_NOOP, 0.0f));
    TEST_ASSERT_TRUE(oibar_app_session_ended()); /* a liveness check changes nothing */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0.0f));
    TEST_ASSERT_FALSE(oibar_app_session_ended());
    host_goes_quiet(20);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE((oibar_fault_flags() & LINK_FAULT_BIT) != 0u);
}

static void test_a_new_handshake_ends_the_planned_end(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_END_SESSION, 0.0f));
    oibar_app_link_state(true); /* a host handshakes again */
    TEST_ASSERT_FALSE(oibar_app_session_ended());
    host_goes_quiet(20);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
}

static void test_a_refused_end_session_is_no_planned_end(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_UNKNOWN_OPCODE, oibar_app_command((oibar_v1_CommandOpcode)200, 0.0f));
    TEST_ASSERT_FALSE(oibar_app_session_ended());
    host_goes_quiet(20);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
}

/* --- end to end through the real link layer ------------------------------ */

static oibar_link_t s_link;
static uint8_t s_out[16384];
static size_t s_out_len;
static uint32_t s_seq;

static bool port_send(void *ctx, const uint8_t *bytes, size_t len)
{
    (void)ctx;
    if (s_out_len + len > sizeof s_out) {
        s_out_len = 0;
    }
    memcpy(s_out + s_out_len, bytes, len);
    s_out_len += len;
    return true;
}

static void link_main_loop(void) { oibar_app_link_run_once(&s_link); }

static void host_send(oibar_v1_Packet *p)
{
    uint8_t frame[OIBAR_FRAME_MAX_WIRE_BYTES];
    p->seq = ++s_seq;
    size_t n = oibar_frame_encode(p, frame, sizeof frame);
    TEST_ASSERT_TRUE(n > 0u);
    for (size_t i = 0; i < n; i++) {
        oibar_link_rx_isr(&s_link, frame[i]);
    }
}

static bool acked(uint32_t seq, oibar_v1_Ack *ack)
{
    oibar_frame_decoder_t dec;
    oibar_frame_decoder_init(&dec, 0xFFFFFFFFu);
    bool found = false;
    for (size_t i = 0; i < s_out_len; i++) {
        oibar_v1_Packet p;
        if (oibar_frame_decoder_feed(&dec, s_out[i], &p) == OIBAR_RX_PACKET &&
            p.which_body == oibar_v1_Packet_ack_tag && p.ack_seq == seq) {
            *ack = p.body.ack;
            found = true;
        }
    }
    s_out_len = 0;
    return found;
}

static void attach_link(void)
{
    oibar_link_config_t cfg;
    oibar_link_config_defaults(&cfg);
    oibar_link_port_t port = { port_send, NULL };
    oibar_link_init(&s_link, &cfg, &port, oibar_app_link_callbacks());
    fake_hal_set_main_loop(link_main_loop);
    s_out_len = 0;
    s_seq = 0;
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_handshake_tag;
    p.body.handshake.protocol_version = oibar_v1_Protocol_PROTOCOL_VERSION;
    host_send(&p);
    fake_hal_advance_ms(2);
    TEST_ASSERT_TRUE(oibar_app_host_link_alive());
}

static void test_over_the_link_a_planned_end_then_silence_is_not_a_fault(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    attach_link();
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_command_tag;
    p.body.command.opcode = oibar_v1_CMD_END_SESSION;
    s_out_len = 0;
    host_send(&p);
    fake_hal_advance_ms(2);
    oibar_v1_Ack ack = oibar_v1_Ack_init_zero;
    TEST_ASSERT_TRUE(acked(s_seq, &ack));
    TEST_ASSERT_TRUE(ack.accepted);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, ack.state);
    drain_events();
    fake_hal_advance_ms(2500); /* the host closes its port: link_timeout_ms passes */
    TEST_ASSERT_FALSE(oibar_app_host_link_alive());
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    TEST_ASSERT_EQUAL_UINT32(0u, oibar_fault_flags());
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

static void test_over_the_link_silence_without_a_planned_end_faults(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    attach_link();
    fake_hal_advance_ms(2500);
    TEST_ASSERT_FALSE(oibar_app_host_link_alive());
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE((oibar_fault_flags() & LINK_FAULT_BIT) != 0u);
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_transferring_stops_the_transfer_and_holds_mated);
    RUN_TEST(test_transfer_armed_disarms_and_holds);
    RUN_TEST(test_docked_states_hold);
    RUN_TEST(test_approach_ready_disarms_to_idle);
    RUN_TEST(test_hard_docking_retracts_to_soft_docked);
    RUN_TEST(test_reception_unconfirmed_releases_and_homes);
    RUN_TEST(test_safe_states_accept_and_stay);
    RUN_TEST(test_loss_without_end_session_still_faults);
    RUN_TEST(test_a_command_after_end_session_takes_the_session_up_again);
    RUN_TEST(test_a_new_handshake_ends_the_planned_end);
    RUN_TEST(test_a_refused_end_session_is_no_planned_end);
    RUN_TEST(test_over_the_link_a_planned_end_then_silence_is_not_a_fault);
    RUN_TEST(test_over_the_link_silence_without_a_planned_end_faults);
    return UNITY_END();
}
