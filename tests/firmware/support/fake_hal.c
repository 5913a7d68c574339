/* Fake HAL and plant model for the unit tests (see fake_hal.h). */
#include "fake_hal.h"

#include <string.h>

#define TX_CAP 8192u

static bool s_di[HAL_DI_COUNT];
static bool s_do[HAL_DO_COUNT];
static uint32_t s_do_writes[HAL_DO_COUNT];
static uint16_t s_adc[HAL_ADC_COUNT];
static bool s_adc_fail[HAL_ADC_COUNT];
static hal_reset_cause_t s_reset_cause;
static uint32_t s_now_ms;
static hal_isr_fn s_tick_fn;
static hal_isr_fn s_step_fn;
static hal_uart_rx_fn s_rx_fn;
static hal_uart_errors_t s_uart_errors;
static void (*s_main_fn)(void);
static bool s_tick_enabled;
static uint32_t s_kicks;
static bool s_step_running;
static uint32_t s_step_period_us;
static uint32_t s_step_acc_us;
static uint32_t s_step_pulses;
static uint32_t s_max_isr_per_ms;
static int s_crit_depth;
static void (*s_irq_fn)(void); /* armed interrupt: fires at an unmasked HAL call */
static uint32_t s_irq_windows;  /* ... at this one (1 = the next) */
static uint8_t s_tx[TX_CAP];
static size_t s_tx_len;

/* parameter flash */
static uint8_t f_mem[HAL_FLASH_SECTORS][HAL_FLASH_SECTOR_BYTES];
static uint32_t f_ops;
static int32_t f_cut_after; /* -1: no cut armed */
static bool f_dead;         /* power is off: nothing programs any more */
static bool f_fail;
static bool f_drop;

/* plant */
static bool p_on;
static bool p_probe;
static uint32_t p_contact_ms;     /* how long the probe has been in */
static uint32_t p_released_ms;    /* how long the latch has been released with the probe in */
static fake_valve_mode_t p_valve_mode[2];
static bool p_valve_open[2];
static uint32_t p_valve_ms[2];    /* stroke progress */
static uint32_t p_valve_stroke_ms; /* FAKE_PLANT_VALVE_STROKE_MS unless a test slows it */
static bool p_plane_jam;
static bool p_step_stall;
static float p_plane_mm;
static int32_t p_latch_steps;
static float p_sv_kpa;
static float p_tv_kpa;
static float p_force_n;
static float p_line_kpa;
static int p_di_ovr[HAL_DI_COUNT];
static int p_adc_ovr[HAL_ADC_COUNT];

void fake_hal_reset(void)
{
    memset(s_di, 0, sizeof s_di);
    s_di[HAL_DI_LATCH_NOT_ENGAGED] = true; /* a healthy latch switch at rest */
    memset(s_do, 0, sizeof s_do);
    memset(s_do_writes, 0, sizeof s_do_writes);
    for (unsigned i = 0; i < HAL_ADC_COUNT; i++) {
        s_adc[i] = 2048u;
        s_adc_fail[i] = false;
    }
    s_reset_cause = HAL_RESET_POWER_ON;
    s_now_ms = 0;
    s_tick_fn = NULL;
    s_step_fn = NULL;
    s_rx_fn = NULL;
    s_main_fn = NULL;
    s_tick_enabled = true;
    s_kicks = 0;
    s_step_running = false;
    s_step_period_us = 0;
    s_step_acc_us = 0;
    s_step_pulses = 0;
    s_max_isr_per_ms = 0;
    s_crit_depth = 0;
    s_irq_fn = NULL;
    s_tx_len = 0;
    s_uart_errors.rx_errors = 0;
    s_uart_errors.rx_overruns = 0;
    fake_flash_blank();
    f_ops = 0;
    f_cut_after = -1;
    f_dead = false;
    f_fail = false;
    f_drop = false;

    p_on = false;
    p_probe = false;
    p_contact_ms = 0;
    p_released_ms = 0;
    for (unsigned v = 0; v < 2; v++) {
        p_valve_mode[v] = FAKE_VALVE_OK;
        p_valve_open[v] = false;
        p_valve_ms[v] = 0;
    }
    p_valve_stroke_ms = FAKE_PLANT_VALVE_STROKE_MS;
    p_plane_jam = false;
    p_step_stall = false;
    p_plane_mm = 0.0f;
    p_latch_steps = 0;
    p_sv_kpa = 2000.0f;
    p_tv_kpa = 200.0f;
    p_force_n = 0.0f;
    p_line_kpa = 100.0f;
    fake_plant_clear_overrides();
}

/* An armed interrupt is taken at the first HAL call made with interrupts
 * enabled (outside every critical section): the finest interleaving the
 * application can observe. */
static void irq_window(void)
{
    if (s_irq_fn != NULL && s_crit_depth == 0 && --s_irq_windows == 0u) {
        void (*fn)(void) = s_irq_fn;
        s_irq_fn = NULL;
        fn();
    }
}

void fake_hal_irq_at_window(uint32_t n, void (*isr)(void))
{
    s_irq_windows = (n == 0u) ? 1u : n;
    s_irq_fn = isr;
}

void fake_hal_irq_at_next_window(void (*isr)(void)) { fake_hal_irq_at_window(1u, isr); }
bool fake_hal_irq_armed(void) { return s_irq_fn != NULL; }

/* --- HAL implementation ------------------------------------------------ */
void hal_init(void) {}
uint32_t hal_time_ms(void)
{
    irq_window();
    return s_now_ms;
}
void hal_control_tick_attach(hal_isr_fn tick) { s_tick_fn = tick; }
bool hal_di_read(hal_di_t di)
{
    irq_window();
    return ((unsigned)di < HAL_DI_COUNT) ? s_di[di] : false;
}

void hal_do_write(hal_do_t out, bool on)
{
    irq_window();
    if ((unsigned)out < HAL_DO_COUNT) {
        s_do[out] = on;
        s_do_writes[out]++;
    }
}

void hal_step_timer_attach(hal_isr_fn isr) { s_step_fn = isr; }

void hal_step_timer_start(uint32_t period_us)
{
    s_step_period_us = period_us;
    s_step_acc_us = 0;
    s_step_running = true;
}

void hal_step_timer_set_period(uint32_t period_us) { s_step_period_us = period_us; }
void hal_step_timer_stop(void) { s_step_running = false; }

void hal_step_pulse(void)
{
    s_step_pulses++;
    if (p_on && s_do[HAL_DO_LATCH_ENABLE] && !p_step_stall) {
        p_latch_steps += s_do[HAL_DO_LATCH_DIR] ? 1 : -1;
        if (p_latch_steps < 0) {
            p_latch_steps = 0; /* mechanical stop behind the home switch */
        }
    }
}

bool hal_adc_read(hal_adc_t ch, uint16_t *counts)
{
    irq_window();
    if ((unsigned)ch >= HAL_ADC_COUNT || s_adc_fail[ch]) {
        return false;
    }
    *counts = s_adc[ch];
    return true;
}

size_t hal_uart_write(const uint8_t *data, size_t len)
{
    size_t n = 0;
    while (n < len && s_tx_len < TX_CAP) {
        s_tx[s_tx_len++] = data[n++];
    }
    return n;
}

void hal_uart_rx_attach(hal_uart_rx_fn on_byte) { s_rx_fn = on_byte; }
void hal_uart_errors(hal_uart_errors_t *out) { *out = s_uart_errors; }
void hal_watchdog_kick(void) { s_kicks++; }

uint32_t hal_critical_enter(void)
{
    irq_window(); /* taken before the mask goes on */
    s_crit_depth++;
    return (uint32_t)s_crit_depth;
}

void hal_critical_exit(uint32_t saved)
{
    (void)saved;
    s_crit_depth--;
    irq_window(); /* a pending interrupt runs as soon as the mask comes off */
}

hal_reset_cause_t hal_reset_cause(void) { return s_reset_cause; }

/* --- parameter flash -------------------------------------------------- */
uint8_t *fake_flash_sector(unsigned sector) { return f_mem[sector % HAL_FLASH_SECTORS]; }
void fake_flash_blank(void) { memset(f_mem, 0xFF, sizeof f_mem); }
uint32_t fake_flash_ops(void) { return f_ops; }
void fake_flash_cut_after(int32_t ops) { f_cut_after = ops; }
void fake_flash_set_fail(bool fail) { f_fail = fail; }
void fake_flash_set_silent_drop(bool drop) { f_drop = drop; }

void fake_hal_power_cycle(void)
{
    static uint8_t keep[HAL_FLASH_SECTORS][HAL_FLASH_SECTOR_BYTES];
    memcpy(keep, f_mem, sizeof keep);
    fake_hal_reset();
    memcpy(f_mem, keep, sizeof keep);
}

static bool flash_range_ok(unsigned sector, uint32_t offset, size_t len)
{
    return sector < HAL_FLASH_SECTORS && offset <= HAL_FLASH_SECTOR_BYTES &&
           len <= HAL_FLASH_SECTOR_BYTES - offset;
}

/* One erase or word program: true when it may run whole; false when the
 * power is gone (the cut one runs half way, `*cut` set). */
static bool flash_op_begins(bool *cut)
{
    *cut = false;
    if (f_dead || f_fail) {
        return false;
    }
    if (f_cut_after == 0) {
        f_dead = true;
        *cut = true;
        return false;
    }
    if (f_cut_after > 0) {
        f_cut_after--;
    }
    f_ops++;
    return true;
}

bool hal_flash_read(unsigned sector, uint32_t offset, void *dst, size_t len)
{
    if (dst == NULL || !flash_range_ok(sector, offset, len)) {
        return false;
    }
    memcpy(dst, &f_mem[sector][offset], len);
    return true;
}

bool hal_flash_erase_sector(unsigned sector)
{
    if (sector >= HAL_FLASH_SECTORS) {
        return false;
    }
    bool cut;
    if (!flash_op_begins(&cut)) {
        if (cut) {
            memset(f_mem[sector], 0xFF, HAL_FLASH_SECTOR_BYTES / 2u);
        }
        return false;
    }
    memset(f_mem[sector], 0xFF, HAL_FLASH_SECTOR_BYTES);
    return true;
}

bool hal_flash_program(unsigned sector, uint32_t offset, const uint32_t *words, size_t n_words)
{
    if (words == NULL || (offset & 3u) != 0u || n_words > HAL_FLASH_SECTOR_BYTES / 4u ||
        !flash_range_ok(sector, offset, n_words * 4u)) {
        return false;
    }
    for (size_t i = 0; i < n_words; i++) {
        uint8_t *at = &f_mem[sector][offset + 4u * i];
        uint32_t old;
        memcpy(&old, at, 4u);
        bool cut;
        if (!flash_op_begins(&cut)) {
            if (cut) {
                const uint32_t half = old & (words[i] | 0x0000FFFFu); /* upper half written */
                memcpy(at, &half, 4u);
            }
            return false;
        }
        const uint32_t v = f_drop ? old : (old & words[i]); /* flash clears bits, never sets them */
        memcpy(at, &v, 4u);
    }
    return true;
}

/* --- knobs ------------------------------------------------------------- */
void fake_hal_set_di(hal_di_t di, bool level)
{
    s_di[di] = level;
    if (di == HAL_DI_LATCH_ENGAGED) {
        s_di[HAL_DI_LATCH_NOT_ENGAGED] = !level; /* the changeover switch's other contact */
    }
}
bool fake_hal_do(hal_do_t out) { return s_do[out]; }
uint32_t fake_hal_do_writes(hal_do_t out) { return s_do_writes[out]; }
void fake_hal_set_adc(hal_adc_t ch, uint16_t counts) { s_adc[ch] = counts; }
void fake_hal_set_adc_fail(hal_adc_t ch, bool fail) { s_adc_fail[ch] = fail; }
void fake_hal_set_reset_cause(hal_reset_cause_t cause) { s_reset_cause = cause; }
void fake_hal_set_main_loop(void (*fn)(void)) { s_main_fn = fn; }
void fake_hal_set_tick_enabled(bool on) { s_tick_enabled = on; }
uint32_t fake_hal_watchdog_kicks(void) { return s_kicks; }
uint32_t fake_hal_step_pulses(void) { return s_step_pulses; }
bool fake_hal_step_timer_running(void) { return s_step_running; }
uint32_t fake_hal_step_period_us(void) { return s_step_period_us; }
int fake_hal_critical_depth(void) { return s_crit_depth; }
uint32_t fake_hal_max_step_isr_per_ms(void) { return s_max_isr_per_ms; }
size_t fake_hal_uart_tx_len(void) { return s_tx_len; }
const uint8_t *fake_hal_uart_tx_data(void) { return s_tx; }
void fake_hal_uart_tx_clear(void) { s_tx_len = 0; }
void fake_hal_uart_set_errors(uint32_t rx_errors, uint32_t rx_overruns)
{
    s_uart_errors.rx_errors = rx_errors;
    s_uart_errors.rx_overruns = rx_overruns;
}

void fake_hal_uart_rx_inject(const uint8_t *bytes, size_t len)
{
    for (size_t i = 0; i < len && s_rx_fn != NULL; i++) {
        s_rx_fn(bytes[i]);
    }
}

/* --- plant ------------------------------------------------------------- */
void fake_plant_enable(bool on) { p_on = on; }
void fake_plant_set_probe(bool inserted) { p_probe = inserted; }
bool fake_plant_probe(void) { return p_probe; }
void fake_plant_set_valve_mode(unsigned valve, fake_valve_mode_t mode) { p_valve_mode[valve & 1u] = mode; }
void fake_plant_set_valve_stroke_ms(uint32_t ms) { p_valve_stroke_ms = (ms == 0u) ? 1u : ms; }
void fake_plant_set_plane_jam(bool jam) { p_plane_jam = jam; }
void fake_plant_set_stepper_stall(bool stall) { p_step_stall = stall; }
void fake_plant_set_force_n(float force_n) { p_force_n = force_n; }
float fake_plant_plane_mm(void) { return p_plane_mm; }
int32_t fake_plant_latch_steps(void) { return p_latch_steps; }
float fake_plant_tv_kpa(void) { return p_tv_kpa; }
float fake_plant_sv_kpa(void) { return p_sv_kpa; }
bool fake_plant_valve_open(unsigned valve) { return p_valve_open[valve & 1u]; }

void fake_plant_set_tanks_kpa(float sv_kpa, float tv_kpa)
{
    p_sv_kpa = sv_kpa;
    p_tv_kpa = tv_kpa;
}

void fake_plant_override_di(hal_di_t di, int level) { p_di_ovr[di] = level; }
void fake_plant_override_adc(hal_adc_t ch, int counts) { p_adc_ovr[ch] = counts; }

void fake_plant_clear_overrides(void)
{
    for (unsigned i = 0; i < HAL_DI_COUNT; i++) {
        p_di_ovr[i] = -1;
    }
    for (unsigned i = 0; i < HAL_ADC_COUNT; i++) {
        p_adc_ovr[i] = -1;
    }
}

static uint16_t kpa_to_counts(float kpa)
{
    float c = kpa / 0.9158f + 410.0f;
    if (c < 0.0f) {
        c = 0.0f;
    }
    if (c > 4095.0f) {
        c = 4095.0f;
    }
    return (uint16_t)(c + 0.5f);
}

static void plant_step_1ms(void)
{
    const hal_do_t coil[2] = { HAL_DO_SV_VALVE, HAL_DO_TV_VALVE };
    for (unsigned v = 0; v < 2; v++) {
        if (p_valve_mode[v] == FAKE_VALVE_STUCK_CLOSED) {
            p_valve_open[v] = false;
        } else if (p_valve_mode[v] == FAKE_VALVE_STUCK_OPEN) {
            p_valve_open[v] = true;
        } else if (s_do[coil[v]] != p_valve_open[v]) {
            if (++p_valve_ms[v] >= p_valve_stroke_ms) {
                p_valve_open[v] = s_do[coil[v]];
                p_valve_ms[v] = 0;
            }
        } else {
            p_valve_ms[v] = 0;
        }
    }
    if (p_valve_open[0] && p_valve_open[1] && p_sv_kpa > p_tv_kpa) {
        p_tv_kpa += 0.2f;  /* 200 kPa/s fill */
        p_sv_kpa -= 0.02f; /* the supply tank is ten times larger */
    }

    if (!p_plane_jam) {
        bool ext = s_do[HAL_DO_PLANE_EXTEND], ret = s_do[HAL_DO_PLANE_RETRACT];
        if (ext && !ret) {
            p_plane_mm += 0.01f; /* 10 mm/s */
        } else if (ret && !ext) {
            p_plane_mm -= 0.01f;
        }
        if (p_plane_mm > FAKE_PLANT_TRAVEL_MM) {
            p_plane_mm = FAKE_PLANT_TRAVEL_MM;
        }
        if (p_plane_mm < 0.0f) {
            p_plane_mm = 0.0f;
        }
    }

    bool released = p_latch_steps >= FAKE_PLANT_LATCH_RELEASE_STEPS;
    p_contact_ms = p_probe ? p_contact_ms + 1u : 0u;
    /* The spring-damper pre-load pushes the probe out once the latch lets go. */
    if (p_probe && released) {
        if (++p_released_ms >= 300u) {
            p_probe = false;
            p_contact_ms = 0;
        }
    } else {
        p_released_ms = 0;
    }
    bool engaged = p_probe && !released && p_contact_ms >= 100u; /* latches pop */
    bool extended = p_plane_mm >= FAKE_PLANT_TRAVEL_MM - 0.05f;

    s_di[HAL_DI_CONTACT] = p_probe;
    s_di[HAL_DI_LATCH_ENGAGED] = engaged;
    s_di[HAL_DI_LATCH_NOT_ENGAGED] = !engaged;
    s_di[HAL_DI_LATCH_HOME] = p_latch_steps <= 0;
    s_di[HAL_DI_PLANE_EXTENDED] = extended;
    s_di[HAL_DI_PLANE_RETRACTED] = p_plane_mm <= 0.05f;
    s_di[HAL_DI_CONNECTOR_MATED] = extended && engaged;
    s_di[HAL_DI_SV_VALVE_OPEN] = p_valve_open[0];
    s_di[HAL_DI_TV_VALVE_OPEN] = p_valve_open[1];

    s_adc[HAL_ADC_SV_TANK] = kpa_to_counts(p_sv_kpa);
    s_adc[HAL_ADC_TV_TANK] = kpa_to_counts(p_tv_kpa);
    /* The line equalises through the valve orifice at up to 1000 kPa/s. */
    float line_goal = (p_valve_open[0] || p_valve_open[1]) ? p_tv_kpa : 100.0f;
    float d = line_goal - p_line_kpa;
    p_line_kpa += (d > 1.0f) ? 1.0f : ((d < -1.0f) ? -1.0f : d);
    s_adc[HAL_ADC_LINE] = kpa_to_counts(p_line_kpa);
    s_adc[HAL_ADC_PLANE_POS] = (uint16_t)(p_plane_mm / 0.01221f);
    float fc = p_force_n / 0.05f;
    s_adc[HAL_ADC_CONTACT_FORCE] = (uint16_t)(fc > 4095.0f ? 4095.0f : (fc < 0.0f ? 0.0f : fc));

    for (unsigned i = 0; i < HAL_DI_COUNT; i++) {
        if (p_di_ovr[i] >= 0) {
            s_di[i] = p_di_ovr[i] != 0;
        }
    }
    for (unsigned i = 0; i < HAL_ADC_COUNT; i++) {
        if (p_adc_ovr[i] >= 0) {
            s_adc[i] = (uint16_t)p_adc_ovr[i];
        }
    }
}

void fake_hal_advance_ms(uint32_t ms)
{
    for (uint32_t i = 0; i < ms; i++) {
        s_now_ms++;
        if (p_on) {
            plant_step_1ms();
        }
        uint32_t isr_calls = 0;
        s_step_acc_us += 1000u;
        while (s_step_running && s_step_fn != NULL && s_step_period_us > 0u &&
               s_step_acc_us >= s_step_period_us && isr_calls < 1000u) {
            s_step_acc_us -= s_step_period_us;
            isr_calls++;
            s_step_fn();
        }
        if (!s_step_running) {
            s_step_acc_us = 0;
        }
        if (isr_calls > s_max_isr_per_ms) {
            s_max_isr_per_ms = isr_calls;
        }
        if (s_tick_fn != NULL && s_tick_enabled) {
            s_tick_fn();
        }
        if (s_main_fn != NULL) {
            s_main_fn();
        }
    }
}

/* --- bench ------------------------------------------------------------- */
#include "oibar/app.h"
#include "oibar/app_faults.h"

void bench_start(void)
{
    fake_hal_reset();
    fake_plant_enable(true);
    fake_hal_advance_ms(1); /* plant settles its outputs */
    oibar_app_init();
    fake_hal_set_main_loop(oibar_app_run_once);
    oibar_app_link_state(true);
    (void)bench_wait_state(oibar_v1_STATE_IDLE, 1000u);
}

bool bench_wait_state(oibar_v1_State st, uint32_t max_ms)
{
    for (uint32_t i = 0; i < max_ms; i++) {
        if (oibar_app_state() == st) {
            return true;
        }
        fake_hal_advance_ms(1);
    }
    return oibar_app_state() == st;
}

void bench_nav_good(void)
{
    oibar_v1_NavUpdate nav;
    memset(&nav, 0, sizeof nav);
    nav.closing_speed_mps = 0.010f;
    nav.has_q_cam_target = true;
    nav.q_cam_target.w = 1.0f;
    nav.range_m = 0.05f;
    nav.confidence = 0.99f;
    nav.valid = true;
    nav.phase = oibar_v1_NAV_PHASE_SOFT_DOCK;
    oibar_app_nav_update(&nav);
}

bool bench_any_valve_driven(void)
{
    return s_do[HAL_DO_SV_VALVE] || s_do[HAL_DO_TV_VALVE];
}

static bool to_hard_docked(void)
{
    if (oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0.0f) != oibar_v1_NACK_NONE) {
        return false;
    }
    bench_nav_good();
    fake_plant_set_probe(true);
    if (!bench_wait_state(oibar_v1_STATE_RECEPTION, 50u)) {
        return false;
    }
    fake_hal_advance_ms(150); /* latches pop and debounce */
    bench_nav_good();
    if (oibar_app_command(oibar_v1_CMD_DOCK, 0.0f) != oibar_v1_NACK_NONE) {
        return false;
    }
    if (oibar_app_command(oibar_v1_CMD_HARD_DOCK, 0.0f) != oibar_v1_NACK_NONE) {
        return false;
    }
    return bench_wait_state(oibar_v1_STATE_HARD_DOCKED, 8000u);
}

bool bench_goto(oibar_v1_State st)
{
    bench_start();
    switch (st) {
    case oibar_v1_STATE_BOOT:
        fake_hal_reset();
        fake_plant_enable(true);
        fake_hal_advance_ms(1);
        oibar_app_init();
        fake_hal_set_main_loop(oibar_app_run_once);
        oibar_app_link_state(true);
        fake_hal_advance_ms(5);
        break;
    case oibar_v1_STATE_IDLE:
        break;
    case oibar_v1_STATE_APPROACH_READY:
        (void)oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0.0f);
        break;
    case oibar_v1_STATE_RECEPTION:
        (void)oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0.0f);
        bench_nav_good();
        fake_plant_set_probe(true);
        (void)bench_wait_state(oibar_v1_STATE_RECEPTION, 50u);
        break;
    case oibar_v1_STATE_SOFT_DOCKED:
        (void)oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0.0f);
        bench_nav_good();
        fake_plant_set_probe(true);
        (void)bench_wait_state(oibar_v1_STATE_RECEPTION, 50u);
        fake_hal_advance_ms(150);
        (void)oibar_app_command(oibar_v1_CMD_DOCK, 0.0f);
        break;
    case oibar_v1_STATE_HARD_DOCKING:
        (void)bench_goto(oibar_v1_STATE_SOFT_DOCKED);
        (void)oibar_app_command(oibar_v1_CMD_HARD_DOCK, 0.0f);
        fake_hal_advance_ms(500);
        break;
    case oibar_v1_STATE_HARD_DOCKED:
        (void)to_hard_docked();
        break;
    case oibar_v1_STATE_TRANSFER_ARMED:
        if (to_hard_docked()) {
            (void)oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0.0f);
        }
        break;
    case oibar_v1_STATE_TRANSFERRING:
        if (to_hard_docked()) {
            (void)oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0.0f);
            (void)oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500.0f);
            fake_hal_advance_ms(200);
        }
        break;
    case oibar_v1_STATE_UNMATING:
        if (to_hard_docked()) {
            (void)oibar_app_command(oibar_v1_CMD_SEPARATE, 0.0f);
            fake_hal_advance_ms(500);
        }
        break;
    case oibar_v1_STATE_LATCH_RELEASE:
    case oibar_v1_STATE_SEPARATING:
    case oibar_v1_STATE_LATCH_RESET:
        if (to_hard_docked()) {
            (void)oibar_app_command(oibar_v1_CMD_SEPARATE, 0.0f);
            (void)bench_wait_state(st, 10000u);
        }
        break;
    case oibar_v1_STATE_ABORTING:
        if (to_hard_docked()) {
            (void)oibar_app_command(oibar_v1_CMD_ABORT, 0.0f);
            fake_hal_advance_ms(500);
        }
        break;
    case oibar_v1_STATE_FAULT:
        oibar_fault_raise(oibar_v1_FAULT_PLANE_TIMEOUT);
        fake_hal_advance_ms(1);
        break;
    default:
        break;
    }
    return oibar_app_state() == st;
}
