/*
 * Parameter persistence: the parameter table in flash, two copies in the two
 * sectors the HAL reserves (hal_flash_*; STM32F405 sectors 1 and 2). A copy is
 * one record at the start of its sector, 32-bit words:
 *
 *   [0] OIBAR_PSTORE_MAGIC
 *   [1] OIBAR_PSTORE_VERSION | OIBAR_PARAM_COUNT << 16
 *   [2] sequence number (serial arithmetic: the newer of two wins across the wrap)
 *   [3 .. 3+N-1] the values, id order, IEEE-754 single
 *   [3+N] CRC-32C (firmware/link) of the bytes of words 0 .. 2+N
 *
 * A save erases the sector that does NOT hold the copy in use, programs the
 * record in address order (the CRC last) and reads it back: a power cut at
 * any step leaves the other copy intact and the half-written one fails its
 * CRC. At boot the newer copy that passes magic, version, count, CRC, every
 * parameter's bounds and the cross-parameter rules is loaded; else the older
 * one; else the defaults stay (docs/firmware.md, "Parameter persistence").
 */
#ifndef OIBAR_APP_PSTORE_H
#define OIBAR_APP_PSTORE_H

#include <stdbool.h>
#include <stdint.h>

#include "oibar/app_params.h"

#define OIBAR_PSTORE_MAGIC 0x5042494Fu /* "OIBP" */
/* Bump when the record's layout or a parameter's meaning changes: a copy of
 * another version is not loaded (defaults and FAULT_PARAMS_INVALID instead). */
#define OIBAR_PSTORE_VERSION 1u
#define OIBAR_PSTORE_WORDS (4u + OIBAR_PARAM_COUNT)

typedef enum {
    OIBAR_PSTORE_LOADED = 0, /* a valid copy is in use */
    OIBAR_PSTORE_BLANK,      /* both record areas erased (never saved): defaults */
    OIBAR_PSTORE_INVALID     /* no valid copy, flash not blank: defaults */
} oibar_pstore_load_t;

/* Boot: load the newer valid copy through oibar_params_apply(); with none the
 * table is left as it is (the caller has set the defaults). */
oibar_pstore_load_t oibar_pstore_load(void);
/* Write the current table as the next copy and read it back. Blocks (flash
 * erase): the caller checks the safe state. False when the erase, the
 * program or the read-back failed; the copy in use is then unchanged. */
bool oibar_pstore_save(void);
/* The copy in use: whether there is one, its sector and sequence number. */
bool oibar_pstore_have_copy(void);
unsigned oibar_pstore_sector(void);
uint32_t oibar_pstore_seq(void);
/* Build a record (the tests write copies of their own with it). */
void oibar_pstore_encode(const float values[OIBAR_PARAM_COUNT], uint32_t seq,
                         uint32_t out[OIBAR_PSTORE_WORDS]);

#endif
