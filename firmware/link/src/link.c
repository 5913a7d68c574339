/* MCU side of the host <-> MCU link; the rules are in docs/link.md. */
#include "oibar/link.h"

#include <string.h>

#include "oibar/assert.h"

/* ------------------------------------------------------------------------- */
/* Small helpers                                                             */

/* Sequence numbers run 1, 2, ..., 2^32 - 1 (SEQ_MAX), 1, ...: 0 means "no seq"
 * and is never used. The same rule as the host's oibar/link/seq.py. */
#define SEQ_HALF 0x7FFFFFFFu /* SEQ_MAX / 2: further ahead than this is behind */
/* A seq this close behind the newest one is a re-send; further behind, the
 * peer restarted its numbering (oibar.link.seq.STALE_SEQ_WINDOW). */
#define SEQ_STALE_WINDOW 1024u

static uint32_t seq_next(uint32_t seq)
{
    return (seq == UINT32_MAX) ? 1u : seq + 1u;
}

/* How many steps `seq` is ahead of `from` along the numbering (0 skipped):
 * 0 when equal, SEQ_MAX - 1 when one behind. Both must be non-zero. */
static uint32_t seq_distance(uint32_t from, uint32_t seq)
{
    uint32_t d = seq - from;
    if (seq < from) {
        d -= 1u; /* the numbering wrapped and skipped 0 */
    }
    return d;
}

/* True if `seq` is newer than `newest`: ahead of it by 1 .. SEQ_MAX / 2. */
static bool seq_is_newer(uint32_t newest, uint32_t seq)
{
    const uint32_t d = seq_distance(newest, seq);
    return (d != 0u) && (d <= SEQ_HALF);
}

/* Wrap-safe: true once `period_ms` has passed since `since_ms`. */
static bool elapsed(uint32_t now_ms, uint32_t since_ms, uint32_t period_ms)
{
    return (uint32_t)(now_ms - since_ms) >= period_ms;
}

/* Next reference time of a periodic job: keep the cadence, but after a
 * stall of more than one period restart from now instead of bursting. */
static uint32_t period_advance(uint32_t last_ms, uint32_t period_ms, uint32_t now_ms)
{
    const uint32_t next_ms = last_ms + period_ms;
    return elapsed(now_ms, next_ms, period_ms) ? now_ms : next_ms;
}

/* Bounded copy that always terminates `dst` (a nanopb char[] field). */
static void copy_str(char *dst, size_t cap, const char *src)
{
    size_t n = 0u;
    if (src != NULL) {
        while (n + 1u < cap && src[n] != '\0') {
            dst[n] = src[n];
            ++n;
        }
    }
    dst[n] = '\0';
}

static oibar_v1_State app_state(const oibar_link_t *link)
{
    return (link->app.get_state != NULL) ? link->app.get_state(link->app.ctx)
                                         : oibar_v1_STATE_UNSPECIFIED;
}

static void app_link_state(const oibar_link_t *link, bool up)
{
    if (link->app.on_link_state != NULL) {
        link->app.on_link_state(link->app.ctx, up);
    }
}

static void request_key(const oibar_v1_Packet *req, uint32_t key[2]);

/* ------------------------------------------------------------------------- */
/* Transmit                                                                  */

static bool port_send(oibar_link_t *link, const uint8_t *bytes, size_t len)
{
    if (link->port.send(link->port.ctx, bytes, len)) {
        ++link->tx_packets;
        return true;
    }
    ++link->stats.tx_failures;
    return false;
}

/* Number `pkt` and encode it into `buf`; 0 if it does not encode. */
static size_t encode_numbered(oibar_link_t *link, oibar_v1_Packet *pkt, uint8_t *buf, size_t cap)
{
    pkt->seq = link->tx_seq;
    link->tx_seq = seq_next(link->tx_seq);
    const size_t len = oibar_frame_encode(pkt, buf, cap);
    if (len == 0u) {
        ++link->stats.tx_failures; /* e.g. an unterminated string from the application */
    }
    return len;
}

/* A packet that is not a response: heartbeat, telemetry, event, nack. */
static bool send_packet(oibar_link_t *link, oibar_v1_Packet *pkt)
{
    const size_t len = encode_numbered(link, pkt, link->tx_frame, sizeof(link->tx_frame));
    return (len > 0u) && port_send(link, link->tx_frame, len);
}

/* The response to a request: sent, and kept to answer a retransmission. */
static void send_response(oibar_link_t *link, oibar_v1_Packet *resp, const oibar_v1_Packet *req)
{
    resp->ack_seq = req->seq;
    link->cache_valid = false;
    const size_t len = encode_numbered(link, resp, link->cache_frame, sizeof(link->cache_frame));
    if (len == 0u) {
        return;
    }
    /* seq 0 means "no seq": such a request cannot be recognised again. */
    link->cache_valid = (req->seq != 0u);
    link->cache_seq = req->seq;
    link->cache_body = req->which_body;
    request_key(req, link->cache_key);
    link->cache_len = len;
    (void)port_send(link, link->cache_frame, len);
}

/* The exact request answered last: same seq, same body type, same content. */
static bool is_duplicate(const oibar_link_t *link, const oibar_v1_Packet *req)
{
    if (!link->cache_valid || req->seq != link->cache_seq || req->which_body != link->cache_body) {
        return false;
    }
    uint32_t key[2];
    request_key(req, key);
    return key[0] == link->cache_key[0] && key[1] == link->cache_key[1];
}

static void send_nack(oibar_link_t *link, const oibar_v1_Packet *req, oibar_v1_NackReason reason,
                      bool cache)
{
    oibar_v1_Packet resp = oibar_v1_Packet_init_zero;
    resp.which_body = oibar_v1_Packet_ack_tag;
    resp.body.ack.accepted = false;
    resp.body.ack.reason = reason;
    resp.body.ack.state = app_state(link);
    if (cache) {
        send_response(link, &resp, req);
    } else {
        resp.ack_seq = req->seq;
        (void)send_packet(link, &resp);
    }
}

static void send_link_event(oibar_link_t *link, uint32_t now_ms, oibar_v1_EventId id,
                            oibar_v1_Severity severity)
{
    oibar_v1_Event ev = oibar_v1_Event_init_zero;
    ev.uptime_ms = now_ms;
    ev.id = id;
    ev.severity = severity;
    (void)oibar_link_send_event(link, &ev);
}

/* ------------------------------------------------------------------------- */
/* Link state                                                                */

static void link_down(oibar_link_t *link)
{
    link->connected = false;
    app_link_state(link, false);
}

static void link_lost(oibar_link_t *link, uint32_t now_ms)
{
    ++link->link_losses;
    link->connected = false;
    link->cache_valid = false; /* the next session must not get this one's answers */
    send_link_event(link, now_ms, oibar_v1_EVT_LINK_LOST, oibar_v1_SEVERITY_WARNING_HI);
    app_link_state(link, false);
}

/* Count packets missing from the peer's numbering (oibar.link.seq
 * follow_peer_seq): a seq at or a little behind the newest one (a
 * retransmission) is not a gap and does not move the mark; one far behind
 * means the peer restarted its numbering. */
static void track_peer_seq(oibar_link_t *link, uint32_t seq)
{
    if (seq == 0u) {
        return;
    }
    if (!link->peer_seq_valid) {
        link->peer_seq_valid = true;
        link->peer_seq = seq;
        return;
    }
    if (seq_distance(seq, link->peer_seq) <= SEQ_STALE_WINDOW) {
        return; /* equal, or a re-send */
    }
    if (seq_is_newer(link->peer_seq, seq)) {
        link->stats.rx_seq_lost += seq_distance(link->peer_seq, seq) - 1u;
    }
    link->peer_seq = seq;
}

/* What identifies a request besides its seq: body type and content. Two
 * requests with the same seq and key are the same request (a retransmission).
 * The handshake's host_version is left out: it changes nothing. */
static void request_key(const oibar_v1_Packet *req, uint32_t key[2])
{
    key[0] = 0u;
    key[1] = 0u;
    switch (req->which_body) {
    case oibar_v1_Packet_command_tag:
        key[0] = (uint32_t)req->body.command.opcode;
        memcpy(&key[1], &req->body.command.target_pressure_kpa, sizeof(key[1]));
        break;
    case oibar_v1_Packet_param_get_tag:
        key[0] = req->body.param_get.param_id;
        break;
    case oibar_v1_Packet_param_set_tag:
        key[0] = req->body.param_set.param_id;
        memcpy(&key[1], &req->body.param_set.value, sizeof(key[1]));
        break;
    case oibar_v1_Packet_handshake_tag:
        key[0] = req->body.handshake.protocol_version;
        break;
    default:
        break;
    }
}

/* The replay window (docs/link.md): NACK_NONE if `req` (not a handshake, not
 * the cached duplicate) may run. Seq 0, a seq at or behind the newest request
 * of this session, and the last request's seq with another body are refused. */
static oibar_v1_NackReason check_request_seq(const oibar_link_t *link, const oibar_v1_Packet *req)
{
    if (req->seq == 0u) {
        return oibar_v1_NACK_STALE_SEQ;
    }
    if (link->cache_valid && req->seq == link->cache_seq) {
        return oibar_v1_NACK_SEQ_REUSED;
    }
    if (link->req_seq_valid && !seq_is_newer(link->req_seq, req->seq)) {
        return oibar_v1_NACK_STALE_SEQ;
    }
    return oibar_v1_NACK_NONE;
}

/* ------------------------------------------------------------------------- */
/* Receive                                                                   */

static void handle_handshake(oibar_link_t *link, const oibar_v1_Packet *req, uint32_t now_ms)
{
    oibar_v1_Packet resp = oibar_v1_Packet_init_zero;
    resp.which_body = oibar_v1_Packet_handshake_reply_tag;
    oibar_v1_HandshakeReply *reply = &resp.body.handshake_reply;
    const bool ok = (req->body.handshake.protocol_version == link->cfg.protocol_version);
    reply->accepted = ok;
    reply->reason = ok ? oibar_v1_NACK_NONE : oibar_v1_NACK_VERSION_MISMATCH;
    reply->protocol_version = link->cfg.protocol_version;
    copy_str(reply->firmware_version, sizeof(reply->firmware_version), link->cfg.firmware_version);
    copy_str(reply->build_id, sizeof(reply->build_id), link->cfg.build_id);
    reply->reset_cause = link->cfg.reset_cause;
    reply->uptime_ms = now_ms;
    if (req->seq == 0u) {
        /* seq 0 means "no seq": a session started on it would have no replay
         * window for its first request (any seq accepted), so it is refused
         * and nothing of the current session changes. */
        reply->accepted = false;
        reply->reason = oibar_v1_NACK_STALE_SEQ;
        ++link->rx_stale;
        send_response(link, &resp, req);
        return;
    }

    /* A new session: restart the peer's numbering and the replay window
     * from this packet. */
    link->peer_seq_valid = true;
    link->peer_seq = req->seq;
    link->req_seq_valid = true;
    link->req_seq = req->seq;
    link->nav_seq_valid = false;
    send_response(link, &resp, req); /* replaces the duplicate memory */

    if (ok && !link->connected) {
        link->connected = true;
        link->last_rx_ms = now_ms;
        send_link_event(link, now_ms, oibar_v1_EVT_LINK_UP, oibar_v1_SEVERITY_ACTIVITY_HI);
        app_link_state(link, true);
    } else if (!ok && link->connected) {
        /* A peer that speaks another version took over the line: do not
         * keep accepting requests on the old session. */
        link_down(link);
    } else if (ok) {
        /* A re-handshake on a live link is a new session: the application
         * drops what it kept from the old one (its navigation record). */
        app_link_state(link, true);
    } else {
        /* a refusal while unconnected */
    }
}

static void handle_command(oibar_link_t *link, const oibar_v1_Packet *req)
{
    oibar_v1_Packet resp = oibar_v1_Packet_init_zero;
    resp.which_body = oibar_v1_Packet_ack_tag;
    oibar_v1_Ack *ack = &resp.body.ack;
    ack->reason = oibar_v1_NACK_NOT_SUPPORTED;
    ack->state = app_state(link);
    if (link->app.on_command != NULL) {
        ack->reason = oibar_v1_NACK_NONE;
        link->app.on_command(link->app.ctx, &req->body.command, ack);
    }
    ack->accepted = (ack->reason == oibar_v1_NACK_NONE);
    send_response(link, &resp, req);
}

static void handle_param(oibar_link_t *link, const oibar_v1_Packet *req)
{
    oibar_v1_Packet resp = oibar_v1_Packet_init_zero;
    resp.which_body = oibar_v1_Packet_param_value_tag;
    oibar_v1_ParamValue *pv = &resp.body.param_value;
    pv->reason = oibar_v1_NACK_UNKNOWN_PARAM;
    if (req->which_body == oibar_v1_Packet_param_get_tag) {
        pv->param_id = req->body.param_get.param_id;
        if (link->app.on_param_get != NULL) {
            pv->reason = oibar_v1_NACK_NONE;
            link->app.on_param_get(link->app.ctx, pv->param_id, pv);
        }
    } else {
        pv->param_id = req->body.param_set.param_id;
        if (link->app.on_param_set != NULL) {
            pv->reason = oibar_v1_NACK_NONE;
            link->app.on_param_set(link->app.ctx, pv->param_id, req->body.param_set.value, pv);
        }
    }
    send_response(link, &resp, req);
}

/* Command, ParamGet, ParamSet: exactly one response each. */
static void handle_request(oibar_link_t *link, const oibar_v1_Packet *req)
{
    if (!link->connected) {
        send_nack(link, req, oibar_v1_NACK_NOT_CONNECTED, true);
    } else if (req->which_body == oibar_v1_Packet_command_tag) {
        handle_command(link, req);
    } else {
        handle_param(link, req);
    }
}

static void handle_packet(oibar_link_t *link, const oibar_v1_Packet *pkt, uint32_t now_ms)
{
    link->last_rx_ms = now_ms; /* any valid packet proves the peer alive */

    const pb_size_t body = pkt->which_body;
    const bool request = (body == oibar_v1_Packet_handshake_tag) || (body == oibar_v1_Packet_command_tag) ||
                         (body == oibar_v1_Packet_param_get_tag) || (body == oibar_v1_Packet_param_set_tag);
    if (request && is_duplicate(link, pkt)) {
        ++link->rx_duplicates; /* a retransmission: answer again, do not execute again */
        (void)port_send(link, link->cache_frame, link->cache_len);
        return;
    }
    if (body == oibar_v1_Packet_handshake_tag) {
        handle_handshake(link, pkt, now_ms);
        return;
    }
    track_peer_seq(link, pkt->seq);
    if (request) {
        /* Unconnected, every request is refused with NACK_NOT_CONNECTED. */
        const oibar_v1_NackReason bad_seq =
            link->connected ? check_request_seq(link, pkt) : oibar_v1_NACK_NONE;
        if (bad_seq != oibar_v1_NACK_NONE) {
            /* A replay, a reordered or a malformed request: never run it. Not
             * cached, so the last request's retransmission still matches. */
            ++link->rx_stale;
            send_nack(link, pkt, bad_seq, false);
            return;
        }
        link->req_seq_valid = true;
        link->req_seq = pkt->seq;
        handle_request(link, pkt);
    } else if (body == oibar_v1_Packet_nav_update_tag) {
        if (pkt->seq == 0u || (link->nav_seq_valid && !seq_is_newer(link->nav_seq, pkt->seq))) {
            ++link->rx_stale; /* an old solution: the newest one already arrived */
            return;
        }
        link->nav_seq_valid = true;
        link->nav_seq = pkt->seq;
        if (link->connected && link->app.on_nav_update != NULL) {
            link->app.on_nav_update(link->app.ctx, &pkt->body.nav_update);
        }
    } else {
        /* Heartbeat: its arrival is all it says. */
    }
}

static void handle_rx(oibar_link_t *link, oibar_rx_result_t result, uint32_t now_ms)
{
    const oibar_v1_Packet *pkt = &link->rx_packet;
    if (result == OIBAR_RX_PACKET) {
        handle_packet(link, pkt, now_ms);
    } else if (result == OIBAR_RX_UNKNOWN_TYPE && pkt->seq != 0u) {
        track_peer_seq(link, pkt->seq);
        send_nack(link, pkt, oibar_v1_NACK_UNKNOWN_MESSAGE, false);
    } else {
        /* dropped frame: counted by the decoder, never acted on */
    }
}

/* Handle the bytes present at entry only: bounded work per poll. */
static void drain_rx(oibar_link_t *link, uint32_t now_ms)
{
    size_t n = oibar_ringbuf_count(&link->rx_ring);
    uint8_t byte = 0u;
    while (n > 0u && oibar_ringbuf_pop(&link->rx_ring, &byte)) {
        --n;
        const oibar_rx_result_t r = oibar_frame_decoder_feed(&link->decoder, byte, &link->rx_packet);
        if (r != OIBAR_RX_NONE) {
            handle_rx(link, r, now_ms);
        }
    }
}

/* ------------------------------------------------------------------------- */
/* Periodic packets                                                          */

static void send_heartbeat(oibar_link_t *link, uint32_t now_ms)
{
    oibar_v1_Packet pkt = oibar_v1_Packet_init_zero;
    pkt.which_body = oibar_v1_Packet_heartbeat_tag;
    pkt.body.heartbeat.uptime_ms = now_ms;
    (void)send_packet(link, &pkt);
}

static void send_telemetry(oibar_link_t *link, uint32_t now_ms)
{
    oibar_v1_Packet pkt = oibar_v1_Packet_init_zero;
    pkt.which_body = oibar_v1_Packet_telemetry_tag;
    oibar_v1_Telemetry *tm = &pkt.body.telemetry;
    tm->uptime_ms = now_ms;
    tm->state = app_state(link);
    if (link->app.fill_telemetry != NULL) {
        link->app.fill_telemetry(link->app.ctx, tm);
    }
    tm->has_link = true;
    oibar_link_get_counters(link, &tm->link);
    tm->host_link_alive = link->connected;
    (void)send_packet(link, &pkt);
}

static void run_timers(oibar_link_t *link, uint32_t now_ms)
{
    if (!link->started) {
        /* First poll: heartbeat and telemetry go out now, the clock starts. */
        link->started = true;
        link->last_heartbeat_ms = now_ms - link->cfg.heartbeat_period_ms;
        link->last_telemetry_ms = now_ms - link->cfg.telemetry_period_ms;
    }
    if (link->connected && elapsed(now_ms, link->last_rx_ms, link->cfg.link_timeout_ms)) {
        link_lost(link, now_ms);
    }
    if (elapsed(now_ms, link->last_heartbeat_ms, link->cfg.heartbeat_period_ms)) {
        send_heartbeat(link, now_ms);
        link->last_heartbeat_ms = period_advance(link->last_heartbeat_ms, link->cfg.heartbeat_period_ms, now_ms);
    }
    if (elapsed(now_ms, link->last_telemetry_ms, link->cfg.telemetry_period_ms)) {
        send_telemetry(link, now_ms);
        link->last_telemetry_ms = period_advance(link->last_telemetry_ms, link->cfg.telemetry_period_ms, now_ms);
    }
}

/* ------------------------------------------------------------------------- */
/* Public API                                                                */

void oibar_link_config_defaults(oibar_link_config_t *cfg)
{
    OIBAR_ASSERT(cfg != NULL);
    memset(cfg, 0, sizeof(*cfg));
    cfg->heartbeat_period_ms = OIBAR_LINK_DEFAULT_HEARTBEAT_PERIOD_MS;
    cfg->telemetry_period_ms = OIBAR_LINK_DEFAULT_TELEMETRY_PERIOD_MS;
    cfg->link_timeout_ms = OIBAR_LINK_DEFAULT_LINK_TIMEOUT_MS;
    cfg->firmware_version = "";
    cfg->build_id = "";
    cfg->reset_cause = oibar_v1_RESET_UNKNOWN;
    cfg->protocol_version = (uint32_t)oibar_v1_PROTOCOL_VERSION;
}

void oibar_link_init(oibar_link_t *link, const oibar_link_config_t *cfg,
                     const oibar_link_port_t *port, const oibar_link_app_t *app)
{
    OIBAR_ASSERT(link != NULL && cfg != NULL && port != NULL && port->send != NULL);
    OIBAR_ASSERT(cfg->heartbeat_period_ms > 0u && cfg->telemetry_period_ms > 0u &&
                 cfg->link_timeout_ms > 0u);
    memset(link, 0, sizeof(*link));
    link->cfg = *cfg;
    link->port = *port;
    if (app != NULL) {
        link->app = *app;
    }
    oibar_ringbuf_init(&link->rx_ring);
    oibar_frame_decoder_init(&link->decoder, OIBAR_BODIES_HOST_TO_MCU);
    link->tx_seq = 1u;
}

void oibar_link_rx_isr(oibar_link_t *link, uint8_t byte)
{
    if (!oibar_ringbuf_push(&link->rx_ring, byte)) {
        link->rx_ring_overflows = link->rx_ring_overflows + 1u;
    }
}

void oibar_link_poll(oibar_link_t *link, uint32_t now_ms)
{
    OIBAR_ASSERT(link != NULL);
    drain_rx(link, now_ms); /* first, so that fresh packets count as alive */
    run_timers(link, now_ms);
}

bool oibar_link_send_event(oibar_link_t *link, const oibar_v1_Event *event)
{
    OIBAR_ASSERT(link != NULL && event != NULL);
    oibar_v1_Packet pkt = oibar_v1_Packet_init_zero;
    pkt.which_body = oibar_v1_Packet_event_tag;
    pkt.body.event = *event;
    return send_packet(link, &pkt);
}

bool oibar_link_is_connected(const oibar_link_t *link)
{
    OIBAR_ASSERT(link != NULL);
    return link->connected;
}

void oibar_link_get_counters(const oibar_link_t *link, oibar_v1_LinkCounters *out)
{
    OIBAR_ASSERT(link != NULL && out != NULL);
    const oibar_frame_counters_t *rx = oibar_frame_decoder_counters(&link->decoder);
    out->rx_packets = rx->rx_packets;
    out->rx_crc_errors = rx->rx_crc_errors;
    out->rx_framing_errors = rx->rx_framing_errors;
    out->rx_oversize = rx->rx_oversize;
    out->rx_bad_header = rx->rx_bad_header;
    out->rx_decode_errors = rx->rx_decode_errors;
    out->rx_unknown_type = rx->rx_unknown_type;
    out->rx_duplicates = link->rx_duplicates;
    out->rx_ring_overflows = link->rx_ring_overflows;
    out->tx_packets = link->tx_packets;
    out->link_losses = link->link_losses;
    out->rx_stale = link->rx_stale;
}

void oibar_link_get_stats(const oibar_link_t *link, oibar_link_stats_t *out)
{
    OIBAR_ASSERT(link != NULL && out != NULL);
    *out = link->stats;
}

const oibar_link_config_t *oibar_link_get_config(const oibar_link_t *link)
{
    OIBAR_ASSERT(link != NULL);
    return &link->cfg;
}

void oibar_link_set_heartbeat_period_ms(oibar_link_t *link, uint32_t period_ms)
{
    OIBAR_ASSERT(link != NULL && period_ms > 0u);
    link->cfg.heartbeat_period_ms = period_ms;
}

void oibar_link_set_telemetry_period_ms(oibar_link_t *link, uint32_t period_ms)
{
    OIBAR_ASSERT(link != NULL && period_ms > 0u);
    link->cfg.telemetry_period_ms = period_ms;
}

void oibar_link_set_link_timeout_ms(oibar_link_t *link, uint32_t timeout_ms)
{
    OIBAR_ASSERT(link != NULL && timeout_ms > 0u);
    link->cfg.link_timeout_ms = timeout_ms;
}
