/**
 * @file ringbuf.h
 * Byte ring between exactly one producer (the UART receive interrupt) and
 * exactly one consumer (the main loop). Lock-free: the producer only writes
 * `head`, the consumer only writes `tail`.
 *
 * Memory-ordering assumption: a single-core Cortex-M (or, on a host, a
 * signal handler or one thread). An interrupt sees the main loop's memory
 * accesses in program order, and 32-bit aligned loads/stores are atomic, so
 * the only reordering to prevent is the compiler's: the data byte must be
 * stored before `head` is published, and read before `tail` releases the
 * slot. atomic_signal_fence() is exactly that compiler-only barrier (no DMB
 * emitted). A multi-core or DMA-coherency setting would need real fences.
 *
 * Indices run freely (uint32_t, wrapping) and are masked on access, so
 * `head - tail` is the fill level and all CAPACITY slots are usable.
 */
#ifndef OIBAR_RINGBUF_H
#define OIBAR_RINGBUF_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* 512 bytes hold ~44 ms of input at 115200 baud: ample for a 1 ms main loop. */
#ifndef OIBAR_RINGBUF_CAPACITY
#define OIBAR_RINGBUF_CAPACITY 512u
#endif

_Static_assert(OIBAR_RINGBUF_CAPACITY >= 2u && OIBAR_RINGBUF_CAPACITY <= 0x80000000u,
               "ring capacity out of range");
_Static_assert((OIBAR_RINGBUF_CAPACITY & (OIBAR_RINGBUF_CAPACITY - 1u)) == 0u,
               "ring capacity must be a power of two");

typedef struct {
    volatile uint32_t head;                /**< next write; written by the producer only */
    volatile uint32_t tail;                /**< next read; written by the consumer only */
    uint8_t data[OIBAR_RINGBUF_CAPACITY];
} oibar_ringbuf_t;

/** Empty the ring. Call before the producer is enabled. */
void oibar_ringbuf_init(oibar_ringbuf_t *rb);

/**
 * Producer (ISR): append one byte. Returns false when the ring is full; the
 * byte is then lost and the caller counts an overflow.
 */
bool oibar_ringbuf_push(oibar_ringbuf_t *rb, uint8_t byte);

/** Consumer: take the oldest byte. Returns false when the ring is empty. */
bool oibar_ringbuf_pop(oibar_ringbuf_t *rb, uint8_t *byte);

/** Bytes waiting; exact for the consumer, a lower bound for anyone else. */
size_t oibar_ringbuf_count(const oibar_ringbuf_t *rb);

#ifdef __cplusplus
}
#endif

#endif /* OIBAR_RINGBUF_H */
