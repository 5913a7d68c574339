/*
 * libFuzzer target: the firmware's message dispatcher, i.e. the link layer and the docking
 * application behind it, on the fake HAL with its plant model.
 *
 * The input is a little program of records, so that the fuzzer reaches deep states with valid
 * frames instead of spending its time on CRCs:
 *   0x00..0x3F  packet:  next byte L, then L bytes of protobuf Packet, framed correctly (header,
 *                        CRC-32C, COBS) and fed through the UART receive path;
 *   0x40..0x7F  time:    advance simulated time by (next byte + 1) * 4 ms;
 *   0x80..0xBF  raw:     next byte L, then L raw bytes fed as received (garbage, partial frames);
 *   0xC0..0xFF  plant:   next byte picks a hardware change (probe in/out, valve stuck, jams,
 *                        pressures, sensor failures).
 * Simulated time per input is capped at MAX_SIM_MS so that executions stay fast; deep states
 * are reached from the seeds (a nominal command walk) rather than by waiting.
 * The safety invariant is checked after every millisecond: a valve coil is energised only in
 * STATE_TRANSFERRING, and never while a fault is latched. Any violation aborts (a finding).
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "oibar/app_link.h"
#include "oibar/frame.h"
#include "oibar/link.h"

#define MAX_SIM_MS 15000u

static oibar_link_t s_link;
static uint32_t s_sim_ms;

static void advance(uint32_t ms) {
    if (s_sim_ms + ms > MAX_SIM_MS) {
        ms = MAX_SIM_MS - s_sim_ms;
    }
    s_sim_ms += ms;
    fake_hal_advance_ms(ms);
}

static bool port_send(void *ctx, const uint8_t *bytes, size_t len) {
    (void)ctx;
    (void)bytes;
    (void)len;
    return true; /* the host side is not modelled here: output is dropped */
}

static void main_loop(void) {
    oibar_app_link_run_once(&s_link);
    const bool valve_on = fake_hal_do(HAL_DO_SV_VALVE) || fake_hal_do(HAL_DO_TV_VALVE);
    if (valve_on && (oibar_app_state() != oibar_v1_STATE_TRANSFERRING || oibar_fault_flags() != 0u)) {
        abort();
    }
}

static void feed(const uint8_t *bytes, size_t len) {
    for (size_t i = 0; i < len; i++) {
        oibar_link_rx_isr(&s_link, bytes[i]);
    }
}

static void plant(uint8_t what) {
    switch (what % 12u) {
    case 0: fake_plant_set_probe(true); break; // PROBE_IN
    case 1: fake_plant_set_probe(false); break;
    case 2: fake_plant_set_valve_mode(what & 1u, FAKE_VALVE_STUCK_OPEN); break;
    case 3: fake_plant_set_valve_mode(what & 1u, FAKE_VALVE_STUCK_CLOSED); break;
    case 4: fake_plant_set_valve_mode(what & 1u, FAKE_VALVE_OK); break;
    case 5: fake_plant_set_plane_jam((what & 0x10u) != 0u); break;
    case 6: fake_plant_set_stepper_stall((what & 0x10u) != 0u); break;
    case 7: fake_plant_set_tanks_kpa(2000.0f + (float)what, (float)what * 8.0f); break;
    case 8: fake_plant_override_adc(HAL_ADC_LINE, (int)what * 16); break;
    case 9: fake_plant_override_di(HAL_DI_CONNECTOR_MATED, (int)(what & 1u)); break;
    case 10: fake_plant_clear_overrides(); break;
    default: fake_plant_set_force_n((float)what * 0.5f); break;
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
    bench_start(); /* fresh MCU: reset HAL and plant, init the application */
    oibar_link_config_t cfg;
    oibar_link_config_defaults(&cfg);
    const oibar_link_port_t port = {.ctx = NULL, .send = port_send};
    oibar_link_init(&s_link, &cfg, &port, oibar_app_link_callbacks());
    fake_hal_set_main_loop(main_loop);

    s_sim_ms = 0;
    size_t i = 0;
    while (i < size && s_sim_ms < MAX_SIM_MS) {
        const uint8_t op = data[i++];
        if (op < 0x40u || (op >= 0x80u && op < 0xC0u)) {
            if (i >= size) {
                break;
            }
            size_t len = data[i++];
            if (len > size - i) {
                len = size - i;
            }
            if (op < 0x40u) {
                uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
                size_t n = oibar_frame_encode_bytes(&data[i], len, wire, sizeof wire);
                feed(wire, n);
            } else {
                feed(&data[i], len);
            }
            i += len;
            advance(1);
        } else if (op < 0x80u) {
            uint32_t ms = (i < size ? (uint32_t)data[i++] + 1u : 1u) * 4u;
            advance(ms);
        } else {
            if (i < size) {
                plant(data[i++]);
            }
            advance(1);
        }
    }
    return 0;
}
