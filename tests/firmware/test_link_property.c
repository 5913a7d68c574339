/* Property test through the link layer (issue 16): the application behind
 * the real link, driven only by frames, as a host and an attacker on the wire
 * would. A random walk mixes a cooperative host's commands with replayed,
 * reordered, reused-seq and seq-0 requests, retransmissions after a lost
 * ack, a full UART queue, link drops, new sessions, garbage bytes and
 * plant faults. Whatever happens:
 *   - no valve is driven open unless the machine is TRANSFERRING with no
 *     blocker and no fault, the link is up, and the application accepted
 *     ARM_TRANSFER then START_TRANSFER, each from a fresh request;
 *   - no request that is not fresh (replayed, reordered, seq 0, a reused seq
 *     with another body, or a retransmission) reaches the application.
 *
 * Seed: fresh per run and printed; OIBAR_LINK_PROPERTY_SEED=<n> replays a
 * run. Steps: 100,000 by default (make test); OIBAR_LINK_PROPERTY_STEPS=<n>
 * for a long run (make property-long: 10 million). */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "oibar/app_link.h"
#include "oibar/app_safety.h"
#include "oibar/frame.h"
#include "oibar/link.h"
#include "unity.h"

#define DEFAULT_STEPS 100000u
#define HISTORY 32u
#define HEARTBEAT_MS 100u

typedef struct {
    uint8_t bytes[OIBAR_FRAME_MAX_WIRE_BYTES];
    size_t len;
    uint32_t seq;
    oibar_v1_Packet pkt;
} recorded_t;

static oibar_link_t s_link;
static oibar_link_app_t s_cb;
static uint32_t s_rng;
static uint32_t s_seed;

/* Host side. */
static uint32_t s_seq;            /* last seq sent in this session */
static recorded_t s_hist[HISTORY]; /* this session's requests, for replays */
static unsigned s_hist_n;
static bool s_host_alive;         /* heartbeats flowing */
static uint32_t s_next_hb_ms;
static unsigned s_phase;          /* 0, 1: ARM accepted, 2: START accepted after ARM */

/* What the MCU did. */
static uint32_t s_exec;           /* requests that reached the application */
static bool s_port_full;
static oibar_frame_decoder_t s_dec;
static bool s_ack_seen;
static uint32_t s_ack_seq;
static oibar_v1_Ack s_ack;
static bool s_pending_valid;      /* the fresh request awaiting its ack */
static oibar_v1_Packet s_pending;

static void host_accounts(const oibar_v1_Packet *p, const oibar_v1_Ack *ack);

/* Coverage. */
static uint32_t s_ms, s_open_ms, s_starts, s_replays, s_reorders, s_retransmits, s_sessions;

void setUp(void) {}
void tearDown(void) {}

static uint32_t rnd(void)
{
    s_rng ^= s_rng << 13;
    s_rng ^= s_rng >> 17;
    s_rng ^= s_rng << 5;
    return s_rng;
}

static uint32_t below(uint32_t n) { return rnd() % n; }

static bool port_send(void *ctx, const uint8_t *bytes, size_t len)
{
    (void)ctx;
    if (s_port_full) {
        return false;
    }
    oibar_v1_Packet p;
    for (size_t i = 0; i < len; i++) {
        if (oibar_frame_decoder_feed(&s_dec, bytes[i], &p) == OIBAR_RX_PACKET &&
            p.which_body == oibar_v1_Packet_ack_tag) {
            s_ack_seen = true;
            s_ack_seq = p.ack_seq;
            s_ack = p.body.ack;

        }
    }
    return true;
}

/* Every request the application sees must be the fresh one being sent; the
 * phase follows what it accepted (its ack may yet be lost on the wire). */
static void counting_on_command(void *ctx, const oibar_v1_Command *cmd, oibar_v1_Ack *out)
{
    char msg[96];
    snprintf(msg, sizeof msg, "seed %u ms %u: a command that is not fresh ran", (unsigned)s_seed,
             (unsigned)s_ms);
    TEST_ASSERT_TRUE_MESSAGE(s_pending_valid && s_pending.which_body == oibar_v1_Packet_command_tag &&
                                 s_pending.body.command.opcode == cmd->opcode,
                             msg);
    s_pending_valid = false; /* at most once */
    s_exec++;
    oibar_app_link_callbacks()->on_command(ctx, cmd, out);
    host_accounts(&s_pending, out);
}

static void counting_on_param_set(void *ctx, uint32_t id, float value, oibar_v1_ParamValue *out)
{
    TEST_ASSERT_TRUE_MESSAGE(s_pending_valid && s_pending.which_body == oibar_v1_Packet_param_set_tag,
                             "a ParamSet that is not fresh ran");
    s_pending_valid = false;
    s_exec++;
    oibar_app_link_callbacks()->on_param_set(ctx, id, value, out);
}

static void main_loop(void) { oibar_app_link_run_once(&s_link); }

/* --- invariant ---------------------------------------------------------- */

static void check_invariant(void)
{
    const oibar_v1_State st = oibar_app_state();
    if (st != oibar_v1_STATE_TRANSFER_ARMED && st != oibar_v1_STATE_TRANSFERRING) {
        s_phase = 0;
    }
    if (!bench_any_valve_driven()) {
        return;
    }
    s_open_ms++;
    char msg[160];
    snprintf(msg, sizeof msg, "seed %u ms %u state %d phase %u blockers 0x%x", (unsigned)s_seed,
             (unsigned)s_ms, (int)st, s_phase, (unsigned)oibar_safety_valve_blockers());
    TEST_ASSERT_EQUAL_INT_MESSAGE(oibar_v1_STATE_TRANSFERRING, st, msg);
    TEST_ASSERT_EQUAL_UINT32_MESSAGE(0u, oibar_safety_valve_blockers(), msg);
    TEST_ASSERT_EQUAL_UINT32_MESSAGE(0u, oibar_fault_flags(), msg);
    TEST_ASSERT_EQUAL_UINT_MESSAGE(2u, s_phase, msg);
    TEST_ASSERT_TRUE_MESSAGE(oibar_link_is_connected(&s_link), msg);
    TEST_ASSERT_TRUE_MESSAGE(oibar_app_host_link_alive(), msg);
}

/* --- the wire ------------------------------------------------------------- */

static void inject(const uint8_t *bytes, size_t len)
{
    for (size_t i = 0; i < len; i++) {
        oibar_link_rx_isr(&s_link, bytes[i]);
    }
}

static size_t encode(oibar_v1_Packet *p, uint8_t *out)
{
    const size_t n = oibar_frame_encode(p, out, OIBAR_FRAME_MAX_WIRE_BYTES);
    TEST_ASSERT_TRUE(n > 0u);
    return n;
}

/* One simulated millisecond: host heartbeats when due, then the MCU. */
static void tick(void)
{
    if (s_host_alive && (int32_t)(s_ms - s_next_hb_ms) >= 0) {
        oibar_v1_Packet hb = oibar_v1_Packet_init_zero;
        hb.which_body = oibar_v1_Packet_heartbeat_tag;
        hb.seq = ++s_seq;
        uint8_t f[OIBAR_FRAME_MAX_WIRE_BYTES];
        inject(f, encode(&hb, f));
        s_next_hb_ms = s_ms + HEARTBEAT_MS;
    }
    fake_hal_advance_ms(1);
    s_ms++;
    check_invariant();
}

static void run_ms(uint32_t ms)
{
    for (uint32_t i = 0; i < ms; i++) {
        tick();
    }
}

/* Put a frame on the wire and let one main-loop pass handle it; returns how
 * many requests reached the application. */
static uint32_t deliver(const uint8_t *bytes, size_t len)
{
    const uint32_t before = s_exec;
    s_ack_seen = false;
    inject(bytes, len);
    tick();
    return s_exec - before;
}

static void remember(const oibar_v1_Packet *p, const uint8_t *bytes, size_t len)
{
    recorded_t *r = &s_hist[s_hist_n % HISTORY];
    memcpy(r->bytes, bytes, len);
    r->len = len;
    r->seq = p->seq;
    r->pkt = *p;
    s_hist_n++;
}

/* The bookkeeping of an accepted fresh command. */
static void host_accounts(const oibar_v1_Packet *p, const oibar_v1_Ack *ack)
{
    if (ack->reason != oibar_v1_NACK_NONE || p->which_body != oibar_v1_Packet_command_tag) {
        return;
    }
    const oibar_v1_CommandOpcode op = p->body.command.opcode;
    if (op == oibar_v1_CMD_ARM_TRANSFER) {
        s_phase = 1;
    } else if (op == oibar_v1_CMD_START_TRANSFER && s_phase == 1u) {
        s_phase = 2;
        s_starts++;
    } else {
        /* other commands leave the phase to the state tracking */
    }
}

/* A fresh request: runs once if the link is up; an exact retransmission
 * after a lost ack never runs again. */
static void fresh(oibar_v1_Packet *p)
{
    char msg[96];
    p->seq = ++s_seq;
    uint8_t f[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t n = encode(p, f);
    remember(p, f, n);
    s_pending = *p;
    s_pending_valid = true;
    const bool up = oibar_link_is_connected(&s_link);
    const uint32_t ran = deliver(f, n);
    snprintf(msg, sizeof msg, "seed %u ms %u: fresh request seq %u", (unsigned)s_seed, (unsigned)s_ms,
             (unsigned)p->seq);
    TEST_ASSERT_EQUAL_UINT32_MESSAGE(up ? 1u : 0u, ran, msg);
    if (!s_ack_seen || s_ack_seq != p->seq) {
        /* Ack lost (full queue): the host resends the same bytes. */
        s_port_full = false;
        s_retransmits++;
        snprintf(msg, sizeof msg, "seed %u ms %u: retransmission of seq %u ran again", (unsigned)s_seed,
                 (unsigned)s_ms, (unsigned)p->seq);
        TEST_ASSERT_EQUAL_UINT32_MESSAGE(0u, deliver(f, n), msg);
    }
    s_pending_valid = false;
}

static void command(oibar_v1_CommandOpcode op, float arg)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_command_tag;
    p.body.command.opcode = op;
    p.body.command.target_pressure_kpa = arg;
    fresh(&p);
}

static void nav_good(void)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_nav_update_tag;
    p.seq = ++s_seq;
    oibar_v1_NavUpdate *nav = &p.body.nav_update;
    nav->closing_speed_mps = 0.010f;
    nav->has_q_cam_target = true;
    nav->q_cam_target.w = 1.0f;
    nav->range_m = 0.05f;
    nav->confidence = 0.99f;
    nav->phase = oibar_v1_NAV_PHASE_SOFT_DOCK;
    nav->valid = true;
    nav->stamp_ms = s_ms;
    uint8_t f[OIBAR_FRAME_MAX_WIRE_BYTES];
    (void)deliver(f, encode(&p, f));
}

static void handshake(void)
{
    s_seq = 0;
    s_hist_n = 0; /* a new window: the old session's frames are not replayed (docs/link.md) */
    s_sessions++;
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_handshake_tag;
    p.seq = ++s_seq;
    p.body.handshake.protocol_version = oibar_v1_Protocol_PROTOCOL_VERSION;
    uint8_t f[OIBAR_FRAME_MAX_WIRE_BYTES];
    s_port_full = false;
    (void)deliver(f, encode(&p, f));
    s_host_alive = true;
    s_next_hb_ms = s_ms + HEARTBEAT_MS;
}

/* --- the attacker ---------------------------------------------------------- */

static void expect_not_run(uint32_t ran, const char *what, uint32_t seq)
{
    char msg[96];
    snprintf(msg, sizeof msg, "seed %u ms %u: %s (seq %u) was executed", (unsigned)s_seed, (unsigned)s_ms,
             what, (unsigned)seq);
    TEST_ASSERT_EQUAL_UINT32_MESSAGE(0u, ran, msg);
}

/* A recorded request of this session, byte for byte. */
static void replay(void)
{
    if (s_hist_n == 0u) {
        return;
    }
    const unsigned avail = (s_hist_n < HISTORY) ? s_hist_n : HISTORY;
    const recorded_t *r = &s_hist[(s_hist_n - 1u - below(avail)) % HISTORY];
    s_replays++;
    expect_not_run(deliver(r->bytes, r->len), "replayed request", r->seq);
}

/* Two requests swapped on the wire: the later one runs, the earlier not. */
static void reorder(void)
{
    oibar_v1_Packet a = oibar_v1_Packet_init_zero;
    a.which_body = oibar_v1_Packet_command_tag;
    a.body.command.opcode = (below(2) == 0) ? oibar_v1_CMD_ARM_TRANSFER : oibar_v1_CMD_START_TRANSFER;
    a.body.command.target_pressure_kpa = 1500.0f;
    a.seq = ++s_seq;
    oibar_v1_Packet b = oibar_v1_Packet_init_zero;
    b.which_body = oibar_v1_Packet_command_tag;
    b.body.command.opcode = oibar_v1_CMD_NOOP;
    b.seq = ++s_seq;
    uint8_t fa[OIBAR_FRAME_MAX_WIRE_BYTES];
    uint8_t fb[OIBAR_FRAME_MAX_WIRE_BYTES];
    const size_t na = encode(&a, fa);
    const size_t nb = encode(&b, fb);
    remember(&b, fb, nb);
    remember(&a, fa, na);
    s_pending = b; /* the later one is fresh */
    s_pending_valid = true;
    (void)deliver(fb, nb);
    s_pending_valid = false;
    s_reorders++;
    expect_not_run(deliver(fa, na), "overtaken request", a.seq);
}

/* Seq 0, or the last request's seq with another body. */
static void forged(void)
{
    oibar_v1_Packet p = oibar_v1_Packet_init_zero;
    p.which_body = oibar_v1_Packet_command_tag;
    p.body.command.opcode = (oibar_v1_CommandOpcode)(1u + below(12));
    p.body.command.target_pressure_kpa = (float)below(3000);
    if (below(2) == 0 || s_hist_n == 0u) {
        p.seq = 0;
    } else {
        const recorded_t *last = &s_hist[(s_hist_n - 1u) % HISTORY];
        p.seq = last->seq;
        if (last->pkt.which_body == oibar_v1_Packet_command_tag &&
            last->pkt.body.command.opcode == p.body.command.opcode) {
            p.body.command.target_pressure_kpa = last->pkt.body.command.target_pressure_kpa + 1.0f;
        }
    }
    uint8_t f[OIBAR_FRAME_MAX_WIRE_BYTES];
    expect_not_run(deliver(f, encode(&p, f)), "seq 0 or reused seq", p.seq);
}

/* Line noise, then the delimiter that ends it (else it spoils the next
 * frame, which this walk does not model as a loss). */
static void garbage(void)
{
    uint8_t junk[41];
    const size_t n = 1u + below(sizeof junk - 1u);
    for (size_t i = 0; i < n; i++) {
        junk[i] = (uint8_t)rnd();
    }
    junk[n] = 0x00u;
    (void)deliver(junk, n + 1u);
}

/* --- the cooperative host ---------------------------------------------------- */

static void guided(void)
{
    switch (oibar_app_state()) {
    case oibar_v1_STATE_IDLE:
        if (fake_plant_probe()) {
            fake_plant_set_probe(false);
        }
        command(oibar_v1_CMD_APPROACH_ARM, 0.0f);
        break;
    case oibar_v1_STATE_APPROACH_READY:
        nav_good();
        fake_plant_set_probe(true);
        break;
    case oibar_v1_STATE_RECEPTION:
        nav_good();
        command(oibar_v1_CMD_DOCK, 0.0f);
        break;
    case oibar_v1_STATE_SOFT_DOCKED:
        command(oibar_v1_CMD_HARD_DOCK, 0.0f);
        break;
    case oibar_v1_STATE_HARD_DOCKED:
        command(below(4) == 0 ? oibar_v1_CMD_SEPARATE : oibar_v1_CMD_ARM_TRANSFER, 0.0f);
        break;
    case oibar_v1_STATE_TRANSFER_ARMED:
        command(oibar_v1_CMD_START_TRANSFER, 300.0f + (float)below(1800));
        break;
    case oibar_v1_STATE_TRANSFERRING:
        if (below(8) == 0) {
            command(oibar_v1_CMD_STOP_TRANSFER, 0.0f);
        }
        break;
    case oibar_v1_STATE_FAULT:
        fake_plant_clear_overrides();
        fake_plant_set_valve_mode(0, FAKE_VALVE_OK);
        fake_plant_set_valve_mode(1, FAKE_VALVE_OK);
        run_ms(30);
        command(oibar_v1_CMD_CLEAR_FAULT, 0.0f);
        break;
    default:
        break;
    }
}

static uint32_t env_u32(const char *name, uint32_t fallback)
{
    const char *v = getenv(name);
    return (v != NULL && *v != '\0') ? (uint32_t)strtoul(v, NULL, 0) : fallback;
}

static void test_no_valve_opens_and_no_replay_runs_through_the_link(void)
{
    s_seed = env_u32("OIBAR_LINK_PROPERTY_SEED", (uint32_t)time(NULL) ^ ((uint32_t)getpid() << 16));
    if (s_seed == 0u) {
        s_seed = 1u; /* xorshift's one bad seed */
    }
    const uint32_t steps = env_u32("OIBAR_LINK_PROPERTY_STEPS", DEFAULT_STEPS);
    printf("test_link_property: seed %u, %u steps (OIBAR_LINK_PROPERTY_SEED=%u reproduces)\n",
           (unsigned)s_seed, (unsigned)steps, (unsigned)s_seed);
    fflush(stdout);
    s_rng = s_seed;

    fake_hal_reset();
    fake_plant_enable(true);
    fake_hal_advance_ms(1);
    oibar_app_init();
    s_cb = *oibar_app_link_callbacks();
    s_cb.on_command = counting_on_command;
    s_cb.on_param_set = counting_on_param_set;
    oibar_link_config_t cfg;
    oibar_link_config_defaults(&cfg);
    oibar_link_port_t port = { port_send, NULL };
    oibar_link_init(&s_link, &cfg, &port, &s_cb);
    oibar_frame_decoder_init(&s_dec, OIBAR_BODIES_MCU_TO_HOST);
    fake_hal_set_main_loop(main_loop);
    s_ms = s_open_ms = s_starts = s_replays = s_reorders = s_retransmits = s_sessions = 0;
    s_exec = 0;
    s_port_full = false;
    s_pending_valid = false;
    handshake();
    run_ms(1000);

    for (uint32_t step = 0; step < steps; step++) {
        uint32_t r = below(1000);
        if (r >= 860u && below(4) != 0) {
            r = 0; /* plant and session upsets at a quarter of their nominal rate */
        }
        if (r < 400) {
            run_ms(1u + below(60));
        } else if (r < 750) {
            guided();
        } else if (r < 790) {
            replay();
        } else if (r < 805) {
            reorder();
        } else if (r < 820) {
            forged();
        } else if (r < 825) {
            command((oibar_v1_CommandOpcode)below(13), (float)below(3000) - 100.0f);
        } else if (r < 835) {
            s_port_full = true; /* the UART queue fills: acks and events wait or are lost */
        } else if (r < 855) {
            s_port_full = false;
        } else if (r < 860) {
            garbage();
        } else if (r < 865) {
            s_host_alive = false; /* the host goes quiet: link loss after 1 s */
            run_ms(900u + below(400));
        } else if (r < 890) {
            handshake(); /* host restart, or back after a loss */
        } else if (r < 905) {
            fake_plant_override_di((hal_di_t)below(HAL_DI_COUNT), (int)below(3) - 1);
        } else if (r < 920) {
            fake_plant_override_adc((hal_adc_t)below(HAL_ADC_COUNT), below(3) == 0 ? (int)below(4096) : -1);
        } else if (r < 925) {
            fake_plant_set_valve_mode(below(2), (fake_valve_mode_t)below(3));
        } else if (r < 930) {
            oibar_fault_raise((oibar_v1_FaultCode)(1u + below(OIBAR_FAULT_CODE_MAX)));
            check_invariant();
        } else if (r < 940) {
            fake_plant_set_probe(below(2) == 0);
        } else {
            fake_plant_clear_overrides();
            fake_plant_set_valve_mode(0, FAKE_VALVE_OK);
            fake_plant_set_valve_mode(1, FAKE_VALVE_OK);
            if (!s_host_alive || !oibar_link_is_connected(&s_link)) {
                handshake();
            }
        }
    }
    char msg[200];
    oibar_v1_LinkCounters c;
    oibar_link_get_counters(&s_link, &c);
    snprintf(msg, sizeof msg,
             "seed %u: %u starts, %u ms valves open, %u replays, %u reorders, %u retransmissions, "
             "%u sessions, %u refused stale, %u ms simulated",
             (unsigned)s_seed, (unsigned)s_starts, (unsigned)s_open_ms, (unsigned)s_replays,
             (unsigned)s_reorders, (unsigned)s_retransmits, (unsigned)s_sessions, (unsigned)c.rx_stale,
             (unsigned)s_ms);
    TEST_MESSAGE(msg);
    if (steps >= DEFAULT_STEPS) {
        /* The walk must reach the transfer, or it proves nothing. */
        TEST_ASSERT_TRUE_MESSAGE(s_starts >= steps / 5000u, msg);
        TEST_ASSERT_TRUE_MESSAGE(s_open_ms >= steps / 50u, msg);
        TEST_ASSERT_TRUE_MESSAGE(s_replays >= steps / 100u, msg);
    }
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_no_valve_opens_and_no_replay_runs_through_the_link);
    return UNITY_END();
}
