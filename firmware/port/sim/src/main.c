/*
 * oibar_sim_mcu: the OIBAR firmware (application + link) on simulated time,
 * in lockstep with the HIL rig's plant (docs/hil.md).
 *
 *   oibar_sim_mcu --lockstep-fd N [--watchdog-ms N] [--build-id S] [--flash-image PATH]
 *   oibar_sim_mcu --list-params
 *
 * --list-params prints the firmware's parameter table (app_params) as
 * tab-separated lines, id name unit default min max integer, and exits: the
 * rig reads parameter names and ids from the firmware, not from a copy.
 *
 * --flash-image PATH (or the environment's OIBAR_SIM_FLASH_IMAGE) keeps the
 * parameter flash (the board's sectors 1 and 2, CMD_SAVE_PARAMS) in that file
 * across processes; without it the flash starts blank (the defaults) and
 * lives only as long as this process (flash_sim.c).
 *
 * Prints "PTY <slave path>" on stdout, then serves lockstep exchanges on the
 * inherited SOCK_SEQPACKET socket N until the plant sends QUIT or closes it.
 * Nothing here reads the wall clock: simulated time advances only when the
 * plant says so, so a mission runs as fast as the two processes can go.
 */
#include <errno.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "oibar/app_link.h"
#include "oibar/app_params.h"
#include "oibar/hal.h"
#include "oibar/hal_sim.h"
#include "oibar/link.h"
#include "oibar/sim_lockstep.h"
#include "oibar/sim_pty.h"

#define SIM_FIRMWARE_VERSION "sim-0.1.0"
/* 115200 baud, 8N1: 11.5 bytes per ms; the UART clocks host bytes in at
 * this pace, whatever burst the host wrote. */
#define UART_RX_BYTES_PER_MS 12u
#define RX_STAGE_BYTES 16384u
#define RX_WAIT_MS 2000

typedef struct {
    int fd;
    uint32_t watchdog_ms;
    const char *build_id;
    const char *flash_image;
} options_t;

static oibar_link_t g_link;
static uint8_t g_stage[RX_STAGE_BYTES]; /* host bytes on the wire, not yet clocked in */
static size_t g_stage_head;
static size_t g_stage_len;
static bool g_hung;          /* main loop stopped (watchdog scenario) */
static uint32_t g_resets;
static uint32_t g_valve_violation_ms;
static uint32_t g_sim_time_ms;
static uint32_t g_expected_frame = 1u;

static void uart_rx_isr(uint8_t byte) { oibar_link_rx_isr(&g_link, byte); }

/* Whole frames or nothing (oibar_link_port_t contract). */
static bool link_send(void *ctx, const uint8_t *bytes, size_t len)
{
    (void)ctx;
    return hal_uart_write(bytes, len) == len;
}

static hal_reset_cause_t boot_cause;

static void mcu_boot(hal_reset_cause_t cause, const options_t *opt)
{
    hal_sim_reset(cause);
    hal_init();
    oibar_app_init();
    oibar_link_config_t cfg;
    oibar_link_config_defaults(&cfg);
    cfg.firmware_version = SIM_FIRMWARE_VERSION;
    cfg.build_id = opt->build_id;
    cfg.reset_cause = oibar_app_reset_cause();
    static const oibar_link_port_t port = { link_send, NULL };
    oibar_link_init(&g_link, &cfg, &port, oibar_app_link_callbacks());
    hal_uart_rx_attach(uart_rx_isr);
    g_hung = false;
    g_stage_len = 0u; /* bytes in the UART during a reset are lost */
    g_stage_head = 0u;
    boot_cause = cause;
}

static void stage_host_bytes(uint32_t n)
{
    uint8_t buf[512];
    while (n > 0u) {
        size_t want = sizeof buf;
        if (n < want) {
            want = n;
        }
        const size_t got = sim_pty_read_exact(buf, want, RX_WAIT_MS);
        for (size_t i = 0; i < got && g_stage_len < RX_STAGE_BYTES; i++) {
            g_stage[(g_stage_head + g_stage_len) % RX_STAGE_BYTES] = buf[i];
            g_stage_len++;
        }
        if (got < want) {
            (void)fprintf(stderr, "oibar_sim_mcu: %zu host bytes announced but not received\n",
                          want - got);
            return;
        }
        n -= (uint32_t)want;
    }
}

static void clock_uart_rx(void)
{
    for (unsigned i = 0; i < UART_RX_BYTES_PER_MS && g_stage_len > 0u; i++) {
        const uint8_t b = g_stage[g_stage_head];
        g_stage_head = (g_stage_head + 1u) % RX_STAGE_BYTES;
        g_stage_len--;
        hal_sim_uart_rx_byte(b);
    }
}

static bool valve_coil_on(uint32_t do_bits)
{
    const uint32_t coils = (1u << (unsigned)HAL_DO_SV_VALVE) | (1u << (unsigned)HAL_DO_TV_VALVE);
    return (do_bits & coils) != 0u;
}

/* One millisecond of the board: interrupts, the UART, one main-loop pass. */
static uint32_t run_1ms(const options_t *opt)
{
    hal_sim_advance_1ms();
    clock_uart_rx();
    if (!g_hung) {
        oibar_app_link_run_once(&g_link);
    }
    g_sim_time_ms++;
    const uint32_t do_bits = hal_sim_do_bits();
    if (valve_coil_on(do_bits) && oibar_app_state() != oibar_v1_STATE_TRANSFERRING) {
        g_valve_violation_ms++;
    }
    if (hal_sim_watchdog_expired()) {
        g_resets++;
        mcu_boot(HAL_RESET_WATCHDOG, opt);
    }
    return do_bits;
}

static void reply(int fd, sim_ls_mcu_t *r)
{
    uint8_t buf[SIM_LS_MCU_BYTES];
    r->magic = SIM_LS_MCU_MAGIC;
    r->version = SIM_LS_VERSION;
    r->expected_frame = g_expected_frame;
    r->sim_time_ms = g_sim_time_ms;
    r->uptime_ms = hal_time_ms();
    r->do_bits = hal_sim_do_bits();
    r->steps_total = hal_sim_steps_total();
    r->uart_tx_bytes = sim_pty_take_tx_count();
    r->uart_rx_pending = (uint32_t)g_stage_len;
    r->resets = g_resets;
    r->reset_cause = (uint32_t)boot_cause;
    r->watchdog_kicks = hal_sim_watchdog_kicks();
    r->flags = (hal_sim_step_timer_running() ? SIM_LS_MCU_STEP_TIMER_RUNNING : 0u) |
               (g_hung ? SIM_LS_MCU_MAIN_HUNG : 0u);
    r->app_state = (uint32_t)oibar_app_state();
    r->valve_violation_ms = g_valve_violation_ms;
    r->fault_flags = oibar_fault_flags();
    const size_t n = sim_ls_encode_mcu(r, buf, sizeof buf);
    if (send(fd, buf, n, 0) != (ssize_t)n) {
        (void)fprintf(stderr, "oibar_sim_mcu: lockstep send failed: %s\n", strerror(errno));
        exit(1);
    }
}

/* Serve one exchange; false when the plant asked to quit or went away. */
static bool exchange(const options_t *opt)
{
    uint8_t buf[256];
    const ssize_t n = recv(opt->fd, buf, sizeof buf, 0);
    if (n <= 0) {
        return false; /* the plant closed its end */
    }
    sim_ls_plant_t in;
    sim_ls_mcu_t out;
    memset(&out, 0, sizeof out);
    if (!sim_ls_decode_plant(buf, (size_t)n, &in)) {
        out.status = SIM_LS_ERR_SIZE;
        reply(opt->fd, &out);
        return true;
    }
    out.frame = in.frame;
    if (in.magic != SIM_LS_PLANT_MAGIC || in.version != SIM_LS_VERSION) {
        out.status = SIM_LS_ERR_MAGIC;
    } else if (in.frame != g_expected_frame) {
        out.status = SIM_LS_ERR_FRAME; /* lost or repeated exchange: nothing runs */
    } else if (in.advance_ms == 0u || in.advance_ms > SIM_LS_MAX_ADVANCE_MS) {
        out.status = SIM_LS_ERR_ADVANCE;
    }
    if (out.status != SIM_LS_OK) {
        reply(opt->fd, &out);
        return true;
    }
    g_expected_frame++;
    if ((in.flags & SIM_LS_FLAG_RESET_PIN) != 0u) {
        /* The MCU restarts (outputs off, RAM lost; the parameter flash kept, as on the
         * board): issue 59 item 5, "reset mid-transfer". */
        g_resets++;
        mcu_boot(HAL_RESET_PIN, opt);
    }
    hal_sim_set_inputs(in.di_bits, in.adc_counts, SIM_LS_ADC_SLOTS, in.adc_fail_bits);
    if ((in.flags & SIM_LS_FLAG_HANG_MAIN_LOOP) != 0u) {
        g_hung = true;
    }
    stage_host_bytes(in.uart_rx_bytes);
    uint32_t any = 0u;
    for (uint32_t i = 0; i < in.advance_ms; i++) {
        any |= run_1ms(opt);
    }
    out.do_any_bits = any;
    hal_sim_take_steps(&out.steps_fwd, &out.steps_rev);
    reply(opt->fd, &out);
    return (in.flags & SIM_LS_FLAG_QUIT) == 0u;
}

static bool parse_u32(const char *s, uint32_t *out)
{
    if (s == NULL || *s == '\0' || s[0] == '-') {
        return false;
    }
    char *end = NULL;
    errno = 0;
    const unsigned long v = strtoul(s, &end, 10);
    if (errno != 0 || *end != '\0' || v > UINT32_MAX) {
        return false;
    }
    *out = (uint32_t)v;
    return true;
}

static bool parse_args(int argc, char **argv, options_t *opt)
{
    uint32_t fd = 0u;
    bool have_fd = false;
    for (int i = 1; i + 1 < argc; i += 2) {
        const char *a = argv[i];
        const char *v = argv[i + 1];
        if (strcmp(a, "--lockstep-fd") == 0 && parse_u32(v, &fd)) {
            have_fd = true;
        } else if (strcmp(a, "--watchdog-ms") == 0 && parse_u32(v, &opt->watchdog_ms)) {
            /* parsed */
        } else if (strcmp(a, "--build-id") == 0) {
            opt->build_id = v;
        } else if (strcmp(a, "--flash-image") == 0 && *v != '\0') {
            opt->flash_image = v;
        } else {
            return false;
        }
    }
    opt->fd = (int)fd;
    return have_fd && (argc % 2) == 1 && opt->watchdog_ms > 0u;
}

static void list_params(void)
{
    for (unsigned i = 0u; i < OIBAR_PARAM_COUNT; i++) {
        const oibar_param_def_t *d = oibar_param_def_at(i);
        (void)printf("%u\t%s\t%s\t%.9g\t%.9g\t%.9g\t%d\n", (unsigned)d->id, d->name, d->unit,
                     (double)d->default_value, (double)d->min, (double)d->max, d->integer ? 1 : 0);
    }
}

int main(int argc, char **argv)
{
    options_t opt = { -1, HAL_WATCHDOG_TIMEOUT_MS, "sim", NULL }; /* the board's watchdog */
    if (argc == 2 && strcmp(argv[1], "--list-params") == 0) {
        list_params();
        return 0;
    }
    if (!parse_args(argc, argv, &opt)) {
        (void)fprintf(stderr, "usage: %s --lockstep-fd N [--watchdog-ms N] [--build-id S] [--flash-image PATH] | --list-params\n", argv[0]);
        return 2;
    }
    char path[128];
    if (!sim_pty_open(path, sizeof path)) {
        perror("oibar_sim_mcu: pty");
        return 1;
    }
    hal_sim_set_uart_tx(sim_pty_write);
    hal_sim_set_watchdog_timeout_ms(opt.watchdog_ms);
    if (opt.flash_image == NULL) {
        const char *env = getenv("OIBAR_SIM_FLASH_IMAGE");
        opt.flash_image = (env != NULL && *env != '\0') ? env : NULL;
    }
    if (opt.flash_image != NULL && !hal_sim_flash_attach(opt.flash_image)) {
        return 1;
    }
    mcu_boot(HAL_RESET_POWER_ON, &opt);
    (void)printf("PTY %s\n", path);
    (void)fflush(stdout);
    while (exchange(&opt)) {
    }
    sim_pty_close();
    return 0;
}
