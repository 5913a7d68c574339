/* COBS encode/decode into caller buffers; bounded, no allocation. */
#include "oibar/cobs.h"

#include <stdbool.h>

#include "oibar/assert.h"

enum { COBS_MAX_CODE = 0xFF }; /* a code byte followed by 254 data bytes, no implied zero */

oibar_cobs_result_t oibar_cobs_encode(const uint8_t *src, size_t src_len,
                                      uint8_t *dst, size_t dst_cap, size_t *dst_len)
{
    OIBAR_ASSERT(src != NULL || src_len == 0u);
    OIBAR_ASSERT(dst != NULL && dst_len != NULL);

    if (dst_cap == 0u) {
        return OIBAR_COBS_ERR_NO_ROOM;
    }
    size_t code_pos = 0u; /* where the current block's code byte goes */
    size_t out = 1u;      /* next data position */
    uint8_t code = 1u;    /* 1 + data bytes in the current block */

    for (size_t i = 0u; i < src_len; ++i) {
        if (src[i] != 0u) {
            if (out >= dst_cap) {
                return OIBAR_COBS_ERR_NO_ROOM;
            }
            dst[out++] = src[i];
            ++code;
        }
        /* Close the block on a zero, or when it is full and more input follows. */
        const bool full = (code == COBS_MAX_CODE) && (i + 1u < src_len);
        if (src[i] == 0u || full) {
            if (out >= dst_cap) {
                return OIBAR_COBS_ERR_NO_ROOM;
            }
            dst[code_pos] = code;
            code_pos = out++;
            code = 1u;
        }
    }
    dst[code_pos] = code;
    *dst_len = out;
    return OIBAR_COBS_OK;
}

oibar_cobs_result_t oibar_cobs_decode(const uint8_t *src, size_t src_len,
                                      uint8_t *dst, size_t dst_cap, size_t *dst_len)
{
    OIBAR_ASSERT(src != NULL || src_len == 0u);
    OIBAR_ASSERT(dst != NULL && dst_len != NULL);

    if (src_len == 0u) {
        return OIBAR_COBS_ERR_TRUNCATED; /* even an empty block encodes to one code byte */
    }
    size_t in = 0u;
    size_t out = 0u;
    while (in < src_len) {
        const uint8_t code = src[in++];
        if (code == 0u) {
            return OIBAR_COBS_ERR_ZERO;
        }
        const size_t data_len = (size_t)code - 1u;
        if (data_len > src_len - in) {
            return OIBAR_COBS_ERR_TRUNCATED;
        }
        for (size_t k = 0u; k < data_len; ++k) {
            const uint8_t b = src[in++]; /* read before write: in-place safe */
            if (b == 0u) {
                return OIBAR_COBS_ERR_ZERO;
            }
            if (out >= dst_cap) {
                return OIBAR_COBS_ERR_NO_ROOM;
            }
            dst[out++] = b;
        }
        /* Every block but a full one and the last ends with an implied zero. */
        if (code != COBS_MAX_CODE && in < src_len) {
            if (out >= dst_cap) {
                return OIBAR_COBS_ERR_NO_ROOM;
            }
            dst[out++] = 0u;
        }
    }
    *dst_len = out;
    return OIBAR_COBS_OK;
}
