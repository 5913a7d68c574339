/* The MCU link rules of docs/link.md, driven through the public API with a
 * fake port (captures transmitted frames) and a fake application. */
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

#include "unity.h"

#include "oibar/frame.h"
#include "oibar/link.h"

/* ------------------------------------------------------------------------- */
/* Fakes                                                                     */

#define MAX_SEEN 256

static oibar_link_t link;
static oibar_link_config_t cfg;

/* Port: what the MCU transmitted, decoded as the host would. */
static bool port_accepts = true;
static oibar_frame_decoder_t host_dec;
static oibar_v1_Packet seen[MAX_SEEN];
static size_t seen_n;
static uint8_t last_tx[OIBAR_FRAME_MAX_WIRE_BYTES];
static size_t last_tx_len;

static bool fake_send(void *ctx, const uint8_t *bytes, size_t len)
{
    TEST_ASSERT_EQUAL_PTR(&port_accepts, ctx);
    TEST_ASSERT_TRUE(len <= OIBAR_FRAME_MAX_WIRE_BYTES);
    TEST_ASSERT_EQUAL_HEX8(0x00, bytes[len - 1]);
    if (!port_accepts) {
        return false;
    }
    memcpy(last_tx, bytes, len);
    last_tx_len = len;
    oibar_v1_Packet p;
    for (size_t i = 0; i < len; ++i) {
        const oibar_rx_result_t r = oibar_frame_decoder_feed(&host_dec, bytes[i], &p);
        if (r != OIBAR_RX_NONE) {
            TEST_ASSERT_EQUAL_MESSAGE(OIBAR_RX_PACKET, r, "MCU sent a frame the host cannot read");
            TEST_ASSERT_EQUAL_size_t(len - 1, i); /* exactly one frame per send() */
            TEST_ASSERT_TRUE(seen_n < MAX_SEEN);
            seen[seen_n++] = p;
        }
    }
    return true;
}

/* Application */
static struct {
    int commands;
    int nav_updates;
    int param_gets;
    int param_sets;
    int telemetry_fills;
    int link_ups;
    int link_downs;
    oibar_v1_Command last_command;
    float last_param_value;
    oibar_v1_NackReason command_reason; /* what on_command answers */
    oibar_v1_State state;
} app;

static void app_command(void *ctx, const oibar_v1_Command *cmd, oibar_v1_Ack *out)
{
    TEST_ASSERT_EQUAL_PTR(&app, ctx);
    TEST_ASSERT_EQUAL(app.state, out->state); /* pre-filled from get_state */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, out->reason);
    ++app.commands;
    app.last_command = *cmd;
    out->reason = app.command_reason;
    if (app.command_reason == oibar_v1_NACK_NONE && cmd->opcode == oibar_v1_CMD_APPROACH_ARM) {
        app.state = oibar_v1_STATE_APPROACH_READY;
    }
    out->state = app.state;
}

static void app_nav(void *ctx, const oibar_v1_NavUpdate *nav)
{
    (void)ctx;
    (void)nav;
    ++app.nav_updates;
}

static void app_param_get(void *ctx, uint32_t id, oibar_v1_ParamValue *out)
{
    (void)ctx;
    TEST_ASSERT_EQUAL_UINT32(id, out->param_id);
    ++app.param_gets;
    if (id != 3u) {
        out->reason = oibar_v1_NACK_UNKNOWN_PARAM;
        return;
    }
    out->value = 1.5f;
    out->min = 0.0f;
    out->max = 10.0f;
    out->default_value = 1.0f;
    strcpy(out->name, "gain");
    strcpy(out->unit, "1");
}

static void app_param_set(void *ctx, uint32_t id, float value, oibar_v1_ParamValue *out)
{
    (void)ctx;
    ++app.param_sets;
    app.last_param_value = value;
    out->value = 1.5f;
    out->reason = (id == 3u && value <= 10.0f) ? oibar_v1_NACK_NONE : oibar_v1_NACK_PARAM_OUT_OF_BOUNDS;
}

static void app_telemetry(void *ctx, oibar_v1_Telemetry *out)
{
    (void)ctx;
    ++app.telemetry_fills;
    out->line_kpa = 101.3f;
    out->link.rx_packets = 12345; /* the link must overwrite this */
}

static void app_link_state(void *ctx, bool up)
{
    (void)ctx;
    if (up) {
        ++app.link_ups;
    } else {
        ++app.link_downs;
    }
}

static oibar_v1_State app_get_state(void *ctx)
{
    (void)ctx;
    return app.state;
}

static const oibar_link_port_t port = {fake_send, &port_accepts};
static const oibar_link_app_t app_cb = {&app, app_command, app_nav, app_param_get, app_param_set,
                                        app_telemetry, app_link_state, app_get_state};

void setUp(void)
{
    memset(&app, 0, sizeof(app));
    app.state = oibar_v1_STATE_IDLE;
    port_accepts = true;
    seen_n = 0;
    oibar_frame_decoder_init(&host_dec, OIBAR_BODIES_MCU_TO_HOST);
    oibar_link_config_defaults(&cfg);
    cfg.firmware_version = "1.4.2";
    cfg.build_id = "abc1234";
    cfg.reset_cause = oibar_v1_RESET_WATCHDOG;
    oibar_link_init(&link, &cfg, &port, &app_cb);
}
void tearDown(void) {}

/* ------------------------------------------------------------------------- */
/* Helpers                                                                   */

static void rx_bytes(const uint8_t *bytes, size_t len)
{
    for (size_t i = 0; i < len; ++i) {
        oibar_link_rx_isr(&link, bytes[i]);
    }
}

static void host_send(const oibar_v1_Packet *p)
{
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t n = oibar_frame_encode(p, wire, sizeof(wire));
    TEST_ASSERT_TRUE(n > 0);
    rx_bytes(wire, n);
}

static oibar_v1_Packet mk(uint32_t seq, pb_size_t body)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = seq;
    p.which_body = body;
    return p;
}

static void send_handshake(uint32_t seq, uint32_t version)
{
    oibar_v1_Packet p = mk(seq, oibar_v1_Packet_handshake_tag);
    p.body.handshake.protocol_version = version;
    strcpy(p.body.handshake.host_version, "host-0.1");
    host_send(&p);
}

static void send_command(uint32_t seq, oibar_v1_CommandOpcode op)
{
    oibar_v1_Packet p = mk(seq, oibar_v1_Packet_command_tag);
    p.body.command.opcode = op;
    host_send(&p);
}

static void send_heartbeat(uint32_t seq)
{
    oibar_v1_Packet p = mk(seq, oibar_v1_Packet_heartbeat_tag);
    host_send(&p);
}

/* Poll once and forget the periodic traffic of the first poll. */
static void start(uint32_t now_ms)
{
    oibar_link_poll(&link, now_ms);
    seen_n = 0;
}

static size_t count_body(pb_size_t body)
{
    size_t n = 0;
    for (size_t i = 0; i < seen_n; ++i) {
        n += (seen[i].which_body == body) ? 1u : 0u;
    }
    return n;
}

/* The k-th (0-based) packet seen with this body; fails if there is none. */
static const oibar_v1_Packet *nth_body(pb_size_t body, size_t k)
{
    for (size_t i = 0; i < seen_n; ++i) {
        if (seen[i].which_body == body && k-- == 0) {
            return &seen[i];
        }
    }
    TEST_FAIL_MESSAGE("expected packet not sent");
    return NULL;
}

static size_t count_events(oibar_v1_EventId id)
{
    size_t n = 0;
    for (size_t i = 0; i < seen_n; ++i) {
        n += (seen[i].which_body == oibar_v1_Packet_event_tag && seen[i].body.event.id == id) ? 1u : 0u;
    }
    return n;
}

static oibar_v1_LinkCounters counters(void)
{
    oibar_v1_LinkCounters c;
    oibar_link_get_counters(&link, &c);
    return c;
}

static void connect(uint32_t seq, uint32_t now_ms)
{
    send_handshake(seq, oibar_v1_PROTOCOL_VERSION);
    oibar_link_poll(&link, now_ms);
    TEST_ASSERT_TRUE(oibar_link_is_connected(&link));
    seen_n = 0;
}

/* ------------------------------------------------------------------------- */
/* Handshake                                                                 */

static void test_handshake_accepted(void)
{
    start(0);
    send_handshake(1, oibar_v1_PROTOCOL_VERSION);
    oibar_link_poll(&link, 50);
    TEST_ASSERT_TRUE(oibar_link_is_connected(&link));
    TEST_ASSERT_EQUAL_size_t(1, count_body(oibar_v1_Packet_handshake_reply_tag));
    const oibar_v1_Packet *r = nth_body(oibar_v1_Packet_handshake_reply_tag, 0);
    TEST_ASSERT_EQUAL_UINT32(1, r->ack_seq);
    TEST_ASSERT_TRUE(r->body.handshake_reply.accepted);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, r->body.handshake_reply.reason);
    TEST_ASSERT_EQUAL_UINT32(oibar_v1_PROTOCOL_VERSION, r->body.handshake_reply.protocol_version);
    TEST_ASSERT_EQUAL_STRING("1.4.2", r->body.handshake_reply.firmware_version);
    TEST_ASSERT_EQUAL_STRING("abc1234", r->body.handshake_reply.build_id);
    TEST_ASSERT_EQUAL(oibar_v1_RESET_WATCHDOG, r->body.handshake_reply.reset_cause);
    TEST_ASSERT_EQUAL_UINT32(50, r->body.handshake_reply.uptime_ms);
    /* EVT_LINK_UP after the reply, and the application told once. */
    TEST_ASSERT_EQUAL_size_t(1, count_events(oibar_v1_EVT_LINK_UP));
    TEST_ASSERT_EQUAL(oibar_v1_Packet_handshake_reply_tag, seen[0].which_body);
    TEST_ASSERT_EQUAL(oibar_v1_Packet_event_tag, seen[1].which_body);
    TEST_ASSERT_EQUAL_INT(1, app.link_ups);
    TEST_ASSERT_EQUAL_INT(0, app.link_downs);
}

static void test_handshake_version_mismatch(void)
{
    start(0);
    send_handshake(1, oibar_v1_PROTOCOL_VERSION + 1u);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_FALSE(oibar_link_is_connected(&link));
    const oibar_v1_Packet *r = nth_body(oibar_v1_Packet_handshake_reply_tag, 0);
    TEST_ASSERT_EQUAL_UINT32(1, r->ack_seq);
    TEST_ASSERT_FALSE(r->body.handshake_reply.accepted);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_VERSION_MISMATCH, r->body.handshake_reply.reason);
    TEST_ASSERT_EQUAL_UINT32(oibar_v1_PROTOCOL_VERSION, r->body.handshake_reply.protocol_version);
    TEST_ASSERT_EQUAL_STRING("1.4.2", r->body.handshake_reply.firmware_version);
    TEST_ASSERT_EQUAL_size_t(0, count_events(oibar_v1_EVT_LINK_UP));
    TEST_ASSERT_EQUAL_INT(0, app.link_ups);
    /* Still unconnected: commands are refused. */
    send_command(2, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 20);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NOT_CONNECTED, nth_body(oibar_v1_Packet_ack_tag, 0)->body.ack.reason);
    TEST_ASSERT_EQUAL_INT(0, app.commands);
}

/* The reply got lost; the host retransmits the same handshake. */
static void test_retransmitted_handshake_answered_from_cache(void)
{
    start(0);
    send_handshake(1, oibar_v1_PROTOCOL_VERSION);
    oibar_link_poll(&link, 10);
    const oibar_v1_Packet first = *nth_body(oibar_v1_Packet_handshake_reply_tag, 0);
    send_handshake(1, oibar_v1_PROTOCOL_VERSION);
    oibar_link_poll(&link, 210);
    TEST_ASSERT_EQUAL_size_t(2, count_body(oibar_v1_Packet_handshake_reply_tag));
    const oibar_v1_Packet *again = nth_body(oibar_v1_Packet_handshake_reply_tag, 1);
    TEST_ASSERT_EQUAL_UINT32(first.seq, again->seq); /* a retransmission keeps its seq */
    TEST_ASSERT_EQUAL_UINT32(1, again->ack_seq);
    TEST_ASSERT_EQUAL_UINT32(10, again->body.handshake_reply.uptime_ms);
    TEST_ASSERT_EQUAL_UINT32(1, counters().rx_duplicates);
    TEST_ASSERT_EQUAL_size_t(1, count_events(oibar_v1_EVT_LINK_UP));
    TEST_ASSERT_EQUAL_INT(1, app.link_ups);
}

/* A mismatching peer taking over a live link does not inherit it. */
static void test_refused_handshake_while_connected_drops_the_link(void)
{
    start(0);
    connect(1, 0);
    send_handshake(2, 99);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_FALSE(oibar_link_is_connected(&link));
    TEST_ASSERT_EQUAL_INT(1, app.link_downs);
    TEST_ASSERT_EQUAL_UINT32(0, counters().link_losses);
    send_command(3, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 20);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NOT_CONNECTED, nth_body(oibar_v1_Packet_ack_tag, 0)->body.ack.reason);
}

/* A new handshake on a live link (host restart) is accepted without a new
 * LINK_UP and resets the duplicate memory. */
static void test_new_handshake_resets_duplicate_memory(void)
{
    start(0);
    connect(1, 0);
    send_command(5, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_INT(1, app.commands);
    send_handshake(1, oibar_v1_PROTOCOL_VERSION); /* restarted host, numbering from 1 again */
    oibar_link_poll(&link, 20);
    TEST_ASSERT_TRUE(nth_body(oibar_v1_Packet_handshake_reply_tag, 0)->body.handshake_reply.accepted);
    TEST_ASSERT_EQUAL_size_t(0, count_events(oibar_v1_EVT_LINK_UP));
    send_command(5, oibar_v1_CMD_NOOP); /* same seq as before the restart: a new request */
    oibar_link_poll(&link, 30);
    TEST_ASSERT_EQUAL_INT(2, app.commands);
    TEST_ASSERT_EQUAL_UINT32(0, counters().rx_duplicates);
}

/* ------------------------------------------------------------------------- */
/* Requests                                                                  */

static void test_requests_before_handshake_are_not_connected(void)
{
    start(0);
    send_command(3, oibar_v1_CMD_NOOP);
    oibar_v1_Packet g = mk(4, oibar_v1_Packet_param_get_tag);
    g.body.param_get.param_id = 3;
    host_send(&g);
    oibar_v1_Packet s = mk(5, oibar_v1_Packet_param_set_tag);
    s.body.param_set.param_id = 3;
    host_send(&s);
    oibar_v1_Packet nav = mk(6, oibar_v1_Packet_nav_update_tag);
    host_send(&nav);
    send_heartbeat(7);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_size_t(3, count_body(oibar_v1_Packet_ack_tag));
    for (size_t i = 0; i < 3; ++i) {
        const oibar_v1_Packet *a = nth_body(oibar_v1_Packet_ack_tag, i);
        TEST_ASSERT_FALSE(a->body.ack.accepted);
        TEST_ASSERT_EQUAL(oibar_v1_NACK_NOT_CONNECTED, a->body.ack.reason);
        TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, a->body.ack.state);
        TEST_ASSERT_EQUAL_UINT32(3 + i, a->ack_seq);
    }
    TEST_ASSERT_EQUAL_size_t(3, seen_n); /* NavUpdate and Heartbeat are not answered */
    TEST_ASSERT_EQUAL_INT(0, app.commands);
    TEST_ASSERT_EQUAL_INT(0, app.param_gets);
    TEST_ASSERT_EQUAL_INT(0, app.param_sets);
    TEST_ASSERT_EQUAL_INT(0, app.nav_updates);
}

static void test_command_accepted_and_refused(void)
{
    start(0);
    connect(1, 0);
    send_command(2, oibar_v1_CMD_APPROACH_ARM);
    oibar_link_poll(&link, 10);
    const oibar_v1_Packet *a = nth_body(oibar_v1_Packet_ack_tag, 0);
    TEST_ASSERT_EQUAL_UINT32(2, a->ack_seq);
    TEST_ASSERT_TRUE(a->body.ack.accepted);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, a->body.ack.reason);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_APPROACH_READY, a->body.ack.state);
    TEST_ASSERT_EQUAL(oibar_v1_CMD_APPROACH_ARM, app.last_command.opcode);

    app.command_reason = oibar_v1_NACK_INVALID_IN_STATE;
    send_command(3, oibar_v1_CMD_START_TRANSFER);
    oibar_link_poll(&link, 20);
    a = nth_body(oibar_v1_Packet_ack_tag, 1);
    TEST_ASSERT_EQUAL_UINT32(3, a->ack_seq);
    TEST_ASSERT_FALSE(a->body.ack.accepted);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_INVALID_IN_STATE, a->body.ack.reason);
    TEST_ASSERT_EQUAL_INT(2, app.commands);
}

/* The point of the cache: a retransmitted command does not move hardware twice. */
static void test_duplicate_command_answered_from_cache_not_reexecuted(void)
{
    start(0);
    connect(1, 0);
    send_command(10, oibar_v1_CMD_APPROACH_ARM);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_INT(1, app.commands);
    uint8_t first_bytes[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t first_len = last_tx_len;
    memcpy(first_bytes, last_tx, first_len);

    send_heartbeat(11);
    send_command(10, oibar_v1_CMD_APPROACH_ARM); /* retransmission */
    oibar_link_poll(&link, 20); /* no periodic packet due: the ack is the last frame */
    TEST_ASSERT_EQUAL_INT(1, app.commands);
    TEST_ASSERT_EQUAL_UINT32(1, counters().rx_duplicates);
    TEST_ASSERT_EQUAL_size_t(2, count_body(oibar_v1_Packet_ack_tag));
    TEST_ASSERT_EQUAL_size_t(first_len, last_tx_len);
    TEST_ASSERT_EQUAL_HEX8_ARRAY(first_bytes, last_tx, first_len); /* byte for byte */

    send_command(12, oibar_v1_CMD_NOOP); /* the next request runs normally */
    oibar_link_poll(&link, 30);
    TEST_ASSERT_EQUAL_INT(2, app.commands);
    TEST_ASSERT_EQUAL_UINT32(12, nth_body(oibar_v1_Packet_ack_tag, 2)->ack_seq);
}

static oibar_v1_NackReason ack_reason(size_t k) { return nth_body(oibar_v1_Packet_ack_tag, k)->body.ack.reason; }

/* SAFETY_RULE (issue 16, item 5): a request runs only if its seq is newer
 * than the newest request of this session. An old seq (a replay, a reordered
 * packet) and seq 0 are refused with NACK_STALE_SEQ and never reach the
 * application. */
static void test_SAFETY_RULE_REPLAYED_OR_REORDERED_REQUEST_REFUSED(void)
{
    start(0);
    connect(1, 0);
    send_command(2, oibar_v1_CMD_NOOP);
    send_command(3, oibar_v1_CMD_APPROACH_ARM);
    send_command(2, oibar_v1_CMD_NOOP);          /* older than the last one */
    send_command(1, oibar_v1_CMD_APPROACH_ARM);  /* the handshake's seq */
    send_command(0, oibar_v1_CMD_NOOP);          /* no seq */
    oibar_v1_Packet g = mk(2, oibar_v1_Packet_param_set_tag);
    g.body.param_set.param_id = 3;
    g.body.param_set.value = 1.0f;
    host_send(&g);                               /* old seq, other body type */
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_INT(2, app.commands);
    TEST_ASSERT_EQUAL_INT(0, app.param_sets);
    TEST_ASSERT_EQUAL_UINT32(0, counters().rx_duplicates);
    TEST_ASSERT_EQUAL_UINT32(4, counters().rx_stale);
    TEST_ASSERT_EQUAL_size_t(6, count_body(oibar_v1_Packet_ack_tag) + count_body(oibar_v1_Packet_param_value_tag));
    for (size_t k = 2; k < 5; ++k) {
        TEST_ASSERT_FALSE(nth_body(oibar_v1_Packet_ack_tag, k)->body.ack.accepted);
        TEST_ASSERT_EQUAL(oibar_v1_NACK_STALE_SEQ, ack_reason(k));
    }
    TEST_ASSERT_EQUAL_UINT32(2, nth_body(oibar_v1_Packet_ack_tag, 2)->ack_seq);
    TEST_ASSERT_EQUAL_UINT32(0, nth_body(oibar_v1_Packet_ack_tag, 4)->ack_seq);
    /* The refusal of a param request is an Ack too (the request never ran). */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_STALE_SEQ, ack_reason(5));
    /* The newest request is still answered from the cache... */
    send_command(3, oibar_v1_CMD_APPROACH_ARM);
    oibar_link_poll(&link, 20);
    TEST_ASSERT_EQUAL_UINT32(1, counters().rx_duplicates);
    TEST_ASSERT_EQUAL_INT(2, app.commands);
    /* ...and the next one runs. */
    send_command(4, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 30);
    TEST_ASSERT_EQUAL_INT(3, app.commands);
}

/* The last request's seq with another body (type or content) is not a
 * retransmission: refused with NACK_SEQ_REUSED, not given the old ack. */
static void test_reused_seq_with_another_body_refused(void)
{
    start(0);
    connect(1, 0);
    send_command(5, oibar_v1_CMD_APPROACH_ARM);
    send_command(5, oibar_v1_CMD_ABORT);          /* same type, other content */
    oibar_v1_Packet g = mk(5, oibar_v1_Packet_param_get_tag);
    g.body.param_get.param_id = 3;
    host_send(&g);                                /* other type */
    oibar_v1_Packet c = mk(5, oibar_v1_Packet_command_tag);
    c.body.command.opcode = oibar_v1_CMD_APPROACH_ARM;
    c.body.command.target_pressure_kpa = 1.0f;    /* other argument */
    host_send(&c);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_INT(1, app.commands);
    TEST_ASSERT_EQUAL_INT(0, app.param_gets);
    TEST_ASSERT_EQUAL_UINT32(0, counters().rx_duplicates);
    TEST_ASSERT_EQUAL_size_t(4, count_body(oibar_v1_Packet_ack_tag));
    for (size_t k = 1; k < 4; ++k) {
        TEST_ASSERT_EQUAL_UINT32(5, nth_body(oibar_v1_Packet_ack_tag, k)->ack_seq);
        TEST_ASSERT_EQUAL(oibar_v1_NACK_SEQ_REUSED, ack_reason(k));
    }
    send_command(5, oibar_v1_CMD_APPROACH_ARM);  /* the exact request: the cached ack */
    oibar_link_poll(&link, 20);
    TEST_ASSERT_EQUAL_UINT32(1, counters().rx_duplicates);
    TEST_ASSERT_TRUE(nth_body(oibar_v1_Packet_ack_tag, 4)->body.ack.accepted);
}

/* The host resends a request whose original was lost after heartbeats and
 * NavUpdates with later seqs: the window follows requests, so it runs. */
static void test_retransmission_after_later_heartbeats_runs(void)
{
    start(0);
    connect(1, 0);
    send_command(2, oibar_v1_CMD_NOOP);
    /* seq 3 (a command) is lost on the wire */
    send_heartbeat(4);
    oibar_v1_Packet nav = mk(5, oibar_v1_Packet_nav_update_tag);
    host_send(&nav);
    send_command(3, oibar_v1_CMD_APPROACH_ARM); /* its retransmission */
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_INT(2, app.commands);
    TEST_ASSERT_EQUAL(oibar_v1_CMD_APPROACH_ARM, app.last_command.opcode);
    TEST_ASSERT_EQUAL_UINT32(0, counters().rx_stale);
}

/* A handshake starts a new window: a host that restarted numbers from 1. */
static void test_handshake_starts_a_new_window(void)
{
    start(0);
    connect(1, 0);
    send_command(500, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 10);
    connect(1, 20);
    send_command(2, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 30);
    TEST_ASSERT_EQUAL_INT(2, app.commands);
    send_command(500, oibar_v1_CMD_NOOP); /* from the old session: newer, so it runs */
    send_command(3, oibar_v1_CMD_NOOP);   /* now behind */
    oibar_link_poll(&link, 40);
    TEST_ASSERT_EQUAL_INT(3, app.commands);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_STALE_SEQ, ack_reason(2));
}

/* The window follows the numbering across its wrap, SEQ_MAX -> 1 (0 skipped),
 * like oibar/link/seq.py. */
static void test_request_window_across_wrap(void)
{
    start(0);
    connect(UINT32_MAX - 1u, 0);
    send_command(UINT32_MAX, oibar_v1_CMD_NOOP);
    send_command(1, oibar_v1_CMD_NOOP);
    send_command(UINT32_MAX, oibar_v1_CMD_ARM_TRANSFER); /* behind 1 */
    send_command(0x80000001u, oibar_v1_CMD_NOOP);        /* over half the numbering ahead of 1: behind */
    send_command(0x80000000u, oibar_v1_CMD_NOOP);        /* SEQ_MAX / 2 ahead: newer */
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_INT(3, app.commands);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_STALE_SEQ, ack_reason(2));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_STALE_SEQ, ack_reason(3));
    TEST_ASSERT_TRUE(nth_body(oibar_v1_Packet_ack_tag, 4)->body.ack.accepted);
}

/* NavUpdates are not acknowledged but replayed or reordered ones are dropped:
 * the newest solution wins. */
static void test_stale_nav_update_dropped(void)
{
    start(0);
    connect(1, 0);
    oibar_v1_Packet nav = mk(5, oibar_v1_Packet_nav_update_tag);
    host_send(&nav);
    nav.seq = 4; /* overtaken */
    host_send(&nav);
    nav.seq = 5; /* replayed */
    host_send(&nav);
    nav.seq = 0;
    host_send(&nav);
    nav.seq = 6;
    host_send(&nav);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_INT(2, app.nav_updates);
    TEST_ASSERT_EQUAL_UINT32(3, counters().rx_stale);
    TEST_ASSERT_EQUAL_size_t(0, count_body(oibar_v1_Packet_ack_tag));
}

static void test_param_get_and_set(void)
{
    start(0);
    connect(1, 0);
    oibar_v1_Packet g = mk(2, oibar_v1_Packet_param_get_tag);
    g.body.param_get.param_id = 3;
    host_send(&g);
    g.seq = 3;
    g.body.param_get.param_id = 77;
    host_send(&g);
    oibar_v1_Packet s = mk(4, oibar_v1_Packet_param_set_tag);
    s.body.param_set.param_id = 3;
    s.body.param_set.value = 99.0f;
    host_send(&s);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_size_t(3, count_body(oibar_v1_Packet_param_value_tag));
    const oibar_v1_Packet *v = nth_body(oibar_v1_Packet_param_value_tag, 0);
    TEST_ASSERT_EQUAL_UINT32(2, v->ack_seq);
    TEST_ASSERT_EQUAL_UINT32(3, v->body.param_value.param_id);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, v->body.param_value.reason);
    TEST_ASSERT_EQUAL_FLOAT(1.5f, v->body.param_value.value);
    TEST_ASSERT_EQUAL_STRING("gain", v->body.param_value.name);
    v = nth_body(oibar_v1_Packet_param_value_tag, 1);
    TEST_ASSERT_EQUAL_UINT32(3, v->ack_seq);
    TEST_ASSERT_EQUAL_UINT32(77, v->body.param_value.param_id);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_UNKNOWN_PARAM, v->body.param_value.reason);
    v = nth_body(oibar_v1_Packet_param_value_tag, 2);
    TEST_ASSERT_EQUAL_UINT32(4, v->ack_seq);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PARAM_OUT_OF_BOUNDS, v->body.param_value.reason);
    TEST_ASSERT_EQUAL_FLOAT(99.0f, app.last_param_value);
}

static void test_nav_update_delivered_when_connected_not_acked(void)
{
    start(0);
    connect(1, 0);
    oibar_v1_Packet nav = mk(2, oibar_v1_Packet_nav_update_tag);
    nav.body.nav_update.frame_id = 17;
    host_send(&nav);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_INT(1, app.nav_updates);
    TEST_ASSERT_EQUAL_size_t(0, count_body(oibar_v1_Packet_ack_tag));
}

static void test_unknown_message_nacked(void)
{
    start(0);
    connect(1, 0);
    oibar_v1_Packet none = mk(7, 0); /* no body */
    host_send(&none);
    oibar_v1_Packet tm = mk(8, oibar_v1_Packet_telemetry_tag); /* an MCU -> host body */
    host_send(&tm);
    oibar_v1_Packet ack = mk(9, oibar_v1_Packet_ack_tag);
    host_send(&ack);
    oibar_v1_Packet silent = mk(0, 0); /* no seq: nothing to correlate, no answer */
    host_send(&silent);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_size_t(3, count_body(oibar_v1_Packet_ack_tag));
    for (size_t i = 0; i < 3; ++i) {
        const oibar_v1_Packet *a = nth_body(oibar_v1_Packet_ack_tag, i);
        TEST_ASSERT_FALSE(a->body.ack.accepted);
        TEST_ASSERT_EQUAL(oibar_v1_NACK_UNKNOWN_MESSAGE, a->body.ack.reason);
        TEST_ASSERT_EQUAL_UINT32(7 + i, a->ack_seq);
    }
    TEST_ASSERT_EQUAL_UINT32(4, counters().rx_unknown_type);
    TEST_ASSERT_EQUAL_UINT32(1, counters().rx_packets); /* the handshake */
}

static void test_no_application_refuses_politely(void)
{
    oibar_link_init(&link, &cfg, &port, NULL);
    start(0);
    connect(1, 0);
    send_command(2, oibar_v1_CMD_NOOP);
    oibar_v1_Packet g = mk(3, oibar_v1_Packet_param_get_tag);
    g.body.param_get.param_id = 1;
    host_send(&g);
    oibar_link_poll(&link, 1);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NOT_SUPPORTED, nth_body(oibar_v1_Packet_ack_tag, 0)->body.ack.reason);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_UNSPECIFIED, nth_body(oibar_v1_Packet_ack_tag, 0)->body.ack.state);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_UNKNOWN_PARAM,
                      nth_body(oibar_v1_Packet_param_value_tag, 0)->body.param_value.reason);
    oibar_link_poll(&link, 100);
    TEST_ASSERT_EQUAL_size_t(1, count_body(oibar_v1_Packet_telemetry_tag));
}

/* ------------------------------------------------------------------------- */
/* Sequence numbers                                                          */

static void test_own_seq_counts_up_and_ack_seq_correlates(void)
{
    start(0);
    connect(40, 0);
    send_command(41, oibar_v1_CMD_NOOP);
    send_command(43, oibar_v1_CMD_NOOP);
    oibar_v1_Packet g = mk(47, oibar_v1_Packet_param_get_tag);
    host_send(&g);
    oibar_link_poll(&link, 150); /* plus a telemetry */
    TEST_ASSERT_EQUAL_UINT32(41, nth_body(oibar_v1_Packet_ack_tag, 0)->ack_seq);
    TEST_ASSERT_EQUAL_UINT32(43, nth_body(oibar_v1_Packet_ack_tag, 1)->ack_seq);
    TEST_ASSERT_EQUAL_UINT32(47, nth_body(oibar_v1_Packet_param_value_tag, 0)->ack_seq);
    TEST_ASSERT_EQUAL_UINT32(0, nth_body(oibar_v1_Packet_telemetry_tag, 0)->ack_seq);
    /* The MCU's own numbering: consecutive over every packet it sent. */
    for (size_t i = 1; i < seen_n; ++i) {
        TEST_ASSERT_EQUAL_UINT32(seen[i - 1].seq + 1u, seen[i].seq);
    }
}

static void test_own_seq_wraps_to_1(void)
{
    start(0);
    link.tx_seq = UINT32_MAX - 1u; /* white-box: jump to the end of the numbering */
    oibar_v1_Event ev = oibar_v1_Event_init_zero;
    ev.id = oibar_v1_EVT_BOOT;
    for (int i = 0; i < 4; ++i) {
        TEST_ASSERT_TRUE(oibar_link_send_event(&link, &ev));
    }
    TEST_ASSERT_EQUAL_size_t(4, seen_n);
    TEST_ASSERT_EQUAL_UINT32(UINT32_MAX - 1u, seen[0].seq);
    TEST_ASSERT_EQUAL_UINT32(UINT32_MAX, seen[1].seq);
    TEST_ASSERT_EQUAL_UINT32(1, seen[2].seq); /* 0 means "none" and is skipped */
    TEST_ASSERT_EQUAL_UINT32(2, seen[3].seq);
}

static uint32_t seq_lost(void)
{
    oibar_link_stats_t s;
    oibar_link_get_stats(&link, &s);
    return s.rx_seq_lost;
}

static void test_peer_seq_gaps_counted(void)
{
    start(0);
    connect(1, 0);
    send_heartbeat(2);
    send_heartbeat(5); /* 3 and 4 lost */
    send_command(6, oibar_v1_CMD_NOOP);
    send_command(6, oibar_v1_CMD_NOOP); /* a retransmission is not a gap */
    send_heartbeat(7);
    send_heartbeat(3); /* late or replayed: ignored */
    send_heartbeat(8);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_UINT32(2, seq_lost());
}

static void test_peer_seq_gap_across_wrap(void)
{
    start(0);
    connect(UINT32_MAX - 2u, 0);
    send_heartbeat(UINT32_MAX - 1u);
    send_heartbeat(UINT32_MAX);
    send_heartbeat(1);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_EQUAL_UINT32(0, seq_lost());
    send_heartbeat(3); /* 2 lost */
    send_heartbeat(UINT32_MAX); /* far behind: ignored */
    oibar_link_poll(&link, 20);
    TEST_ASSERT_EQUAL_UINT32(1, seq_lost());
    connect(UINT32_MAX - 1u, 30);
    send_heartbeat(2); /* UINT32_MAX and 1 lost; 0 is not a seq */
    oibar_link_poll(&link, 40);
    TEST_ASSERT_EQUAL_UINT32(3, seq_lost());
}

/* ------------------------------------------------------------------------- */
/* Timing                                                                    */

static void run_ms(uint32_t from_ms, uint32_t to_ms)
{
    for (uint32_t t = from_ms; t != to_ms + 1u; ++t) {
        oibar_link_poll(&link, t);
    }
}

static void check_periodic_timing(uint32_t t0)
{
    run_ms(t0, t0 + 1000u);
    TEST_ASSERT_EQUAL_size_t(6, count_body(oibar_v1_Packet_heartbeat_tag)); /* 0, 200, ... 1000 */
    TEST_ASSERT_EQUAL_size_t(11, count_body(oibar_v1_Packet_telemetry_tag)); /* 0, 100, ... 1000 */
    for (size_t k = 0; k < 6; ++k) {
        TEST_ASSERT_EQUAL_UINT32(t0 + 200u * k, nth_body(oibar_v1_Packet_heartbeat_tag, k)->body.heartbeat.uptime_ms);
    }
    for (size_t k = 0; k < 11; ++k) {
        TEST_ASSERT_EQUAL_UINT32(t0 + 100u * k, nth_body(oibar_v1_Packet_telemetry_tag, k)->body.telemetry.uptime_ms);
    }
}

static void test_heartbeat_and_telemetry_periods(void)
{
    check_periodic_timing(5000);
}

static void test_periods_survive_clock_wrap(void)
{
    check_periodic_timing(UINT32_MAX - 450u);
}

static void test_changed_periods_take_effect(void)
{
    oibar_link_set_heartbeat_period_ms(&link, 50);
    oibar_link_set_telemetry_period_ms(&link, 500);
    TEST_ASSERT_EQUAL_UINT32(50, oibar_link_get_config(&link)->heartbeat_period_ms);
    run_ms(0, 999);
    TEST_ASSERT_EQUAL_size_t(20, count_body(oibar_v1_Packet_heartbeat_tag));
    TEST_ASSERT_EQUAL_size_t(2, count_body(oibar_v1_Packet_telemetry_tag));
}

/* A main loop that stalls does not cause a burst of catch-up packets. */
static void test_stalled_loop_does_not_burst(void)
{
    start(0);
    oibar_link_poll(&link, 1000);
    TEST_ASSERT_EQUAL_size_t(1, count_body(oibar_v1_Packet_heartbeat_tag));
    TEST_ASSERT_EQUAL_size_t(1, count_body(oibar_v1_Packet_telemetry_tag));
    oibar_link_poll(&link, 1100);
    TEST_ASSERT_EQUAL_size_t(2, count_body(oibar_v1_Packet_telemetry_tag));
}

static void test_telemetry_carries_link_counters(void)
{
    start(0);
    connect(1, 0);
    const uint8_t junk[] = {0x02, 0x01, 0x00}; /* too short: framing error */
    rx_bytes(junk, sizeof(junk));
    oibar_link_poll(&link, 100);
    const oibar_v1_Telemetry *t = &nth_body(oibar_v1_Packet_telemetry_tag, 0)->body.telemetry;
    TEST_ASSERT_TRUE(t->has_link);
    TEST_ASSERT_EQUAL_UINT32(1, t->link.rx_packets);
    TEST_ASSERT_EQUAL_UINT32(1, t->link.rx_framing_errors);
    TEST_ASSERT_TRUE(t->link.tx_packets >= 4); /* first heartbeat, telemetry, reply, event */
    TEST_ASSERT_TRUE(t->host_link_alive);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, t->state);
    TEST_ASSERT_EQUAL_FLOAT(101.3f, t->line_kpa); /* the application's part */
    TEST_ASSERT_EQUAL_UINT32(100, t->uptime_ms);
    TEST_ASSERT_EQUAL_INT(2, app.telemetry_fills);
}

/* ------------------------------------------------------------------------- */
/* Link loss                                                                 */

static void test_link_loss_after_timeout(void)
{
    start(0);
    connect(1, 0);
    run_ms(1, 999);
    TEST_ASSERT_TRUE(oibar_link_is_connected(&link));
    TEST_ASSERT_EQUAL_size_t(0, count_events(oibar_v1_EVT_LINK_LOST));
    oibar_link_poll(&link, 1000);
    TEST_ASSERT_FALSE(oibar_link_is_connected(&link));
    TEST_ASSERT_EQUAL_UINT32(1, counters().link_losses);
    TEST_ASSERT_EQUAL_size_t(1, count_events(oibar_v1_EVT_LINK_LOST));
    for (size_t i = 0; i < seen_n; ++i) {
        if (seen[i].which_body == oibar_v1_Packet_event_tag) {
            TEST_ASSERT_EQUAL_UINT32(1000, seen[i].body.event.uptime_ms);
        }
    }
    TEST_ASSERT_EQUAL_INT(1, app.link_downs);
    /* Unconnected again: a command needs a new handshake first. */
    seen_n = 0;
    send_command(2, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 1010);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NOT_CONNECTED, nth_body(oibar_v1_Packet_ack_tag, 0)->body.ack.reason);
    TEST_ASSERT_EQUAL_INT(0, app.commands);
    /* Nothing more to lose while unconnected. */
    run_ms(1011, 5000);
    TEST_ASSERT_EQUAL_UINT32(1, counters().link_losses);
    TEST_ASSERT_EQUAL_INT(1, app.link_downs);
    /* And it comes back. */
    seen_n = 0;
    connect(1, 5001);
    TEST_ASSERT_EQUAL_INT(2, app.link_ups);
}

/* D4: a re-handshake on a live link is a new session: the application is
 * told (it drops its navigation record), the link stays up. */
static void test_rehandshake_on_a_live_link_tells_the_app(void)
{
    start(0);
    connect(1, 10);
    TEST_ASSERT_EQUAL_INT(1, app.link_ups);
    send_handshake(7, oibar_v1_PROTOCOL_VERSION);
    oibar_link_poll(&link, 20);
    TEST_ASSERT_TRUE(oibar_link_is_connected(&link));
    TEST_ASSERT_EQUAL_INT(2, app.link_ups);
    TEST_ASSERT_EQUAL_INT(0, app.link_downs);
}

/* Suspected item of issue 59: a handshake with seq 0 opened a session with no
 * replay window for its first request. It is refused, and changes nothing. */
static void test_handshake_with_seq_0_is_refused(void)
{
    start(0);
    send_handshake(0, oibar_v1_PROTOCOL_VERSION);
    oibar_link_poll(&link, 10);
    TEST_ASSERT_FALSE(oibar_link_is_connected(&link));
    const oibar_v1_Packet *r = nth_body(oibar_v1_Packet_handshake_reply_tag, 0);
    TEST_ASSERT_NOT_NULL(r);
    TEST_ASSERT_FALSE(r->body.handshake_reply.accepted);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_STALE_SEQ, r->body.handshake_reply.reason);
    TEST_ASSERT_EQUAL_INT(0, app.link_ups);
    /* On a live session it neither drops it nor resets its window. */
    connect(5, 20);
    send_command(6, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 30);
    seen_n = 0;
    send_handshake(0, oibar_v1_PROTOCOL_VERSION);
    oibar_link_poll(&link, 40);
    TEST_ASSERT_TRUE(oibar_link_is_connected(&link));
    send_command(6, oibar_v1_CMD_NOOP); /* replayed after it: still stale */
    oibar_link_poll(&link, 50);
    const oibar_v1_Packet *a = nth_body(oibar_v1_Packet_ack_tag, 0);
    TEST_ASSERT_NOT_NULL(a);
    TEST_ASSERT_NOT_EQUAL(oibar_v1_NACK_NONE, a->body.ack.reason);
}

static void test_heartbeats_keep_the_link_alive(void)
{
    start(0);
    connect(1, 0);
    uint32_t seq = 2;
    for (uint32_t t = 1; t <= 10000; ++t) {
        if (t % 500u == 0u) {
            send_heartbeat(seq++);
        }
        oibar_link_poll(&link, t);
    }
    TEST_ASSERT_TRUE(oibar_link_is_connected(&link));
    TEST_ASSERT_EQUAL_UINT32(0, counters().link_losses);
}

/* Bad frames are not signs of life. */
static void test_garbage_does_not_keep_the_link_alive(void)
{
    start(0);
    connect(1, 0);
    const uint8_t junk[] = {0x03, 0x11, 0x22, 0x00};
    for (uint32_t t = 1; t <= 1000; ++t) {
        rx_bytes(junk, sizeof(junk));
        oibar_link_poll(&link, t);
    }
    TEST_ASSERT_FALSE(oibar_link_is_connected(&link));
    TEST_ASSERT_EQUAL_UINT32(1000, counters().rx_framing_errors);
}

/* The retransmission of a request from before the loss is not answered from
 * the old session's cache. */
static void test_link_loss_forgets_cached_response(void)
{
    start(0);
    connect(1, 0);
    send_command(2, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 10);
    oibar_link_poll(&link, 1010);
    TEST_ASSERT_FALSE(oibar_link_is_connected(&link));
    seen_n = 0;
    send_command(2, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 1020);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NOT_CONNECTED, nth_body(oibar_v1_Packet_ack_tag, 0)->body.ack.reason);
    TEST_ASSERT_EQUAL_UINT32(0, counters().rx_duplicates);
}

static void test_link_timeout_configurable(void)
{
    oibar_link_set_link_timeout_ms(&link, 300);
    start(0);
    connect(1, 0);
    run_ms(1, 299);
    TEST_ASSERT_TRUE(oibar_link_is_connected(&link));
    oibar_link_poll(&link, 300);
    TEST_ASSERT_FALSE(oibar_link_is_connected(&link));
}

/* ------------------------------------------------------------------------- */
/* Receive path                                                              */

static void test_ring_overflow_counted_then_recovers(void)
{
    start(0);
    connect(1, 0);
    /* More than the ring holds before the main loop runs. */
    uint8_t flood[OIBAR_RINGBUF_CAPACITY + 100];
    memset(flood, 0x42, sizeof(flood));
    rx_bytes(flood, sizeof(flood));
    TEST_ASSERT_EQUAL_UINT32(100, counters().rx_ring_overflows);
    oibar_link_poll(&link, 10);
    send_command(2, oibar_v1_CMD_NOOP); /* glued to the garbage: lost */
    rx_bytes((const uint8_t[]){0x00}, 1);
    send_command(3, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 20);
    TEST_ASSERT_EQUAL_INT(1, app.commands);
    TEST_ASSERT_EQUAL_UINT32(3, nth_body(oibar_v1_Packet_ack_tag, 0)->ack_seq);
    TEST_ASSERT_EQUAL_UINT32(1, counters().rx_oversize);
}

/* A byte lost in the ring spoils its frame (CRC or framing), nothing else. */
static void test_lost_byte_spoils_only_its_frame(void)
{
    start(0);
    connect(1, 0);
    oibar_v1_Packet p = mk(2, oibar_v1_Packet_command_tag);
    p.body.command.opcode = oibar_v1_CMD_NOOP;
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    rx_bytes(wire, 3);
    rx_bytes(&wire[4], n - 4); /* byte 3 never made it */
    send_command(3, oibar_v1_CMD_NOOP);
    oibar_link_poll(&link, 10);
    const oibar_v1_LinkCounters c = counters();
    TEST_ASSERT_EQUAL_UINT32(1, c.rx_crc_errors + c.rx_framing_errors + c.rx_decode_errors);
    TEST_ASSERT_EQUAL_INT(1, app.commands);
}

/* Everything in the ring is handled by the next poll, however it arrived. */
static void test_bytes_split_across_polls(void)
{
    start(0);
    oibar_v1_Packet p = mk(1, oibar_v1_Packet_handshake_tag);
    p.body.handshake.protocol_version = oibar_v1_PROTOCOL_VERSION;
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    for (size_t i = 0; i < n; ++i) {
        TEST_ASSERT_FALSE(oibar_link_is_connected(&link));
        oibar_link_rx_isr(&link, wire[i]);
        oibar_link_poll(&link, (uint32_t)i);
    }
    TEST_ASSERT_TRUE(oibar_link_is_connected(&link));
}

/* ------------------------------------------------------------------------- */
/* Transmit path                                                             */

static void test_send_event(void)
{
    start(0);
    oibar_v1_Event ev = oibar_v1_Event_init_zero;
    ev.uptime_ms = 77;
    ev.id = oibar_v1_EVT_STATE_CHANGE;
    ev.severity = oibar_v1_SEVERITY_ACTIVITY_HI;
    ev.from_state = oibar_v1_STATE_IDLE;
    ev.to_state = oibar_v1_STATE_APPROACH_READY;
    TEST_ASSERT_TRUE(oibar_link_send_event(&link, &ev));
    const oibar_v1_Event *e = &nth_body(oibar_v1_Packet_event_tag, 0)->body.event;
    TEST_ASSERT_EQUAL(oibar_v1_EVT_STATE_CHANGE, e->id);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_APPROACH_READY, e->to_state);
    TEST_ASSERT_EQUAL_UINT32(77, e->uptime_ms);
    TEST_ASSERT_EQUAL_UINT32(0, nth_body(oibar_v1_Packet_event_tag, 0)->ack_seq);
}

static void test_port_refusal_counted(void)
{
    start(0);
    const uint32_t tx_before = counters().tx_packets;
    port_accepts = false;
    oibar_v1_Event ev = oibar_v1_Event_init_zero;
    TEST_ASSERT_FALSE(oibar_link_send_event(&link, &ev));
    oibar_link_stats_t s;
    oibar_link_get_stats(&link, &s);
    TEST_ASSERT_EQUAL_UINT32(1, s.tx_failures);
    TEST_ASSERT_EQUAL_UINT32(tx_before, counters().tx_packets);
    port_accepts = true;
    TEST_ASSERT_TRUE(oibar_link_send_event(&link, &ev));
    TEST_ASSERT_EQUAL_UINT32(tx_before + 1u, counters().tx_packets);
}

static void test_long_strings_in_config_are_cut(void)
{
    cfg.firmware_version = "0123456789abcdefXYZ"; /* 19 > 16 */
    cfg.build_id = NULL;
    oibar_link_init(&link, &cfg, &port, &app_cb);
    start(0);
    connect(1, 0);
    send_handshake(2, oibar_v1_PROTOCOL_VERSION);
    oibar_link_poll(&link, 1);
    const oibar_v1_HandshakeReply *r = &nth_body(oibar_v1_Packet_handshake_reply_tag, 0)->body.handshake_reply;
    TEST_ASSERT_EQUAL_STRING("0123456789abcdef", r->firmware_version);
    TEST_ASSERT_EQUAL_STRING("", r->build_id);
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_handshake_accepted);
    RUN_TEST(test_handshake_version_mismatch);
    RUN_TEST(test_retransmitted_handshake_answered_from_cache);
    RUN_TEST(test_refused_handshake_while_connected_drops_the_link);
    RUN_TEST(test_new_handshake_resets_duplicate_memory);
    RUN_TEST(test_requests_before_handshake_are_not_connected);
    RUN_TEST(test_command_accepted_and_refused);
    RUN_TEST(test_duplicate_command_answered_from_cache_not_reexecuted);
    RUN_TEST(test_SAFETY_RULE_REPLAYED_OR_REORDERED_REQUEST_REFUSED);
    RUN_TEST(test_reused_seq_with_another_body_refused);
    RUN_TEST(test_retransmission_after_later_heartbeats_runs);
    RUN_TEST(test_handshake_starts_a_new_window);
    RUN_TEST(test_request_window_across_wrap);
    RUN_TEST(test_stale_nav_update_dropped);
    RUN_TEST(test_param_get_and_set);
    RUN_TEST(test_nav_update_delivered_when_connected_not_acked);
    RUN_TEST(test_unknown_message_nacked);
    RUN_TEST(test_no_application_refuses_politely);
    RUN_TEST(test_own_seq_counts_up_and_ack_seq_correlates);
    RUN_TEST(test_own_seq_wraps_to_1);
    RUN_TEST(test_peer_seq_gaps_counted);
    RUN_TEST(test_peer_seq_gap_across_wrap);
    RUN_TEST(test_heartbeat_and_telemetry_periods);
    RUN_TEST(test_periods_survive_clock_wrap);
    RUN_TEST(test_changed_periods_take_effect);
    RUN_TEST(test_stalled_loop_does_not_burst);
    RUN_TEST(test_telemetry_carries_link_counters);
    RUN_TEST(test_link_loss_after_timeout);
    RUN_TEST(test_rehandshake_on_a_live_link_tells_the_app);
    RUN_TEST(test_handshake_with_seq_0_is_refused);
    RUN_TEST(test_heartbeats_keep_the_link_alive);
    RUN_TEST(test_garbage_does_not_keep_the_link_alive);
    RUN_TEST(test_link_loss_forgets_cached_response);
    RUN_TEST(test_link_timeout_configurable);
    RUN_TEST(test_ring_overflow_counted_then_recovers);
    RUN_TEST(test_lost_byte_spoils_only_its_frame);
    RUN_TEST(test_bytes_split_across_polls);
    RUN_TEST(test_send_event);
    RUN_TEST(test_port_refusal_counted);
    RUN_TEST(test_long_strings_in_config_are_cut);
    return UNITY_END();
}
