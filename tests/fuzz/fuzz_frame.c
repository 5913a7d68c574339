/*
 * libFuzzer target: the firmware's streaming frame decoder.
 *
 * Any byte stream goes in, byte by byte, as the UART receive path delivers it. Invariants:
 *  - nothing crashes, leaks or overflows (ASan + UBSan);
 *  - every frame the decoder accepts re-encodes to a frame that decodes to the same packet;
 *  - every frame-ending 0x00 yields at most one outcome and the counters add up to the
 *    number of outcomes seen.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "oibar/frame.h"

static void check(int ok) {
    if (!ok) {
        abort(); /* libFuzzer reports the input as a crash */
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
    static oibar_frame_decoder_t dec;
    oibar_frame_decoder_init(&dec, OIBAR_BODIES_ALL);
    uint32_t outcomes = 0;
    for (size_t i = 0; i < size; i++) {
        oibar_v1_Packet p;
        oibar_rx_result_t r = oibar_frame_decoder_feed(&dec, data[i], &p);
        if (r != OIBAR_RX_NONE) {
            outcomes++;
        }
        if (r != OIBAR_RX_PACKET) {
            continue;
        }
        uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
        size_t n = oibar_frame_encode(&p, wire, sizeof wire);
        check(n > 0 && n <= OIBAR_FRAME_MAX_WIRE_BYTES && wire[n - 1] == 0);
        static oibar_frame_decoder_t again;
        oibar_frame_decoder_init(&again, OIBAR_BODIES_ALL);
        oibar_v1_Packet q;
        oibar_rx_result_t r2 = OIBAR_RX_NONE;
        for (size_t k = 0; k < n; k++) {
            r2 = oibar_frame_decoder_feed(&again, wire[k], &q);
            check(k + 1 == n || r2 == OIBAR_RX_NONE);
        }
        check(r2 == OIBAR_RX_PACKET);
        uint8_t wire2[OIBAR_FRAME_MAX_WIRE_BYTES];
        size_t n2 = oibar_frame_encode(&q, wire2, sizeof wire2);
        check(n2 == n && memcmp(wire, wire2, n) == 0);
    }
    const oibar_frame_counters_t *c = oibar_frame_decoder_counters(&dec);
    check(c->rx_packets + c->rx_crc_errors + c->rx_framing_errors + c->rx_oversize +
              c->rx_bad_header + c->rx_decode_errors + c->rx_unknown_type ==
          outcomes);
    return 0;
}
