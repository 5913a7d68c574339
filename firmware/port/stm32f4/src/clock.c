/*
 * Clock tree: 168 MHz core from the crystal through the main PLL
 * (RM0090 section 6.3), AHB /1, APB1 /4 (42 MHz, timers 84 MHz),
 * APB2 /2 (84 MHz).
 *
 * Every wait on a hardware flag is bounded. If the crystal does not start
 * the PLL runs from the internal 16 MHz RC instead (still 168 MHz, less
 * accurate baud rate); if the PLL does not lock or the switch does not take,
 * the core stays on the 16 MHz RC and every divider below is computed from
 * what is actually running, so the link still works at the right baud rate.
 *
 * Five flash wait states at 168 MHz hold only for a 2.7-3.6 V supply, so the
 * brown-out reset is programmed to level 3 (2.70 V) before the clock goes
 * up: below that the chip is held in reset instead of misreading flash.
 *
 * Clock security (RCC_CR.CSSON) is switched on once the core runs from the
 * crystal: if the HSE stops in flight the hardware switches SYSCLK to the
 * HSI at once and raises the NMI (RM0090 section 6.2.7). NMI_Handler drives
 * every output to its safe level (valves de-energised, motors off), notes
 * PORT_NOTE_CLOCK_FAILURE and resets; the next boot finds no crystal, runs
 * the PLL from the HSI (CLOCK_SRC_HSI_PLL) and starts in FAULT (the note
 * makes the reset a RESET_LOCKUP). Without CSS a dead crystal would stop the
 * core until the 250 ms watchdog.
 *
 * Built with OIBAR_QEMU (the emulator image of `make qemu-test` only): an RCC
 * that reports nothing is taken to run the nominal 168 MHz (QEMU's stub).
 * The flight image never assumes a clock it cannot see.
 */
#include "board.h"
#include "port.h"
#include "stm32f4_regs.h"

/* At 16 MHz a polling loop iteration takes a few cycles: 50,000 of them is
 * ~10-20 ms, well beyond the crystal's 2 ms start-up and the PLL's 0.1 ms
 * lock time from the datasheet. */
#define CLOCK_WAIT_LOOPS 50000u

#define PLL_VCO_IN_HZ 1000000u /* 1 MHz VCO input: lowest jitter per RM0090 */
#define PLL_N 336u             /* VCO 336 MHz */
/* PLLP = 0b00: SYSCLK = VCO / 2 = 168 MHz (the field stays 0 below). */
#define PLL_Q 7u               /* 48 MHz for USB/SDIO (unused, but must be <= 48) */
#define FLASH_WAIT_STATES_168MHZ 5u /* 2.7-3.6 V supply, RM0090 table 10 */
/* Option-byte programming takes milliseconds at most (datasheet tPROG);
 * this bound is far beyond it and still short of the watchdog's start. */
#define OPTION_WAIT_LOOPS 2000000u

static clock_info_t s_info;

static bool wait_set(const volatile uint32_t *reg, uint32_t mask, uint32_t value)
{
    for (uint32_t n = 0; n < CLOCK_WAIT_LOOPS; n++) {
        if ((*reg & mask) == value) {
            return true;
        }
    }
    return false;
}

static void info_hsi(clock_info_t *out, clock_source_t src)
{
    out->source = src;
    out->hclk_hz = BOARD_HSI_HZ;
    out->pclk2_hz = BOARD_HSI_HZ;     /* prescalers left at /1 */
    out->tim_apb1_hz = BOARD_HSI_HZ;  /* APB1 /1: timer clock = PCLK1 */
}

static void info_168(clock_info_t *out, clock_source_t src)
{
    out->source = src;
    out->hclk_hz = BOARD_SYSCLK_TARGET_HZ;
    out->pclk2_hz = BOARD_SYSCLK_TARGET_HZ / 2u;
    /* APB1 prescaler != 1: the timers run at twice PCLK1 (RM0090 6.2). */
    out->tim_apb1_hz = 2u * (BOARD_SYSCLK_TARGET_HZ / 4u);
}

/* Brown-out reset at level 3 (2.70 V), the supply range of 5 wait states at
 * 168 MHz (RM0090 table 10 and section 3.7.1). The option byte is written
 * only when it differs, so a board is programmed once, at its first boot
 * (the factory value is BOR off). True when the level reads back as set. */
bool clock_bor_level3(void)
{
    if ((FLASH->OPTCR & FLASH_OPTCR_BOR_LEV_MASK) == FLASH_OPTCR_BOR_LEVEL3) {
        return true;
    }
    if (!wait_set(&FLASH->SR, FLASH_SR_BSY, 0u)) {
        return false;
    }
    FLASH->OPTKEYR = FLASH_OPTKEY1;
    FLASH->OPTKEYR = FLASH_OPTKEY2;
    if ((FLASH->OPTCR & FLASH_OPTCR_OPTLOCK) != 0u) {
        return false; /* the keys did not unlock it: leave it be */
    }
    FLASH->OPTCR = (FLASH->OPTCR & ~FLASH_OPTCR_BOR_LEV_MASK) | FLASH_OPTCR_BOR_LEVEL3;
    FLASH->OPTCR |= FLASH_OPTCR_OPTSTRT;
    for (uint32_t n = 0; n < OPTION_WAIT_LOOPS && (FLASH->SR & FLASH_SR_BSY) != 0u; n++) {
    }
    FLASH->OPTCR |= FLASH_OPTCR_OPTLOCK;
    return (FLASH->OPTCR & FLASH_OPTCR_BOR_LEV_MASK) == FLASH_OPTCR_BOR_LEVEL3;
}

void clock_init(clock_info_t *out)
{
#if defined(OIBAR_QEMU) && OIBAR_QEMU
    /* Out of reset the core runs from the HSI, so HSIRDY reads 1 on any real
     * chip. QEMU's netduinoplus2 RCC stub does not even report that: nothing
     * is programmed and the nominal 168 MHz, which the model provides, is
     * assumed. Emulator image only. */
    if ((RCC->CR & RCC_CR_HSIRDY) == 0u) {
        info_168(out, CLOCK_SRC_UNVERIFIED);
        s_info = *out;
        return;
    }
#endif
    /* No 168 MHz without the brown-out level that makes 5 wait states safe. */
    if (!clock_bor_level3()) {
        info_hsi(out, CLOCK_SRC_HSI);
        s_info = *out;
        return;
    }

    /* Regulator scale 1 is needed above 144 MHz. */
    RCC->APB1ENR |= RCC_APB1ENR_PWREN;
    (void)RCC->APB1ENR; /* read back: the enable takes effect before PWR is touched */
    PWR->CR |= PWR_CR_VOS;

    clock_source_t src = CLOCK_SRC_HSE_PLL;
    uint32_t pll_in_hz = BOARD_HSE_HZ;
    RCC->CR |= RCC_CR_HSEON;
    if (!wait_set(&RCC->CR, RCC_CR_HSERDY, RCC_CR_HSERDY)) {
        RCC->CR &= ~RCC_CR_HSEON; /* do not leave a half-started oscillator */
        src = CLOCK_SRC_HSI_PLL;
        pll_in_hz = BOARD_HSI_HZ;
    }

    RCC->CR &= ~RCC_CR_PLLON; /* PLLCFGR may only change while the PLL is off */
    (void)wait_set(&RCC->CR, RCC_CR_PLLRDY, 0u);
    uint32_t pllm = pll_in_hz / PLL_VCO_IN_HZ;
    RCC->PLLCFGR = (pllm << RCC_PLLCFGR_PLLM_POS) | (PLL_N << RCC_PLLCFGR_PLLN_POS) |
                   (PLL_Q << RCC_PLLCFGR_PLLQ_POS) |
                   ((src == CLOCK_SRC_HSE_PLL) ? RCC_PLLCFGR_PLLSRC_HSE : 0u);
    RCC->CR |= RCC_CR_PLLON;
    if (!wait_set(&RCC->CR, RCC_CR_PLLRDY, RCC_CR_PLLRDY)) {
        RCC->CR &= ~(RCC_CR_PLLON | RCC_CR_HSEON);
        info_hsi(out, CLOCK_SRC_HSI);
        s_info = *out;
        return;
    }

    /* Flash wait states before the clock goes up, and check they took:
     * running 168 MHz with too few wait states reads garbage. */
    FLASH->ACR = FLASH_ACR_PRFTEN | FLASH_ACR_ICEN | FLASH_ACR_DCEN | FLASH_WAIT_STATES_168MHZ;
    if (!wait_set(&FLASH->ACR, FLASH_ACR_LATENCY_MASK, FLASH_WAIT_STATES_168MHZ)) {
        RCC->CR &= ~(RCC_CR_PLLON | RCC_CR_HSEON);
        info_hsi(out, CLOCK_SRC_HSI);
        s_info = *out;
        return;
    }

    /* HPRE = 0 (AHB /1); APB1 /4 (42 MHz max), APB2 /2 (84 MHz max). */
    RCC->CFGR = (RCC_CFGR_PPRE_DIV4 << RCC_CFGR_PPRE1_POS) |
                (RCC_CFGR_PPRE_DIV2 << RCC_CFGR_PPRE2_POS);
    RCC->CFGR = (RCC->CFGR & ~RCC_CFGR_SW_MASK) | RCC_CFGR_SW_PLL;
    if (!wait_set(&RCC->CFGR, RCC_CFGR_SW_MASK << RCC_CFGR_SWS_POS,
                  RCC_CFGR_SW_PLL << RCC_CFGR_SWS_POS)) {
        /* Back to the RC with the prescalers at /1, so the dividers match. */
        RCC->CFGR = RCC_CFGR_SW_HSI;
        (void)wait_set(&RCC->CFGR, RCC_CFGR_SW_MASK << RCC_CFGR_SWS_POS, 0u);
        RCC->CR &= ~(RCC_CR_PLLON | RCC_CR_HSEON);
        info_hsi(out, CLOCK_SRC_HSI);
        s_info = *out;
        return;
    }
    if (src == CLOCK_SRC_HSE_PLL) {
        RCC->CR |= RCC_CR_CSSON; /* HSE failure from now on: NMI_Handler */
    }
    info_168(out, src);
    s_info = *out;
}

/* The only NMI source on this board is the clock security system; any NMI
 * is handled the same way: outputs safe first, then the reset. */
void NMI_Handler(void)
{
    port_outputs_safe(); /* valves closed, motors off, before anything else */
    uint32_t reason = PORT_NOTE_UNEXPECTED_IRQ;
    if ((RCC->CIR & RCC_CIR_CSSF) != 0u) {
        RCC->CIR = RCC_CIR_CSSC; /* acknowledged, or the NMI re-enters at once */
        reason = PORT_NOTE_CLOCK_FAILURE;
    }
    port_fatal_reset(reason, 0u);
}

const clock_info_t *clock_info(void) { return &s_info; }
