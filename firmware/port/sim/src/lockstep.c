/* Lockstep message codec: packed little-endian, independent of the host's
 * struct layout and endianness (see oibar/sim_lockstep.h). */
#include "oibar/sim_lockstep.h"

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)((v >> 24) & 0xFFu);
}

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
}

static uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static uint16_t get_u16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

size_t sim_ls_encode_plant(const sim_ls_plant_t *m, uint8_t *buf, size_t cap)
{
    if (cap < SIM_LS_PLANT_BYTES) {
        return 0u;
    }
    const uint32_t w[8] = { m->magic, m->version, m->frame, m->advance_ms,
                            m->flags, m->di_bits, m->adc_fail_bits, m->uart_rx_bytes };
    for (unsigned i = 0; i < 8u; i++) {
        put_u32(&buf[4u * i], w[i]);
    }
    for (unsigned i = 0; i < SIM_LS_ADC_SLOTS; i++) {
        put_u16(&buf[32u + 2u * i], m->adc_counts[i]);
    }
    return SIM_LS_PLANT_BYTES;
}

bool sim_ls_decode_plant(const uint8_t *buf, size_t len, sim_ls_plant_t *m)
{
    if (len != SIM_LS_PLANT_BYTES) {
        return false;
    }
    m->magic = get_u32(&buf[0]);
    m->version = get_u32(&buf[4]);
    m->frame = get_u32(&buf[8]);
    m->advance_ms = get_u32(&buf[12]);
    m->flags = get_u32(&buf[16]);
    m->di_bits = get_u32(&buf[20]);
    m->adc_fail_bits = get_u32(&buf[24]);
    m->uart_rx_bytes = get_u32(&buf[28]);
    for (unsigned i = 0; i < SIM_LS_ADC_SLOTS; i++) {
        m->adc_counts[i] = get_u16(&buf[32u + 2u * i]);
    }
    return true;
}

size_t sim_ls_encode_mcu(const sim_ls_mcu_t *m, uint8_t *buf, size_t cap)
{
    if (cap < SIM_LS_MCU_BYTES) {
        return 0u;
    }
    const uint32_t w[21] = {
        m->magic, m->version, m->frame, m->status, m->expected_frame,
        m->sim_time_ms, m->uptime_ms, m->do_bits, m->do_any_bits, m->steps_fwd,
        m->steps_rev, m->steps_total, m->uart_tx_bytes, m->uart_rx_pending, m->resets,
        m->reset_cause, m->watchdog_kicks, m->flags, m->app_state, m->valve_violation_ms, m->fault_flags,
    };
    for (unsigned i = 0; i < 21u; i++) {
        put_u32(&buf[4u * i], w[i]);
    }
    return SIM_LS_MCU_BYTES;
}

bool sim_ls_decode_mcu(const uint8_t *buf, size_t len, sim_ls_mcu_t *m)
{
    if (len != SIM_LS_MCU_BYTES) {
        return false;
    }
    uint32_t w[21];
    for (unsigned i = 0; i < 21u; i++) {
        w[i] = get_u32(&buf[4u * i]);
    }
    m->magic = w[0];
    m->version = w[1];
    m->frame = w[2];
    m->status = w[3];
    m->expected_frame = w[4];
    m->sim_time_ms = w[5];
    m->uptime_ms = w[6];
    m->do_bits = w[7];
    m->do_any_bits = w[8];
    m->steps_fwd = w[9];
    m->steps_rev = w[10];
    m->steps_total = w[11];
    m->uart_tx_bytes = w[12];
    m->uart_rx_pending = w[13];
    m->resets = w[14];
    m->reset_cause = w[15];
    m->watchdog_kicks = w[16];
    m->flags = w[17];
    m->app_state = w[18];
    m->valve_violation_ms = w[19];
    m->fault_flags = w[20];
    return true;
}
