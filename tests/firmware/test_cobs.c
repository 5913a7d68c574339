/* COBS: published vectors, round trips, buffer limits, malformed input. */
#include <stdint.h>
#include <string.h>

#include "unity.h"

#include "oibar/cobs.h"

void setUp(void) {}
void tearDown(void) {}

static uint32_t rng_state = 0xC0B5u;
static uint32_t rng(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 17;
    rng_state ^= rng_state << 5;
    return rng_state;
}

static void check_vector(const uint8_t *raw, size_t raw_len, const uint8_t *enc, size_t enc_len)
{
    uint8_t out[600];
    size_t n = 0;
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_encode(raw, raw_len, out, sizeof(out), &n));
    TEST_ASSERT_EQUAL_size_t(enc_len, n);
    TEST_ASSERT_EQUAL_HEX8_ARRAY(enc, out, enc_len);
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_decode(enc, enc_len, out, sizeof(out), &n));
    TEST_ASSERT_EQUAL_size_t(raw_len, n);
    if (raw_len > 0) {
        TEST_ASSERT_EQUAL_HEX8_ARRAY(raw, out, raw_len);
    }
}

#define VEC(raw, enc) check_vector(raw, sizeof(raw), enc, sizeof(enc))

static void test_short_vectors(void)
{
    {
        const uint8_t r[] = {0x00}, e[] = {0x01, 0x01};
        VEC(r, e);
    }
    {
        const uint8_t r[] = {0x00, 0x00}, e[] = {0x01, 0x01, 0x01};
        VEC(r, e);
    }
    {
        const uint8_t r[] = {0x00, 0x11, 0x00}, e[] = {0x01, 0x02, 0x11, 0x01};
        VEC(r, e);
    }
    {
        const uint8_t r[] = {0x11, 0x22, 0x00, 0x33}, e[] = {0x03, 0x11, 0x22, 0x02, 0x33};
        VEC(r, e);
    }
    {
        const uint8_t r[] = {0x11, 0x22, 0x33, 0x44}, e[] = {0x05, 0x11, 0x22, 0x33, 0x44};
        VEC(r, e);
    }
    {
        const uint8_t r[] = {0x11, 0x00, 0x00, 0x00}, e[] = {0x02, 0x11, 0x01, 0x01, 0x01};
        VEC(r, e);
    }
}

static void test_empty_input_encodes_to_one_code_byte(void)
{
    uint8_t out[4];
    size_t n = 99;
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_encode(NULL, 0, out, sizeof(out), &n));
    TEST_ASSERT_EQUAL_size_t(1, n);
    TEST_ASSERT_EQUAL_HEX8(0x01, out[0]);
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_decode(out, 1, out, sizeof(out), &n));
    TEST_ASSERT_EQUAL_size_t(0, n);
}

/* The 254-byte boundary cases of the COBS paper / Wikipedia table. */
static void test_long_run_vectors(void)
{
    uint8_t raw[256], enc[260];
    /* 01..FE: one full block, no trailing code */
    for (int i = 0; i < 254; ++i) raw[i] = (uint8_t)(i + 1);
    enc[0] = 0xFF;
    memcpy(&enc[1], raw, 254);
    check_vector(raw, 254, enc, 255);
    /* 00 01..FE */
    raw[0] = 0x00;
    for (int i = 1; i < 255; ++i) raw[i] = (uint8_t)i;
    enc[0] = 0x01;
    enc[1] = 0xFF;
    memcpy(&enc[2], &raw[1], 254);
    check_vector(raw, 255, enc, 256);
    /* 01..FF */
    for (int i = 0; i < 255; ++i) raw[i] = (uint8_t)(i + 1);
    enc[0] = 0xFF;
    memcpy(&enc[1], raw, 254);
    enc[255] = 0x02;
    enc[256] = 0xFF;
    check_vector(raw, 255, enc, 257);
    /* 02..FF 00 */
    for (int i = 0; i < 254; ++i) raw[i] = (uint8_t)(i + 2);
    raw[254] = 0x00;
    enc[0] = 0xFF;
    memcpy(&enc[1], raw, 254);
    enc[255] = 0x01;
    enc[256] = 0x01;
    check_vector(raw, 255, enc, 257);
    /* 03..FF 00 01 */
    for (int i = 0; i < 253; ++i) raw[i] = (uint8_t)(i + 3);
    raw[253] = 0x00;
    raw[254] = 0x01;
    enc[0] = 0xFE;
    memcpy(&enc[1], raw, 253);
    enc[254] = 0x02;
    enc[255] = 0x01;
    check_vector(raw, 255, enc, 256);
}

/* Some encoders end a final full block with an extra 0x01 code: same data. */
static void test_decode_accepts_trailing_code_after_full_block(void)
{
    uint8_t enc[256], out[256];
    enc[0] = 0xFF;
    for (int i = 0; i < 254; ++i) enc[1 + i] = (uint8_t)(i + 1);
    enc[255] = 0x01;
    size_t n = 0;
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_decode(enc, 256, out, sizeof(out), &n));
    TEST_ASSERT_EQUAL_size_t(254, n);
    TEST_ASSERT_EQUAL_HEX8_ARRAY(&enc[1], out, 254);
}

static void test_random_round_trips_have_no_zeros_and_bounded_size(void)
{
    static uint8_t raw[700], enc[720], dec[720];
    for (int round = 0; round < 2000; ++round) {
        const size_t len = rng() % sizeof(raw);
        const uint32_t zero_odds = 1u + rng() % 64u; /* from all zeros to almost none */
        for (size_t i = 0; i < len; ++i) {
            raw[i] = (rng() % zero_odds == 0u) ? 0u : (uint8_t)(1u + rng() % 255u);
        }
        size_t n = 0, m = 0;
        TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_encode(raw, len, enc, sizeof(enc), &n));
        TEST_ASSERT_TRUE(n <= OIBAR_COBS_MAX_ENCODED(len));
        TEST_ASSERT_NULL(memchr(enc, 0, n));
        TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_decode(enc, n, dec, sizeof(dec), &m));
        TEST_ASSERT_EQUAL_size_t(len, m);
        if (len > 0) {
            TEST_ASSERT_EQUAL_HEX8_ARRAY(raw, dec, len);
        }
        /* In place gives the same. */
        TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_decode(enc, n, enc, n, &m));
        TEST_ASSERT_EQUAL_size_t(len, m);
        if (len > 0) {
            TEST_ASSERT_EQUAL_HEX8_ARRAY(raw, enc, len);
        }
    }
}

static void test_encode_reports_no_room_and_fits_exactly(void)
{
    uint8_t raw[245], enc[247];
    for (size_t i = 0; i < sizeof(raw); ++i) raw[i] = (uint8_t)(i % 7u);
    size_t need = 0;
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_encode(raw, sizeof(raw), enc, sizeof(enc), &need));
    for (size_t cap = 0; cap < need; ++cap) {
        size_t n = 0;
        TEST_ASSERT_EQUAL(OIBAR_COBS_ERR_NO_ROOM, oibar_cobs_encode(raw, sizeof(raw), enc, cap, &n));
    }
    size_t n = 0;
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_encode(raw, sizeof(raw), enc, need, &n));
    TEST_ASSERT_EQUAL_size_t(need, n);
    /* All non-zero: a single block, exactly one byte of overhead. */
    memset(raw, 0xAA, sizeof(raw));
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_encode(raw, sizeof(raw), enc, sizeof(enc), &n));
    TEST_ASSERT_EQUAL_size_t(246, n);
}

static void test_decode_reports_no_room(void)
{
    const uint8_t enc[] = {0x03, 0x11, 0x22, 0x02, 0x33};
    uint8_t out[8];
    size_t n = 0;
    TEST_ASSERT_EQUAL(OIBAR_COBS_ERR_NO_ROOM, oibar_cobs_decode(enc, sizeof(enc), out, 3, &n));
    TEST_ASSERT_EQUAL(OIBAR_COBS_OK, oibar_cobs_decode(enc, sizeof(enc), out, 4, &n));
}

static void test_decode_rejects_code_past_end(void)
{
    uint8_t out[16];
    size_t n = 0;
    const uint8_t a[] = {0x05, 0x11, 0x22};             /* wants 4 data bytes, has 2 */
    const uint8_t b[] = {0x02, 0x11, 0x04, 0x22};       /* second block too short */
    const uint8_t c[] = {0xFF};                         /* full block, nothing follows */
    TEST_ASSERT_EQUAL(OIBAR_COBS_ERR_TRUNCATED, oibar_cobs_decode(a, sizeof(a), out, sizeof(out), &n));
    TEST_ASSERT_EQUAL(OIBAR_COBS_ERR_TRUNCATED, oibar_cobs_decode(b, sizeof(b), out, sizeof(out), &n));
    TEST_ASSERT_EQUAL(OIBAR_COBS_ERR_TRUNCATED, oibar_cobs_decode(c, sizeof(c), out, sizeof(out), &n));
    TEST_ASSERT_EQUAL(OIBAR_COBS_ERR_TRUNCATED, oibar_cobs_decode(a, 0, out, sizeof(out), &n));
}

static void test_decode_rejects_zero_inside(void)
{
    uint8_t out[16];
    size_t n = 0;
    const uint8_t a[] = {0x03, 0x11, 0x00, 0x22}; /* zero among data bytes */
    const uint8_t b[] = {0x02, 0x11, 0x00};       /* zero where a code byte belongs */
    const uint8_t c[] = {0x00};
    TEST_ASSERT_EQUAL(OIBAR_COBS_ERR_ZERO, oibar_cobs_decode(a, sizeof(a), out, sizeof(out), &n));
    TEST_ASSERT_EQUAL(OIBAR_COBS_ERR_ZERO, oibar_cobs_decode(b, sizeof(b), out, sizeof(out), &n));
    TEST_ASSERT_EQUAL(OIBAR_COBS_ERR_ZERO, oibar_cobs_decode(c, sizeof(c), out, sizeof(out), &n));
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_short_vectors);
    RUN_TEST(test_empty_input_encodes_to_one_code_byte);
    RUN_TEST(test_long_run_vectors);
    RUN_TEST(test_decode_accepts_trailing_code_after_full_block);
    RUN_TEST(test_random_round_trips_have_no_zeros_and_bounded_size);
    RUN_TEST(test_encode_reports_no_room_and_fits_exactly);
    RUN_TEST(test_decode_reports_no_room);
    RUN_TEST(test_decode_rejects_code_past_end);
    RUN_TEST(test_decode_rejects_zero_inside);
    return UNITY_END();
}
