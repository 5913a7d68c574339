/* SPSC byte ring: ISR pushes, main loop pops. See ringbuf.h for ordering. */
#include "oibar/ringbuf.h"

#include <stdatomic.h>

#include "oibar/assert.h"

#define RING_MASK (OIBAR_RINGBUF_CAPACITY - 1u)

void oibar_ringbuf_init(oibar_ringbuf_t *rb)
{
    OIBAR_ASSERT(rb != NULL);
    rb->head = 0u;
    rb->tail = 0u;
}

bool oibar_ringbuf_push(oibar_ringbuf_t *rb, uint8_t byte)
{
    const uint32_t head = rb->head;
    if ((uint32_t)(head - rb->tail) >= OIBAR_RINGBUF_CAPACITY) {
        return false;
    }
    rb->data[head & RING_MASK] = byte;
    atomic_signal_fence(memory_order_release); /* byte stored before it is published */
    rb->head = head + 1u;
    return true;
}

bool oibar_ringbuf_pop(oibar_ringbuf_t *rb, uint8_t *byte)
{
    OIBAR_ASSERT(byte != NULL);
    const uint32_t tail = rb->tail;
    if (rb->head == tail) {
        return false;
    }
    atomic_signal_fence(memory_order_acquire); /* head seen before the byte is read */
    *byte = rb->data[tail & RING_MASK];
    atomic_signal_fence(memory_order_release); /* byte read before the slot is freed */
    rb->tail = tail + 1u;
    return true;
}

size_t oibar_ringbuf_count(const oibar_ringbuf_t *rb)
{
    OIBAR_ASSERT(rb != NULL);
    return (size_t)(uint32_t)(rb->head - rb->tail);
}
