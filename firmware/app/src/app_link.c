/* Application <-> link glue (see oibar/app_link.h). */
#include "oibar/app_link.h"

#include <stddef.h>

#include "oibar/app.h"
#include "oibar/app_events.h"
#include "oibar/hal.h"

static uint32_t s_unsent;

static void on_command(void *ctx, const oibar_v1_Command *cmd, oibar_v1_Ack *out)
{
    (void)ctx;
    out->reason = oibar_app_command(cmd->opcode, cmd->target_pressure_kpa);
    out->state = oibar_app_state();
}

static void on_nav_update(void *ctx, const oibar_v1_NavUpdate *nav)
{
    (void)ctx;
    oibar_app_nav_update(nav);
}

static void on_param_get(void *ctx, uint32_t id, oibar_v1_ParamValue *out)
{
    (void)ctx;
    oibar_app_param_get(id, out);
}

static void on_param_set(void *ctx, uint32_t id, float value, oibar_v1_ParamValue *out)
{
    (void)ctx;
    oibar_app_param_set(id, value, out);
}

static void fill_telemetry(void *ctx, oibar_v1_Telemetry *out)
{
    (void)ctx;
    oibar_app_fill_telemetry(out);
    out->events_lost = oibar_evlog_dropped();
    hal_uart_errors_t uart;
    hal_uart_errors(&uart);
    out->uart_rx_errors = uart.rx_errors;
    out->uart_rx_overruns = uart.rx_overruns;
}

static void on_link_state(void *ctx, bool up)
{
    (void)ctx;
    oibar_app_link_state(up);
}

static oibar_v1_State get_state(void *ctx)
{
    (void)ctx;
    return oibar_app_state();
}

static const oibar_link_app_t k_callbacks = {
    .ctx = NULL,
    .on_command = on_command,
    .on_nav_update = on_nav_update,
    .on_param_get = on_param_get,
    .on_param_set = on_param_set,
    .fill_telemetry = fill_telemetry,
    .on_link_state = on_link_state,
    .get_state = get_state,
};

const oibar_link_app_t *oibar_app_link_callbacks(void) { return &k_callbacks; }

uint32_t oibar_app_link_forward_events(oibar_link_t *link)
{
    oibar_v1_Event ev;
    /* Oldest first, bounded by the log's length. An event leaves the log only
     * once the port took it: when the UART queue is full it stays, in order,
     * for the next pass. Only a full log loses events (oldest first, counted
     * in Telemetry.events_lost). */
    for (unsigned n = oibar_evlog_count(); n > 0u && oibar_evlog_peek(&ev); --n) {
        if (!oibar_link_send_event(link, &ev)) {
            s_unsent++;
            break;
        }
        (void)oibar_evlog_pop(&ev);
    }
    return oibar_evlog_count();
}

void oibar_app_link_run_once(oibar_link_t *link)
{
    oibar_link_poll(link, hal_time_ms());
    oibar_app_run_once();
    (void)oibar_app_link_forward_events(link);
}

uint32_t oibar_app_link_events_unsent(void) { return s_unsent; }
