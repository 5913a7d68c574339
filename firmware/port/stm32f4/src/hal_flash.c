/*
 * Parameter flash for the STM32F405 (hal.h, hal_flash_*): sectors 1 and 2,
 * 16 KiB each at 0x08004000 and 0x08008000, reserved by stm32f405.ld
 * (PARAMS region; check_image.cmake fails the build if the image has bytes
 * there). RM0090 section 3.6: unlock through KEYR, SER + SNB + STRT for a
 * sector erase, PG with PSIZE x32 for each word, BSY polled until done.
 *
 * While the flash bank is busy, every fetch from flash stalls the bus, and an
 * interrupt would fetch its vector and handler from flash. So the part that
 * starts an operation and waits for it runs from RAM (.ramfunc, copied with
 * .data at reset) with interrupts masked, and touches nothing in flash: no
 * calls, its constants as immediates or in its own literal pool (in RAM with
 * it). The 16 KiB erase takes up to 500 ms at x32 (datasheet), twice the
 * 250 ms watchdog: the wait loop reloads the IWDG on every poll of BSY (the
 * prescaler stays as it is), bounded by FLASH_WAIT_POLLS so a flash that
 * never finishes still ends in an error and, after it, in the watchdog.
 * The SysTick and the UART receive interrupt are held off meanwhile: time
 * (hal_time_ms) falls behind by the erase's duration and bytes the host sends
 * during it are lost (the link retransmits). That is why the application
 * saves only in a safe state (app.c, CMD_SAVE_PARAMS).
 */
#include "oibar/hal.h"

#include "port.h"
#include "stm32f4_regs.h"

#define PARAM_FLASH_BASE 0x08004000u
#define PARAM_FIRST_SECTOR 1u /* RM0090 table 5: sector 1 = 0x08004000, 16 KiB */
/* Polls of BSY before giving up: each takes at least ~10 core cycles at
 * 168 MHz (an AHB read and a store to the IWDG), so this bounds the wait to
 * well above the 500 ms worst case of a 16 KiB erase (~3 s) and below
 * forever. */
#define FLASH_WAIT_POLLS 50000000u

_Static_assert(HAL_FLASH_SECTOR_BYTES == 16384u, "sectors 1 and 2 are 16 KiB");

/* Runs from RAM: start the operation CR already describes (STRT for an erase,
 * nothing for a word program, which the write itself starts) and wait,
 * reloading the watchdog. Returns SR's error bits, or BSY when it timed out. */
__attribute__((section(".ramfunc"), noinline, long_call)) uint32_t port_flash_ram_wait(
    volatile uint32_t *word, uint32_t value, uint32_t cr);
__attribute__((section(".ramfunc"), noinline, long_call)) uint32_t port_flash_ram_wait(
    volatile uint32_t *word, uint32_t value, uint32_t cr)
{
    FLASH->CR = cr;
    if (word != 0) {
        *word = value; /* PG set: this write is the program operation */
    } else {
        FLASH->CR = cr | FLASH_CR_STRT;
    }
    uint32_t n = 0u;
    while ((FLASH->SR & FLASH_SR_BSY) != 0u && n < FLASH_WAIT_POLLS) {
        IWDG->KR = IWDG_KEY_RELOAD;
        n++;
    }
    IWDG->KR = IWDG_KEY_RELOAD;
    uint32_t sr = FLASH->SR;
    FLASH->CR = 0u;
    return (sr & (FLASH_SR_ERRORS | FLASH_SR_BSY));
}

static void flash_unlock(void)
{
    if ((FLASH->CR & FLASH_CR_LOCK) != 0u) {
        FLASH->KEYR = FLASH_KEY1;
        FLASH->KEYR = FLASH_KEY2;
    }
    FLASH->SR = FLASH_SR_ERRORS | FLASH_SR_EOP; /* write 1 to clear old flags */
}

static void flash_lock_and_flush(void)
{
    FLASH->CR = FLASH_CR_LOCK;
    /* The data cache may hold the old contents of what was just written. */
    uint32_t acr = FLASH->ACR;
    FLASH->ACR = acr & ~FLASH_ACR_DCEN;
    FLASH->ACR = (acr & ~FLASH_ACR_DCEN) | FLASH_ACR_DCRST;
    FLASH->ACR = acr & ~FLASH_ACR_DCRST;
}

static volatile uint32_t *sector_addr(unsigned sector, uint32_t offset)
{
    return (volatile uint32_t *)(uintptr_t)(PARAM_FLASH_BASE + sector * HAL_FLASH_SECTOR_BYTES + offset);
}

static bool range_ok(unsigned sector, uint32_t offset, size_t len)
{
    return sector < HAL_FLASH_SECTORS && offset <= HAL_FLASH_SECTOR_BYTES &&
           len <= HAL_FLASH_SECTOR_BYTES - offset;
}

bool hal_flash_read(unsigned sector, uint32_t offset, void *dst, size_t len)
{
    if (dst == 0 || !range_ok(sector, offset, len)) {
        return false;
    }
    const volatile uint8_t *src = (const volatile uint8_t *)sector_addr(sector, offset);
    uint8_t *out = (uint8_t *)dst;
    for (size_t i = 0; i < len; i++) {
        out[i] = src[i];
    }
    return true;
}

bool hal_flash_erase_sector(unsigned sector)
{
    if (sector >= HAL_FLASH_SECTORS) {
        return false;
    }
    const uint32_t snb = PARAM_FIRST_SECTOR + sector;
    uint32_t saved = hal_critical_enter();
    IWDG->KR = IWDG_KEY_RELOAD;
    flash_unlock();
    uint32_t err = port_flash_ram_wait(0, 0u,
                                       FLASH_CR_PSIZE_X32 | FLASH_CR_SER | (snb << FLASH_CR_SNB_POS));
    flash_lock_and_flush();
    hal_critical_exit(saved);
    return err == 0u;
}

bool hal_flash_program(unsigned sector, uint32_t offset, const uint32_t *words, size_t n_words)
{
    if (words == 0 || (offset & 3u) != 0u || n_words > HAL_FLASH_SECTOR_BYTES / 4u ||
        !range_ok(sector, offset, n_words * 4u)) {
        return false;
    }
    uint32_t err = 0u;
    uint32_t saved = hal_critical_enter();
    flash_unlock();
    for (size_t i = 0; i < n_words && err == 0u; i++) {
        IWDG->KR = IWDG_KEY_RELOAD;
        err = port_flash_ram_wait(sector_addr(sector, offset + 4u * (uint32_t)i), words[i],
                                  FLASH_CR_PSIZE_X32 | FLASH_CR_PG);
    }
    flash_lock_and_flush();
    hal_critical_exit(saved);
    return err == 0u;
}
