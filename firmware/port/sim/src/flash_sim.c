/* The parameter flash of the simulated MCU (hal.h, hal_flash_*): the same two
 * 16 KiB sectors as the board's (STM32F405 sectors 1 and 2), erased = 0xFF,
 * programming clears bits only. In memory, so a copy survives the simulated
 * MCU's own resets (watchdog) within one process; with an image file
 * (hal_sim_flash_attach: --flash-image PATH or OIBAR_SIM_FLASH_IMAGE) every
 * erase and program is written through to the file at once, so a later
 * process (a power cycle) boots from it. Without a file every process starts
 * blank: the defaults, as before persistence existed. */
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "oibar/hal_sim.h"

#define IMAGE_BYTES (HAL_FLASH_SECTORS * HAL_FLASH_SECTOR_BYTES)

static uint8_t s_flash[HAL_FLASH_SECTORS][HAL_FLASH_SECTOR_BYTES];
static bool s_init;
static int s_fd = -1;

static void ensure_init(void)
{
    if (!s_init) {
        memset(s_flash, 0xFF, sizeof s_flash);
        s_init = true;
    }
}

bool hal_sim_flash_attach(const char *path)
{
    ensure_init();
    int fd = open(path, O_RDWR | O_CREAT, 0644);
    if (fd < 0) {
        (void)fprintf(stderr, "oibar_sim_mcu: flash image %s: %s\n", path, strerror(errno));
        return false;
    }
    struct stat st;
    if (fstat(fd, &st) != 0) {
        (void)close(fd);
        return false;
    }
    if (st.st_size == 0) {
        /* A new image: blank flash. */
        if (pwrite(fd, s_flash, IMAGE_BYTES, 0) != (ssize_t)IMAGE_BYTES) {
            (void)close(fd);
            return false;
        }
    } else if (st.st_size != (off_t)IMAGE_BYTES ||
               pread(fd, s_flash, IMAGE_BYTES, 0) != (ssize_t)IMAGE_BYTES) {
        (void)fprintf(stderr, "oibar_sim_mcu: flash image %s is not %u bytes\n", path,
                      (unsigned)IMAGE_BYTES);
        (void)close(fd);
        return false;
    }
    s_fd = fd;
    return true;
}

static bool write_through(unsigned sector, uint32_t offset, size_t len)
{
    if (s_fd < 0) {
        return true;
    }
    const off_t at = (off_t)sector * HAL_FLASH_SECTOR_BYTES + (off_t)offset;
    return pwrite(s_fd, &s_flash[sector][offset], len, at) == (ssize_t)len;
}

static bool range_ok(unsigned sector, uint32_t offset, size_t len)
{
    return sector < HAL_FLASH_SECTORS && offset <= HAL_FLASH_SECTOR_BYTES &&
           len <= HAL_FLASH_SECTOR_BYTES - offset;
}

bool hal_flash_read(unsigned sector, uint32_t offset, void *dst, size_t len)
{
    ensure_init();
    if (dst == NULL || !range_ok(sector, offset, len)) {
        return false;
    }
    memcpy(dst, &s_flash[sector][offset], len);
    return true;
}

bool hal_flash_erase_sector(unsigned sector)
{
    ensure_init();
    if (sector >= HAL_FLASH_SECTORS) {
        return false;
    }
    memset(s_flash[sector], 0xFF, HAL_FLASH_SECTOR_BYTES);
    return write_through(sector, 0u, HAL_FLASH_SECTOR_BYTES);
}

bool hal_flash_program(unsigned sector, uint32_t offset, const uint32_t *words, size_t n_words)
{
    ensure_init();
    if (words == NULL || (offset & 3u) != 0u || n_words > HAL_FLASH_SECTOR_BYTES / 4u ||
        !range_ok(sector, offset, n_words * 4u)) {
        return false;
    }
    for (size_t i = 0; i < n_words; i++) {
        uint8_t *at = &s_flash[sector][offset + 4u * i];
        uint32_t v;
        memcpy(&v, at, 4u);
        v &= words[i];
        memcpy(at, &v, 4u);
        if (!write_through(sector, offset + 4u * (uint32_t)i, 4u)) {
            return false;
        }
    }
    return true;
}
