/* The application behind the real link layer: frames in, acks and events
 * out, link loss safes the mechanism. */
#include <string.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_events.h"
#include "oibar/app_link.h"
#include "oibar/frame.h"
#include "oibar/link.h"
#include "unity.h"

static oibar_link_t s_link;
static uint8_t s_out[16384];
static size_t s_out_len;
static uint32_t s_seq;

static bool port_send(void *ctx, const uint8_t *bytes, size_t len)
{
    (void)ctx;
    if (s_out_len + len > sizeof s_out) {
        s_out_len = 0; /* old traffic is of no interest */
    }
    memcpy(s_out + s_out_len, bytes, len);
    s_out_len += len;
    return true;
}

static void main_loop(void) { oibar_app_link_run_once(&s_link); }

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

/* Decode what the MCU sent; return the ack for `seq` (if any) and whether
 * an event with `id` was seen. */
static bool host_read(uint32_t seq, oibar_v1_Ack *ack, oibar_v1_EventId id, bool *saw)
{
    oibar_frame_decoder_t dec;
    oibar_frame_decoder_init(&dec, 0xFFFFFFFFu);
    bool found = false;
    for (size_t i = 0; i < s_out_len; i++) {
        oibar_v1_Packet p;
        if (oibar_frame_decoder_feed(&dec, s_out[i], &p) != OIBAR_RX_PACKET) {
            continue;
        }
        if (p.which_body == oibar_v1_Packet_ack_tag && p.ack_seq == seq && ack != NULL) {
            *ack = p.body.ack;
            found = true;
        }
        if (p.which_body == oibar_v1_Packet_event_tag && saw != NULL && p.body.event.id == id) {
            *saw = true;
        }
    }
    s_out_len = 0;
    return found;
}

static oibar_v1_Ack command(oibar_v1_CommandOpcode op, float target)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_command_tag;
    p.body.command.opcode = op;
    p.body.command.target_pressure_kpa = target;
    s_out_len = 0;
    host_send(&p);
    fake_hal_advance_ms(2);
    oibar_v1_Ack ack = oibar_v1_Ack_init_zero;
    TEST_ASSERT_TRUE_MESSAGE(host_read(s_seq, &ack, oibar_v1_EVT_UNSPECIFIED, NULL), "no ack");
    return ack;
}

void setUp(void)
{
    fake_hal_reset();
    fake_plant_enable(true);
    fake_hal_advance_ms(1);
    oibar_app_init();
    oibar_link_config_t cfg;
    oibar_link_config_defaults(&cfg);
    oibar_link_port_t port = { port_send, NULL };
    oibar_link_init(&s_link, &cfg, &port, oibar_app_link_callbacks());
    fake_hal_set_main_loop(main_loop);
    s_out_len = 0;
    s_seq = 0;
    fake_hal_advance_ms(200);
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_handshake_tag;
    p.body.handshake.protocol_version = oibar_v1_Protocol_PROTOCOL_VERSION;
    host_send(&p);
    fake_hal_advance_ms(2);
    TEST_ASSERT_TRUE(oibar_app_host_link_alive());
}
void tearDown(void) {}

static void test_commands_are_acked_with_state(void)
{
    oibar_v1_Ack a = command(oibar_v1_CMD_APPROACH_ARM, 0);
    TEST_ASSERT_TRUE(a.accepted);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_APPROACH_READY, a.state);
    a = command(oibar_v1_CMD_START_TRANSFER, 1500);
    TEST_ASSERT_FALSE(a.accepted);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_INVALID_IN_STATE, a.reason);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_APPROACH_READY, a.state);
}

static void test_events_reach_the_host(void)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_command_tag;
    p.body.command.opcode = oibar_v1_CMD_APPROACH_ARM;
    s_out_len = 0;
    host_send(&p);
    fake_hal_advance_ms(2);
    bool saw = false;
    (void)host_read(s_seq, NULL, oibar_v1_EVT_STATE_CHANGE, &saw);
    TEST_ASSERT_TRUE(saw);
}

static void test_link_loss_safes_the_mechanism(void)
{
    TEST_ASSERT_TRUE(command(oibar_v1_CMD_APPROACH_ARM, 0).accepted);
    /* Host silent, heartbeats stop: the link times out after 1 s. */
    fake_hal_advance_ms(1100);
    TEST_ASSERT_FALSE(oibar_app_host_link_alive());
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
}

static void test_params_over_the_link(void)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_param_set_tag;
    p.body.param_set.param_id = 6; /* debounce_ms */
    p.body.param_set.value = 15.0f;
    s_out_len = 0;
    host_send(&p);
    fake_hal_advance_ms(2);
    oibar_frame_decoder_t dec;
    oibar_frame_decoder_init(&dec, 0xFFFFFFFFu);
    bool found = false;
    for (size_t i = 0; i < s_out_len; i++) {
        oibar_v1_Packet r;
        if (oibar_frame_decoder_feed(&dec, s_out[i], &r) == OIBAR_RX_PACKET &&
            r.which_body == oibar_v1_Packet_param_value_tag && r.ack_seq == s_seq) {
            found = true;
            TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, r.body.param_value.reason);
            TEST_ASSERT_EQUAL_FLOAT(15.0f, r.body.param_value.value);
            TEST_ASSERT_EQUAL_STRING("debounce_ms", r.body.param_value.name);
        }
    }
    TEST_ASSERT_TRUE(found);
}

/* Send `p` numbered with the next seq and keep its wire bytes in `rec`. */
static size_t host_send_recorded(oibar_v1_Packet *p, uint8_t *rec, size_t cap)
{
    p->seq = ++s_seq;
    size_t n = oibar_frame_encode(p, rec, cap);
    TEST_ASSERT_TRUE(n > 0u);
    for (size_t i = 0; i < n; i++) {
        oibar_link_rx_isr(&s_link, rec[i]);
    }
    return n;
}

static void host_replay(const uint8_t *rec, size_t n)
{
    for (size_t i = 0; i < n; i++) {
        oibar_link_rx_isr(&s_link, rec[i]);
    }
}

/* Run `ms` milliseconds with host heartbeats every 100 ms; false if a valve
 * coil was driven at any millisecond. */
static bool run_valves_shut(uint32_t ms)
{
    bool shut = true;
    for (uint32_t t = 0; t < ms; t++) {
        if (t % 100u == 0u) {
            oibar_v1_Packet hb = oibar_v1_Packet_init_zero;
            hb.which_body = oibar_v1_Packet_heartbeat_tag;
            host_send(&hb);
        }
        fake_hal_advance_ms(1);
        shut = shut && !bench_any_valve_driven();
    }
    return shut;
}

/* SAFETY_RULE (issue 16, item 5): a recorded ARM_TRANSFER + START_TRANSFER,
 * replayed byte for byte after STOP_TRANSFER, must not reopen the valves. */
static void test_SAFETY_RULE_REPLAYED_ARM_START_DO_NOT_REOPEN_VALVES(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    /* The link in front of the application, as in setUp. */
    oibar_link_config_t cfg;
    oibar_link_config_defaults(&cfg);
    oibar_link_port_t port = { port_send, NULL };
    oibar_link_init(&s_link, &cfg, &port, oibar_app_link_callbacks());
    fake_hal_set_main_loop(main_loop);
    s_seq = 0;
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_handshake_tag;
    p.body.handshake.protocol_version = oibar_v1_Protocol_PROTOCOL_VERSION;
    host_send(&p);
    fake_hal_advance_ms(2);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());

    uint8_t arm[OIBAR_FRAME_MAX_WIRE_BYTES];
    uint8_t go[OIBAR_FRAME_MAX_WIRE_BYTES];
    p = (oibar_v1_Packet)oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_command_tag;
    p.body.command.opcode = oibar_v1_CMD_ARM_TRANSFER;
    const size_t arm_n = host_send_recorded(&p, arm, sizeof arm);
    fake_hal_advance_ms(2);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFER_ARMED, oibar_app_state());
    p.body.command.opcode = oibar_v1_CMD_START_TRANSFER;
    p.body.command.target_pressure_kpa = 1500.0f;
    const size_t go_n = host_send_recorded(&p, go, sizeof go);
    fake_hal_advance_ms(2);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFERRING, oibar_app_state());
    TEST_ASSERT_TRUE(bench_any_valve_driven());

    TEST_ASSERT_TRUE(command(oibar_v1_CMD_STOP_TRANSFER, 0).accepted);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_TRUE(run_valves_shut(200)); /* the valves read closed */

    s_out_len = 0;
    host_replay(arm, arm_n);
    TEST_ASSERT_TRUE(run_valves_shut(5));
    host_replay(go, go_n);
    TEST_ASSERT_TRUE(run_valves_shut(500));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    oibar_v1_LinkCounters c;
    oibar_link_get_counters(&s_link, &c);
    TEST_ASSERT_EQUAL_UINT32(2, c.rx_stale);
}

/* Events wait in the log while the UART queue is full, and go out in order
 * once it drains: none is removed before it is sent. */
static bool s_port_full;
static bool port_send_maybe_full(void *ctx, const uint8_t *bytes, size_t len)
{
    return s_port_full ? false : port_send(ctx, bytes, len);
}

static void test_events_kept_until_the_port_takes_them(void)
{
    oibar_link_config_t cfg;
    oibar_link_config_defaults(&cfg);
    oibar_link_port_t port = { port_send_maybe_full, NULL };
    oibar_link_init(&s_link, &cfg, &port, oibar_app_link_callbacks());
    s_seq = 0;
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_handshake_tag;
    p.body.handshake.protocol_version = oibar_v1_Protocol_PROTOCOL_VERSION;
    host_send(&p);
    fake_hal_advance_ms(2);
    s_out_len = 0;
    s_port_full = true;
    p = (oibar_v1_Packet)oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_command_tag;
    p.body.command.opcode = oibar_v1_CMD_APPROACH_ARM;
    host_send(&p);
    fake_hal_advance_ms(5); /* the state change event cannot go out */
    TEST_ASSERT_EQUAL(oibar_v1_STATE_APPROACH_READY, oibar_app_state());
    TEST_ASSERT_TRUE(oibar_app_link_events_unsent() > 0u);
    s_port_full = false;
    fake_hal_advance_ms(2);
    bool saw = false;
    (void)host_read(0, NULL, oibar_v1_EVT_STATE_CHANGE, &saw);
    TEST_ASSERT_TRUE_MESSAGE(saw, "the event held back by the full queue was lost");
    oibar_v1_Telemetry tm = oibar_v1_Telemetry_init_zero;
    oibar_app_link_callbacks()->fill_telemetry(NULL, &tm);
    TEST_ASSERT_EQUAL_UINT32(0, tm.events_lost);
}

/* Only a full log loses events, oldest first, and telemetry counts them. */
static void test_events_lost_to_a_full_log_are_counted(void)
{
    oibar_v1_Event ev = oibar_v1_Event_init_zero;
    ev.id = oibar_v1_EVT_STATE_CHANGE;
    for (unsigned i = 0; i < OIBAR_EVT_LOG_LEN + 3u; i++) {
        oibar_evlog_push(&ev);
    }
    oibar_v1_Telemetry tm = oibar_v1_Telemetry_init_zero;
    oibar_app_link_callbacks()->fill_telemetry(NULL, &tm);
    TEST_ASSERT_TRUE(tm.events_lost >= 3u);
}

/* The UART's receive errors (framing/noise/parity, overruns; FMEA LINK-NOISE)
 * reach the host in every telemetry, encoded and decoded over the frame. */
static void test_uart_receive_errors_are_in_telemetry(void)
{
    fake_hal_uart_set_errors(7u, 3u);
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_telemetry_tag;
    oibar_app_link_callbacks()->fill_telemetry(NULL, &p.body.telemetry);
    TEST_ASSERT_EQUAL_UINT32(7u, p.body.telemetry.uart_rx_errors);
    TEST_ASSERT_EQUAL_UINT32(3u, p.body.telemetry.uart_rx_overruns);
    uint8_t frame[OIBAR_FRAME_MAX_WIRE_BYTES];
    size_t n = oibar_frame_encode(&p, frame, sizeof frame);
    TEST_ASSERT_TRUE(n > 0u);
    oibar_frame_decoder_t dec;
    oibar_frame_decoder_init(&dec, OIBAR_BODIES_MCU_TO_HOST);
    oibar_v1_Packet back = oibar_v1_Packet_init_zero;
    size_t used = 0;
    TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, oibar_frame_decoder_feed_buf(&dec, frame, n, &used, &back));
    TEST_ASSERT_EQUAL_UINT32(7u, back.body.telemetry.uart_rx_errors);
    TEST_ASSERT_EQUAL_UINT32(3u, back.body.telemetry.uart_rx_overruns);
    fake_hal_uart_set_errors(0u, 0u);
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_commands_are_acked_with_state);
    RUN_TEST(test_events_reach_the_host);
    RUN_TEST(test_link_loss_safes_the_mechanism);
    RUN_TEST(test_params_over_the_link);
    RUN_TEST(test_SAFETY_RULE_REPLAYED_ARM_START_DO_NOT_REOPEN_VALVES);
    RUN_TEST(test_events_kept_until_the_port_takes_them);
    RUN_TEST(test_events_lost_to_a_full_log_are_counted);
    RUN_TEST(test_uart_receive_errors_are_in_telemetry);
    return UNITY_END();
}
