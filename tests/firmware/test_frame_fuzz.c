/* Seeded, bounded fuzzing of the streaming decoder. One long byte stream of
 * random junk and damaged frames, interleaved with clean ones. It must never
 * crash (ASan/UBSan are on), and:
 *   - exactly one counter moves per frame, so the counters add up to the
 *     number of frames an independent model of the delimiter rules sees;
 *   - every decoded packet re-encodes to a frame that decodes to the same
 *     packet;
 *   - a clean frame after a delimiter always decodes, whatever came before. */
#include <stdbool.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <pb_encode.h>

#include "unity.h"

#include "oibar/cobs.h"
#include "oibar/crc32c.h"
#include "oibar/frame.h"

#ifndef FUZZ_ITERATIONS
#define FUZZ_ITERATIONS 200000u
#endif
#define FUZZ_SEED 0x0B1A2C0Du

void setUp(void) {}
void tearDown(void) {}

static uint32_t rng_state;
static uint32_t rng(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 17;
    rng_state ^= rng_state << 5;
    return rng_state;
}
static uint32_t below(uint32_t n)
{
    return rng() % n;
}

/* ------------------------------------------------------------------------- */
/* Random packets                                                            */

static void random_string(char *s, size_t cap)
{
    const size_t len = below((uint32_t)cap); /* 0 .. cap-1 */
    for (size_t i = 0; i < len; ++i) {
        s[i] = (char)(0x20 + below(0x5F));
    }
    s[len] = '\0';
}

static bool random_bool(void)
{
    return (rng() & 1u) != 0u;
}

static void random_packet(oibar_v1_Packet *p)
{
    memset(p, 0, sizeof(*p));
    p->seq = (below(8) == 0) ? 0u : rng();
    p->ack_seq = (below(2) == 0) ? 0u : rng();
    p->which_body = (pb_size_t)(oibar_v1_Packet_handshake_tag + below(11));
    uint8_t *raw = (uint8_t *)&p->body;
    for (size_t i = 0; i < sizeof(p->body); ++i) {
        /* mostly small values so that varints vary in length */
        raw[i] = (below(3) == 0) ? (uint8_t)rng() : 0u;
    }
    switch (p->which_body) {
    case oibar_v1_Packet_handshake_tag:
        random_string(p->body.handshake.host_version, sizeof(p->body.handshake.host_version));
        break;
    case oibar_v1_Packet_handshake_reply_tag:
        p->body.handshake_reply.accepted = random_bool();
        random_string(p->body.handshake_reply.firmware_version, sizeof(p->body.handshake_reply.firmware_version));
        random_string(p->body.handshake_reply.build_id, sizeof(p->body.handshake_reply.build_id));
        break;
    case oibar_v1_Packet_ack_tag: p->body.ack.accepted = random_bool(); break;
    case oibar_v1_Packet_nav_update_tag:
        p->body.nav_update.has_t_cam_target_m = random_bool();
        p->body.nav_update.has_q_cam_target = random_bool();
        break;
    case oibar_v1_Packet_param_value_tag:
        random_string(p->body.param_value.name, sizeof(p->body.param_value.name));
        random_string(p->body.param_value.unit, sizeof(p->body.param_value.unit));
        break;
    case oibar_v1_Packet_telemetry_tag: {
        oibar_v1_Telemetry *t = &p->body.telemetry;
        t->latch_engaged = random_bool();
        t->contact = random_bool();
        t->connector_mated = random_bool();
        t->sv_valve_cmd_open = random_bool();
        t->sv_valve_open = random_bool();
        t->tv_valve_cmd_open = random_bool();
        t->tv_valve_open = random_bool();
        t->has_link = random_bool();
        t->host_link_alive = random_bool();
        break;
    }
    default: break;
    }
}

static void assert_same_bytes(const uint8_t *a, size_t na, const uint8_t *b, size_t nb)
{
    TEST_ASSERT_EQUAL_size_t(na, nb);
    if (na > 0u) { /* Unity refuses to compare zero bytes */
        TEST_ASSERT_EQUAL_MEMORY(a, b, na);
    }
}

static size_t pb_bytes(const oibar_v1_Packet *p, uint8_t *buf, size_t cap)
{
    pb_ostream_t s = pb_ostream_from_buffer(buf, cap);
    TEST_ASSERT_TRUE(pb_encode(&s, oibar_v1_Packet_fields, p));
    return s.bytes_written;
}

/* ------------------------------------------------------------------------- */
/* The stream under test                                                     */

static oibar_frame_decoder_t dec;
static oibar_v1_Packet out;
static size_t model_run;      /* non-zero bytes since the last 0x00 */
static uint32_t model_frames; /* frames the delimiter rules say ended */
static uint32_t outcomes;     /* non-NONE results returned */
static uint32_t packets_checked;

static bool body_accepted(pb_size_t tag)
{
    return (OIBAR_BODIES_HOST_TO_MCU & OIBAR_BODY_BIT(tag)) != 0u;
}

/* A decoded packet must re-encode, and that frame must decode to it again. */
static void check_reencodes(oibar_rx_result_t r)
{
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES], pb1[256], pb2[256];
    const size_t n = oibar_frame_encode(&out, wire, sizeof(wire));
    TEST_ASSERT_TRUE_MESSAGE(n > 0, "decoded packet does not re-encode");
    const size_t len1 = pb_bytes(&out, pb1, sizeof(pb1));

    static oibar_frame_decoder_t fresh;
    static oibar_v1_Packet again;
    oibar_frame_decoder_init(&fresh, OIBAR_BODIES_HOST_TO_MCU);
    size_t used = 0;
    TEST_ASSERT_EQUAL(r, oibar_frame_decoder_feed_buf(&fresh, wire, n, &used, &again));
    TEST_ASSERT_EQUAL_size_t(n, used);
    const size_t len2 = pb_bytes(&again, pb2, sizeof(pb2));
    assert_same_bytes(pb1, len1, pb2, len2);
    ++packets_checked;
}

static oibar_rx_result_t feed(uint8_t b)
{
    /* Independent model: a frame ends at a 0x00 after 1..246 bytes, or at
     * the 247th byte of a run (oversize), after which the run is dead. */
    if (b == 0u) {
        if (model_run > 0u && model_run <= OIBAR_FRAME_MAX_ENCODED_BYTES) {
            ++model_frames;
        }
        model_run = 0u;
    } else if (++model_run == OIBAR_FRAME_MAX_ENCODED_BYTES + 1u) {
        ++model_frames;
    }
    const oibar_rx_result_t r = oibar_frame_decoder_feed(&dec, b, &out);
    if (r != OIBAR_RX_NONE) {
        ++outcomes;
    }
    if (r == OIBAR_RX_PACKET || r == OIBAR_RX_UNKNOWN_TYPE) {
        check_reencodes(r);
    }
    return r;
}

static void feed_all(const uint8_t *b, size_t n)
{
    for (size_t i = 0; i < n; ++i) {
        (void)feed(b[i]);
    }
}

/* ------------------------------------------------------------------------- */
/* Mutations                                                                 */

static size_t valid_frame(uint8_t *wire, size_t cap, oibar_v1_Packet *p)
{
    random_packet(p);
    const size_t n = oibar_frame_encode(p, wire, cap);
    TEST_ASSERT_TRUE(n > 0);
    return n;
}

static void mutate_bit_flips(uint8_t *w, size_t n)
{
    const uint32_t flips = 1u + below(8);
    for (uint32_t i = 0; i < flips; ++i) {
        const size_t pos = below((uint32_t)n);
        w[pos] ^= (uint8_t)(1u << below(8));
    }
}

static size_t mutate_insert(uint8_t *w, size_t n, size_t cap)
{
    const uint32_t k = 1u + below(4);
    for (uint32_t i = 0; i < k && n < cap; ++i) {
        const size_t pos = below((uint32_t)n + 1u);
        memmove(&w[pos + 1], &w[pos], n - pos);
        w[pos] = (below(4) == 0) ? 0u : (uint8_t)rng();
        ++n;
    }
    return n;
}

static size_t mutate_delete(uint8_t *w, size_t n)
{
    const uint32_t k = 1u + below(4);
    for (uint32_t i = 0; i < k && n > 1u; ++i) {
        const size_t pos = below((uint32_t)n);
        memmove(&w[pos], &w[pos + 1], n - pos - 1u);
        --n;
    }
    return n;
}

/* Damage before COBS and CRC, so that the CRC passes and protobuf or the
 * header checks see the damage. */
static size_t raw_level_damage(uint8_t *wire, size_t cap)
{
    uint8_t raw[OIBAR_FRAME_MAX_RAW_BYTES + 8];
    size_t len = 1u + below(OIBAR_FRAME_MAX_PACKET_BYTES + 1u);
    raw[0] = (below(16) == 0) ? (uint8_t)rng() : OIBAR_FRAME_HEADER;
    if (below(2) == 0) {
        for (size_t i = 1; i < len; ++i) {
            raw[i] = (uint8_t)rng();
        }
    } else {
        oibar_v1_Packet p;
        random_packet(&p);
        len = 1u + pb_bytes(&p, &raw[1], sizeof(raw) - 1u);
        const uint32_t flips = below(4);
        for (uint32_t i = 0; i < flips && len > 1u; ++i) {
            raw[1u + below((uint32_t)len - 1u)] ^= (uint8_t)(1u << below(8));
        }
    }
    const uint32_t crc = oibar_crc32c(raw, len);
    for (unsigned i = 0; i < 4; ++i) {
        raw[len++] = (uint8_t)(crc >> (8u * i));
    }
    size_t n = 0;
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_encode(raw, len, wire, cap - 1u, &n));
    wire[n++] = 0x00;
    return n;
}

static void one_iteration(void)
{
    uint8_t wire[600];
    oibar_v1_Packet p;
    size_t n = 0;
    switch (below(8)) {
    case 0: /* random bytes, sometimes long enough to be oversize */
        n = below(below(8) == 0 ? 600 : 80);
        for (size_t i = 0; i < n; ++i) {
            wire[i] = (below(16) == 0) ? 0u : (uint8_t)rng();
        }
        break;
    case 1:
        n = valid_frame(wire, sizeof(wire), &p);
        mutate_bit_flips(wire, n);
        break;
    case 2: /* truncated, with or without its delimiter */
        n = valid_frame(wire, sizeof(wire), &p);
        n = below((uint32_t)n);
        if (below(2) == 0) {
            wire[n++] = 0x00;
        }
        break;
    case 3:
        n = valid_frame(wire, sizeof(wire), &p);
        n = mutate_insert(wire, n, sizeof(wire));
        break;
    case 4:
        n = valid_frame(wire, sizeof(wire), &p);
        n = mutate_delete(wire, n);
        break;
    case 5:
        n = raw_level_damage(wire, sizeof(wire));
        break;
    default: { /* clean: after a delimiter it must decode exactly */
        n = valid_frame(wire, sizeof(wire), &p);
        (void)feed(0x00);
        oibar_rx_result_t last = OIBAR_RX_NONE;
        for (size_t i = 0; i < n; ++i) {
            const oibar_rx_result_t r = feed(wire[i]);
            TEST_ASSERT_TRUE(r == OIBAR_RX_NONE || i + 1u == n);
            last = r;
        }
        TEST_ASSERT_EQUAL(body_accepted(p.which_body) ? OIBAR_RX_PACKET : OIBAR_RX_UNKNOWN_TYPE, last);
        uint8_t pb1[256], pb2[256];
        const size_t len1 = pb_bytes(&p, pb1, sizeof(pb1));
        const size_t len2 = pb_bytes(&out, pb2, sizeof(pb2));
        assert_same_bytes(pb1, len1, pb2, len2);
        return;
    }
    }
    feed_all(wire, n);
}

static uint32_t counters_sum(const oibar_frame_counters_t *c)
{
    return c->rx_packets + c->rx_crc_errors + c->rx_framing_errors + c->rx_oversize +
           c->rx_bad_header + c->rx_decode_errors + c->rx_unknown_type;
}

static void test_decoder_survives_and_counts_everything(void)
{
    rng_state = FUZZ_SEED;
    oibar_frame_decoder_init(&dec, OIBAR_BODIES_HOST_TO_MCU);
    for (uint32_t i = 0; i < FUZZ_ITERATIONS; ++i) {
        one_iteration();
        if ((i & 0x3FFu) == 0u) {
            TEST_ASSERT_EQUAL_UINT32(model_frames, outcomes);
            TEST_ASSERT_EQUAL_UINT32(outcomes, counters_sum(&dec.counters));
        }
    }
    (void)feed(0x00); /* close whatever is pending */
    TEST_ASSERT_EQUAL_UINT32(model_frames, outcomes);
    TEST_ASSERT_EQUAL_UINT32(outcomes, counters_sum(&dec.counters));

    /* The run really exercised every outcome. */
    const oibar_frame_counters_t *c = &dec.counters;
    TEST_ASSERT_TRUE(c->rx_packets > 1000u);
    TEST_ASSERT_TRUE(c->rx_crc_errors > 100u);
    TEST_ASSERT_TRUE(c->rx_framing_errors > 100u);
    TEST_ASSERT_TRUE(c->rx_oversize > 100u);
    TEST_ASSERT_TRUE(c->rx_bad_header > 100u);
    TEST_ASSERT_TRUE(c->rx_decode_errors > 100u);
    TEST_ASSERT_TRUE(c->rx_unknown_type > 100u);
    TEST_ASSERT_TRUE(packets_checked >= c->rx_packets);
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_decoder_survives_and_counts_everything);
    return UNITY_END();
}
