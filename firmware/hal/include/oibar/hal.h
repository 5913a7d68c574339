/*
 * OIBAR hardware abstraction layer.
 *
 * The application talks to the hardware only through these functions; a port
 * (firmware/port/<target>/) implements them for one board, the fake HAL
 * (tests/firmware/support/fake_hal.c) implements them for the unit tests.
 *
 * Contract for every port:
 *  - nothing here blocks: reads return the latest sampled value, writes are
 *    queued or immediate;
 *  - functions marked "ISR-safe" may be called from interrupt context;
 *  - signals are named by what they mean, never by pin: the port maps them.
 */
#ifndef OIBAR_HAL_H
#define OIBAR_HAL_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Digital inputs, already converted to "true = the named condition holds"
 * (the port handles active-low wiring). Debouncing is the application's. */
typedef enum {
    HAL_DI_CONTACT = 0,        /* probe is in contact with the drogue */
    HAL_DI_LATCH_ENGAGED,      /* latch switch NO contact closed: latches popped out */
    HAL_DI_LATCH_HOME,         /* latch stepper at its home (default) position */
    HAL_DI_PLANE_EXTENDED,     /* fluidic plane at its extended end switch */
    HAL_DI_PLANE_RETRACTED,    /* fluidic plane at its retracted end switch */
    HAL_DI_CONNECTOR_MATED,    /* electrical connector mated (sense loop closed) */
    HAL_DI_SV_VALVE_OPEN,      /* service-vehicle valve position switch: open */
    HAL_DI_TV_VALVE_OPEN,      /* target-vehicle valve position switch: open */
    /* Latch switch NC contact closed: latches not engaged. With
     * HAL_DI_LATCH_ENGAGED it makes a changeover pair: exactly one of the two
     * holds on a healthy switch, so a broken wire (or a short) shows as
     * "both" or "neither" (drv_inputs faults on it). Appended last so the
     * other indices, and the sim's di_bits, keep their numbers. */
    HAL_DI_LATCH_NOT_ENGAGED,
    HAL_DI_COUNT
} hal_di_t;

/* Digital outputs, "true = energised". Every output is false after reset,
 * which is the safe state: valves are normally closed, actuators off. */
typedef enum {
    HAL_DO_LATCH_DIR = 0,      /* stepper direction: true = towards release */
    HAL_DO_LATCH_ENABLE,       /* stepper driver enable (holding torque) */
    HAL_DO_PLANE_EXTEND,       /* H-bridge: drive the plane towards the fixture */
    HAL_DO_PLANE_RETRACT,      /* H-bridge: drive the plane back */
    HAL_DO_SV_VALVE,           /* service-vehicle valve coil (normally closed) */
    HAL_DO_TV_VALVE,           /* target-vehicle valve coil (normally closed) */
    HAL_DO_COUNT
} hal_do_t;

/* ADC channels. Counts are raw 12-bit conversions (0..4095). */
typedef enum {
    HAL_ADC_SV_TANK = 0,       /* supply tank pressure transducer */
    HAL_ADC_TV_TANK,           /* receiving tank pressure transducer */
    HAL_ADC_LINE,              /* transfer line pressure transducer */
    HAL_ADC_PLANE_POS,         /* plane position potentiometer */
    HAL_ADC_CONTACT_FORCE,     /* probe load cell amplifier */
    HAL_ADC_COUNT
} hal_adc_t;

#define HAL_ADC_MAX_COUNTS 4095u

typedef enum {
    HAL_RESET_UNKNOWN = 0,
    HAL_RESET_POWER_ON,
    HAL_RESET_PIN,
    HAL_RESET_WATCHDOG,
    HAL_RESET_BROWNOUT,
    HAL_RESET_SOFTWARE,
    HAL_RESET_LOCKUP
} hal_reset_cause_t;

typedef void (*hal_isr_fn)(void);
typedef void (*hal_uart_rx_fn)(uint8_t byte);

/* Bring up clocks and peripherals; every output false. Called once. */
void hal_init(void);

/* --- time base --------------------------------------------------------- */
/* Milliseconds since reset, wraps after 49.7 days. ISR-safe. */
uint32_t hal_time_ms(void);
/* The port calls `tick` from its 1 kHz control timer interrupt. */
void hal_control_tick_attach(hal_isr_fn tick);

/* --- digital I/O ------------------------------------------------------- */
bool hal_di_read(hal_di_t di);              /* ISR-safe */
void hal_do_write(hal_do_t out, bool on);   /* ISR-safe */

/* --- step-pulse timer -------------------------------------------------- */
/* The timer calls `isr` once per period; the ISR emits one pulse with
 * hal_step_pulse(). The period may be changed from inside the ISR: the new
 * value is the time from this call of the ISR to the next one (not one period
 * later). Outside the ISR it applies to the period running. Ports: the fake
 * HAL (tests/firmware/support) and the sim port count down the new value
 * from the last call; the STM32F4 port writes TIM2's ARR unbuffered. */
void hal_step_timer_attach(hal_isr_fn isr);
void hal_step_timer_start(uint32_t period_us);
void hal_step_timer_set_period(uint32_t period_us);  /* ISR-safe */
void hal_step_timer_stop(void);                      /* ISR-safe */
/* One step pulse of the driver's minimum width (port: timer one-pulse mode). */
void hal_step_pulse(void);                           /* ISR-safe */

/* --- ADC --------------------------------------------------------------- */
/* Latest conversion of a continuously scanned channel. Returns false when
 * the conversion failed or is stale; the caller treats that as a sensor
 * fault. ISR-safe. */
bool hal_adc_read(hal_adc_t ch, uint16_t *counts);

/* --- UART to the companion computer ------------------------------------ */
/* Queue bytes for transmission; returns how many were accepted (may be fewer
 * than len when the transmit buffer is full). Never blocks. */
size_t hal_uart_write(const uint8_t *data, size_t len);
/* The port calls `on_byte` from the receive interrupt for each byte. */
void hal_uart_rx_attach(hal_uart_rx_fn on_byte);
/* Receive errors the UART counted since the reset (Telemetry.uart_rx_errors
 * and uart_rx_overruns): framing, noise and parity errors; overruns (a byte
 * arrived before the previous one was read). */
typedef struct {
    uint32_t rx_errors;
    uint32_t rx_overruns;
} hal_uart_errors_t;
void hal_uart_errors(hal_uart_errors_t *out);

/* --- watchdog, critical sections, reset cause -------------------------- */
/* The watchdog fires if it is not kicked for this long: one number for every
 * port, the board's IWDG (stm32f4/src/hal_core.c) and the simulated MCU's
 * (port/sim, its default; `--watchdog-ms` overrides it for a test only). The
 * main loop kicks about every millisecond; 250 ms leaves room for the slowest
 * pass (a 247-byte frame encoded and queued) without hiding a stuck loop. */
#define HAL_WATCHDOG_TIMEOUT_MS 250u
void hal_watchdog_kick(void);
/* Disable interrupts; returns the previous mask for hal_critical_exit.
 * Nests. */
uint32_t hal_critical_enter(void);
void hal_critical_exit(uint32_t saved);
hal_reset_cause_t hal_reset_cause(void);

/* --- parameter flash (app/src/pstore.c) -------------------------------- */
/* Two flash sectors reserved for the stored parameters, numbered 0 and 1 here
 * (STM32F405: sectors 1 and 2, 16 KiB each at 0x08004000 and 0x08008000,
 * kept out of the image by the linker script and checked after the link).
 * Erased flash reads 0xFF; programming only clears bits.
 *
 * The one exception to "nothing here blocks": hal_flash_erase_sector and
 * hal_flash_program return when the operation has finished. A 16 KiB sector
 * erase stalls the flash bank for up to about a second (typical 250 ms,
 * 500 ms maximum at 32-bit parallelism, STM32F405 datasheet), longer than the
 * 250 ms watchdog: the port keeps the watchdog fed while it waits (STM32F4:
 * from code in RAM, interrupts masked, the IWDG reloaded on every poll of
 * BSY). Interrupts and the control tick are held off for that time, so the
 * application calls these only from the main loop in a safe state
 * (STATE_BOOT or STATE_IDLE, valves closed: CMD_SAVE_PARAMS).
 * Each returns false on a bad argument (sector >= HAL_FLASH_SECTORS, a range
 * past the sector's end, an offset not word-aligned) or a hardware error. */
#define HAL_FLASH_SECTORS 2u
#define HAL_FLASH_SECTOR_BYTES 16384u
bool hal_flash_read(unsigned sector, uint32_t offset, void *dst, size_t len);
bool hal_flash_erase_sector(unsigned sector);
/* Program n_words 32-bit words at a word-aligned offset, in increasing
 * address order (a power cut leaves a prefix written). */
bool hal_flash_program(unsigned sector, uint32_t offset, const uint32_t *words, size_t n_words);

#ifdef __cplusplus
}
#endif

#endif /* OIBAR_HAL_H */
