/*
 * oibar_link_peer: the firmware link (oibar_link) running on Linux over a
 * pseudo-terminal, for interop tests and the demo.
 *
 * It prints one line "PTY <slave path>" on stdout, then serves the link on
 * the pty master with a 1 ms poll loop until SIGTERM or SIGINT. The
 * application behind the link is deliberately minimal and has no mechanism:
 * state is always STATE_IDLE, CMD_NOOP is accepted, every other known opcode
 * is refused with NACK_NOT_SUPPORTED, and the parameter table holds the
 * link's own timing, changed live.
 *
 * Options:
 *   --protocol-version N   claim protocol version N in the handshake
 *   --build-id S           HandshakeReply.build_id
 *   --silent-after-ms N    transmit nothing once N ms have passed
 *   --log                  one line per link event on stderr
 */
#define _XOPEN_SOURCE 700

#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "oibar/link.h"
#include "oibar_pty.h"

#define PEER_FIRMWARE_VERSION "peer-0.1.0"
#define PEER_TXQ_BYTES 8192u /* whole frames waiting for the pty to take them */
#define PEER_READ_CHUNK 256u /* < ring capacity: poll the link after each chunk */

_Static_assert(PEER_READ_CHUNK <= OIBAR_RINGBUF_CAPACITY, "a read chunk must fit the RX ring");

static volatile sig_atomic_t g_stop;

typedef struct {
    uint32_t protocol_version;
    const char *build_id;
    bool silent;             /* --silent-after-ms given */
    uint32_t silent_after_ms;
    bool log;
} peer_options_t;

typedef struct {
    int fd;                  /* pty master */
    bool slave_open;         /* someone holds the slave side */
    uint32_t now_ms;         /* since start */
    const peer_options_t *opt;
    oibar_link_t *link;
    size_t txq_len;
    uint8_t txq[PEER_TXQ_BYTES];
} peer_t;

/* ------------------------------------------------------------------------- */
/* Helpers                                                                   */

static uint32_t monotonic_ms(void)
{
    struct timespec ts;
    (void)clock_gettime(CLOCK_MONOTONIC, &ts);
    const uint64_t ms = (uint64_t)ts.tv_sec * 1000u + (uint64_t)ts.tv_nsec / 1000000u;
    return (uint32_t)(ms & 0xFFFFFFFFu);
}

static void on_signal(int sig)
{
    (void)sig;
    g_stop = 1;
}

static void peer_log(const peer_t *p, const char *fmt, ...) __attribute__((format(printf, 2, 3)));

static void peer_log(const peer_t *p, const char *fmt, ...)
{
    if (!p->opt->log) {
        return;
    }
    va_list ap;
    va_start(ap, fmt);
    (void)fprintf(stderr, "[peer %10lu ms] ", (unsigned long)p->now_ms);
    (void)vfprintf(stderr, fmt, ap);
    (void)fputc('\n', stderr);
    va_end(ap);
}

/* ------------------------------------------------------------------------- */
/* The application: no mechanism, only the link's own parameters            */

typedef struct {
    uint32_t id;
    const char *name;
    const char *unit;
    float min;
    float max;
    float default_value;
} peer_param_t;

enum { PARAM_HEARTBEAT_PERIOD = 1, PARAM_TELEMETRY_PERIOD = 2, PARAM_LINK_TIMEOUT = 3 };

static const peer_param_t k_params[] = {
    {PARAM_HEARTBEAT_PERIOD, "heartbeat_period_ms", "ms", 50.0f, 2000.0f, (float)OIBAR_LINK_DEFAULT_HEARTBEAT_PERIOD_MS},
    {PARAM_TELEMETRY_PERIOD, "telemetry_period_ms", "ms", 20.0f, 2000.0f, (float)OIBAR_LINK_DEFAULT_TELEMETRY_PERIOD_MS},
    {PARAM_LINK_TIMEOUT, "link_timeout_ms", "ms", 200.0f, 10000.0f, (float)OIBAR_LINK_DEFAULT_LINK_TIMEOUT_MS},
};

static const peer_param_t *param_find(uint32_t id)
{
    for (size_t i = 0u; i < sizeof(k_params) / sizeof(k_params[0]); ++i) {
        if (k_params[i].id == id) {
            return &k_params[i];
        }
    }
    return NULL;
}

static uint32_t param_current(const oibar_link_t *link, uint32_t id)
{
    const oibar_link_config_t *cfg = oibar_link_get_config(link);
    switch (id) {
    case PARAM_HEARTBEAT_PERIOD: return cfg->heartbeat_period_ms;
    case PARAM_TELEMETRY_PERIOD: return cfg->telemetry_period_ms;
    default:                     return cfg->link_timeout_ms;
    }
}

static void param_apply(oibar_link_t *link, uint32_t id, uint32_t value)
{
    switch (id) {
    case PARAM_HEARTBEAT_PERIOD: oibar_link_set_heartbeat_period_ms(link, value); break;
    case PARAM_TELEMETRY_PERIOD: oibar_link_set_telemetry_period_ms(link, value); break;
    default:                     oibar_link_set_link_timeout_ms(link, value); break;
    }
}

static void param_describe(const peer_param_t *prm, const oibar_link_t *link, oibar_v1_ParamValue *out)
{
    out->value = (float)param_current(link, prm->id);
    out->min = prm->min;
    out->max = prm->max;
    out->default_value = prm->default_value;
    (void)snprintf(out->name, sizeof(out->name), "%s", prm->name);
    (void)snprintf(out->unit, sizeof(out->unit), "%s", prm->unit);
}

static void app_param_get(void *ctx, uint32_t param_id, oibar_v1_ParamValue *out)
{
    const peer_t *p = ctx;
    const peer_param_t *prm = param_find(param_id);
    if (prm == NULL) {
        out->reason = oibar_v1_NACK_UNKNOWN_PARAM;
    } else {
        param_describe(prm, p->link, out);
        out->reason = oibar_v1_NACK_NONE;
    }
    peer_log(p, "param get id=%lu -> reason %d", (unsigned long)param_id, (int)out->reason);
}

static void app_param_set(void *ctx, uint32_t param_id, float value, oibar_v1_ParamValue *out)
{
    const peer_t *p = ctx;
    const peer_param_t *prm = param_find(param_id);
    if (prm == NULL) {
        out->reason = oibar_v1_NACK_UNKNOWN_PARAM;
    } else if (!(value >= prm->min && value <= prm->max)) { /* also refuses NaN */
        out->reason = oibar_v1_NACK_PARAM_OUT_OF_BOUNDS;
        param_describe(prm, p->link, out);
    } else {
        param_apply(p->link, param_id, (uint32_t)(value + 0.5f) /* in bounds, so positive */);
        param_describe(prm, p->link, out);
        out->reason = oibar_v1_NACK_NONE;
    }
    peer_log(p, "param set id=%lu value=%g -> reason %d", (unsigned long)param_id, (double)value,
             (int)out->reason);
}

static void app_command(void *ctx, const oibar_v1_Command *cmd, oibar_v1_Ack *out)
{
    const peer_t *p = ctx;
    out->state = oibar_v1_STATE_IDLE;
    if (cmd->opcode == oibar_v1_CMD_NOOP) {
        out->reason = oibar_v1_NACK_NONE;
    } else if (cmd->opcode > oibar_v1_CMD_UNSPECIFIED && cmd->opcode <= _oibar_v1_CommandOpcode_MAX) {
        out->reason = oibar_v1_NACK_NOT_SUPPORTED; /* no mechanism here */
    } else {
        out->reason = oibar_v1_NACK_UNKNOWN_OPCODE;
    }
    peer_log(p, "command opcode=%d -> reason %d", (int)cmd->opcode, (int)out->reason);
}

static void app_nav_update(void *ctx, const oibar_v1_NavUpdate *nav)
{
    const peer_t *p = ctx;
    peer_log(p, "nav update frame=%lu range=%.3f m", (unsigned long)nav->frame_id, (double)nav->range_m);
}

static void app_telemetry(void *ctx, oibar_v1_Telemetry *out)
{
    (void)ctx;
    out->state = oibar_v1_STATE_IDLE;
}

static void app_link_state(void *ctx, bool up)
{
    const peer_t *p = ctx;
    oibar_v1_LinkCounters c;
    oibar_link_get_counters(p->link, &c);
    peer_log(p, "link %s (link_losses=%lu)", up ? "up" : "down", (unsigned long)c.link_losses);
}

static oibar_v1_State app_state(void *ctx)
{
    (void)ctx;
    return oibar_v1_STATE_IDLE;
}

/* ------------------------------------------------------------------------- */
/* The port: a pty master                                                    */

static bool transmitting(const peer_t *p)
{
    return !(p->opt->silent && p->now_ms >= p->opt->silent_after_ms);
}

static bool port_send(void *ctx, const uint8_t *bytes, size_t len)
{
    peer_t *p = ctx;
    if (!transmitting(p) || !p->slave_open) {
        return true; /* like a UART with nobody listening: the bytes are gone */
    }
    if (len > sizeof(p->txq) - p->txq_len) {
        return false; /* whole frames or nothing */
    }
    memcpy(&p->txq[p->txq_len], bytes, len);
    p->txq_len += len;
    return true;
}

static void port_flush(peer_t *p)
{
    if (p->txq_len == 0u) {
        return;
    }
    const ssize_t n = write(p->fd, p->txq, p->txq_len);
    if (n > 0) {
        const size_t done = (size_t)n;
        memmove(p->txq, &p->txq[done], p->txq_len - done);
        p->txq_len -= done;
    } else if (n < 0 && errno != EAGAIN && errno != EINTR) {
        p->txq_len = 0u; /* EIO: the slave went away */
    } else {
        /* pty full: try again next loop */
    }
}

static void set_slave_open(peer_t *p, bool open)
{
    if (open != p->slave_open) {
        p->slave_open = open;
        p->txq_len = 0u; /* stale frames are for no one */
        peer_log(p, "pty slave %s", open ? "opened" : "closed");
    }
}

/* Read what is there, feeding the link as the UART interrupt would. */
static void port_receive(peer_t *p)
{
    uint8_t buf[PEER_READ_CHUNK];
    for (;;) {
        const ssize_t n = read(p->fd, buf, sizeof(buf));
        if (n <= 0) {
            if (n < 0 && errno == EIO) {
                set_slave_open(p, false); /* the host closed the slave; it may reopen */
            }
            return;
        }
        for (ssize_t i = 0; i < n; ++i) {
            oibar_link_rx_isr(p->link, buf[i]);
        }
        oibar_link_poll(p->link, p->now_ms); /* drain before the ring can fill */
    }
}

static int open_pty(void)
{
    char slave_path[64];
    const int fd = oibar_pty_open_raw(slave_path, sizeof slave_path);
    if (fd < 0) {
        perror("pty");
        return -1;
    }
    /* Open and close the slave once: until then Linux reports no hang-up on
     * the master, and frames would pile up for a host that is not there. */
    const int slave = open(slave_path, O_RDWR | O_NOCTTY);
    if (slave >= 0) {
        (void)close(slave);
    }
    return fd;
}

/* ------------------------------------------------------------------------- */
/* Main                                                                      */

static bool parse_u32(const char *s, uint32_t *out)
{
    if (s == NULL || *s == '\0') {
        return false;
    }
    char *end = NULL;
    errno = 0;
    const unsigned long long v = strtoull(s, &end, 10);
    if (errno != 0 || *end != '\0' || v > UINT32_MAX || s[0] == '-') {
        return false;
    }
    *out = (uint32_t)v;
    return true;
}

static int usage(const char *argv0)
{
    (void)fprintf(stderr,
                  "usage: %s [--protocol-version N] [--build-id S] [--silent-after-ms N] [--log]\n",
                  argv0);
    return 2;
}

static bool parse_args(int argc, char **argv, peer_options_t *opt)
{
    for (int i = 1; i < argc; ++i) {
        const char *a = argv[i];
        const char *v = (i + 1 < argc) ? argv[i + 1] : NULL;
        if (strcmp(a, "--log") == 0) {
            opt->log = true;
            continue;
        }
        if (strcmp(a, "--protocol-version") == 0 && parse_u32(v, &opt->protocol_version)) {
            ++i;
        } else if (strcmp(a, "--silent-after-ms") == 0 && parse_u32(v, &opt->silent_after_ms)) {
            opt->silent = true;
            ++i;
        } else if (strcmp(a, "--build-id") == 0 && v != NULL) {
            opt->build_id = v;
            ++i;
        } else {
            (void)fprintf(stderr, "bad argument: %s\n", a);
            return false;
        }
    }
    return true;
}

static peer_t g_peer;
static oibar_link_t g_link;

int main(int argc, char **argv)
{
    peer_options_t opt = {(uint32_t)oibar_v1_PROTOCOL_VERSION, "oibar-link-peer", false, 0u, false};
    if (!parse_args(argc, argv, &opt)) {
        return usage(argv[0]);
    }

    struct sigaction sa;
    memset(&sa, 0, sizeof(sa));
    sa.sa_handler = on_signal;
    (void)sigemptyset(&sa.sa_mask);
    (void)sigaction(SIGTERM, &sa, NULL);
    (void)sigaction(SIGINT, &sa, NULL);

    peer_t *p = &g_peer;
    p->opt = &opt;
    p->link = &g_link;
    p->fd = open_pty();
    if (p->fd < 0) {
        return 1;
    }

    oibar_link_config_t cfg;
    oibar_link_config_defaults(&cfg);
    cfg.firmware_version = PEER_FIRMWARE_VERSION;
    cfg.build_id = opt.build_id;
    cfg.reset_cause = oibar_v1_RESET_POWER_ON;
    cfg.protocol_version = opt.protocol_version;
    const oibar_link_port_t port = {port_send, p};
    const oibar_link_app_t app = {p, app_command, app_nav_update, app_param_get, app_param_set,
                                  app_telemetry, app_link_state, app_state};
    oibar_link_init(p->link, &cfg, &port, &app);

    (void)printf("PTY %s\n", ptsname(p->fd));
    (void)fflush(stdout);

    const uint32_t start_ms = monotonic_ms();
    bool was_transmitting = true;
    while (g_stop == 0) {
        struct pollfd pfd = {p->fd, (short)(POLLIN | (p->txq_len > 0u ? POLLOUT : 0)), 0};
        const int rc = poll(&pfd, 1, 1);
        p->now_ms = monotonic_ms() - start_ms;
        if (rc < 0 && errno != EINTR) {
            perror("poll");
            break;
        }
        if (rc > 0 && (pfd.revents & POLLHUP) != 0) {
            set_slave_open(p, false);
            (void)poll(NULL, 0, 1); /* no slave: POLLHUP would return at once, so wait here */
        } else if (rc >= 0) {
            set_slave_open(p, true);
        }
        if (rc > 0 && (pfd.revents & POLLIN) != 0) {
            port_receive(p);
        }
        if (was_transmitting && !transmitting(p)) {
            was_transmitting = false;
            peer_log(p, "silent from now on (--silent-after-ms %lu)", (unsigned long)opt.silent_after_ms);
        }
        oibar_link_poll(p->link, p->now_ms);
        port_flush(p);
    }

    oibar_v1_LinkCounters c;
    oibar_link_get_counters(p->link, &c);
    peer_log(p, "exit: rx_packets=%lu crc=%lu framing=%lu oversize=%lu bad_header=%lu decode=%lu "
                "unknown=%lu dup=%lu ring_ovf=%lu tx=%lu losses=%lu",
             (unsigned long)c.rx_packets, (unsigned long)c.rx_crc_errors, (unsigned long)c.rx_framing_errors,
             (unsigned long)c.rx_oversize, (unsigned long)c.rx_bad_header, (unsigned long)c.rx_decode_errors,
             (unsigned long)c.rx_unknown_type, (unsigned long)c.rx_duplicates,
             (unsigned long)c.rx_ring_overflows, (unsigned long)c.tx_packets, (unsigned long)c.link_losses);
    (void)close(p->fd);
    return 0;
}
