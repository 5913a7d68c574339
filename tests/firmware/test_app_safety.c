/* SPEC section 3: one test per named safety rule (oibar/app_safety.h). */
#include <stdio.h>
#include <string.h>
#include "oibar/drv_pressure.h"

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "oibar/app_fsm.h"
#include "oibar/app_link.h"
#include "oibar/app_params.h"
#include "oibar/app_safety.h"
#include "oibar/drv_inputs.h"
#include "oibar/drv_pressure.h"
#include "oibar/drv_valves.h"
#include "oibar/frame.h"
#include "oibar/link.h"
#include "unity.h"

void setUp(void) {}
void tearDown(void) {}

static void test_SAFETY_RULE_SAFE_START(void)
{
    const hal_reset_cause_t causes[] = { HAL_RESET_POWER_ON, HAL_RESET_WATCHDOG,
                                         HAL_RESET_BROWNOUT, HAL_RESET_LOCKUP };
    for (unsigned i = 0; i < 4; i++) {
        fake_hal_reset();
        /* Outputs left energised by whatever ran before the reset. */
        for (unsigned o = 0; o < HAL_DO_COUNT; o++) {
            hal_do_write((hal_do_t)o, true);
        }
        fake_hal_set_reset_cause(causes[i]);
        oibar_app_init();
        for (unsigned o = 0; o < HAL_DO_COUNT; o++) {
            TEST_ASSERT_FALSE(fake_hal_do((hal_do_t)o));
        }
        TEST_ASSERT_EQUAL(oibar_v1_STATE_BOOT, oibar_app_state());
    }
    /* A restart with the mechanism docked is neither idle nor safed by
     * itself: it waits in FAULT (SAFETY_RULE_NO_MOTION_AFTER_RESET). */
    fake_hal_reset();
    fake_plant_enable(true);
    fake_plant_set_probe(true);
    fake_hal_advance_ms(200);
    oibar_app_init();
    fake_hal_set_main_loop(oibar_app_run_once);
    oibar_app_link_state(true);
    fake_hal_advance_ms(150);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
}

/* Any reset cause, mechanism away from home (probe latched, plane at full
 * mate): after the self test the firmware sits in FAULT and nothing moves,
 * with or without a host, until the host clears the fault. */
static void test_SAFETY_RULE_NO_MOTION_AFTER_RESET(void)
{
    const hal_reset_cause_t causes[] = { HAL_RESET_POWER_ON, HAL_RESET_PIN, HAL_RESET_SOFTWARE,
                                         HAL_RESET_BROWNOUT, HAL_RESET_UNKNOWN, HAL_RESET_WATCHDOG,
                                         HAL_RESET_LOCKUP };
    for (unsigned i = 0; i < sizeof causes / sizeof causes[0]; i++) {
        TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
        const float plane_mm = fake_plant_plane_mm();
        /* The MCU restarts; the plant (the mechanism) stays where it is. */
        fake_hal_set_main_loop(NULL);
        fake_hal_set_reset_cause(causes[i]);
        oibar_app_init();
        fake_hal_set_main_loop(oibar_app_run_once);
        if (i % 2u == 0u) {
            oibar_app_link_state(true); /* with a host, or without one */
        }
        for (unsigned ms = 0; ms < 3000u; ms++) {
            fake_hal_advance_ms(1);
            TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
            TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
            TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_LATCH_ENABLE));
            TEST_ASSERT_FALSE(bench_any_valve_driven());
        }
        TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
        const bool wd = causes[i] == HAL_RESET_WATCHDOG || causes[i] == HAL_RESET_LOCKUP;
        TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(wd ? oibar_v1_FAULT_WATCHDOG_RESET
                                                                  : oibar_v1_FAULT_RESET_AWAY_FROM_HOME));
        TEST_ASSERT_EQUAL_FLOAT(plane_mm, fake_plant_plane_mm());
    }
    /* The host clears the fault: only then does the mechanism safe itself. */
    oibar_app_link_state(true);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_ABORTING, oibar_app_state());
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_SOFT_DOCKED, 8000));
    /* At home, an ordinary reset goes to IDLE as before. */
    bench_start();
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
}

static void test_SAFETY_RULE_VALVES_ONLY_WHEN_TRANSFERRING(void)
{
    for (unsigned st = 1; st <= 15; st++) {
        TEST_ASSERT_TRUE(bench_goto((oibar_v1_State)st));
        bool open_ok = oibar_valves_open_both();
        TEST_ASSERT_EQUAL(st == oibar_v1_STATE_TRANSFERRING, open_ok);
        TEST_ASSERT_EQUAL(st == oibar_v1_STATE_TRANSFERRING, bench_any_valve_driven());
    }
}

/* SAFETY_RULE_VALVE_OPEN_ATOMIC: a fault raised (by an interrupt) and not
 * yet taken by the main loop blocks the interlock like a latched one. */
static void test_SAFETY_RULE_VALVE_OPEN_ATOMIC_pending_fault_blocks_interlock(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_TRUE(oibar_safety_valves_permitted());
    oibar_fault_raise(oibar_v1_FAULT_PRESSURE_SENSOR_RATE);
    TEST_ASSERT_FALSE(oibar_safety_valves_permitted());
    TEST_ASSERT_TRUE((oibar_safety_valve_blockers() &
                      OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_NO_FAULT)) != 0u);
    TEST_ASSERT_FALSE(oibar_valves_open_both());
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

static void test_SAFETY_RULE_VALVES_NEED_ARM_THEN_START(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    /* Start without arm: refused, valves closed. */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_INVALID_IN_STATE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    /* Arm alone opens nothing. */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0));
    fake_hal_advance_ms(100);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_TRUE(oibar_safety_valve_blockers() & OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_ARM_THEN_START));
    /* Arming is one-shot: after a transfer the next needs a new arm. */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 400));
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_HARD_DOCKED, 5000));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_INVALID_IN_STATE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
}

static void lose_during_transfer(hal_di_t di, oibar_v1_FaultCode want)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    fake_plant_override_di(di, 0);
    fake_hal_advance_ms(11);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(want));
}

static void test_SAFETY_RULE_VALVES_NEED_CONNECTOR_MATED(void)
{
    lose_during_transfer(HAL_DI_CONNECTOR_MATED, oibar_v1_FAULT_CONNECTOR_LOST);
}

static void test_SAFETY_RULE_VALVES_NEED_LATCH_ENGAGED(void)
{
    lose_during_transfer(HAL_DI_LATCH_ENGAGED, oibar_v1_FAULT_LATCH_LOST);
}

static void test_SAFETY_RULE_VALVES_NEED_SENSORS_HEALTHY(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_hal_set_adc_fail(HAL_ADC_LINE, true); /* conversion fails: sensor lost */
    /* Shorter than the bound it is a glitch (SAFETY_RULE_ADC_GLITCH_BOUNDED);
     * the run that reaches the bound closes the valves and faults. */
    fake_hal_advance_ms(OIBAR_PRESSURE_BAD_RUN_MS - 1u);
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    fake_hal_advance_ms(1);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    fake_hal_advance_ms(1);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(oibar_v1_FAULT_PRESSURE_SENSOR_RANGE));
}

static void test_SAFETY_RULE_VALVES_NEED_HOST_LINK_ALIVE(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFER_ARMED));
    oibar_app_link_state(false);
    /* The loss is handled before the start: armed -> FAULT, start refused. */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_FAULT_ACTIVE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    oibar_app_link_state(false);
    TEST_ASSERT_FALSE(bench_any_valve_driven()); /* closed in the callback itself */
    fake_hal_advance_ms(1);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(oibar_v1_FAULT_HOST_LINK_LOSS));
}

static void test_SAFETY_RULE_VALVES_NEED_NO_FAULT(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_FAULT));
    TEST_ASSERT_TRUE(oibar_safety_valve_blockers() & OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_NO_FAULT));
    TEST_ASSERT_FALSE(oibar_valves_open_both());
}

/* The interlock itself, without the state machine: the main loop is held,
 * so the debounced input changes (the tick runs) but no event is ever
 * handled; oibar_safety_enforce() alone must close the valves and name the
 * lost precondition, whatever the state machine still believes. */
static void lost_precondition_interlock_only(hal_di_t di, oibar_v1_FaultCode want)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    fake_hal_set_main_loop(NULL); /* the state machine sees nothing from here */
    fake_plant_override_di(di, 0);
    fake_hal_advance_ms(oibar_param_u32(PARAM_DEBOUNCE_MS) + 5u);
    TEST_ASSERT_FALSE(oibar_input(di));          /* the firmware's view has changed */
    TEST_ASSERT_TRUE(bench_any_valve_driven());  /* nobody acted on it yet */
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFERRING, oibar_fsm_state());
    TEST_ASSERT_NOT_EQUAL(0u, oibar_safety_valve_blockers());
    oibar_safety_enforce();
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_SV_VALVE));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_TV_VALVE));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_TRANSFERRING, oibar_fsm_state()); /* not the FSM's doing */
    TEST_ASSERT_EQUAL(want, oibar_fault_take_pending());
    fake_hal_set_main_loop(oibar_app_run_once);
}

static void test_SAFETY_RULE_LOST_PRECONDITION_CLOSES_VALVES(void)
{
    lost_precondition_interlock_only(HAL_DI_CONNECTOR_MATED, oibar_v1_FAULT_CONNECTOR_LOST);
    lost_precondition_interlock_only(HAL_DI_LATCH_ENGAGED, oibar_v1_FAULT_LATCH_LOST);
}

static void test_SAFETY_RULE_FAULT_CLOSES_VALVES_AND_REPORTS(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    oibar_fault_raise(oibar_v1_FAULT_OVERPRESSURE);
    TEST_ASSERT_FALSE(bench_any_valve_driven()); /* at the raise, from any context */
    fake_hal_advance_ms(1);
    oibar_v1_Event ev;
    bool reported = false;
    while (oibar_app_next_event(&ev)) {
        reported = reported || (ev.id == oibar_v1_EVT_FAULT && ev.fault == oibar_v1_FAULT_OVERPRESSURE);
    }
    TEST_ASSERT_TRUE(reported);
}

static void test_SAFETY_RULE_FAULT_NEEDS_EXPLICIT_CLEAR(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_FAULT));
    fake_hal_advance_ms(60000);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_FAULT_ACTIVE, oibar_app_command(oibar_v1_CMD_APPROACH_ARM, 0));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_CLEAR_FAULT, 0));
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_IDLE, 3000));
}

static void test_SAFETY_RULE_INVALID_COMMAND_CHANGES_NOTHING(void)
{
    /* Exhaustively in test_app_commands; here the telemetry view. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_SOFT_DOCKED));
    oibar_v1_Telemetry a, b;
    memset(&a, 0, sizeof a);
    memset(&b, 0, sizeof b);
    oibar_app_fill_telemetry(&a);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_INVALID_IN_STATE, oibar_app_command(oibar_v1_CMD_START_TRANSFER, 1500));
    oibar_app_fill_telemetry(&b);
    TEST_ASSERT_EQUAL_MEMORY(&a, &b, sizeof a);
}

/* --- the application behind the real link layer (malformed frames) --- */
static oibar_link_t s_link;
static size_t s_tx_bytes;

static bool link_port_send(void *ctx, const uint8_t *bytes, size_t len)
{
    (void)ctx;
    (void)bytes;
    s_tx_bytes += len;
    return true;
}

static void link_main_loop(void) { oibar_app_link_run_once(&s_link); }

static size_t encode_command(uint32_t seq, oibar_v1_CommandOpcode op, uint8_t *wire, size_t cap)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.seq = seq;
    p.which_body = oibar_v1_Packet_command_tag;
    p.body.command.opcode = op;
    size_t n = oibar_frame_encode(&p, wire, cap);
    TEST_ASSERT_TRUE(n > 4u);
    return n;
}

static void inject(const uint8_t *wire, size_t n)
{
    for (size_t i = 0; i < n; i++) {
        oibar_link_rx_isr(&s_link, wire[i]);
    }
    fake_hal_advance_ms(2);
}

static void test_SAFETY_RULE_MALFORMED_FRAME_DROPPED(void)
{
    fake_hal_reset();
    fake_plant_enable(true);
    fake_hal_advance_ms(1);
    oibar_app_init();
    oibar_link_config_t cfg;
    oibar_link_config_defaults(&cfg);
    oibar_link_port_t port = { link_port_send, NULL };
    oibar_link_init(&s_link, &cfg, &port, oibar_app_link_callbacks());
    fake_hal_set_main_loop(link_main_loop);
    fake_hal_advance_ms(200);
    oibar_v1_Packet hs = oibar_v1_Packet_init_zero;
    hs.seq = 1;
    hs.which_body = oibar_v1_Packet_handshake_tag;
    hs.body.handshake.protocol_version = oibar_v1_Protocol_PROTOCOL_VERSION;
    uint8_t wire[OIBAR_FRAME_MAX_WIRE_BYTES];
    size_t n = oibar_frame_encode(&hs, wire, sizeof wire);
    inject(wire, n);
    TEST_ASSERT_TRUE(oibar_app_host_link_alive());
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());

    oibar_v1_LinkCounters c0, c1;
    oibar_link_get_counters(&s_link, &c0);
    /* 1. A CMD_APPROACH_ARM frame with one payload byte corrupted (CRC). */
    n = encode_command(2, oibar_v1_CMD_APPROACH_ARM, wire, sizeof wire);
    uint8_t bad[OIBAR_FRAME_MAX_WIRE_BYTES];
    memcpy(bad, wire, n);
    bad[n / 2u] = (uint8_t)(bad[n / 2u] ^ 0x10u);
    if (bad[n / 2u] == 0u) {
        bad[n / 2u] = 0x5Au;
    }
    inject(bad, n);
    /* 2. The same frame cut short (delimiter after half of it). */
    memcpy(bad, wire, n / 2u);
    bad[n / 2u] = 0x00;
    inject(bad, n / 2u + 1u);
    /* 3. Line noise: bytes that are no COBS frame at all. */
    const uint8_t noise[] = { 0x01, 0x01, 0x01, 0x00, 0xFF, 0x00 };
    inject(noise, sizeof noise);
    oibar_link_get_counters(&s_link, &c1);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state()); /* nothing executed */
    TEST_ASSERT_EQUAL_UINT32(c0.rx_packets, c1.rx_packets);
    const uint32_t dropped0 = c0.rx_crc_errors + c0.rx_framing_errors + c0.rx_bad_header +
                              c0.rx_decode_errors;
    const uint32_t dropped1 = c1.rx_crc_errors + c1.rx_framing_errors + c1.rx_bad_header +
                              c1.rx_decode_errors;
    TEST_ASSERT_TRUE_MESSAGE(dropped1 >= dropped0 + 3u, "malformed frames not counted");
    TEST_ASSERT_TRUE(oibar_app_host_link_alive()); /* dropped, not fatal */
    /* The intact frame is executed: the drops above were the frames' fault. */
    inject(wire, n);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_APPROACH_READY, oibar_app_state());
    /* An opcode the application does not know is refused without effect. */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_UNKNOWN_OPCODE, oibar_app_command((oibar_v1_CommandOpcode)77, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_APPROACH_READY, oibar_app_state());
}

static void test_SAFETY_RULE_WATCHDOG_NEEDS_BOTH_LOOPS(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_IDLE));
    uint32_t k0 = fake_hal_watchdog_kicks();
    fake_hal_advance_ms(100);
    TEST_ASSERT_EQUAL_UINT32(k0 + 100u, fake_hal_watchdog_kicks());
    /* Control tick dead, main loop running: no kick. */
    fake_hal_set_tick_enabled(false);
    k0 = fake_hal_watchdog_kicks();
    fake_hal_advance_ms(100);
    TEST_ASSERT_EQUAL_UINT32(k0, fake_hal_watchdog_kicks());
    /* Tick alive, main loop stuck: no kick. */
    fake_hal_set_tick_enabled(true);
    fake_hal_set_main_loop(NULL);
    fake_hal_advance_ms(100);
    TEST_ASSERT_EQUAL_UINT32(k0, fake_hal_watchdog_kicks());
    /* Both back: kicks resume. */
    fake_hal_set_main_loop(oibar_app_run_once);
    fake_hal_advance_ms(10);
    TEST_ASSERT_TRUE(fake_hal_watchdog_kicks() > k0);
}

static void test_SAFETY_RULE_CONTACT_FORCE_LIMIT(void)
{
    TEST_ASSERT_EQUAL_FLOAT(30.0f, oibar_safety_force_limit_n(oibar_v1_STATE_SOFT_DOCKED));
    TEST_ASSERT_EQUAL_FLOAT(30.0f, oibar_safety_force_limit_n(oibar_v1_STATE_RECEPTION));
    TEST_ASSERT_EQUAL_FLOAT(60.0f, oibar_safety_force_limit_n(oibar_v1_STATE_HARD_DOCKING));
    TEST_ASSERT_EQUAL_FLOAT(60.0f, oibar_safety_force_limit_n(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_plant_set_force_n(70.0f);
    fake_hal_advance_ms(12);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(oibar_v1_FAULT_CONTACT_OVERLOAD));
}

/* In `st`, with `valve` stuck open and sensed so (not yet a fault), `cmd` is refused and the
 * plane stays still; with the valve closed again it is accepted and leads to `next`. */
static void refused_while_a_valve_reads_open(oibar_v1_State st, unsigned valve,
                                             oibar_v1_CommandOpcode cmd, oibar_v1_State next)
{
    TEST_ASSERT_TRUE(bench_goto(st));
    fake_plant_set_valve_mode(valve, FAKE_VALVE_STUCK_OPEN);
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 20u); /* sensed open, not yet a fault */
    TEST_ASSERT_EQUAL(st, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED, oibar_app_command(cmd, 0));
    TEST_ASSERT_EQUAL(st, oibar_app_state());
    fake_hal_advance_ms(1);
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    /* Valve closed again: the command goes ahead. */
    fake_plant_set_valve_mode(valve, FAKE_VALVE_OK);
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 20u);
    TEST_ASSERT_EQUAL(st, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(cmd, 0));
    TEST_ASSERT_EQUAL(next, oibar_app_state());
}

static void test_SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN(void)
{
    /* A target valve stuck open right after a transfer: separating now would pull the
     * couplings apart with fluid in the line, so the command is refused and nothing moves. */
    refused_while_a_valve_reads_open(oibar_v1_STATE_HARD_DOCKED, 1, oibar_v1_CMD_SEPARATE,
                                     oibar_v1_STATE_UNMATING);
}

/* Found by the property test (seed 2574239216): a valve failed open while the
 * plane was still extending (HARD_DOCKING, 34.7 mm, inside the coupling travel)
 * and CMD_SEPARATE, unguarded there, drove the plane back out through the
 * venting zone. Every way into UNMATING now needs [valves_closed]. */
static void test_SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN_every_way_in(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKING));
    for (unsigned ms = 0; ms < 6000u && fake_plant_plane_mm() < 32.0f; ms += 5u) {
        fake_hal_advance_ms(5);
    }
    TEST_ASSERT_TRUE(fake_plant_plane_mm() >= 32.0f);
    fake_plant_set_valve_mode(0, FAKE_VALVE_STUCK_OPEN);
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 20u); /* sensed open, not yet a fault */
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKING, oibar_app_state());
    const float at_mm = fake_plant_plane_mm();
    TEST_ASSERT_TRUE(at_mm > 30.0f && at_mm < FAKE_PLANT_TRAVEL_MM - 1.0f);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED, oibar_app_command(oibar_v1_CMD_SEPARATE, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKING, oibar_app_state());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    fake_hal_advance_ms(1);
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    TEST_ASSERT_TRUE(fake_plant_plane_mm() >= at_mm); /* never moved back */
    /* The valve monitor then calls it a fault; FAULT re-seats the plane. */
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_FAULT, 2000));
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(oibar_v1_FAULT_VALVE_MISMATCH));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    fake_plant_set_valve_mode(0, FAKE_VALVE_OK);

    /* Soft docked (plane home) with a valve reading open: refused the same way. */
    refused_while_a_valve_reads_open(oibar_v1_STATE_SOFT_DOCKED, 1, oibar_v1_CMD_SEPARATE,
                                     oibar_v1_STATE_UNMATING);
}

/* The other direction: CMD_HARD_DOCK would carry the couplings into their venting travel with a
 * valve that reads open (before the valve monitor calls it a fault), so it is refused. */
static void test_SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN_no_mating_with_valve_open(void)
{
    refused_while_a_valve_reads_open(oibar_v1_STATE_SOFT_DOCKED, 0, oibar_v1_CMD_HARD_DOCK,
                                     oibar_v1_STATE_HARD_DOCKING);
}

static void test_SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN(void)
{
    /* Unmating: the plane is on its way out when a valve fails open. The valve monitor
     * faults; the FAULT entry must drive the plane back to full mate, not stop it halfway. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 50u);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_SEPARATE, 0));
    fake_hal_advance_ms(300);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_UNMATING, oibar_app_state());
    const float half_mm = fake_plant_plane_mm();
    TEST_ASSERT_TRUE(half_mm > 1.0f && half_mm < FAKE_PLANT_TRAVEL_MM - 1.0f);
    fake_plant_set_valve_mode(0, FAKE_VALVE_STUCK_OPEN);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_FAULT, 2000));
    TEST_ASSERT_TRUE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    fake_hal_advance_ms(6000);
    TEST_ASSERT_TRUE(fake_plant_plane_mm() > FAKE_PLANT_TRAVEL_MM - 0.5f); /* re-seated */
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));                  /* and stopped */
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());

    /* A valve failing open while the plane is still short of the couplings (hard docking
     * just started): moving on would cross the venting zone, so the plane stops. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKING));
    fake_hal_advance_ms(300);
    TEST_ASSERT_TRUE(fake_plant_plane_mm() < 20.0f);
    fake_plant_set_valve_mode(0, FAKE_VALVE_STUCK_OPEN);
    TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_FAULT, 2000));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    fake_plant_set_valve_mode(0, FAKE_VALVE_OK);

    /* The same fault with the valves healthy leaves the plane still, as before. */
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 50u);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_SEPARATE, 0));
    fake_hal_advance_ms(300);
    oibar_fault_raise(oibar_v1_FAULT_LATCH_STALL);
    fake_hal_advance_ms(5);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_EXTEND));
    TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
}

/* Found by the property test: the end switch alone said "mated" (stuck) while
 * the plane stood at 29 mm, and the valves opened. The position sensor must
 * agree, at arming and all through the transfer. */
static void test_SAFETY_RULE_VALVES_NEED_PLANE_MATED(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    TEST_ASSERT_TRUE(bench_any_valve_driven());
    fake_plant_override_adc(HAL_ADC_PLANE_POS, (int)(29.0f / 0.01221f));
    fake_hal_advance_ms(3);
    TEST_ASSERT_TRUE(hal_di_read(HAL_DI_PLANE_EXTENDED)); /* the switch still says mated */
    TEST_ASSERT_FALSE(bench_any_valve_driven());
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(oibar_v1_FAULT_PLANE_POSITION));
    TEST_ASSERT_TRUE(oibar_safety_valve_blockers() &
                     OIBAR_SAFETY_BIT(SAFETY_RULE_VALVES_NEED_PLANE_MATED));
    TEST_ASSERT_FALSE(oibar_valves_open_both());
}

static bool any_valve_reads_open(void)
{
    return hal_di_read(HAL_DI_SV_VALVE_OPEN) || hal_di_read(HAL_DI_TV_VALVE_OPEN);
}

/* Issue 16, item 1: ABORT from the mated states with valves slower than the
 * plane. Until both valves read closed, the plane must not be driven back. */
static void test_abort_holds_the_plane_until_the_valves_read_closed(void)
{
    const oibar_v1_State from[] = { oibar_v1_STATE_TRANSFERRING, oibar_v1_STATE_TRANSFER_ARMED,
                                    oibar_v1_STATE_HARD_DOCKED };
    for (unsigned i = 0; i < 3u; i++) {
        TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
        fake_plant_set_valve_stroke_ms(150u); /* slow, but within valve_mismatch_ms */
        if (from[i] != oibar_v1_STATE_TRANSFERRING) {
            /* STOP then ARM again: the valves are still travelling shut. */
            TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_STOP_TRANSFER, 0));
        }
        fake_hal_advance_ms(20);
        TEST_ASSERT_TRUE(any_valve_reads_open());
        TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ABORT, 0));
        TEST_ASSERT_EQUAL(oibar_v1_STATE_ABORTING, oibar_app_state());
        unsigned held_ms = 0;
        while (any_valve_reads_open()) {
            TEST_ASSERT_FALSE_MESSAGE(fake_hal_do(HAL_DO_PLANE_RETRACT), oibar_fsm_state_name(from[i]));
            TEST_ASSERT_TRUE(fake_plant_plane_mm() > FAKE_PLANT_TRAVEL_MM - 0.1f);
            fake_hal_advance_ms(1);
            TEST_ASSERT_TRUE(++held_ms < 400u);
        }
        /* Valves read closed: the abort goes on and safes the mechanism. */
        TEST_ASSERT_TRUE(bench_wait_state(oibar_v1_STATE_SOFT_DOCKED, 8000));
        TEST_ASSERT_EQUAL_UINT32(0u, oibar_fault_flags());
    }
}

/* A valve that never reads closed: FAULT after valve_mismatch_ms, the plane
 * still at full mate (where the couplings seal) and never driven back. */
static void test_abort_with_a_valve_stuck_open_faults_with_the_plane_held(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_TRANSFERRING));
    fake_plant_set_valve_mode(1, FAKE_VALVE_STUCK_OPEN);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ABORT, 0));
    const uint32_t limit_ms = oibar_param_u32(PARAM_VALVE_MISMATCH_MS);
    for (uint32_t ms = 0; ms < limit_ms + 3000u; ms++) {
        fake_hal_advance_ms(1);
        TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
        if (ms > limit_ms + 5u) {
            TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
        }
    }
    TEST_ASSERT_TRUE(oibar_fault_flags() & OIBAR_FAULT_BIT(oibar_v1_FAULT_VALVE_MISMATCH));
    TEST_ASSERT_TRUE(fake_plant_plane_mm() > FAKE_PLANT_TRAVEL_MM - 0.1f);
    TEST_ASSERT_FALSE(bench_any_valve_driven());
}

/* Whatever the state machine commanded: a valve that starts reading open
 * while the plane is leaving the coupling travel stops the plane now, not
 * after the valve monitor's valve_mismatch_ms. */
static void test_plane_stops_at_once_when_a_valve_reads_open_while_unmating(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    fake_hal_advance_ms(FAKE_PLANT_VALVE_STROKE_MS + 50u);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_SEPARATE, 0));
    fake_hal_advance_ms(100);
    TEST_ASSERT_TRUE(fake_hal_do(HAL_DO_PLANE_RETRACT));
    fake_plant_set_valve_mode(0, FAKE_VALVE_STUCK_OPEN);
    unsigned open_ms = 0;
    for (unsigned ms = 0; ms < 100u; ms++) {
        fake_hal_advance_ms(1);
        open_ms = any_valve_reads_open() ? open_ms + 1u : 0u;
        if (open_ms > oibar_param_u32(PARAM_DEBOUNCE_MS) + 2u) {
            TEST_ASSERT_FALSE(fake_hal_do(HAL_DO_PLANE_RETRACT));
        }
    }
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
}

/* Move an ADC reading slowly (1 count/ms, under the rate check). */
static void ramp_adc(hal_adc_t ch, int to)
{
    uint16_t c = 0;
    TEST_ASSERT_TRUE(hal_adc_read(ch, &c));
    int v = (int)c;
    while (v != to) {
        v += (to > v) ? 1 : -1;
        fake_plant_override_adc(ch, v);
        fake_hal_advance_ms(1);
    }
    fake_hal_advance_ms(20);
}

/* Issue 16, item 2: ARM_TRANSFER refuses, with a reason, when the sensors
 * disagree with the physics of a closed line or one is unhealthy. */
static void test_SAFETY_RULE_PREARM_CHECKS(void)
{
    TEST_ASSERT_TRUE(bench_goto(oibar_v1_STATE_HARD_DOCKED));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_safety_prearm());
    /* Line reads far above both tanks (2000 / 200 kPa): a calibration error. */
    ramp_adc(HAL_ADC_LINE, 410 + 2512); /* about 2300 kPa, below the trip */
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PREARM_IMPLAUSIBLE, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    /* A tank reads below zero (offset wrong). */
    ramp_adc(HAL_ADC_LINE, 410 + 109); /* back to the plant's 100 kPa */
    fake_plant_clear_overrides();
    ramp_adc(HAL_ADC_TV_TANK, 250); /* valid counts, about -147 kPa */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PREARM_IMPLAUSIBLE, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0));
    /* The plane's end switch says extended, its position sensor 29 mm. */
    fake_plant_override_adc(HAL_ADC_PLANE_POS, (int)(29.0f / 0.01221f));
    fake_hal_advance_ms(3);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PREARM_IMPLAUSIBLE, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0));
    fake_plant_override_adc(HAL_ADC_PLANE_POS, -1);
    fake_hal_advance_ms(3);
    /* A few ms out of the valid window are a glitch, not a broken sensor
     * (SAFETY_RULE_ADC_GLITCH_BOUNDED): the last good value is held, and that
     * one (about -147 kPa) is still refused as implausible. */
    fake_plant_override_adc(HAL_ADC_TV_TANK, 100);
    fake_hal_advance_ms(3);
    TEST_ASSERT_TRUE(oibar_pressure_sensor_ok(OIBAR_PSENS_TV));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PREARM_IMPLAUSIBLE, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0));
    fake_plant_override_adc(HAL_ADC_TV_TANK, 250);
    fake_hal_advance_ms(20);
    /* Consistent again: armed. */
    ramp_adc(HAL_ADC_TV_TANK, 410 + 218); /* the plant's 200 kPa */
    fake_plant_clear_overrides();
    fake_hal_advance_ms(20);
    TEST_ASSERT_EQUAL(oibar_v1_STATE_HARD_DOCKED, oibar_app_state());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_ARM_TRANSFER, 0));
    /* Out of its window for longer than the bad-run bound, the sensor is
     * unhealthy and the pre-arm check names it as a sensor (its range fault
     * also takes the app to FAULT, which refuses ARM_TRANSFER by state). */
    fake_plant_override_adc(HAL_ADC_TV_TANK, 100);
    fake_hal_advance_ms(OIBAR_PRESSURE_BAD_RUN_MS + 5u);
    TEST_ASSERT_FALSE(oibar_pressure_sensor_ok(OIBAR_PSENS_TV));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PREARM_SENSOR, oibar_safety_prearm());
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
    fake_plant_clear_overrides();
}

/* Issue 16, item 2: no ParamSet in bounds switches a protection off. */
static void test_SAFETY_RULE_LIMITS_NOT_TUNABLE(void)
{
    bench_start();
    const struct {
        oibar_param_id_t id;
        float value;
    } attacks[] = {
        { PARAM_SOFT_DOCK_MAX_FORCE_N, 0.0f },      /* 0 read as "not monitored" */
        { PARAM_HARD_DOCK_MAX_FORCE_N, 0.0f },
        { PARAM_OVERPRESSURE_KPA, 3000.0f },        /* trip at the tank rating */
        { PARAM_OVERPRESSURE_KPA, 2800.0f },
        { PARAM_PRESS_TV_KPA_PER_COUNT, 0.1f },     /* gain hides an over-pressure */
        { PARAM_PRESS_SV_KPA_PER_COUNT, 0.5f },
        { PARAM_PRESS_LINE_KPA_PER_COUNT, 10.0f },
        { PARAM_PRESS_ZERO_COUNTS, 1000.0f },       /* offset hides 540 kPa */
        { PARAM_PRESS_VALID_MIN_COUNTS, 0.0f },     /* hides an open wire */
        { PARAM_PRESS_VALID_MAX_COUNTS, 4095.0f },  /* hides a short */
        { PARAM_PRESS_MAX_RATE_KPA_S, 100000.0f },
        { PARAM_FORCE_N_PER_COUNT, 0.001f },        /* gain hides an overload */
        { PARAM_VALVE_MISMATCH_MS, 2000.0f },
        { PARAM_PLANE_COUPLING_MM, 40.0f },         /* no half-mated zone left */
        { PARAM_NAV_MIN_CONFIDENCE, 0.0f },
        { PARAM_PLANE_MM_PER_COUNT, 0.02f },        /* a short plane reads as mated */
    };
    for (unsigned i = 0; i < sizeof attacks / sizeof attacks[0]; i++) {
        const oibar_param_def_t *d = oibar_param_def((uint32_t)attacks[i].id);
        oibar_v1_ParamValue out;
        oibar_app_param_set((uint32_t)attacks[i].id, attacks[i].value, &out);
        TEST_ASSERT_EQUAL_MESSAGE(oibar_v1_NACK_PARAM_OUT_OF_BOUNDS, out.reason, d->name);
        TEST_ASSERT_EQUAL_FLOAT_MESSAGE(d->default_value, out.value, d->name);
    }
    /* Every bound keeps its margin: the loosest value in bounds still trips
     * below the rating, and the trip point is inside every sensor's valid
     * window (the sensor does not saturate as "out of range" first). */
    const oibar_param_def_t *op = oibar_param_def(PARAM_OVERPRESSURE_KPA);
    TEST_ASSERT_TRUE(op->max <= 0.9f * OIBAR_TANK_RATING_KPA);
    const oibar_param_def_t *g = oibar_param_def(PARAM_PRESS_TV_KPA_PER_COUNT);
    const oibar_param_def_t *z = oibar_param_def(PARAM_PRESS_ZERO_COUNTS);
    const oibar_param_def_t *mx = oibar_param_def(PARAM_PRESS_VALID_MAX_COUNTS);
    TEST_ASSERT_TRUE(z->max + op->max / g->min < mx->min);
    TEST_ASSERT_TRUE(oibar_param_def(PARAM_SOFT_DOCK_MAX_FORCE_N)->min > 0.0f);
    TEST_ASSERT_TRUE(oibar_param_def(PARAM_HARD_DOCK_MAX_FORCE_N)->min > 0.0f);
}

static void test_rule_names_are_the_identifiers(void)
{
    TEST_ASSERT_EQUAL_STRING("SAFETY_RULE_SAFE_START", oibar_safety_rule_name(SAFETY_RULE_SAFE_START));
    TEST_ASSERT_EQUAL_STRING("SAFETY_RULE_CONTACT_FORCE_LIMIT", oibar_safety_rule_name(SAFETY_RULE_CONTACT_FORCE_LIMIT));
    for (unsigned r = 0; r < SAFETY_RULE_COUNT; r++) {
        TEST_ASSERT_EQUAL_INT(0, strncmp("SAFETY_RULE_", oibar_safety_rule_name((oibar_safety_rule_t)r), 12));
    }
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_SAFETY_RULE_SAFE_START);
    RUN_TEST(test_SAFETY_RULE_VALVES_ONLY_WHEN_TRANSFERRING);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_ARM_THEN_START);
    RUN_TEST(test_SAFETY_RULE_VALVE_OPEN_ATOMIC_pending_fault_blocks_interlock);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_CONNECTOR_MATED);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_LATCH_ENGAGED);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_SENSORS_HEALTHY);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_HOST_LINK_ALIVE);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_NO_FAULT);
    RUN_TEST(test_SAFETY_RULE_LOST_PRECONDITION_CLOSES_VALVES);
    RUN_TEST(test_SAFETY_RULE_FAULT_CLOSES_VALVES_AND_REPORTS);
    RUN_TEST(test_SAFETY_RULE_FAULT_NEEDS_EXPLICIT_CLEAR);
    RUN_TEST(test_SAFETY_RULE_INVALID_COMMAND_CHANGES_NOTHING);
    RUN_TEST(test_SAFETY_RULE_MALFORMED_FRAME_DROPPED);
    RUN_TEST(test_SAFETY_RULE_WATCHDOG_NEEDS_BOTH_LOOPS);
    RUN_TEST(test_SAFETY_RULE_CONTACT_FORCE_LIMIT);
    RUN_TEST(test_SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN);
    RUN_TEST(test_SAFETY_RULE_NO_UNMATE_WITH_VALVE_OPEN_every_way_in);
    RUN_TEST(test_SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN_no_mating_with_valve_open);
    RUN_TEST(test_SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN);
    RUN_TEST(test_SAFETY_RULE_NO_MOTION_AFTER_RESET);
    RUN_TEST(test_abort_holds_the_plane_until_the_valves_read_closed);
    RUN_TEST(test_abort_with_a_valve_stuck_open_faults_with_the_plane_held);
    RUN_TEST(test_plane_stops_at_once_when_a_valve_reads_open_while_unmating);
    RUN_TEST(test_SAFETY_RULE_PREARM_CHECKS);
    RUN_TEST(test_SAFETY_RULE_LIMITS_NOT_TUNABLE);
    RUN_TEST(test_SAFETY_RULE_VALVES_NEED_PLANE_MATED);
    RUN_TEST(test_rule_names_are_the_identifiers);
    return UNITY_END();
}
