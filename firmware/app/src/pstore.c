/* Parameter persistence (app_pstore.h). Static memory only; the flash
 * through hal_flash_* (the one blocking HAL call, used only by a save in a
 * safe state, app.c). */
#include "oibar/app_pstore.h"

#include <string.h>

#include "oibar/app_assert.h"
#include "oibar/crc32c.h"
#include "oibar/hal.h"

#define W_MAGIC 0u
#define W_LAYOUT 1u
#define W_SEQ 2u
#define W_VALUES 3u
#define W_CRC (OIBAR_PSTORE_WORDS - 1u)
#define LAYOUT_WORD (OIBAR_PSTORE_VERSION | ((uint32_t)OIBAR_PARAM_COUNT << 16))

_Static_assert(OIBAR_PSTORE_WORDS * 4u <= HAL_FLASH_SECTOR_BYTES, "a copy fits its sector");
_Static_assert(sizeof(float) == sizeof(uint32_t), "values are stored as 32-bit words");

static bool s_have;
static unsigned s_sector;
static uint32_t s_seq;
/* Scratch for one record: static, not on the stack. */
static uint32_t s_rec[OIBAR_PSTORE_WORDS];
static uint32_t s_back[OIBAR_PSTORE_WORDS];

static uint32_t record_crc(const uint32_t *rec)
{
    /* The bytes of the words as they lie in memory (little-endian on both
     * the board and the host builds). */
    return oibar_crc32c((const uint8_t *)rec, (size_t)W_CRC * 4u);
}

void oibar_pstore_encode(const float values[OIBAR_PARAM_COUNT], uint32_t seq,
                         uint32_t out[OIBAR_PSTORE_WORDS])
{
    out[W_MAGIC] = OIBAR_PSTORE_MAGIC;
    out[W_LAYOUT] = LAYOUT_WORD;
    out[W_SEQ] = seq;
    memcpy(&out[W_VALUES], values, (size_t)OIBAR_PARAM_COUNT * 4u);
    out[W_CRC] = record_crc(out);
}

/* Newer by serial-number arithmetic (RFC 1982 style): survives the wrap. */
static bool seq_newer(uint32_t a, uint32_t b) { return (int32_t)(a - b) > 0; }

typedef struct {
    bool framed; /* magic, version, count and CRC good */
    bool blank;  /* the record area reads erased */
    uint32_t seq;
    float values[OIBAR_PARAM_COUNT];
} copy_t;

static copy_t s_copy[HAL_FLASH_SECTORS];

static void read_copy(unsigned sector, copy_t *c)
{
    memset(c, 0, sizeof *c);
    if (!hal_flash_read(sector, 0u, s_rec, sizeof s_rec)) {
        return; /* unreadable: neither blank nor valid */
    }
    c->blank = true;
    for (unsigned i = 0; i < OIBAR_PSTORE_WORDS; i++) {
        c->blank = c->blank && s_rec[i] == 0xFFFFFFFFu;
    }
    if (s_rec[W_MAGIC] != OIBAR_PSTORE_MAGIC || s_rec[W_LAYOUT] != LAYOUT_WORD ||
        s_rec[W_CRC] != record_crc(s_rec)) {
        return;
    }
    c->framed = true;
    c->seq = s_rec[W_SEQ];
    memcpy(c->values, &s_rec[W_VALUES], sizeof c->values);
}

oibar_pstore_load_t oibar_pstore_load(void)
{
    s_have = false;
    s_sector = 0u;
    s_seq = 0u;
    for (unsigned s = 0; s < HAL_FLASH_SECTORS; s++) {
        read_copy(s, &s_copy[s]);
    }
    /* Try the newer framed copy first, then the other: a copy is valid only
     * if oibar_params_apply accepts it (bounds, integers, cross rules). */
    unsigned first = (s_copy[1].framed && (!s_copy[0].framed || seq_newer(s_copy[1].seq, s_copy[0].seq)))
                         ? 1u : 0u;
    const unsigned order[2] = { first, 1u - first };
    for (unsigned k = 0; k < 2u; k++) {
        const copy_t *c = &s_copy[order[k]];
        if (c->framed && oibar_params_apply(c->values)) {
            s_have = true;
            s_sector = order[k];
            s_seq = c->seq;
            return OIBAR_PSTORE_LOADED;
        }
    }
    return (s_copy[0].blank && s_copy[1].blank) ? OIBAR_PSTORE_BLANK : OIBAR_PSTORE_INVALID;
}

bool oibar_pstore_save(void)
{
    float values[OIBAR_PARAM_COUNT];
    oibar_params_snapshot(values);
    /* Every set keeps the table consistent; a save of one that is not would
     * be refused at the next boot anyway. */
    if (!OIBAR_REQUIRE(oibar_params_consistent())) {
        return false;
    }
    const unsigned target = s_have ? 1u - s_sector : 0u;
    const uint32_t seq = s_have ? s_seq + 1u : 1u;
    oibar_pstore_encode(values, seq, s_rec);
    if (!hal_flash_erase_sector(target) || !hal_flash_program(target, 0u, s_rec, OIBAR_PSTORE_WORDS) ||
        !hal_flash_read(target, 0u, s_back, sizeof s_back) ||
        memcmp(s_rec, s_back, sizeof s_rec) != 0) {
        return false; /* the copy in use (the other sector) is untouched */
    }
    s_have = true;
    s_sector = target;
    s_seq = seq;
    return true;
}

bool oibar_pstore_have_copy(void) { return s_have; }
unsigned oibar_pstore_sector(void) { return s_sector; }
uint32_t oibar_pstore_seq(void) { return s_seq; }
