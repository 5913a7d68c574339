/* CRC-32C: check value, published vectors, incremental == one-shot, and a
 * bit-by-bit reference for random data. */
#include <stdint.h>
#include <string.h>

#include "unity.h"

#include "oibar/crc32c.h"

void setUp(void) {}
void tearDown(void) {}

/* Straight from the definition: one bit at a time, reflected. */
static uint32_t crc32c_bitwise(const uint8_t *data, size_t len)
{
    uint32_t crc = 0xFFFFFFFFu;
    for (size_t i = 0; i < len; ++i) {
        crc ^= data[i];
        for (int b = 0; b < 8; ++b) {
            crc = (crc & 1u) ? (crc >> 1) ^ 0x82F63B78u : (crc >> 1);
        }
    }
    return ~crc;
}

static uint32_t rng_state = 12345u;
static uint32_t rng(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 17;
    rng_state ^= rng_state << 5;
    return rng_state;
}

static void test_check_value(void)
{
    const char *s = "123456789";
    TEST_ASSERT_EQUAL_HEX32(0xE3069283u, oibar_crc32c((const uint8_t *)s, strlen(s)));
    TEST_ASSERT_EQUAL_HEX32(OIBAR_CRC32C_CHECK, oibar_crc32c((const uint8_t *)s, strlen(s)));
}

static void test_empty_input(void)
{
    TEST_ASSERT_EQUAL_HEX32(0x00000000u, oibar_crc32c(NULL, 0));
}

/* RFC 3720 (iSCSI), appendix B.4. */
static void test_rfc3720_vectors(void)
{
    uint8_t buf[32];
    memset(buf, 0x00, sizeof(buf));
    TEST_ASSERT_EQUAL_HEX32(0x8A9136AAu, oibar_crc32c(buf, sizeof(buf)));
    memset(buf, 0xFF, sizeof(buf));
    TEST_ASSERT_EQUAL_HEX32(0x62A8AB43u, oibar_crc32c(buf, sizeof(buf)));
    for (size_t i = 0; i < sizeof(buf); ++i) {
        buf[i] = (uint8_t)i;
    }
    TEST_ASSERT_EQUAL_HEX32(0x46DD794Eu, oibar_crc32c(buf, sizeof(buf)));
    for (size_t i = 0; i < sizeof(buf); ++i) {
        buf[i] = (uint8_t)(31u - i);
    }
    TEST_ASSERT_EQUAL_HEX32(0x113FDB5Cu, oibar_crc32c(buf, sizeof(buf)));
}

static void test_incremental_equals_one_shot(void)
{
    uint8_t buf[300];
    for (size_t i = 0; i < sizeof(buf); ++i) {
        buf[i] = (uint8_t)rng();
    }
    const uint32_t whole = oibar_crc32c(buf, sizeof(buf));
    for (size_t split = 0; split <= sizeof(buf); ++split) {
        uint32_t c = oibar_crc32c_init();
        c = oibar_crc32c_update(c, buf, split);
        c = oibar_crc32c_update(c, &buf[split], sizeof(buf) - split);
        TEST_ASSERT_EQUAL_HEX32(whole, oibar_crc32c_final(c));
    }
}

static void test_matches_bitwise_reference(void)
{
    uint8_t buf[256];
    for (int round = 0; round < 500; ++round) {
        const size_t len = rng() % (sizeof(buf) + 1u);
        for (size_t i = 0; i < len; ++i) {
            buf[i] = (uint8_t)rng();
        }
        TEST_ASSERT_EQUAL_HEX32(crc32c_bitwise(buf, len), oibar_crc32c(buf, len));
    }
}

/* Every single-bit error in a max-size raw frame changes the CRC. */
static void test_detects_every_single_bit_flip(void)
{
    uint8_t buf[241];
    for (size_t i = 0; i < sizeof(buf); ++i) {
        buf[i] = (uint8_t)rng();
    }
    const uint32_t good = oibar_crc32c(buf, sizeof(buf));
    for (size_t bit = 0; bit < sizeof(buf) * 8u; ++bit) {
        buf[bit / 8u] ^= (uint8_t)(1u << (bit % 8u));
        TEST_ASSERT_NOT_EQUAL(good, oibar_crc32c(buf, sizeof(buf)));
        buf[bit / 8u] ^= (uint8_t)(1u << (bit % 8u));
    }
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_check_value);
    RUN_TEST(test_empty_input);
    RUN_TEST(test_rfc3720_vectors);
    RUN_TEST(test_incremental_equals_one_shot);
    RUN_TEST(test_matches_bitwise_reference);
    RUN_TEST(test_detects_every_single_bit_flip);
    return UNITY_END();
}
