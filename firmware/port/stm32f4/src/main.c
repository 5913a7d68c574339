/*
 * OIBAR firmware for the STM32F405: HAL, application and link wired
 * together (firmware/app/include/oibar/app.h and app_link.h), then the main
 * loop forever. Interrupts only capture facts; everything else runs here.
 */
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "oibar/app.h"
#include "oibar/app_link.h"
#include "oibar/assert.h"
#include "oibar/hal.h"
#include "oibar/link.h"
#include "port.h"

/* Injected by the build (CMake): firmware version and `git describe`. */
#ifndef OIBAR_FW_VERSION
#error "OIBAR_FW_VERSION must be defined by the build"
#endif
#ifndef OIBAR_BUILD_ID
#error "OIBAR_BUILD_ID must be defined by the build"
#endif

/* Also in the image as plain text, so `strings` on a .bin tells what it is. */
__attribute__((used)) const char g_firmware_version[] = OIBAR_FW_VERSION;
__attribute__((used)) const char g_build_id[] = OIBAR_BUILD_ID;

static oibar_link_t s_link;

static bool link_send(void *ctx, const uint8_t *bytes, size_t len)
{
    (void)ctx;
    return hal_uart_write(bytes, len) == len; /* the port queues all or nothing */
}

static void link_rx_isr(uint8_t byte) { oibar_link_rx_isr(&s_link, byte); }

/* A broken contract inside the link layer: safe the outputs and reset; the
 * next boot reports RESET_LOCKUP and the application waits in FAULT. */
_Noreturn void oibar_assert_failed(const char *file, int line)
{
    (void)file;
    port_fatal_reset(PORT_NOTE_ASSERT, (uint32_t)line);
}

int main(void)
{
    hal_init();
    oibar_app_init();

    oibar_link_config_t cfg;
    oibar_link_config_defaults(&cfg);
    cfg.firmware_version = g_firmware_version;
    cfg.build_id = g_build_id;
    cfg.reset_cause = oibar_app_reset_cause();
    static const oibar_link_port_t k_port = { .send = link_send, .ctx = NULL };
    oibar_link_init(&s_link, &cfg, &k_port, oibar_app_link_callbacks());
    hal_uart_rx_attach(link_rx_isr); /* only now: the link must exist first */

    for (;;) {
        oibar_app_link_run_once(&s_link);
        /* Sleep until the next interrupt: the 1 kHz tick bounds the wait, a
         * received byte ends it early. */
        __asm volatile("wfi" ::: "memory");
    }
}
