/* Frame encoder and streaming decoder: every row of the receive table in
 * docs/link.md, each followed by a valid frame to prove resynchronisation. */
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

#include <pb_encode.h>

#include "unity.h"

#include "oibar/cobs.h"
#include "oibar/crc32c.h"
#include "oibar/frame.h"

static oibar_frame_decoder_t dec;
static oibar_v1_Packet out;

void setUp(void)
{
    oibar_frame_decoder_init(&dec, OIBAR_BODIES_HOST_TO_MCU);
    memset(&out, 0, sizeof(out));
}
void tearDown(void) {}

/* ------------------------------------------------------------------------- */
/* Helpers                                                                   */

static uint32_t rng_state = 0xF4A3Eu;
static uint32_t rng(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 17;
    rng_state ^= rng_state << 5;
    return rng_state;
}

static oibar_v1_Packet heartbeat(uint32_t seq, uint32_t uptime_ms)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = seq;
    p.which_body = oibar_v1_Packet_heartbeat_tag;
    p.body.heartbeat.uptime_ms = uptime_ms;
    return p;
}

static size_t pb_bytes(const oibar_v1_Packet *p, uint8_t *buf, size_t cap)
{
    pb_ostream_t s = pb_ostream_from_buffer(buf, cap);
    TEST_ASSERT_TRUE(pb_encode(&s, oibar_v1_Packet_fields, p));
    return s.bytes_written;
}

/* A wire frame built by hand, so that any part of it can be wrong. */
static size_t make_wire(uint8_t header, const uint8_t *pb, size_t pb_len, uint32_t crc_xor,
                        uint8_t *wire, size_t cap)
{
    uint8_t raw[400];
    TEST_ASSERT_TRUE(pb_len + 5u <= sizeof(raw));
    raw[0] = header;
    if (pb_len > 0) {
        memcpy(&raw[1], pb, pb_len);
    }
    const uint32_t crc = oibar_crc32c(raw, 1u + pb_len) ^ crc_xor;
    for (unsigned i = 0; i < 4; ++i) {
        raw[1u + pb_len + i] = (uint8_t)(crc >> (8u * i));
    }
    size_t n = 0;
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_encode(raw, pb_len + 5u, wire, cap - 1u, &n));
    wire[n] = 0x00;
    return n + 1u;
}

/* Protobuf bytes of exactly `len` bytes: seq, a heartbeat, then an unknown
 * length-delimited field (number 15) as padding, which decoders skip. */
static size_t padded_pb(size_t len, uint8_t *buf)
{
    const uint8_t head[] = {0x08, 0x07, 0x2A, 0x02, 0x08, 0x2A}; /* seq 7, heartbeat{uptime 42} */
    memcpy(buf, head, sizeof(head));
    size_t n = sizeof(head);
    const size_t rest = len - n; /* tag + length varint + payload */
    buf[n++] = 0x7A;             /* field 15, wire type 2 */
    const size_t payload = (rest - 1u >= 129u) ? rest - 3u : rest - 2u;
    if (payload >= 128u) {
        buf[n++] = (uint8_t)(0x80u | (payload & 0x7Fu));
        buf[n++] = (uint8_t)(payload >> 7);
    } else {
        buf[n++] = (uint8_t)payload;
    }
    memset(&buf[n], 0x55, payload);
    n += payload;
    TEST_ASSERT_EQUAL_size_t(len, n);
    return n;
}

/* Feed a whole buffer one byte at a time; every byte but the last must be
 * absorbed silently. Returns the outcome of the last byte. */
static oibar_rx_result_t feed_frame(const uint8_t *wire, size_t len)
{
    for (size_t i = 0; i + 1u < len; ++i) {
        TEST_ASSERT_EQUAL_MESSAGE(OIBAR_RX_NONE, oibar_frame_decoder_feed(&dec, wire[i], &out),
                                  "frame ended early");
    }
    return oibar_frame_decoder_feed(&dec, wire[len - 1u], &out);
}

static void feed_silently(const uint8_t *bytes, size_t len)
{
    for (size_t i = 0; i < len; ++i) {
        TEST_ASSERT_EQUAL(OIBAR_RX_NONE, oibar_frame_decoder_feed(&dec, bytes[i], &out));
    }
}

/* The resynchronisation check that follows every bad-input case. */
static void expect_next_valid_frame_decodes(void)
{
    static uint32_t seq = 1000;
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const oibar_v1_Packet p = heartbeat(++seq, 77);
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    const uint32_t before = dec.counters.rx_packets;
    TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, feed_frame(wire, n));
    TEST_ASSERT_EQUAL_UINT32(seq, out.seq);
    TEST_ASSERT_EQUAL_UINT32(before + 1u, dec.counters.rx_packets);
}

static uint32_t counters_sum(const oibar_frame_counters_t *c)
{
    return c->rx_packets + c->rx_crc_errors + c->rx_framing_errors + c->rx_oversize +
           c->rx_bad_header + c->rx_decode_errors + c->rx_unknown_type;
}

/* ------------------------------------------------------------------------- */
/* Encoder                                                                   */

static void test_encode_layout(void)
{
    const oibar_v1_Packet p = heartbeat(1, 0x1234);
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    TEST_ASSERT_TRUE(n > 0);
    TEST_ASSERT_EQUAL_HEX8(0x00, wire[n - 1]);
    TEST_ASSERT_NULL(memchr(wire, 0, n - 1));

    uint8_t raw[OIBAR_FRAME_MAX_WIRE_BYTES];
    size_t raw_len = 0;
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_decode(wire, n - 1, raw, sizeof(raw), &raw_len));
    uint8_t pb[64];
    const size_t pb_len = pb_bytes(&p, pb, sizeof(pb));
    TEST_ASSERT_EQUAL_size_t(1 + pb_len + 4, raw_len);
    TEST_ASSERT_EQUAL_HEX8(OIBAR_FRAME_HEADER, raw[0]);
    TEST_ASSERT_EQUAL_HEX8_ARRAY(pb, &raw[1], pb_len);
    const uint32_t crc = oibar_crc32c(raw, 1 + pb_len);
    TEST_ASSERT_EQUAL_HEX8((uint8_t)crc, raw[1 + pb_len]); /* little-endian */
    TEST_ASSERT_EQUAL_HEX8((uint8_t)(crc >> 24), raw[1 + pb_len + 3]);

    /* Same bytes as framing the protobuf encoding directly. */
    uint8_t wire2[OIBAR_FRAME_MAX_WIRE_BYTES];
    TEST_ASSERT_EQUAL_size_t(n, oibar_frame_encode_bytes(pb, pb_len, wire2, sizeof(wire2)));
    TEST_ASSERT_EQUAL_HEX8_ARRAY(wire, wire2, n);
}

/* Packet{seq: 1, heartbeat{uptime_ms: 0}}, worked out by hand: protobuf
 * 08 01 2A 00, raw 01 08 01 2A 00 + CRC-32C LE, then COBS. */
static void test_encode_known_bytes(void)
{
    const oibar_v1_Packet p = heartbeat(1, 0);
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    const uint8_t raw_head[] = {0x01, 0x08, 0x01, 0x2A, 0x00};
    const uint32_t crc = oibar_crc32c(raw_head, sizeof(raw_head));
    const uint8_t c0 = (uint8_t)crc, c1 = (uint8_t)(crc >> 8), c2 = (uint8_t)(crc >> 16),
                  c3 = (uint8_t)(crc >> 24);
    TEST_ASSERT_TRUE(c0 && c1 && c2 && c3); /* keeps the expected COBS layout simple */
    const uint8_t expect[] = {0x05, 0x01, 0x08, 0x01, 0x2A, 0x05, c0, c1, c2, c3, 0x00};
    TEST_ASSERT_EQUAL_size_t(sizeof(expect), n);
    TEST_ASSERT_EQUAL_HEX8_ARRAY(expect, wire, n);
}

static void test_encode_needs_room(void)
{
    const oibar_v1_Packet p = heartbeat(9, 99);
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    for (size_t cap = 0; cap < n; ++cap) {
        TEST_ASSERT_EQUAL_size_t(0, oibar_frame_encode(&p, wire, cap));
    }
    TEST_ASSERT_EQUAL_size_t(n, oibar_frame_encode(&p, wire, n));
}

/* A string without its terminator is an application bug: no frame, no crash. */
static void test_encode_refuses_unterminated_string(void)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_handshake_reply_tag;
    memset(p.body.handshake_reply.build_id, 'x', sizeof(p.body.handshake_reply.build_id));
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    TEST_ASSERT_EQUAL_size_t(0, oibar_frame_encode(&p, wire, sizeof(wire)));
}

/* The largest Packet the schema allows fits PROTOCOL_MAX_PACKET_BYTES. */
static void test_encode_largest_schema_packet(void)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = UINT32_MAX;
    p.ack_seq = UINT32_MAX;
    p.which_body = oibar_v1_Packet_telemetry_tag;
    oibar_v1_Telemetry *t = &p.body.telemetry;
    t->uptime_ms = UINT32_MAX;
    t->state = oibar_v1_STATE_FAULT;
    t->fault_flags = UINT32_MAX;
    t->latch_pos_steps = INT32_MIN; /* negative int32: 10-byte varint */
    t->latch_engaged = t->contact = t->connector_mated = true;
    t->sv_valve_cmd_open = t->sv_valve_open = t->tv_valve_cmd_open = t->tv_valve_open = true;
    t->plane_pos_mm = t->sv_tank_kpa = t->tv_tank_kpa = t->line_kpa = t->target_pressure_kpa = 1.5f;
    t->has_link = true;
    uint32_t *c = &t->link.rx_packets;
    for (int i = 0; i < 11; ++i) {
        c[i] = UINT32_MAX;
    }
    t->event_queue_overflows = UINT32_MAX;
    t->host_link_alive = true;
    uint8_t pb[300];
    const size_t len = pb_bytes(&p, pb, sizeof(pb));
    TEST_ASSERT_TRUE(len <= oibar_v1_Packet_size);
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    TEST_ASSERT_TRUE(n > 0);
    oibar_frame_decoder_init(&dec, OIBAR_BODIES_MCU_TO_HOST);
    TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, feed_frame(wire, n));
    TEST_ASSERT_EQUAL_INT32(INT32_MIN, out.body.telemetry.latch_pos_steps);
}

/* ------------------------------------------------------------------------- */
/* Decoder: good input                                                       */

static void test_decode_round_trip(void)
{
    const oibar_v1_Packet p = heartbeat(42, 123456);
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, feed_frame(wire, n));
    TEST_ASSERT_EQUAL_UINT32(42, out.seq);
    TEST_ASSERT_EQUAL(oibar_v1_Packet_heartbeat_tag, out.which_body);
    TEST_ASSERT_EQUAL_UINT32(123456, out.body.heartbeat.uptime_ms);
    TEST_ASSERT_EQUAL_UINT32(1, dec.counters.rx_packets);
    TEST_ASSERT_EQUAL_UINT32(1, counters_sum(&dec.counters));
}

/* Every body type survives encode -> decode unchanged. */
static void test_every_body_round_trips(void)
{
    oibar_frame_decoder_init(&dec, OIBAR_BODIES_ALL);
    for (pb_size_t tag = oibar_v1_Packet_handshake_tag; tag <= oibar_v1_Packet_event_tag; ++tag) {
        oibar_v1_Packet p = oibar_v1_Packet_init_zero;
        p.seq = 1000u + tag;
        p.ack_seq = 7u;
        p.which_body = tag;
        uint8_t *body = (uint8_t *)&p.body;
        for (size_t i = 0; i < sizeof(p.body); ++i) {
            body[i] = (uint8_t)(1u + i % 3u); /* small non-zero values everywhere */
        }
        /* make strings and bools valid */
        switch (tag) {
        case oibar_v1_Packet_handshake_tag: strcpy(p.body.handshake.host_version, "host-1.0"); break;
        case oibar_v1_Packet_handshake_reply_tag:
            p.body.handshake_reply.accepted = true;
            strcpy(p.body.handshake_reply.firmware_version, "1.2.3");
            strcpy(p.body.handshake_reply.build_id, "abcdef0123456789abcdef0");
            break;
        case oibar_v1_Packet_ack_tag: p.body.ack.accepted = false; break;
        case oibar_v1_Packet_nav_update_tag:
            p.body.nav_update.has_t_cam_target_m = true;
            p.body.nav_update.has_q_cam_target = true;
            break;
        case oibar_v1_Packet_param_value_tag:
            strcpy(p.body.param_value.name, "telemetry_period_ms");
            strcpy(p.body.param_value.unit, "ms");
            break;
        case oibar_v1_Packet_telemetry_tag: {
            oibar_v1_Telemetry *t = &p.body.telemetry;
            t->latch_engaged = t->contact = t->connector_mated = true;
            t->sv_valve_cmd_open = t->sv_valve_open = false;
            t->tv_valve_cmd_open = t->tv_valve_open = t->host_link_alive = true;
            t->has_link = true;
            break;
        }
        default: break;
        }
        uint8_t pb1[300], pb2[300], wire[OIBAR_FRAME_MAX_WIRE_BYTES];
        const size_t len1 = pb_bytes(&p, pb1, sizeof(pb1));
        const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
        TEST_ASSERT_TRUE(n > 0);
        TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, feed_frame(wire, n));
        TEST_ASSERT_EQUAL(tag, out.which_body);
        const size_t len2 = pb_bytes(&out, pb2, sizeof(pb2));
        TEST_ASSERT_EQUAL_size_t(len1, len2);
        TEST_ASSERT_EQUAL_HEX8_ARRAY(pb1, pb2, len1);
    }
    TEST_ASSERT_EQUAL_UINT32(11, dec.counters.rx_packets);
}

static void test_idle_delimiters_are_ignored(void)
{
    const uint8_t zeros[10] = {0};
    feed_silently(zeros, sizeof(zeros));
    TEST_ASSERT_EQUAL_UINT32(0, counters_sum(&dec.counters));
    expect_next_valid_frame_decodes();
    feed_silently(zeros, sizeof(zeros));
    expect_next_valid_frame_decodes();
    TEST_ASSERT_EQUAL_UINT32(2, counters_sum(&dec.counters));
}

/* A leading 0x00 (frame start marker) does no harm. */
static void test_leading_delimiter_is_harmless(void)
{
    TEST_ASSERT_EQUAL(OIBAR_RX_NONE, oibar_frame_decoder_feed(&dec, 0x00, &out));
    expect_next_valid_frame_decodes();
}

static void test_max_size_packet_accepted(void)
{
    uint8_t pb[OIBAR_FRAME_MAX_PACKET_BYTES];
    const size_t len = padded_pb(sizeof(pb), pb);
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t n = oibar_frame_encode_bytes(pb, len, wire, sizeof(wire));
    TEST_ASSERT_EQUAL_size_t(OIBAR_FRAME_MAX_WIRE_BYTES, n); /* exactly 247 on the wire */
    TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, feed_frame(wire, n));
    TEST_ASSERT_EQUAL_UINT32(7, out.seq);
    TEST_ASSERT_EQUAL_UINT32(42, out.body.heartbeat.uptime_ms);
    expect_next_valid_frame_decodes();
}

static void test_one_byte_over_max_rejected(void)
{
    uint8_t pb[OIBAR_FRAME_MAX_PACKET_BYTES + 1];
    const size_t len = padded_pb(sizeof(pb), pb);
    uint8_t wire[300];
    /* The encoder refuses it ... */
    TEST_ASSERT_EQUAL_size_t(0, oibar_frame_encode_bytes(pb, len, wire, sizeof(wire)));
    /* ... and the decoder drops it when a peer sends it anyway. */
    const size_t n = make_wire(OIBAR_FRAME_HEADER, pb, len, 0, wire, sizeof(wire));
    TEST_ASSERT_EQUAL_size_t(OIBAR_FRAME_MAX_WIRE_BYTES + 1, n);
    oibar_rx_result_t last = OIBAR_RX_NONE;
    for (size_t i = 0; i < n; ++i) {
        const oibar_rx_result_t r = oibar_frame_decoder_feed(&dec, wire[i], &out);
        if (r != OIBAR_RX_NONE) {
            TEST_ASSERT_EQUAL(OIBAR_RX_NONE, last); /* only one outcome per frame */
            TEST_ASSERT_EQUAL_size_t(OIBAR_FRAME_MAX_ENCODED_BYTES, i); /* at the 247th byte */
            last = r;
        }
    }
    TEST_ASSERT_EQUAL(OIBAR_RX_OVERSIZE, last);
    TEST_ASSERT_EQUAL_UINT32(1, dec.counters.rx_oversize);
    TEST_ASSERT_EQUAL_UINT32(1, counters_sum(&dec.counters));
    expect_next_valid_frame_decodes();
}

static void test_oversize_garbage_counted_once(void)
{
    uint8_t junk[1000];
    memset(junk, 0xA5, sizeof(junk));
    for (size_t i = 0; i < sizeof(junk); ++i) {
        (void)oibar_frame_decoder_feed(&dec, junk[i], &out);
    }
    TEST_ASSERT_EQUAL_UINT32(1, dec.counters.rx_oversize);
    TEST_ASSERT_EQUAL(OIBAR_RX_NONE, oibar_frame_decoder_feed(&dec, 0x00, &out));
    TEST_ASSERT_EQUAL_UINT32(1, counters_sum(&dec.counters));
    expect_next_valid_frame_decodes();
}

/* A 246-byte run is still a frame (a bad one here), not oversize. */
static void test_246_bytes_is_not_oversize(void)
{
    uint8_t junk[OIBAR_FRAME_MAX_ENCODED_BYTES + 1];
    memset(junk, 0x33, sizeof(junk));
    junk[sizeof(junk) - 1] = 0x00;
    TEST_ASSERT_NOT_EQUAL(OIBAR_RX_OVERSIZE, feed_frame(junk, sizeof(junk)));
    TEST_ASSERT_EQUAL_UINT32(0, dec.counters.rx_oversize);
    TEST_ASSERT_EQUAL_UINT32(1, dec.counters.rx_framing_errors); /* code 0x33 overruns */
    expect_next_valid_frame_decodes();
}

/* ------------------------------------------------------------------------- */
/* Decoder: each bad-input row                                               */

static void test_cobs_code_past_end_is_framing_error(void)
{
    const uint8_t bad[] = {0x09, 0x01, 0x02, 0x03, 0x00};
    TEST_ASSERT_EQUAL(OIBAR_RX_FRAMING_ERROR, feed_frame(bad, sizeof(bad)));
    TEST_ASSERT_EQUAL_UINT32(1, dec.counters.rx_framing_errors);
    expect_next_valid_frame_decodes();
}

static void test_truncated_frames_are_framing_errors(void)
{
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const oibar_v1_Packet p = heartbeat(5, 5);
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    uint32_t expected_errors = 0;
    /* Cut after k encoded bytes, then the delimiter. */
    for (size_t k = 1; k + 1 < n; ++k) {
        feed_silently(wire, k);
        const oibar_rx_result_t r = oibar_frame_decoder_feed(&dec, 0x00, &out);
        TEST_ASSERT_TRUE(r == OIBAR_RX_FRAMING_ERROR || r == OIBAR_RX_CRC_ERROR);
        ++expected_errors;
        expect_next_valid_frame_decodes();
    }
    TEST_ASSERT_EQUAL_UINT32(expected_errors, dec.counters.rx_framing_errors + dec.counters.rx_crc_errors);
}

static void test_raw_frame_shorter_than_5_bytes(void)
{
    for (size_t raw_len = 1; raw_len < 5; ++raw_len) {
        uint8_t raw[4] = {0x01, 0x11, 0x22, 0x33};
        uint8_t wire[8];
        size_t n = 0;
        TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_encode(raw, raw_len, wire, sizeof(wire), &n));
        wire[n++] = 0x00;
        TEST_ASSERT_EQUAL(OIBAR_RX_FRAMING_ERROR, feed_frame(wire, n));
        expect_next_valid_frame_decodes();
    }
    TEST_ASSERT_EQUAL_UINT32(4, dec.counters.rx_framing_errors);
}

/* 5 bytes (header + empty packet + CRC) is long enough: it decodes to a
 * packet without a body. */
static void test_empty_packet_is_unknown_type(void)
{
    uint8_t wire[16];
    const size_t n = make_wire(OIBAR_FRAME_HEADER, NULL, 0, 0, wire, sizeof(wire));
    TEST_ASSERT_EQUAL(OIBAR_RX_UNKNOWN_TYPE, feed_frame(wire, n));
    TEST_ASSERT_EQUAL_UINT32(0, out.seq);
    TEST_ASSERT_EQUAL_UINT32(1, dec.counters.rx_unknown_type);
    expect_next_valid_frame_decodes();
}

static void test_bad_header(void)
{
    uint8_t pb[32], wire[64];
    const oibar_v1_Packet p = heartbeat(3, 3);
    const size_t len = pb_bytes(&p, pb, sizeof(pb));
    const uint8_t headers[] = {0x00, 0x02, 0x7F, 0xFF};
    for (size_t i = 0; i < sizeof(headers); ++i) {
        const size_t n = make_wire(headers[i], pb, len, 0, wire, sizeof(wire));
        TEST_ASSERT_EQUAL(OIBAR_RX_BAD_HEADER, feed_frame(wire, n));
        expect_next_valid_frame_decodes();
    }
    TEST_ASSERT_EQUAL_UINT32(4, dec.counters.rx_bad_header);
}

static void test_bad_crc(void)
{
    uint8_t pb[32], wire[64];
    const oibar_v1_Packet p = heartbeat(3, 3);
    const size_t len = pb_bytes(&p, pb, sizeof(pb));
    /* wrong CRC value */
    size_t n = make_wire(OIBAR_FRAME_HEADER, pb, len, 0x00000100u, wire, sizeof(wire));
    TEST_ASSERT_EQUAL(OIBAR_RX_CRC_ERROR, feed_frame(wire, n));
    expect_next_valid_frame_decodes();
    /* right CRC, one payload bit flipped on the way */
    n = make_wire(OIBAR_FRAME_HEADER, pb, len, 0, wire, sizeof(wire));
    wire[2] ^= 0x04;
    TEST_ASSERT_NOT_EQUAL(0, wire[2]);
    TEST_ASSERT_EQUAL(OIBAR_RX_CRC_ERROR, feed_frame(wire, n));
    expect_next_valid_frame_decodes();
    TEST_ASSERT_EQUAL_UINT32(2, dec.counters.rx_crc_errors);
}

static void test_protobuf_that_does_not_decode(void)
{
    const uint8_t wrong_wire_type[] = {0x0A, 0x01, 0x01};   /* seq as length-delimited */
    const uint8_t truncated_varint[] = {0x08, 0x80};        /* varint never ends */
    const uint8_t truncated_body[] = {0x2A, 0x05, 0x08};    /* heartbeat says 5 bytes, has 1 */
    uint8_t long_string[24] = {0x1A, 0x16, 0x12, 0x14};     /* handshake.host_version, 20 chars > 16 */
    memset(&long_string[4], 'v', 20);
    const struct {
        const uint8_t *pb;
        size_t len;
    } cases[] = {
        {wrong_wire_type, sizeof(wrong_wire_type)},
        {truncated_varint, sizeof(truncated_varint)},
        {truncated_body, sizeof(truncated_body)},
        {long_string, sizeof(long_string)},
    };
    uint8_t wire[64];
    for (size_t i = 0; i < sizeof(cases) / sizeof(cases[0]); ++i) {
        const size_t n = make_wire(OIBAR_FRAME_HEADER, cases[i].pb, cases[i].len, 0, wire, sizeof(wire));
        TEST_ASSERT_EQUAL(OIBAR_RX_DECODE_ERROR, feed_frame(wire, n));
        expect_next_valid_frame_decodes();
    }
    TEST_ASSERT_EQUAL_UINT32(4, dec.counters.rx_decode_errors);
}

static void test_unknown_body(void)
{
    uint8_t wire[64];
    /* no body at all, but a seq the MCU can nack */
    const uint8_t no_body[] = {0x08, 0x09};
    size_t n = make_wire(OIBAR_FRAME_HEADER, no_body, sizeof(no_body), 0, wire, sizeof(wire));
    TEST_ASSERT_EQUAL(OIBAR_RX_UNKNOWN_TYPE, feed_frame(wire, n));
    TEST_ASSERT_EQUAL_UINT32(9, out.seq);
    expect_next_valid_frame_decodes();
    /* a body from a future schema (field 14) */
    const uint8_t future_body[] = {0x08, 0x0A, 0x72, 0x02, 0x08, 0x01};
    n = make_wire(OIBAR_FRAME_HEADER, future_body, sizeof(future_body), 0, wire, sizeof(wire));
    TEST_ASSERT_EQUAL(OIBAR_RX_UNKNOWN_TYPE, feed_frame(wire, n));
    TEST_ASSERT_EQUAL_UINT32(10, out.seq);
    expect_next_valid_frame_decodes();
    /* a body this receiver does not take: Telemetry sent to the MCU */
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = 11;
    p.which_body = oibar_v1_Packet_telemetry_tag;
    n = oibar_frame_encode(&p, wire, sizeof(wire));
    TEST_ASSERT_EQUAL(OIBAR_RX_UNKNOWN_TYPE, feed_frame(wire, n));
    TEST_ASSERT_EQUAL_UINT32(11, out.seq);
    expect_next_valid_frame_decodes();
    TEST_ASSERT_EQUAL_UINT32(3, dec.counters.rx_unknown_type);
    TEST_ASSERT_EQUAL_UINT32(3, dec.counters.rx_packets);
}

static void test_garbage_between_frames_costs_nothing_else(void)
{
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const oibar_v1_Packet p = heartbeat(20, 1);
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, feed_frame(wire, n));
    const uint8_t garbage[] = {0x13, 0x37, 0xBE, 0xEF, 0x42, 0x00};
    const oibar_rx_result_t r = feed_frame(garbage, sizeof(garbage));
    TEST_ASSERT_NOT_EQUAL(OIBAR_RX_PACKET, r);
    TEST_ASSERT_NOT_EQUAL(OIBAR_RX_NONE, r);
    TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, feed_frame(wire, n));
    TEST_ASSERT_EQUAL_UINT32(2, dec.counters.rx_packets);
    TEST_ASSERT_EQUAL_UINT32(3, counters_sum(&dec.counters));
}

/* Garbage with no delimiter of its own spoils only the frame it touches. */
static void test_garbage_glued_to_a_frame_costs_that_frame_only(void)
{
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    const oibar_v1_Packet p = heartbeat(21, 1);
    const size_t n = oibar_frame_encode(&p, wire, sizeof(wire));
    const uint8_t garbage[] = {0x13, 0x37, 0xBE};
    feed_silently(garbage, sizeof(garbage));
    const oibar_rx_result_t r = feed_frame(wire, n);
    TEST_ASSERT_NOT_EQUAL(OIBAR_RX_PACKET, r);
    TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, feed_frame(wire, n));
    TEST_ASSERT_EQUAL_UINT32(2, counters_sum(&dec.counters));
}

static void test_frames_split_across_many_feeds(void)
{
    static uint8_t stream[20 * OIBAR_FRAME_MAX_WIRE_BYTES];
    size_t len = 0;
    for (uint32_t i = 0; i < 20; ++i) {
        const oibar_v1_Packet p = heartbeat(100 + i, i * 1000u);
        len += oibar_frame_encode(&p, &stream[len], sizeof(stream) - len);
    }
    /* Byte-sized to 40-byte chunks, chunk edges anywhere. */
    size_t pos = 0;
    uint32_t got = 0;
    while (pos < len) {
        size_t chunk = 1u + rng() % 40u;
        if (chunk > len - pos) {
            chunk = len - pos;
        }
        size_t off = 0;
        while (off < chunk) {
            size_t used = 0;
            const oibar_rx_result_t r = oibar_frame_decoder_feed_buf(&dec, &stream[pos + off], chunk - off, &used, &out);
            TEST_ASSERT_TRUE(used > 0);
            off += used;
            if (r != OIBAR_RX_NONE) {
                TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, r);
                TEST_ASSERT_EQUAL_UINT32(100 + got, out.seq);
                TEST_ASSERT_EQUAL_UINT32(got * 1000u, out.body.heartbeat.uptime_ms);
                ++got;
            }
        }
        pos += chunk;
    }
    TEST_ASSERT_EQUAL_UINT32(20, got);
    TEST_ASSERT_EQUAL_UINT32(20, counters_sum(&dec.counters));
}

static void test_feed_buf_stops_after_each_frame(void)
{
    uint8_t two[2 * OIBAR_FRAME_MAX_WIRE_BYTES];
    const oibar_v1_Packet a = heartbeat(1, 1), b = heartbeat(2, 2);
    const size_t na = oibar_frame_encode(&a, two, sizeof(two));
    const size_t nb = oibar_frame_encode(&b, &two[na], sizeof(two) - na);
    size_t used = 0;
    TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, oibar_frame_decoder_feed_buf(&dec, two, na + nb, &used, &out));
    TEST_ASSERT_EQUAL_size_t(na, used);
    TEST_ASSERT_EQUAL_UINT32(1, out.seq);
    TEST_ASSERT_EQUAL(OIBAR_RX_PACKET, oibar_frame_decoder_feed_buf(&dec, &two[na], nb, &used, &out));
    TEST_ASSERT_EQUAL_size_t(nb, used);
    TEST_ASSERT_EQUAL_UINT32(2, out.seq);
    TEST_ASSERT_EQUAL(OIBAR_RX_NONE, oibar_frame_decoder_feed_buf(&dec, two, 3, &used, &out));
    TEST_ASSERT_EQUAL_size_t(3, used);
}

static void test_init_clears_counters_and_partial_frame(void)
{
    const uint8_t partial[] = {0x05, 0x01};
    feed_silently(partial, sizeof(partial));
    dec.counters.rx_crc_errors = 5;
    oibar_frame_decoder_init(&dec, OIBAR_BODIES_HOST_TO_MCU);
    TEST_ASSERT_EQUAL_UINT32(0, counters_sum(oibar_frame_decoder_counters(&dec)));
    expect_next_valid_frame_decodes();
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_encode_layout);
    RUN_TEST(test_encode_known_bytes);
    RUN_TEST(test_encode_needs_room);
    RUN_TEST(test_encode_refuses_unterminated_string);
    RUN_TEST(test_encode_largest_schema_packet);
    RUN_TEST(test_decode_round_trip);
    RUN_TEST(test_every_body_round_trips);
    RUN_TEST(test_idle_delimiters_are_ignored);
    RUN_TEST(test_leading_delimiter_is_harmless);
    RUN_TEST(test_max_size_packet_accepted);
    RUN_TEST(test_one_byte_over_max_rejected);
    RUN_TEST(test_oversize_garbage_counted_once);
    RUN_TEST(test_246_bytes_is_not_oversize);
    RUN_TEST(test_cobs_code_past_end_is_framing_error);
    RUN_TEST(test_truncated_frames_are_framing_errors);
    RUN_TEST(test_raw_frame_shorter_than_5_bytes);
    RUN_TEST(test_empty_packet_is_unknown_type);
    RUN_TEST(test_bad_header);
    RUN_TEST(test_bad_crc);
    RUN_TEST(test_protobuf_that_does_not_decode);
    RUN_TEST(test_unknown_body);
    RUN_TEST(test_garbage_between_frames_costs_nothing_else);
    RUN_TEST(test_garbage_glued_to_a_frame_costs_that_frame_only);
    RUN_TEST(test_frames_split_across_many_feeds);
    RUN_TEST(test_feed_buf_stops_after_each_frame);
    RUN_TEST(test_init_clears_counters_and_partial_frame);
    return UNITY_END();
}
