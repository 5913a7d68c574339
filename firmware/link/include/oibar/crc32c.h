/**
 * @file crc32c.h
 * CRC-32C (Castagnoli): reflected polynomial 0x82F63B78, init 0xFFFFFFFF,
 * final XOR 0xFFFFFFFF. Check value of "123456789" is 0xE3069283.
 *
 * A 16-entry (nibble) table: 64 bytes of flash, two lookups per byte.
 * Why this CRC and not the STM32's hardware unit: see docs/link.md.
 */
#ifndef OIBAR_CRC32C_H
#define OIBAR_CRC32C_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define OIBAR_CRC32C_CHECK 0xE3069283u /**< CRC-32C of "123456789" */

/** Start value of an incremental computation. */
uint32_t oibar_crc32c_init(void);

/** Feed `len` bytes; `data` may be NULL only when `len` is 0. */
uint32_t oibar_crc32c_update(uint32_t crc, const uint8_t *data, size_t len);

/** The final CRC value of an incremental computation. */
uint32_t oibar_crc32c_final(uint32_t crc);

/** One-shot: init, update, final. */
uint32_t oibar_crc32c(const uint8_t *data, size_t len);

#ifdef __cplusplus
}
#endif

#endif /* OIBAR_CRC32C_H */
