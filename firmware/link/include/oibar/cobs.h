/**
 * @file cobs.h
 * Consistent Overhead Byte Stuffing: removes every 0x00 from a block so that
 * 0x00 can delimit frames on the wire. Overhead: one byte per started 254.
 *
 * Neither function writes the 0x00 delimiter; framing is frame.h's job.
 */
#ifndef OIBAR_COBS_H
#define OIBAR_COBS_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/** Upper bound of the encoded size of `n` input bytes (no delimiter). */
#define OIBAR_COBS_MAX_ENCODED(n) ((n) + ((n) / 254u) + 1u)

typedef enum {
    OIBAR_COBS_OK = 0,
    OIBAR_COBS_ERR_NO_ROOM,   /**< the output does not fit in `dst_cap` */
    OIBAR_COBS_ERR_TRUNCATED, /**< a code byte points past the end (or no input) */
    OIBAR_COBS_ERR_ZERO,      /**< a 0x00 inside an encoded block */
} oibar_cobs_result_t;

/**
 * Encode `src_len` bytes into `dst` (capacity `dst_cap`); on success the
 * encoded length is stored in `*dst_len`. `dst` must not overlap `src`.
 */
oibar_cobs_result_t oibar_cobs_encode(const uint8_t *src, size_t src_len,
                                      uint8_t *dst, size_t dst_cap, size_t *dst_len);

/**
 * Decode one complete encoded block (delimiter already stripped). Decoding
 * in place (`dst == src`) is allowed: the output never overtakes the input.
 * Accepts both the short form and the form with a trailing 0x01 code after
 * a final run of 254 non-zero bytes.
 */
oibar_cobs_result_t oibar_cobs_decode(const uint8_t *src, size_t src_len,
                                      uint8_t *dst, size_t dst_cap, size_t *dst_len);

#ifdef __cplusplus
}
#endif

#endif /* OIBAR_COBS_H */
