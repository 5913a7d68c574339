/* Wire framing: [0x01][Packet][CRC-32C LE] -> COBS -> 0x00. See docs/link.md. */
#include "oibar/frame.h"

#include <string.h>

#include <pb_decode.h>
#include <pb_encode.h>

#include "oibar/assert.h"
#include "oibar/crc32c.h"

/* Every Packet the schema can express must fit the protocol's packet limit,
 * so encoding a well-formed Packet never fails for size. */
_Static_assert(oibar_v1_Packet_size <= oibar_v1_PROTOCOL_MAX_PACKET_BYTES,
               "oibar_v1_Packet can outgrow PROTOCOL_MAX_PACKET_BYTES");
/* The largest raw frame, COBS encoded, plus the delimiter fits the wire limit. */
_Static_assert(OIBAR_COBS_MAX_ENCODED(OIBAR_FRAME_MAX_RAW_BYTES) + 1u <= OIBAR_FRAME_MAX_WIRE_BYTES,
               "PROTOCOL_MAX_FRAME_BYTES too small for PROTOCOL_MAX_PACKET_BYTES");
_Static_assert(oibar_v1_Packet_event_tag < 32, "body tags must fit a uint32_t mask");

/* ------------------------------------------------------------------------- */
/* Encoder                                                                   */

/* raw[0..raw_len) holds header + packet; appends the CRC (raw must have room
 * for it) and writes COBS + delimiter into out. */
static size_t frame_finish(uint8_t *raw, size_t raw_len, uint8_t *out, size_t out_cap)
{
    const uint32_t crc = oibar_crc32c(raw, raw_len);
    raw[raw_len++] = (uint8_t)(crc & 0xFFu);
    raw[raw_len++] = (uint8_t)((crc >> 8) & 0xFFu);
    raw[raw_len++] = (uint8_t)((crc >> 16) & 0xFFu);
    raw[raw_len++] = (uint8_t)((crc >> 24) & 0xFFu);

    if (out_cap < 1u) {
        return 0u;
    }
    size_t enc_len = 0u;
    if (oibar_cobs_encode(raw, raw_len, out, out_cap - 1u, &enc_len) != OIBAR_COBS_OK) {
        return 0u;
    }
    out[enc_len] = 0x00u;
    return enc_len + 1u;
}

size_t oibar_frame_encode(const oibar_v1_Packet *packet, uint8_t *out, size_t out_cap)
{
    OIBAR_ASSERT(packet != NULL && out != NULL);
    uint8_t raw[OIBAR_FRAME_MAX_RAW_BYTES];
    raw[0] = OIBAR_FRAME_HEADER;
    pb_ostream_t stream = pb_ostream_from_buffer(&raw[1], OIBAR_FRAME_MAX_PACKET_BYTES);
    if (!pb_encode(&stream, oibar_v1_Packet_fields, packet)) {
        return 0u;
    }
    return frame_finish(raw, 1u + stream.bytes_written, out, out_cap);
}

size_t oibar_frame_encode_bytes(const uint8_t *packet_bytes, size_t packet_len,
                                uint8_t *out, size_t out_cap)
{
    OIBAR_ASSERT(packet_bytes != NULL || packet_len == 0u);
    OIBAR_ASSERT(out != NULL);
    if (packet_len > OIBAR_FRAME_MAX_PACKET_BYTES) {
        return 0u;
    }
    uint8_t raw[OIBAR_FRAME_MAX_RAW_BYTES];
    raw[0] = OIBAR_FRAME_HEADER;
    if (packet_len > 0u) {
        memcpy(&raw[1], packet_bytes, packet_len);
    }
    return frame_finish(raw, 1u + packet_len, out, out_cap);
}

/* ------------------------------------------------------------------------- */
/* Decoder                                                                   */

void oibar_frame_decoder_init(oibar_frame_decoder_t *dec, uint32_t accepted_bodies)
{
    OIBAR_ASSERT(dec != NULL);
    memset(dec, 0, sizeof(*dec));
    dec->accepted_bodies = accepted_bodies;
}

static uint32_t read_le32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

/* Validate the gathered frame, in the order of the table in docs/link.md. */
static oibar_rx_result_t frame_validate(oibar_frame_decoder_t *dec, oibar_v1_Packet *out)
{
    size_t raw_len = 0u;
    if (oibar_cobs_decode(dec->buf, dec->len, dec->buf, sizeof(dec->buf), &raw_len) != OIBAR_COBS_OK ||
        raw_len < OIBAR_FRAME_MIN_RAW_BYTES) {
        return OIBAR_RX_FRAMING_ERROR;
    }
    const uint8_t *raw = dec->buf;
    if (raw[0] != OIBAR_FRAME_HEADER) {
        return OIBAR_RX_BAD_HEADER;
    }
    const size_t body_len = raw_len - OIBAR_FRAME_CRC_BYTES;
    if (oibar_crc32c(raw, body_len) != read_le32(&raw[body_len])) {
        return OIBAR_RX_CRC_ERROR;
    }
    /* 246 encoded bytes decode to at most 245 raw ones: the packet fits. */
    OIBAR_ASSERT(body_len - 1u <= OIBAR_FRAME_MAX_PACKET_BYTES);
    pb_istream_t stream = pb_istream_from_buffer(&raw[1], body_len - 1u);
    if (!pb_decode(&stream, oibar_v1_Packet_fields, out)) {
        return OIBAR_RX_DECODE_ERROR;
    }
    const pb_size_t tag = out->which_body;
    if (tag == 0u || tag >= 32u || (dec->accepted_bodies & OIBAR_BODY_BIT(tag)) == 0u) {
        return OIBAR_RX_UNKNOWN_TYPE;
    }
    return OIBAR_RX_PACKET;
}

static void count_outcome(oibar_frame_counters_t *c, oibar_rx_result_t r)
{
    switch (r) {
    case OIBAR_RX_PACKET:        ++c->rx_packets; break;
    case OIBAR_RX_UNKNOWN_TYPE:  ++c->rx_unknown_type; break;
    case OIBAR_RX_OVERSIZE:      ++c->rx_oversize; break;
    case OIBAR_RX_FRAMING_ERROR: ++c->rx_framing_errors; break;
    case OIBAR_RX_BAD_HEADER:    ++c->rx_bad_header; break;
    case OIBAR_RX_CRC_ERROR:     ++c->rx_crc_errors; break;
    case OIBAR_RX_DECODE_ERROR:  ++c->rx_decode_errors; break;
    case OIBAR_RX_NONE:          break;
    default:                     OIBAR_ASSERT(0); break;
    }
}

oibar_rx_result_t oibar_frame_decoder_feed(oibar_frame_decoder_t *dec, uint8_t byte,
                                           oibar_v1_Packet *out)
{
    OIBAR_ASSERT(dec != NULL && out != NULL);
    oibar_rx_result_t r = OIBAR_RX_NONE;

    if (byte == 0x00u) {
        /* Delimiter: an empty frame is idle line; an oversize one was counted already. */
        if (!dec->skipping && dec->len > 0u) {
            r = frame_validate(dec, out);
        }
        dec->len = 0u;
        dec->skipping = false;
    } else if (!dec->skipping) {
        if (dec->len < sizeof(dec->buf)) {
            dec->buf[dec->len++] = byte;
        } else {
            r = OIBAR_RX_OVERSIZE; /* counted now, even if no 0x00 ever comes */
            dec->len = 0u;
            dec->skipping = true;
        }
    } else {
        /* skipping the rest of an oversize frame */
    }
    count_outcome(&dec->counters, r);
    return r;
}

oibar_rx_result_t oibar_frame_decoder_feed_buf(oibar_frame_decoder_t *dec,
                                               const uint8_t *data, size_t len,
                                               size_t *used, oibar_v1_Packet *out)
{
    OIBAR_ASSERT(data != NULL || len == 0u);
    OIBAR_ASSERT(used != NULL);
    oibar_rx_result_t r = OIBAR_RX_NONE;
    size_t i = 0u;
    while (i < len && r == OIBAR_RX_NONE) {
        r = oibar_frame_decoder_feed(dec, data[i], out);
        ++i;
    }
    *used = i;
    return r;
}

const oibar_frame_counters_t *oibar_frame_decoder_counters(const oibar_frame_decoder_t *dec)
{
    OIBAR_ASSERT(dec != NULL);
    return &dec->counters;
}
