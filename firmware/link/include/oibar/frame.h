/**
 * @file frame.h
 * The wire framing of docs/link.md:
 *
 *     raw frame  = [0x01 header] [protobuf Packet, <= 240 bytes] [CRC-32C LE, 4 bytes]
 *     wire frame = COBS(raw frame) 0x00                          (<= 247 bytes)
 *
 * Encoder: one call turns a Packet into wire bytes in a caller buffer.
 * Decoder: fed one byte at a time (from the RX ring), it gathers encoded
 * bytes up to the 0x00 delimiter, validates the frame, counts the outcome
 * and resynchronises at the next 0x00 whatever happened. No allocation;
 * the decoder is a plain struct the caller owns.
 */
#ifndef OIBAR_FRAME_H
#define OIBAR_FRAME_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "oibar.pb.h"
#include "oibar/cobs.h"

#ifdef __cplusplus
extern "C" {
#endif

/** Frame format byte of this framing; any other value is rx_bad_header. */
#define OIBAR_FRAME_HEADER 0x01u
#define OIBAR_FRAME_CRC_BYTES 4u

/** Largest protobuf Packet (240). */
#define OIBAR_FRAME_MAX_PACKET_BYTES ((size_t)oibar_v1_PROTOCOL_MAX_PACKET_BYTES)
/** Smallest raw frame: header + empty packet + CRC (5). */
#define OIBAR_FRAME_MIN_RAW_BYTES (1u + OIBAR_FRAME_CRC_BYTES)
/** Largest raw frame (245). */
#define OIBAR_FRAME_MAX_RAW_BYTES (1u + OIBAR_FRAME_MAX_PACKET_BYTES + OIBAR_FRAME_CRC_BYTES)
/** Largest wire frame including the 0x00 delimiter (247): size of an encode buffer. */
#define OIBAR_FRAME_MAX_WIRE_BYTES ((size_t)oibar_v1_PROTOCOL_MAX_FRAME_BYTES)
/** Most encoded bytes before a 0x00 (246); one more is rx_oversize. */
#define OIBAR_FRAME_MAX_ENCODED_BYTES (OIBAR_FRAME_MAX_WIRE_BYTES - 1u)

/* Bit masks of Packet body tags (oibar_v1_Packet_*_tag) that a receiver
 * accepts. Anything else decodes as OIBAR_RX_UNKNOWN_TYPE. */
#define OIBAR_BODY_BIT(tag) (1u << (tag))
/** What the MCU accepts: the host's bodies. */
#define OIBAR_BODIES_HOST_TO_MCU                                                 \
    (OIBAR_BODY_BIT(oibar_v1_Packet_handshake_tag) |                             \
     OIBAR_BODY_BIT(oibar_v1_Packet_heartbeat_tag) |                             \
     OIBAR_BODY_BIT(oibar_v1_Packet_command_tag) |                               \
     OIBAR_BODY_BIT(oibar_v1_Packet_nav_update_tag) |                            \
     OIBAR_BODY_BIT(oibar_v1_Packet_param_get_tag) |                             \
     OIBAR_BODY_BIT(oibar_v1_Packet_param_set_tag))
/** What the host accepts: the MCU's bodies (for tools and tests). */
#define OIBAR_BODIES_MCU_TO_HOST                                                 \
    (OIBAR_BODY_BIT(oibar_v1_Packet_handshake_reply_tag) |                       \
     OIBAR_BODY_BIT(oibar_v1_Packet_heartbeat_tag) |                             \
     OIBAR_BODY_BIT(oibar_v1_Packet_ack_tag) |                                   \
     OIBAR_BODY_BIT(oibar_v1_Packet_param_value_tag) |                           \
     OIBAR_BODY_BIT(oibar_v1_Packet_telemetry_tag) |                             \
     OIBAR_BODY_BIT(oibar_v1_Packet_event_tag))
#define OIBAR_BODIES_ALL (OIBAR_BODIES_HOST_TO_MCU | OIBAR_BODIES_MCU_TO_HOST)

/* ------------------------------------------------------------------------- */
/* Encoder                                                                   */

/**
 * Encode `packet` into a wire frame (COBS, trailing 0x00) in `out`.
 * Returns the wire length (<= OIBAR_FRAME_MAX_WIRE_BYTES), or 0 when the
 * packet does not encode (e.g. an unterminated string) or `out_cap` is too
 * small. A buffer of OIBAR_FRAME_MAX_WIRE_BYTES always suffices.
 */
size_t oibar_frame_encode(const oibar_v1_Packet *packet, uint8_t *out, size_t out_cap);

/**
 * Frame already-encoded protobuf bytes (golden vectors, tests, tools).
 * Returns the wire length, or 0 when `packet_len` exceeds
 * OIBAR_FRAME_MAX_PACKET_BYTES or `out_cap` is too small.
 */
size_t oibar_frame_encode_bytes(const uint8_t *packet_bytes, size_t packet_len,
                                uint8_t *out, size_t out_cap);

/* ------------------------------------------------------------------------- */
/* Decoder                                                                   */

/** Outcome of feeding one byte. Each outcome but NONE bumps one counter. */
typedef enum {
    OIBAR_RX_NONE = 0,      /**< byte absorbed, no frame ended */
    OIBAR_RX_PACKET,        /**< valid packet in *out (rx_packets) */
    OIBAR_RX_UNKNOWN_TYPE,  /**< decoded, but no body or one not accepted here;
                                 *out is valid, e.g. for its seq (rx_unknown_type) */
    OIBAR_RX_OVERSIZE,      /**< more than 246 bytes before a 0x00; the rest up to
                                 the next 0x00 is skipped (rx_oversize) */
    OIBAR_RX_FRAMING_ERROR, /**< bad COBS or raw frame < 5 bytes (rx_framing_errors) */
    OIBAR_RX_BAD_HEADER,    /**< header byte other than 0x01 (rx_bad_header) */
    OIBAR_RX_CRC_ERROR,     /**< CRC mismatch (rx_crc_errors) */
    OIBAR_RX_DECODE_ERROR,  /**< CRC fine, protobuf does not decode (rx_decode_errors) */
} oibar_rx_result_t;

/** One counter per outcome; names as in oibar_v1_LinkCounters. */
typedef struct {
    uint32_t rx_packets;
    uint32_t rx_crc_errors;
    uint32_t rx_framing_errors;
    uint32_t rx_oversize;
    uint32_t rx_bad_header;
    uint32_t rx_decode_errors;
    uint32_t rx_unknown_type;
} oibar_frame_counters_t;

/** Streaming decoder state. Treat the fields as private. */
typedef struct {
    uint8_t buf[OIBAR_FRAME_MAX_ENCODED_BYTES]; /* encoded bytes, decoded in place */
    size_t len;                                 /* encoded bytes gathered so far */
    bool skipping;                              /* oversize: dropping up to the next 0x00 */
    uint32_t accepted_bodies;                   /* OIBAR_BODY_BIT mask */
    oibar_frame_counters_t counters;
} oibar_frame_decoder_t;

/** Reset the decoder and its counters; `accepted_bodies` is an OIBAR_BODIES_* mask. */
void oibar_frame_decoder_init(oibar_frame_decoder_t *dec, uint32_t accepted_bodies);

/**
 * Feed one received byte. When a frame ends, validates it per docs/link.md,
 * counts the outcome and returns it; `*out` is written only for
 * OIBAR_RX_PACKET and OIBAR_RX_UNKNOWN_TYPE (otherwise its content is
 * unspecified). Bounded time: at most one COBS pass, one CRC and one
 * protobuf decode of <= 245 bytes, on the delimiter byte.
 */
oibar_rx_result_t oibar_frame_decoder_feed(oibar_frame_decoder_t *dec, uint8_t byte,
                                           oibar_v1_Packet *out);

/**
 * Feed bytes until a frame ends or `len` bytes are used. Stores in `*used`
 * how many bytes were consumed and returns the outcome of the frame that
 * ended (OIBAR_RX_NONE when none did). Call again with the remaining bytes.
 */
oibar_rx_result_t oibar_frame_decoder_feed_buf(oibar_frame_decoder_t *dec,
                                               const uint8_t *data, size_t len,
                                               size_t *used, oibar_v1_Packet *out);

/** The decoder's outcome counters. */
const oibar_frame_counters_t *oibar_frame_decoder_counters(const oibar_frame_decoder_t *dec);

#ifdef __cplusplus
}
#endif

#endif /* OIBAR_FRAME_H */
