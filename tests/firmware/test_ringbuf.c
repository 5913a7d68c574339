/* The UART RX ring: FIFO order, full/empty, overflow, index wrap-around. */
#include <stdint.h>

#include "unity.h"

#include "oibar/ringbuf.h"

static oibar_ringbuf_t rb;

void setUp(void)
{
    oibar_ringbuf_init(&rb);
}
void tearDown(void) {}

static void test_starts_empty(void)
{
    uint8_t b = 0x5A;
    TEST_ASSERT_EQUAL_size_t(0, oibar_ringbuf_count(&rb));
    TEST_ASSERT_FALSE(oibar_ringbuf_pop(&rb, &b));
    TEST_ASSERT_EQUAL_HEX8(0x5A, b);
}

static void test_fifo_order(void)
{
    for (unsigned i = 0; i < 100; ++i) {
        TEST_ASSERT_TRUE(oibar_ringbuf_push(&rb, (uint8_t)i));
    }
    TEST_ASSERT_EQUAL_size_t(100, oibar_ringbuf_count(&rb));
    for (unsigned i = 0; i < 100; ++i) {
        uint8_t b = 0;
        TEST_ASSERT_TRUE(oibar_ringbuf_pop(&rb, &b));
        TEST_ASSERT_EQUAL_HEX8((uint8_t)i, b);
    }
    TEST_ASSERT_EQUAL_size_t(0, oibar_ringbuf_count(&rb));
}

static void test_every_slot_usable_then_full(void)
{
    for (unsigned i = 0; i < OIBAR_RINGBUF_CAPACITY; ++i) {
        TEST_ASSERT_TRUE(oibar_ringbuf_push(&rb, (uint8_t)(i * 7u)));
    }
    TEST_ASSERT_EQUAL_size_t(OIBAR_RINGBUF_CAPACITY, oibar_ringbuf_count(&rb));
    TEST_ASSERT_FALSE(oibar_ringbuf_push(&rb, 0xEE));
    uint8_t b = 0;
    TEST_ASSERT_TRUE(oibar_ringbuf_pop(&rb, &b));
    TEST_ASSERT_EQUAL_HEX8(0, b);
    TEST_ASSERT_TRUE(oibar_ringbuf_push(&rb, 0xEE)); /* one slot freed, one accepted */
    TEST_ASSERT_FALSE(oibar_ringbuf_push(&rb, 0xEF));
}

/* The producer counts what push refuses; the bytes that got in are intact. */
static void test_overflow_is_counted_by_the_producer(void)
{
    uint32_t overflows = 0;
    const unsigned sent = OIBAR_RINGBUF_CAPACITY + 37u;
    for (unsigned i = 0; i < sent; ++i) {
        if (!oibar_ringbuf_push(&rb, (uint8_t)i)) {
            ++overflows;
        }
    }
    TEST_ASSERT_EQUAL_UINT32(37, overflows);
    for (unsigned i = 0; i < OIBAR_RINGBUF_CAPACITY; ++i) {
        uint8_t b = 0;
        TEST_ASSERT_TRUE(oibar_ringbuf_pop(&rb, &b));
        TEST_ASSERT_EQUAL_HEX8((uint8_t)i, b);
    }
    uint8_t b = 0;
    TEST_ASSERT_FALSE(oibar_ringbuf_pop(&rb, &b));
}

/* Free-running indices cross 2^32 without losing count or order. */
static void test_indices_wrap_around_uint32(void)
{
    rb.head = 0xFFFFFF00u;
    rb.tail = 0xFFFFFF00u;
    uint32_t next_out = 0;
    uint32_t next_in = 0;
    for (unsigned round = 0; round < 50; ++round) {
        for (unsigned i = 0; i < 11; ++i) {
            TEST_ASSERT_TRUE(oibar_ringbuf_push(&rb, (uint8_t)next_in++));
        }
        TEST_ASSERT_EQUAL_size_t(next_in - next_out, oibar_ringbuf_count(&rb));
        for (unsigned i = 0; i < 9; ++i) {
            uint8_t b = 0;
            TEST_ASSERT_TRUE(oibar_ringbuf_pop(&rb, &b));
            TEST_ASSERT_EQUAL_HEX8((uint8_t)next_out++, b);
        }
    }
    TEST_ASSERT_TRUE(rb.head < 0x1000u); /* really wrapped */
    uint8_t b = 0;
    while (oibar_ringbuf_pop(&rb, &b)) {
        TEST_ASSERT_EQUAL_HEX8((uint8_t)next_out++, b);
    }
    TEST_ASSERT_EQUAL_UINT32(next_in, next_out);
}

static void test_full_detected_across_wrap(void)
{
    rb.head = 0xFFFFFFF0u;
    rb.tail = 0xFFFFFFF0u;
    for (unsigned i = 0; i < OIBAR_RINGBUF_CAPACITY; ++i) {
        TEST_ASSERT_TRUE(oibar_ringbuf_push(&rb, (uint8_t)i));
    }
    TEST_ASSERT_FALSE(oibar_ringbuf_push(&rb, 0));
    TEST_ASSERT_EQUAL_size_t(OIBAR_RINGBUF_CAPACITY, oibar_ringbuf_count(&rb));
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_starts_empty);
    RUN_TEST(test_fifo_order);
    RUN_TEST(test_every_slot_usable_then_full);
    RUN_TEST(test_overflow_is_counted_by_the_producer);
    RUN_TEST(test_indices_wrap_around_uint32);
    RUN_TEST(test_full_detected_across_wrap);
    return UNITY_END();
}
