/**
 * @file link.h
 * The MCU side of the host <-> MCU link (docs/link.md): framing, sequence
 * numbers, handshake, request/response with duplicate suppression,
 * heartbeats, periodic telemetry and link-loss detection.
 *
 * The link owns no hardware and no clock:
 *   - received bytes go in through oibar_link_rx_isr() (UART RX interrupt);
 *   - oibar_link_poll(link, now_ms) runs everything else from the main loop;
 *   - bytes go out through the port's send() callback;
 *   - the application plugs in through oibar_link_app_t callbacks, all of
 *     them called from oibar_link_poll() (never from the ISR).
 *
 * Memory: one oibar_link_t (about 1.6 KB with a 512-byte ring), allocated
 * statically by the caller. Nothing blocks, nothing allocates.
 *
 * Typical use:
 *
 *     static oibar_link_t link;
 *     oibar_link_config_t cfg;
 *     oibar_link_config_defaults(&cfg);
 *     cfg.firmware_version = "1.2.0"; cfg.build_id = BUILD_ID; cfg.reset_cause = cause;
 *     oibar_link_init(&link, &cfg, &port, &app);
 *     // USART IRQ:  oibar_link_rx_isr(&link, byte);
 *     // main loop:  oibar_link_poll(&link, millis());
 */
#ifndef OIBAR_LINK_H
#define OIBAR_LINK_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "oibar.pb.h"
#include "oibar/frame.h"
#include "oibar/ringbuf.h"

#ifdef __cplusplus
extern "C" {
#endif

#define OIBAR_LINK_DEFAULT_HEARTBEAT_PERIOD_MS 200u
#define OIBAR_LINK_DEFAULT_TELEMETRY_PERIOD_MS 100u
#define OIBAR_LINK_DEFAULT_LINK_TIMEOUT_MS 1000u

/** Link configuration; start from oibar_link_config_defaults(). */
typedef struct {
    uint32_t heartbeat_period_ms;    /**< Heartbeat every this long (> 0; default 200) */
    uint32_t telemetry_period_ms;    /**< Telemetry every this long (> 0; default 100) */
    uint32_t link_timeout_ms;        /**< no valid packet this long while connected = link loss (> 0; default 1000) */
    const char *firmware_version;    /**< HandshakeReply.firmware_version; NULL = ""; cut to 16 chars */
    const char *build_id;            /**< HandshakeReply.build_id; NULL = ""; cut to 24 chars */
    oibar_v1_ResetCause reset_cause; /**< HandshakeReply.reset_cause */
    uint32_t protocol_version;       /**< PROTOCOL_VERSION; only test tools pretend another */
} oibar_link_config_t;

/**
 * The port's transmit function: queue `len` bytes (one whole wire frame)
 * without blocking. Return false if they could not be queued (counted in
 * oibar_link_stats_t.tx_failures); queue all or nothing, or the host sees a
 * damaged frame (which it then counts and drops).
 */
typedef bool (*oibar_link_send_fn)(void *ctx, const uint8_t *bytes, size_t len);

typedef struct {
    oibar_link_send_fn send; /**< required */
    void *ctx;               /**< passed to send() */
} oibar_link_port_t;

/**
 * Application callbacks; every one is optional (NULL) and is called from
 * oibar_link_poll() only. `ctx` is passed back unchanged. A callback may call
 * oibar_link_send_event() but must not call oibar_link_poll().
 */
typedef struct {
    void *ctx;

    /**
     * A Command from a connected host (never a retransmission: duplicates
     * are answered from the cache and do not reach the application). On
     * entry out->state holds get_state() and out->reason NACK_NONE. Set
     * out->reason (NACK_NONE = accepted) and out->state (state after
     * handling); the link sets out->accepted = (reason == NACK_NONE).
     * NULL: every command is refused with NACK_NOT_SUPPORTED.
     */
    void (*on_command)(void *ctx, const oibar_v1_Command *cmd, oibar_v1_Ack *out);

    /** A NavUpdate from a connected host (not acknowledged; newest wins). */
    void (*on_nav_update)(void *ctx, const oibar_v1_NavUpdate *nav);

    /**
     * ParamGet / ParamSet from a connected host. On entry `out` is zeroed
     * with out->param_id set; fill value, min, max, default_value, name,
     * unit and reason (NACK_NONE, NACK_UNKNOWN_PARAM,
     * NACK_PARAM_OUT_OF_BOUNDS, NACK_PARAM_LOCKED...). On a refused set,
     * report the unchanged current value. NULL: NACK_UNKNOWN_PARAM.
     */
    void (*on_param_get)(void *ctx, uint32_t param_id, oibar_v1_ParamValue *out);
    void (*on_param_set)(void *ctx, uint32_t param_id, float value, oibar_v1_ParamValue *out);

    /**
     * Fill a Telemetry every telemetry_period_ms. On entry it is zeroed with
     * uptime_ms = now_ms and state = get_state(). Afterwards the link
     * overwrites `link` (its counters) and `host_link_alive`.
     */
    void (*fill_telemetry)(void *ctx, oibar_v1_Telemetry *out);

    /**
     * The link came up (handshake accepted while unconnected, or again on a
     * re-handshake while connected: a new session) or went down (link loss,
     * or a refused handshake while connected). On `up == false` the
     * application safes the mechanism; on every `up` it drops what it kept
     * from an earlier session.
     */
    void (*on_link_state)(void *ctx, bool up);

    /** Current state machine state, for Ack.state and Telemetry.state. NULL: STATE_UNSPECIFIED. */
    oibar_v1_State (*get_state)(void *ctx);
} oibar_link_app_t;

/** Counters that have no field in oibar_v1_LinkCounters. */
typedef struct {
    uint32_t rx_seq_lost; /**< packets missing in the peer's seq numbering */
    uint32_t tx_failures; /**< packets not sent: the encoder or the port refused them */
} oibar_link_stats_t;

/** The link's state. Allocate statically; treat every field as private. */
typedef struct {
    oibar_link_config_t cfg;
    oibar_link_port_t port;
    oibar_link_app_t app;

    oibar_ringbuf_t rx_ring;                /* filled by oibar_link_rx_isr() */
    volatile uint32_t rx_ring_overflows;    /* written by the ISR only */
    oibar_frame_decoder_t decoder;
    oibar_v1_Packet rx_packet;              /* the packet being handled */
    uint8_t tx_frame[OIBAR_FRAME_MAX_WIRE_BYTES];

    /* Duplicate memory: the last request handled (seq, body type, content)
     * and its response, on the wire. */
    bool cache_valid;
    uint32_t cache_seq;
    pb_size_t cache_body;
    uint32_t cache_key[2];
    size_t cache_len;
    uint8_t cache_frame[OIBAR_FRAME_MAX_WIRE_BYTES];

    uint32_t tx_seq;         /* seq of the next packet sent: 1, 2, ... wraps to 1 */
    bool peer_seq_valid;
    uint32_t peer_seq;       /* newest seq seen from the peer */
    /* Replay window (docs/link.md), restarted by each handshake: a request
     * runs only if its seq is newer than req_seq, a NavUpdate only if newer
     * than nav_seq. */
    bool req_seq_valid;
    uint32_t req_seq;        /* newest request (or handshake) seq accepted */
    bool nav_seq_valid;
    uint32_t nav_seq;        /* newest NavUpdate seq accepted */
    bool connected;
    bool started;            /* the first poll has set the timers */
    uint32_t last_rx_ms;     /* last valid packet from the peer */
    uint32_t last_heartbeat_ms;
    uint32_t last_telemetry_ms;

    uint32_t rx_duplicates;
    uint32_t rx_stale;       /* requests refused and NavUpdates dropped by the replay window */
    uint32_t tx_packets;
    uint32_t link_losses;
    oibar_link_stats_t stats;
} oibar_link_t;

/** Fill `cfg` with the defaults of docs/link.md and PROTOCOL_VERSION. */
void oibar_link_config_defaults(oibar_link_config_t *cfg);

/**
 * Initialise `link` unconnected. `cfg`, `port` and `app` are copied (the
 * strings cfg points to must stay valid). `app` may be NULL (no application).
 * Call before the UART receive interrupt is enabled.
 */
void oibar_link_init(oibar_link_t *link, const oibar_link_config_t *cfg,
                     const oibar_link_port_t *port, const oibar_link_app_t *app);

/**
 * UART receive interrupt: queue one byte. Constant time. When the ring is
 * full the byte is lost and rx_ring_overflows counted.
 */
void oibar_link_rx_isr(oibar_link_t *link, uint8_t byte);

/**
 * Main loop, as often as convenient (every 1 ms is ideal; a period longer
 * than the ring's fill time loses bytes). Handles the bytes received so far,
 * answers requests, detects link loss, sends heartbeats and telemetry when
 * due. `now_ms`: a free-running millisecond clock; wrapping is fine.
 */
void oibar_link_poll(oibar_link_t *link, uint32_t now_ms);

/** Send an Event now (seq assigned by the link). False if not sent. */
bool oibar_link_send_event(oibar_link_t *link, const oibar_v1_Event *event);

/** True between an accepted handshake and the next link loss. */
bool oibar_link_is_connected(const oibar_link_t *link);

/** Snapshot of all link counters, as reported in Telemetry.link. */
void oibar_link_get_counters(const oibar_link_t *link, oibar_v1_LinkCounters *out);

/** Snapshot of the counters without a LinkCounters field. */
void oibar_link_get_stats(const oibar_link_t *link, oibar_link_stats_t *out);

/** Current configuration (read-only; change timing with the setters below). */
const oibar_link_config_t *oibar_link_get_config(const oibar_link_t *link);

/** Change timing live (each value > 0); takes effect from the next poll. */
void oibar_link_set_heartbeat_period_ms(oibar_link_t *link, uint32_t period_ms);
void oibar_link_set_telemetry_period_ms(oibar_link_t *link, uint32_t period_ms);
void oibar_link_set_link_timeout_ms(oibar_link_t *link, uint32_t timeout_ms);

#ifdef __cplusplus
}
#endif

#endif /* OIBAR_LINK_H */
