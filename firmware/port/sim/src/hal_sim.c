/* HAL on simulated time (docs/hil.md). Single-threaded: the lockstep loop
 * calls the "interrupts" in between main-loop passes, so a critical section
 * only has to nest correctly, never to mask anything. */
#include "oibar/hal_sim.h"


/* A step period shorter than this would mean more than 1000 interrupts per
 * ms; the real timer could not do it either, so the sim bounds the loop. */
#define MAX_STEP_ISR_PER_MS 1000u

static bool s_di[HAL_DI_COUNT];
static uint16_t s_adc[HAL_ADC_COUNT];
static uint32_t s_adc_fail_bits;
static uint32_t s_do_bits;
static uint32_t s_uptime_ms;
static hal_reset_cause_t s_reset_cause = HAL_RESET_POWER_ON;

static hal_isr_fn s_tick_fn;
static hal_isr_fn s_step_fn;
static hal_uart_rx_fn s_rx_fn;
static hal_sim_tx_fn s_tx_fn;

static bool s_step_running;
static uint32_t s_step_period_us;
static uint32_t s_step_acc_us;
static uint32_t s_steps_fwd;
static uint32_t s_steps_rev;
static uint32_t s_steps_total;

static uint32_t s_wdg_timeout_ms = HAL_WATCHDOG_TIMEOUT_MS; /* the board's number */
static uint32_t s_wdg_since_kick_ms;
static uint32_t s_wdg_kicks;
static uint32_t s_crit_depth;

void hal_sim_reset(hal_reset_cause_t cause)
{
    s_do_bits = 0u;
    s_uptime_ms = 0u;
    s_reset_cause = cause;
    s_tick_fn = NULL;
    s_step_fn = NULL;
    s_rx_fn = NULL;
    s_step_running = false;
    s_step_period_us = 0u;
    s_step_acc_us = 0u;
    s_wdg_since_kick_ms = 0u;
    s_crit_depth = 0u;
}

void hal_sim_set_inputs(uint32_t di_bits, const uint16_t *adc_counts, size_t n_adc,
                        uint32_t adc_fail_bits)
{
    for (unsigned i = 0; i < (unsigned)HAL_DI_COUNT; i++) {
        s_di[i] = ((di_bits >> i) & 1u) != 0u;
    }
    for (unsigned i = 0; i < (unsigned)HAL_ADC_COUNT && i < n_adc; i++) {
        s_adc[i] = (adc_counts[i] > HAL_ADC_MAX_COUNTS) ? (uint16_t)HAL_ADC_MAX_COUNTS : adc_counts[i];
    }
    s_adc_fail_bits = adc_fail_bits;
}

void hal_sim_advance_1ms(void)
{
    s_uptime_ms++;
    s_wdg_since_kick_ms++;
    uint32_t calls = 0u;
    s_step_acc_us += 1000u;
    while (s_step_running && s_step_fn != NULL && s_step_period_us > 0u &&
           s_step_acc_us >= s_step_period_us && calls < MAX_STEP_ISR_PER_MS) {
        s_step_acc_us -= s_step_period_us;
        calls++;
        s_step_fn();
    }
    if (!s_step_running) {
        s_step_acc_us = 0u;
    }
    if (s_tick_fn != NULL) {
        s_tick_fn();
    }
}

uint32_t hal_sim_do_bits(void) { return s_do_bits; }
bool hal_sim_step_timer_running(void) { return s_step_running; }

void hal_sim_take_steps(uint32_t *fwd, uint32_t *rev)
{
    *fwd = s_steps_fwd;
    *rev = s_steps_rev;
    s_steps_fwd = 0u;
    s_steps_rev = 0u;
}

uint32_t hal_sim_steps_total(void) { return s_steps_total; }

void hal_sim_set_watchdog_timeout_ms(uint32_t timeout_ms)
{
    s_wdg_timeout_ms = (timeout_ms == 0u) ? 1u : timeout_ms;
}

bool hal_sim_watchdog_expired(void) { return s_wdg_since_kick_ms >= s_wdg_timeout_ms; }
uint32_t hal_sim_watchdog_kicks(void) { return s_wdg_kicks; }
void hal_sim_set_uart_tx(hal_sim_tx_fn tx) { s_tx_fn = tx; }

void hal_sim_uart_rx_byte(uint8_t byte)
{
    if (s_rx_fn != NULL) {
        s_rx_fn(byte);
    }
}

/* --- oibar/hal.h --------------------------------------------------------- */

void hal_init(void)
{
    /* Outputs were cleared by the reset; the watchdog runs from here on. */
    s_do_bits = 0u;
    s_wdg_since_kick_ms = 0u;
}

uint32_t hal_time_ms(void) { return s_uptime_ms; }
void hal_control_tick_attach(hal_isr_fn tick) { s_tick_fn = tick; }

bool hal_di_read(hal_di_t di) { return ((unsigned)di < (unsigned)HAL_DI_COUNT) ? s_di[di] : false; }

void hal_do_write(hal_do_t out, bool on)
{
    if ((unsigned)out >= (unsigned)HAL_DO_COUNT) {
        return;
    }
    const uint32_t bit = 1u << (unsigned)out;
    s_do_bits = on ? (s_do_bits | bit) : (s_do_bits & ~bit);
}

void hal_step_timer_attach(hal_isr_fn isr) { s_step_fn = isr; }

void hal_step_timer_start(uint32_t period_us)
{
    s_step_period_us = period_us;
    s_step_acc_us = 0u;
    s_step_running = true;
}

void hal_step_timer_set_period(uint32_t period_us) { s_step_period_us = period_us; }
void hal_step_timer_stop(void) { s_step_running = false; }

void hal_step_pulse(void)
{
    /* The plant decides what a pulse does (enable, stall); here we only
     * count it with the direction the driver sees. */
    if ((s_do_bits & (1u << (unsigned)HAL_DO_LATCH_DIR)) != 0u) {
        s_steps_fwd++;
    } else {
        s_steps_rev++;
    }
    s_steps_total++;
}

bool hal_adc_read(hal_adc_t ch, uint16_t *counts)
{
    if ((unsigned)ch >= (unsigned)HAL_ADC_COUNT || ((s_adc_fail_bits >> (unsigned)ch) & 1u) != 0u) {
        return false;
    }
    *counts = s_adc[ch];
    return true;
}

size_t hal_uart_write(const uint8_t *data, size_t len)
{
    return (s_tx_fn != NULL) ? s_tx_fn(data, len) : len; /* no wire: bytes vanish */
}

void hal_uart_rx_attach(hal_uart_rx_fn on_byte) { s_rx_fn = on_byte; }
/* The pty delivers whole bytes: the simulated UART sees no framing error or
 * overrun (the rig's bit errors damage bytes, which the frame CRC drops). */
void hal_uart_errors(hal_uart_errors_t *out)
{
    out->rx_errors = 0u;
    out->rx_overruns = 0u;
}

void hal_watchdog_kick(void)
{
    s_wdg_since_kick_ms = 0u;
    s_wdg_kicks++;
}

uint32_t hal_critical_enter(void)
{
    s_crit_depth++;
    return s_crit_depth;
}

void hal_critical_exit(uint32_t saved)
{
    (void)saved;
    if (s_crit_depth > 0u) {
        s_crit_depth--;
    }
}

hal_reset_cause_t hal_reset_cause(void) { return s_reset_cause; }
