/*
 * STM32F405 register map: only the peripherals and bits this port uses.
 * Names, offsets and bit positions follow the reference manual RM0090
 * (STM32F405/415/407/417) and the Cortex-M4 generic user guide for the core
 * peripherals. Written for this project; no vendor header is used.
 *
 * Each peripheral is a struct laid over its base address; reserved gaps are
 * padding arrays so every field lands on its RM0090 offset (checked below
 * with static asserts).
 */
#ifndef OIBAR_STM32F4_REGS_H
#define OIBAR_STM32F4_REGS_H

#include <stddef.h>
#include <stdint.h>

#define REG32 volatile uint32_t

/* --- memory map (RM0090 section 2.3) ----------------------------------- */
#define PERIPH_BASE_APB1 0x40000000u
#define PERIPH_BASE_APB2 0x40010000u
#define PERIPH_BASE_AHB1 0x40020000u

/* --- RCC: reset and clock control (RM0090 section 7.3) ----------------- */
typedef struct {
    REG32 CR;          /* 0x00 clock control */
    REG32 PLLCFGR;     /* 0x04 PLL configuration */
    REG32 CFGR;        /* 0x08 clock configuration */
    REG32 CIR;         /* 0x0C clock interrupt */
    REG32 AHB1RSTR;    /* 0x10 */
    REG32 AHB2RSTR;    /* 0x14 */
    REG32 AHB3RSTR;    /* 0x18 */
    uint32_t rsv0;     /* 0x1C */
    REG32 APB1RSTR;    /* 0x20 */
    REG32 APB2RSTR;    /* 0x24 */
    uint32_t rsv1[2];  /* 0x28 */
    REG32 AHB1ENR;     /* 0x30 peripheral clock enable */
    REG32 AHB2ENR;     /* 0x34 */
    REG32 AHB3ENR;     /* 0x38 */
    uint32_t rsv2;     /* 0x3C */
    REG32 APB1ENR;     /* 0x40 */
    REG32 APB2ENR;     /* 0x44 */
    uint32_t rsv3[10]; /* 0x48 .. 0x6C */
    REG32 BDCR;        /* 0x70 backup domain control */
    REG32 CSR;         /* 0x74 control/status: reset flags */
} rcc_regs_t;
#define RCC ((rcc_regs_t *)(PERIPH_BASE_AHB1 + 0x3800u))

#define RCC_CR_HSION (1u << 0)
#define RCC_CR_HSIRDY (1u << 1)
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_CSSON (1u << 19)  /* clock security: HSE failure -> NMI, SYSCLK to HSI */
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)

#define RCC_CIR_CSSF (1u << 7)   /* clock security interrupt flag (HSE failed) */
#define RCC_CIR_CSSC (1u << 23)  /* write 1: clear CSSF */

#define RCC_PLLCFGR_PLLM_POS 0u   /* VCO input divider, 2..63 */
#define RCC_PLLCFGR_PLLN_POS 6u   /* VCO multiplier, 50..432 */
#define RCC_PLLCFGR_PLLP_POS 16u  /* 00 = /2, 01 = /4, ... */
#define RCC_PLLCFGR_PLLSRC_HSE (1u << 22)
#define RCC_PLLCFGR_PLLQ_POS 24u  /* 48 MHz domain divider */

#define RCC_CFGR_SW_MASK 0x3u
#define RCC_CFGR_SW_HSI 0x0u
#define RCC_CFGR_SW_HSE 0x1u
#define RCC_CFGR_SW_PLL 0x2u
#define RCC_CFGR_SWS_POS 2u
#define RCC_CFGR_HPRE_POS 4u      /* AHB prescaler, 0 = /1 */
#define RCC_CFGR_PPRE1_POS 10u    /* APB1 prescaler, 0b101 = /4 */
#define RCC_CFGR_PPRE2_POS 13u    /* APB2 prescaler, 0b100 = /2 */
#define RCC_CFGR_PPRE_DIV2 0x4u
#define RCC_CFGR_PPRE_DIV4 0x5u

#define RCC_AHB1ENR_GPIOAEN (1u << 0)
#define RCC_AHB1ENR_GPIOBEN (1u << 1)
#define RCC_AHB1ENR_GPIOCEN (1u << 2)
#define RCC_APB1ENR_TIM2EN (1u << 0)
#define RCC_APB1ENR_TIM3EN (1u << 1)
#define RCC_APB1ENR_PWREN (1u << 28)
#define RCC_APB2ENR_USART1EN (1u << 4)
#define RCC_APB2ENR_ADC1EN (1u << 8)

#define RCC_CSR_LSION (1u << 0)
#define RCC_CSR_LSIRDY (1u << 1)
#define RCC_CSR_RMVF (1u << 24)      /* write 1: clear the reset flags */
#define RCC_CSR_BORRSTF (1u << 25)
#define RCC_CSR_PINRSTF (1u << 26)
#define RCC_CSR_PORRSTF (1u << 27)
#define RCC_CSR_SFTRSTF (1u << 28)
#define RCC_CSR_IWDGRSTF (1u << 29)
#define RCC_CSR_WWDGRSTF (1u << 30)
#define RCC_CSR_LPWRRSTF (1u << 31)

/* --- FLASH interface (RM0090 section 3.9) ------------------------------ */
typedef struct {
    REG32 ACR;     /* 0x00 access control: wait states, caches */
    REG32 KEYR;    /* 0x04 */
    REG32 OPTKEYR; /* 0x08 */
    REG32 SR;      /* 0x0C */
    REG32 CR;      /* 0x10 */
    REG32 OPTCR;   /* 0x14 */
} flash_regs_t;
#define FLASH ((flash_regs_t *)(PERIPH_BASE_AHB1 + 0x3C00u))

#define FLASH_ACR_LATENCY_MASK 0x7u
#define FLASH_OPTKEY1 0x08192A3Bu
#define FLASH_OPTKEY2 0x4C5D6E7Fu
#define FLASH_SR_BSY (1u << 16)
#define FLASH_OPTCR_OPTLOCK (1u << 0)
#define FLASH_OPTCR_OPTSTRT (1u << 1)
#define FLASH_OPTCR_BOR_LEV_POS 2u
#define FLASH_OPTCR_BOR_LEV_MASK (3u << FLASH_OPTCR_BOR_LEV_POS)
/* BOR_LEV = 00: BOR level 3, reset below 2.70 V (the factory value 11 is off). */
#define FLASH_OPTCR_BOR_LEVEL3 (0u << FLASH_OPTCR_BOR_LEV_POS)
#define FLASH_ACR_PRFTEN (1u << 8)
#define FLASH_ACR_ICEN (1u << 9)
#define FLASH_ACR_DCEN (1u << 10)
#define FLASH_ACR_DCRST (1u << 12) /* data cache reset (only while DCEN is off) */
/* Program/erase (RM0090 section 3.6). */
#define FLASH_KEY1 0x45670123u
#define FLASH_KEY2 0xCDEF89ABu
#define FLASH_SR_EOP (1u << 0)
#define FLASH_SR_OPERR (1u << 1)
#define FLASH_SR_WRPERR (1u << 4)
#define FLASH_SR_PGAERR (1u << 5)
#define FLASH_SR_PGPERR (1u << 6)
#define FLASH_SR_PGSERR (1u << 7)
#define FLASH_SR_ERRORS (FLASH_SR_OPERR | FLASH_SR_WRPERR | FLASH_SR_PGAERR | FLASH_SR_PGPERR | FLASH_SR_PGSERR)
#define FLASH_CR_PG (1u << 0)
#define FLASH_CR_SER (1u << 1)
#define FLASH_CR_SNB_POS 3u
#define FLASH_CR_PSIZE_X32 (2u << 8) /* 32-bit parallelism: needs 2.7-3.6 V (BOR level 3) */
#define FLASH_CR_STRT (1u << 16)
#define FLASH_CR_LOCK (1u << 31)

/* --- PWR (RM0090 section 5.4) ------------------------------------------ */
typedef struct {
    REG32 CR;  /* 0x00 */
    REG32 CSR; /* 0x04 */
} pwr_regs_t;
#define PWR ((pwr_regs_t *)(PERIPH_BASE_APB1 + 0x7000u))

#define PWR_CR_VOS (1u << 14) /* regulator scale 1: needed above 144 MHz */

/* --- DBGMCU (RM0090 section 38.16) ------------------------------------- */
#define DBGMCU_APB1_FZ (*(REG32 *)0xE0042008u)
#define DBGMCU_APB1_FZ_DBG_IWDG_STOP (1u << 12) /* IWDG stops while the core is halted */

/* --- GPIO (RM0090 section 8.4) ----------------------------------------- */
typedef struct {
    REG32 MODER;   /* 0x00 2 bits/pin: 00 in, 01 out, 10 alternate, 11 analog */
    REG32 OTYPER;  /* 0x04 */
    REG32 OSPEEDR; /* 0x08 */
    REG32 PUPDR;   /* 0x0C 2 bits/pin: 01 pull-up, 10 pull-down */
    REG32 IDR;     /* 0x10 */
    REG32 ODR;     /* 0x14 */
    REG32 BSRR;    /* 0x18 low half sets, high half resets: atomic */
    REG32 LCKR;    /* 0x1C */
    REG32 AFR[2];  /* 0x20 AFRL (pins 0-7), 0x24 AFRH (pins 8-15) */
} gpio_regs_t;
#define GPIOA ((gpio_regs_t *)(PERIPH_BASE_AHB1 + 0x0000u))
#define GPIOB ((gpio_regs_t *)(PERIPH_BASE_AHB1 + 0x0400u))
#define GPIOC ((gpio_regs_t *)(PERIPH_BASE_AHB1 + 0x0800u))

#define GPIO_MODE_INPUT 0x0u
#define GPIO_MODE_OUTPUT 0x1u
#define GPIO_MODE_ALTERNATE 0x2u
#define GPIO_MODE_ANALOG 0x3u
#define GPIO_PULL_NONE 0x0u
#define GPIO_PULL_UP 0x1u
#define GPIO_SPEED_MEDIUM 0x1u
#define GPIO_AF_TIM3 2u
#define GPIO_AF_USART1 7u

/* --- USART (RM0090 section 30.6) --------------------------------------- */
typedef struct {
    REG32 SR;   /* 0x00 status */
    REG32 DR;   /* 0x04 data */
    REG32 BRR;  /* 0x08 baud rate: PCLK / baud with OVER8 = 0 */
    REG32 CR1;  /* 0x0C */
    REG32 CR2;  /* 0x10 */
    REG32 CR3;  /* 0x14 */
    REG32 GTPR; /* 0x18 */
} usart_regs_t;
#define USART1 ((usart_regs_t *)(PERIPH_BASE_APB2 + 0x1000u))

#define USART_SR_PE (1u << 0)
#define USART_SR_FE (1u << 1)
#define USART_SR_NF (1u << 2)
#define USART_SR_ORE (1u << 3)
#define USART_SR_RXNE (1u << 5)
#define USART_SR_TXE (1u << 7)
#define USART_CR1_RE (1u << 2)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_RXNEIE (1u << 5)
#define USART_CR1_TXEIE (1u << 7)
#define USART_CR1_UE (1u << 13)

/* --- general-purpose timers TIM2..TIM5 (RM0090 section 18.4) ----------- */
typedef struct {
    REG32 CR1;   /* 0x00 */
    REG32 CR2;   /* 0x04 */
    REG32 SMCR;  /* 0x08 */
    REG32 DIER;  /* 0x0C interrupt enable */
    REG32 SR;    /* 0x10 status: write 0 to clear a flag */
    REG32 EGR;   /* 0x14 event generation */
    REG32 CCMR1; /* 0x18 */
    REG32 CCMR2; /* 0x1C */
    REG32 CCER;  /* 0x20 */
    REG32 CNT;   /* 0x24 */
    REG32 PSC;   /* 0x28 prescaler: f_cnt = f_tim / (PSC + 1) */
    REG32 ARR;   /* 0x2C auto-reload: period = ARR + 1 counts */
    uint32_t rsv0;
    REG32 CCR1;  /* 0x34 */
    REG32 CCR2;  /* 0x38 */
    REG32 CCR3;  /* 0x3C */
    REG32 CCR4;  /* 0x40 */
} tim_regs_t;
#define TIM2 ((tim_regs_t *)(PERIPH_BASE_APB1 + 0x0000u))
#define TIM3 ((tim_regs_t *)(PERIPH_BASE_APB1 + 0x0400u))

#define TIM_CR1_CEN (1u << 0)
#define TIM_CR1_OPM (1u << 3)   /* one-pulse: counter stops at the update event */
#define TIM_CR1_ARPE (1u << 7)  /* ARR buffered: a new period starts at the next update */
#define TIM_DIER_UIE (1u << 0)
#define TIM_SR_UIF (1u << 0)
#define TIM_EGR_UG (1u << 0)
#define TIM_CCMR1_OC1M_PWM2 (0x7u << 4) /* output active while CNT >= CCR1 */
#define TIM_CCER_CC1E (1u << 0)

/* --- ADC1 (RM0090 section 13.13) --------------------------------------- */
typedef struct {
    REG32 SR;      /* 0x00 */
    REG32 CR1;     /* 0x04 */
    REG32 CR2;     /* 0x08 */
    REG32 SMPR1;   /* 0x0C sample time, channels 10..18 */
    REG32 SMPR2;   /* 0x10 sample time, channels 0..9 */
    REG32 JOFR[4]; /* 0x14 */
    REG32 HTR;     /* 0x24 */
    REG32 LTR;     /* 0x28 */
    REG32 SQR1;    /* 0x2C regular sequence length L in bits 23:20 */
    REG32 SQR2;    /* 0x30 */
    REG32 SQR3;    /* 0x34 first conversion's channel in bits 4:0 */
    REG32 JSQR;    /* 0x38 */
    REG32 JDR[4];  /* 0x3C */
    REG32 DR;      /* 0x4C regular data; reading it clears EOC */
} adc_regs_t;
#define ADC1 ((adc_regs_t *)(PERIPH_BASE_APB2 + 0x2000u))
#define ADC_CCR (*(REG32 *)(PERIPH_BASE_APB2 + 0x2300u + 0x04u)) /* common control */

#define ADC_SR_EOC (1u << 1)
#define ADC_SR_OVR (1u << 5)
#define ADC_CR2_ADON (1u << 0)
#define ADC_CR2_SWSTART (1u << 30)
#define ADC_CCR_ADCPRE_DIV4 (0x1u << 16) /* ADC clock = PCLK2 / 4 (<= 36 MHz) */
#define ADC_SMP_144_CYCLES 0x6u

/* --- IWDG: independent watchdog on the ~32 kHz LSI (RM0090 section 21.4) */
typedef struct {
    REG32 KR;  /* 0x00 key */
    REG32 PR;  /* 0x04 prescaler */
    REG32 RLR; /* 0x08 reload */
    REG32 SR;  /* 0x0C update in progress flags */
} iwdg_regs_t;
#define IWDG ((iwdg_regs_t *)(PERIPH_BASE_APB1 + 0x3000u))

#define IWDG_KEY_RELOAD 0xAAAAu
#define IWDG_KEY_UNLOCK 0x5555u
#define IWDG_KEY_START 0xCCCCu
#define IWDG_PR_DIV32 0x3u
#define IWDG_SR_PVU (1u << 0)
#define IWDG_SR_RVU (1u << 1)

/* --- Cortex-M4 core peripherals (ARM DDI 0439 / PM0214) ---------------- */
typedef struct {
    REG32 CTRL;  /* 0x00 SYST_CSR */
    REG32 LOAD;  /* 0x04 SYST_RVR */
    REG32 VAL;   /* 0x08 SYST_CVR */
    REG32 CALIB; /* 0x0C */
} systick_regs_t;
#define SYSTICK ((systick_regs_t *)0xE000E010u)
#define SYSTICK_CTRL_ENABLE (1u << 0)
#define SYSTICK_CTRL_TICKINT (1u << 1)
#define SYSTICK_CTRL_CLKSOURCE_CPU (1u << 2)

typedef struct {
    REG32 CPUID; /* 0x00 */
    REG32 ICSR;  /* 0x04 */
    REG32 VTOR;  /* 0x08 vector table offset */
    REG32 AIRCR; /* 0x0C */
    REG32 SCR;   /* 0x10 */
    REG32 CCR;   /* 0x14 */
    volatile uint8_t SHPR[12]; /* 0x18 system handler priorities, handlers 4..15 */
    REG32 SHCSR; /* 0x24 */
    REG32 CFSR;  /* 0x28 configurable fault status */
    REG32 HFSR;  /* 0x2C hard fault status */
} scb_regs_t;
#define SCB ((scb_regs_t *)0xE000ED00u)
#define SCB_CPACR (*(REG32 *)0xE000ED88u) /* coprocessor access: CP10/CP11 = FPU */
#define SCB_CPACR_FPU_FULL (0xFu << 20)
#define SCB_AIRCR_VECTKEY (0x05FAu << 16)
#define SCB_AIRCR_SYSRESETREQ (1u << 2)
#define SCB_SHPR_IDX_SYSTICK (15u - 4u)

#define NVIC_ISER ((REG32 *)0xE000E100u)          /* set-enable, 32 IRQs per word */
#define NVIC_ICER ((REG32 *)0xE000E180u)          /* clear-enable */
#define NVIC_ISPR ((REG32 *)0xE000E200u)          /* set-pending: run an ISR from software */
#define NVIC_IPR ((volatile uint8_t *)0xE000E400u) /* one priority byte per IRQ */
#define NVIC_PRIO_BITS 4u                          /* STM32F4: 16 levels, upper nibble */

/* IRQ numbers (RM0090 table 61). */
#define IRQN_ADC 18u
#define IRQN_TIM2 28u
#define IRQN_TIM3 29u
#define IRQN_USART1 37u
#define IRQN_COUNT 82u

/* Offsets as RM0090 gives them; a typo in a padding array fails the build. */
_Static_assert(offsetof(rcc_regs_t, AHB1ENR) == 0x30u, "RCC_AHB1ENR offset");
_Static_assert(offsetof(rcc_regs_t, APB2ENR) == 0x44u, "RCC_APB2ENR offset");
_Static_assert(offsetof(rcc_regs_t, CSR) == 0x74u, "RCC_CSR offset");
_Static_assert(offsetof(gpio_regs_t, AFR) == 0x20u, "GPIO_AFRL offset");
_Static_assert(offsetof(tim_regs_t, ARR) == 0x2Cu, "TIM_ARR offset");
_Static_assert(offsetof(tim_regs_t, CCR1) == 0x34u, "TIM_CCR1 offset");
_Static_assert(offsetof(adc_regs_t, SQR3) == 0x34u, "ADC_SQR3 offset");
_Static_assert(offsetof(adc_regs_t, DR) == 0x4Cu, "ADC_DR offset");
_Static_assert(offsetof(scb_regs_t, CFSR) == 0x28u, "SCB_CFSR offset");

static inline void nvic_enable(uint32_t irqn, uint32_t priority)
{
    NVIC_IPR[irqn] = (uint8_t)(priority << (8u - NVIC_PRIO_BITS));
    NVIC_ISER[irqn >> 5] = 1u << (irqn & 31u);
}

static inline void nvic_disable(uint32_t irqn)
{
    NVIC_ICER[irqn >> 5] = 1u << (irqn & 31u);
}

static inline void cpu_dsb(void) { __asm volatile("dsb 0xF" ::: "memory"); }
static inline void cpu_isb(void) { __asm volatile("isb 0xF" ::: "memory"); }

#endif /* OIBAR_STM32F4_REGS_H */
