/*
 * Golden link frames: the C side against the committed bytes.
 *
 * mcu_to_host frames are *written* here: each packet is built in C, encoded by the firmware's
 * frame encoder and compared with tests/golden/mcu_to_host/<name>.hex, which the Python decoder
 * reads (tests/host/test_golden.py) and checks against the fields in tests/golden/vectors.json.
 * host_to_mcu frames, written by the Python encoder, are *read* here through the streaming
 * decoder, byte by byte, and their fields checked.
 *
 * With OIBAR_GOLDEN_WRITE=1 in the environment the mcu_to_host files are rewritten (`make golden`).
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "oibar/frame.h"
#include "unity.h"

#ifndef OIBAR_SOURCE_DIR
#error "OIBAR_SOURCE_DIR must name the repository root"
#endif

#define HEX_MAX (2u * OIBAR_FRAME_MAX_WIRE_BYTES + 8u)

void setUp(void) {}
void tearDown(void) {}

static void golden_path(char *out, size_t cap, const char *dir, const char *name) {
    int n = snprintf(out, cap, "%s/tests/golden/%s/%s.hex", OIBAR_SOURCE_DIR, dir, name);
    TEST_ASSERT_TRUE_MESSAGE(n > 0 && (size_t)n < cap, "golden path too long");
}

/* Reads a golden file into bytes; returns the length. */
static size_t read_golden(const char *dir, const char *name, uint8_t *out, size_t cap) {
    char path[512];
    char hex[HEX_MAX];
    golden_path(path, sizeof path, dir, name);
    FILE *f = fopen(path, "r");
    TEST_ASSERT_NOT_NULL_MESSAGE(f, path);
    size_t n = fread(hex, 1, sizeof hex - 1, f);
    fclose(f);
    hex[n] = '\0';
    while (n > 0 && (hex[n - 1] == '\n' || hex[n - 1] == '\r')) {
        hex[--n] = '\0';
    }
    TEST_ASSERT_EQUAL_MESSAGE(0, n % 2, "odd number of hex digits");
    TEST_ASSERT_TRUE_MESSAGE(n / 2 <= cap, "golden frame larger than the buffer");
    for (size_t i = 0; i < n / 2; i++) {
        unsigned v = 0;
        TEST_ASSERT_EQUAL_MESSAGE(1, sscanf(&hex[2 * i], "%2x", &v), "bad hex digit");
        out[i] = (uint8_t)v;
    }
    return n / 2;
}

static void write_golden(const char *dir, const char *name, const uint8_t *wire, size_t len) {
    char path[512];
    golden_path(path, sizeof path, dir, name);
    FILE *f = fopen(path, "w");
    TEST_ASSERT_NOT_NULL_MESSAGE(f, path);
    for (size_t i = 0; i < len; i++) {
        fprintf(f, "%02x", wire[i]);
    }
    fputc('\n', f);
    fclose(f);
}

/* Encode `p` and compare with (or, in write mode, write) the golden file. */
static void check_written(const char *name, const oibar_v1_Packet *p) {
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    size_t len = oibar_frame_encode(p, wire, sizeof wire);
    TEST_ASSERT_TRUE_MESSAGE(len > 0, name);
    const char *mode = getenv("OIBAR_GOLDEN_WRITE");
    if (mode != NULL && strcmp(mode, "1") == 0) {
        write_golden("mcu_to_host", name, wire, len);
    }
    uint8_t golden[OIBAR_FRAME_MAX_WIRE_BYTES];
    size_t golden_len = read_golden("mcu_to_host", name, golden, sizeof golden);
    TEST_ASSERT_EQUAL_UINT_MESSAGE(golden_len, len, name);
    TEST_ASSERT_EQUAL_HEX8_ARRAY_MESSAGE(golden, wire, len, name);
}

/* Decode a host_to_mcu golden frame byte by byte; exactly one packet must come out, at the
 * delimiter, and the decoder must count exactly one good packet. */
static oibar_v1_Packet read_host_frame(const char *name) {
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    size_t len = read_golden("host_to_mcu", name, wire, sizeof wire);
    oibar_frame_decoder_t dec;
    oibar_frame_decoder_init(&dec, OIBAR_BODIES_HOST_TO_MCU);
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    for (size_t i = 0; i < len; i++) {
        oibar_rx_result_t r = oibar_frame_decoder_feed(&dec, wire[i], &p);
        TEST_ASSERT_EQUAL_INT_MESSAGE(i + 1 == len ? OIBAR_RX_PACKET : OIBAR_RX_NONE, r, name);
    }
    TEST_ASSERT_EQUAL_UINT32(1, oibar_frame_decoder_counters(&dec)->rx_packets);
    /* And the C encoder gives the same bytes back: no drift in either direction. */
    uint8_t again[OIBAR_FRAME_MAX_WIRE_BYTES];
    size_t again_len = oibar_frame_encode(&p, again, sizeof again);
    TEST_ASSERT_EQUAL_UINT(len, again_len);
    TEST_ASSERT_EQUAL_HEX8_ARRAY(wire, again, len);
    return p;
}

/* ---------------------------------------------------------------- host -> MCU (read) */

static void test_reads_handshake_v2(void) {
    oibar_v1_Packet p = read_host_frame("handshake_v2");
    TEST_ASSERT_EQUAL_UINT32(1, p.seq);
    TEST_ASSERT_EQUAL(oibar_v1_Packet_handshake_tag, p.which_body);
    TEST_ASSERT_EQUAL_UINT32(2, oibar_v1_PROTOCOL_VERSION);
    TEST_ASSERT_EQUAL_UINT32(oibar_v1_PROTOCOL_VERSION, p.body.handshake.protocol_version);
    TEST_ASSERT_EQUAL_STRING("oibar-host 0.1.0", p.body.handshake.host_version);
}

/* An old host (version 1: it never sets NavUpdate.valid) is another version. */
static void test_reads_handshake_v1(void) {
    oibar_v1_Packet p = read_host_frame("handshake_v1");
    TEST_ASSERT_EQUAL(oibar_v1_Packet_handshake_tag, p.which_body);
    TEST_ASSERT_EQUAL_UINT32(1, p.body.handshake.protocol_version);
    TEST_ASSERT_NOT_EQUAL(oibar_v1_PROTOCOL_VERSION, p.body.handshake.protocol_version);
    TEST_ASSERT_EQUAL_STRING("old-host", p.body.handshake.host_version);
}

static void test_reads_heartbeat_host(void) {
    oibar_v1_Packet p = read_host_frame("heartbeat_host");
    TEST_ASSERT_EQUAL_UINT32(2, p.seq);
    TEST_ASSERT_EQUAL(oibar_v1_Packet_heartbeat_tag, p.which_body);
    TEST_ASSERT_EQUAL_UINT32(65536, p.body.heartbeat.uptime_ms);
}

static void test_reads_command_start_transfer(void) {
    oibar_v1_Packet p = read_host_frame("command_start_transfer");
    TEST_ASSERT_EQUAL_UINT32(41, p.seq);
    TEST_ASSERT_EQUAL(oibar_v1_Packet_command_tag, p.which_body);
    TEST_ASSERT_EQUAL(oibar_v1_CMD_START_TRANSFER, p.body.command.opcode);
    TEST_ASSERT_EQUAL_FLOAT(1200.5f, p.body.command.target_pressure_kpa);
}

static void test_reads_command_abort(void) {
    oibar_v1_Packet p = read_host_frame("command_abort");
    TEST_ASSERT_EQUAL_UINT32(42, p.seq);
    TEST_ASSERT_EQUAL(oibar_v1_CMD_ABORT, p.body.command.opcode);
    TEST_ASSERT_EQUAL_FLOAT(0.0f, p.body.command.target_pressure_kpa);
}

static void test_reads_command_end_session(void) {
    oibar_v1_Packet p = read_host_frame("command_end_session");
    TEST_ASSERT_EQUAL_UINT32(43, p.seq);
    TEST_ASSERT_EQUAL(oibar_v1_Packet_command_tag, p.which_body);
    TEST_ASSERT_EQUAL(oibar_v1_CMD_END_SESSION, p.body.command.opcode);
    TEST_ASSERT_EQUAL_FLOAT(0.0f, p.body.command.target_pressure_kpa);
}

static void test_reads_nav_update(void) {
    oibar_v1_Packet p = read_host_frame("nav_update");
    const oibar_v1_NavUpdate *n = &p.body.nav_update;
    TEST_ASSERT_EQUAL_UINT32(1000, p.seq);
    TEST_ASSERT_EQUAL(oibar_v1_Packet_nav_update_tag, p.which_body);
    TEST_ASSERT_EQUAL_UINT32(3021, n->frame_id);
    TEST_ASSERT_EQUAL_UINT32(302100, n->stamp_ms);
    TEST_ASSERT_TRUE(n->has_t_cam_target_m);
    TEST_ASSERT_EQUAL_FLOAT(-0.0625f, n->t_cam_target_m.x);
    TEST_ASSERT_EQUAL_FLOAT(0.125f, n->t_cam_target_m.y);
    TEST_ASSERT_EQUAL_FLOAT(4.25f, n->t_cam_target_m.z);
    TEST_ASSERT_TRUE(n->has_q_cam_target);
    TEST_ASSERT_EQUAL_FLOAT(0.5f, n->q_cam_target.w);
    TEST_ASSERT_EQUAL_FLOAT(-0.5f, n->q_cam_target.x);
    TEST_ASSERT_EQUAL_FLOAT(0.5f, n->q_cam_target.y);
    TEST_ASSERT_EQUAL_FLOAT(0.5f, n->q_cam_target.z);
    TEST_ASSERT_EQUAL_FLOAT(4.25f, n->range_m);
    TEST_ASSERT_TRUE(n->valid);
    TEST_ASSERT_EQUAL_FLOAT(0.03125f, n->closing_speed_mps);
    TEST_ASSERT_EQUAL(oibar_v1_NAV_PHASE_FORCED_TRANSLATION, n->phase);
    TEST_ASSERT_EQUAL_FLOAT(0.875f, n->confidence);
}

static void test_reads_param_get(void) {
    oibar_v1_Packet p = read_host_frame("param_get");
    TEST_ASSERT_EQUAL_UINT32(7, p.seq);
    TEST_ASSERT_EQUAL(oibar_v1_Packet_param_get_tag, p.which_body);
    TEST_ASSERT_EQUAL_UINT32(3, p.body.param_get.param_id);
}

static void test_reads_param_set(void) {
    oibar_v1_Packet p = read_host_frame("param_set");
    TEST_ASSERT_EQUAL_UINT32(8, p.seq);
    TEST_ASSERT_EQUAL(oibar_v1_Packet_param_set_tag, p.which_body);
    TEST_ASSERT_EQUAL_UINT32(3, p.body.param_set.param_id);
    TEST_ASSERT_EQUAL_FLOAT(1500.0f, p.body.param_set.value);
}

/* ---------------------------------------------------------------- MCU -> host (write) */

static void test_writes_handshake_reply_accepted(void) {
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = 1;
    p.ack_seq = 1;
    p.which_body = oibar_v1_Packet_handshake_reply_tag;
    oibar_v1_HandshakeReply *r = &p.body.handshake_reply;
    r->accepted = true;
    r->protocol_version = oibar_v1_PROTOCOL_VERSION;
    strcpy(r->firmware_version, "0.1.0");
    strcpy(r->build_id, "golden-0001");
    r->reset_cause = oibar_v1_RESET_POWER_ON;
    r->uptime_ms = 1234;
    check_written("handshake_reply_accepted", &p);
}

static void test_writes_handshake_reply_version_mismatch(void) {
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = 2;
    p.ack_seq = 1;
    p.which_body = oibar_v1_Packet_handshake_reply_tag;
    oibar_v1_HandshakeReply *r = &p.body.handshake_reply;
    r->accepted = false;
    r->reason = oibar_v1_NACK_VERSION_MISMATCH;
    r->protocol_version = oibar_v1_PROTOCOL_VERSION;
    strcpy(r->firmware_version, "0.1.0");
    strcpy(r->build_id, "golden-0001");
    r->reset_cause = oibar_v1_RESET_WATCHDOG;
    r->uptime_ms = 99;
    check_written("handshake_reply_version_mismatch", &p);
}

static void test_writes_ack_accepted(void) {
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = 17;
    p.ack_seq = 41;
    p.which_body = oibar_v1_Packet_ack_tag;
    p.body.ack.accepted = true;
    p.body.ack.state = oibar_v1_STATE_TRANSFERRING;
    check_written("ack_accepted", &p);
}

static void test_writes_ack_nack_invalid_in_state(void) {
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = 3;
    p.ack_seq = 7;
    p.which_body = oibar_v1_Packet_ack_tag;
    p.body.ack.accepted = false;
    p.body.ack.reason = oibar_v1_NACK_INVALID_IN_STATE;
    p.body.ack.state = oibar_v1_STATE_IDLE;
    check_written("ack_nack_invalid_in_state", &p);
}

static void test_writes_telemetry_transferring(void) {
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = 500;
    p.which_body = oibar_v1_Packet_telemetry_tag;
    oibar_v1_Telemetry *t = &p.body.telemetry;
    t->uptime_ms = 600000;
    t->state = oibar_v1_STATE_TRANSFERRING;
    t->latch_pos_steps = -12;
    t->latch_engaged = true;
    t->plane_pos_mm = 42.5f;
    t->contact = true;
    t->connector_mated = true;
    t->sv_valve_cmd_open = true;
    t->sv_valve_open = true;
    t->tv_valve_cmd_open = true;
    t->tv_valve_open = true;
    t->sv_tank_kpa = 2500.25f;
    t->tv_tank_kpa = 1100.75f;
    t->line_kpa = 1800.5f;
    t->target_pressure_kpa = 1200.5f;
    t->has_link = true;
    t->link.rx_packets = 4321;
    t->link.rx_crc_errors = 2;
    t->link.rx_framing_errors = 1;
    t->link.rx_duplicates = 3;
    t->link.tx_packets = 5000;
    t->host_link_alive = true;
    check_written("telemetry_transferring", &p);
}

static void test_writes_telemetry_link_errors(void) {
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = 502;
    p.which_body = oibar_v1_Packet_telemetry_tag;
    oibar_v1_Telemetry *t = &p.body.telemetry;
    t->uptime_ms = 600100;
    t->state = oibar_v1_STATE_HARD_DOCKED;
    t->has_link = true;
    t->link.rx_packets = 900;
    t->link.rx_crc_errors = 4;
    t->host_link_alive = true;
    t->events_lost = 2;
    t->uart_rx_errors = 5;
    t->uart_rx_overruns = 300;
    check_written("telemetry_link_errors", &p);
}

static void test_writes_event_fault_overpressure(void) {
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = 501;
    p.which_body = oibar_v1_Packet_event_tag;
    oibar_v1_Event *e = &p.body.event;
    e->uptime_ms = 600050;
    e->id = oibar_v1_EVT_FAULT;
    e->severity = oibar_v1_SEVERITY_WARNING_HI;
    e->from_state = oibar_v1_STATE_TRANSFERRING;
    e->to_state = oibar_v1_STATE_FAULT;
    e->fault = oibar_v1_FAULT_OVERPRESSURE;
    check_written("event_fault_overpressure", &p);
}

static void test_writes_param_value(void) {
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = 4;
    p.ack_seq = 7;
    p.which_body = oibar_v1_Packet_param_value_tag;
    oibar_v1_ParamValue *v = &p.body.param_value;
    v->param_id = 3;
    v->value = 1000.0f;
    v->min = 200.0f;
    v->max = 10000.0f;
    v->default_value = 1000.0f;
    strcpy(v->name, "link_timeout_ms");
    strcpy(v->unit, "ms");
    check_written("param_value", &p);
}

static void test_writes_heartbeat_mcu_max_seq(void) {
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = UINT32_MAX;
    p.which_body = oibar_v1_Packet_heartbeat_tag;
    p.body.heartbeat.uptime_ms = UINT32_MAX;
    check_written("heartbeat_mcu_max_seq", &p);
}

int main(void) {
    UNITY_BEGIN();
    RUN_TEST(test_reads_handshake_v2);
    RUN_TEST(test_reads_handshake_v1);
    RUN_TEST(test_reads_heartbeat_host);
    RUN_TEST(test_reads_command_start_transfer);
    RUN_TEST(test_reads_command_abort);
    RUN_TEST(test_reads_command_end_session);
    RUN_TEST(test_reads_nav_update);
    RUN_TEST(test_reads_param_get);
    RUN_TEST(test_reads_param_set);
    RUN_TEST(test_writes_handshake_reply_accepted);
    RUN_TEST(test_writes_handshake_reply_version_mismatch);
    RUN_TEST(test_writes_ack_accepted);
    RUN_TEST(test_writes_ack_nack_invalid_in_state);
    RUN_TEST(test_writes_telemetry_transferring);
    RUN_TEST(test_writes_telemetry_link_errors);
    RUN_TEST(test_writes_event_fault_overpressure);
    RUN_TEST(test_writes_param_value);
    RUN_TEST(test_writes_heartbeat_mcu_max_seq);
    return UNITY_END();
}
