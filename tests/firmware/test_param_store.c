/* Issue 59 (3): parameter persistence on the fake HAL's in-memory flash.
 * Two copies with sequence number and CRC, the newer valid one loaded at
 * boot, defaults plus an event (blank) or a fault (invalid copies) without
 * one, a power cut at every step of a save, and the save only in a safe
 * state. */
#include <string.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_faults.h"
#include "oibar/app_params.h"
#include "oibar/app_pstore.h"
#include "oibar/crc32c.h"
#include "unity.h"

void setUp(void) { fake_hal_reset(); }
void tearDown(void) {}

/* A parameter no rule ties to another: any value in its bounds is a valid table. */
#define FREE_PARAM PARAM_NAV_MAX_AGE_MS

static void defaults(float v[OIBAR_PARAM_COUNT])
{
    for (unsigned i = 0; i < OIBAR_PARAM_COUNT; i++) {
        v[i] = oibar_param_def_at(i)->default_value;
    }
}

/* Write a copy of `v` with `seq` into a sector, as a save would have. */
static void put_copy(unsigned sector, const float v[OIBAR_PARAM_COUNT], uint32_t seq)
{
    uint32_t rec[OIBAR_PSTORE_WORDS];
    oibar_pstore_encode(v, seq, rec);
    memset(fake_flash_sector(sector), 0xFF, HAL_FLASH_SECTOR_BYTES);
    memcpy(fake_flash_sector(sector), rec, sizeof rec);
}

static void put_free_value(unsigned sector, float value, uint32_t seq)
{
    float v[OIBAR_PARAM_COUNT];
    defaults(v);
    v[FREE_PARAM - 1] = value;
    put_copy(sector, v, seq);
}

/* Boot the parameter table alone: defaults, then the store. */
static oibar_pstore_load_t boot_params(void)
{
    oibar_params_init();
    return oibar_pstore_load();
}

static float free_value(void) { return oibar_param_f(FREE_PARAM); }

static bool fault_latched(oibar_v1_FaultCode code)
{
    return (oibar_fault_flags() & OIBAR_FAULT_BIT(code)) != 0u;
}

/* The whole application on the plant, after a power cycle that keeps the flash. */
static void app_power_cycle(void)
{
    fake_hal_power_cycle();
    fake_plant_enable(true);
    fake_hal_advance_ms(1);
    oibar_app_init();
    fake_hal_set_main_loop(oibar_app_run_once);
    oibar_app_link_state(true);
    fake_hal_advance_ms(300);
}

static bool event_seen(oibar_v1_EventId id, uint32_t arg)
{
    oibar_v1_Event ev;
    bool seen = false;
    while (oibar_app_next_event(&ev)) {
        seen = seen || (ev.id == id && ev.arg == arg);
    }
    return seen;
}

static oibar_v1_NackReason set_param(oibar_param_id_t id, float value)
{
    oibar_v1_ParamValue out;
    oibar_app_param_set((uint32_t)id, value, &out);
    return out.reason;
}

/* --- boot ----------------------------------------------------------------- */

static void test_blank_flash_gives_defaults_and_an_event_not_a_fault(void)
{
    app_power_cycle();
    TEST_ASSERT_FALSE(oibar_pstore_have_copy());
    TEST_ASSERT_EQUAL_FLOAT(oibar_param_def(FREE_PARAM)->default_value, free_value());
    TEST_ASSERT_TRUE(event_seen(oibar_v1_EVT_PARAMS_DEFAULTED, 0u));
    TEST_ASSERT_FALSE(fault_latched(oibar_v1_FAULT_PARAMS_INVALID));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
}

static void test_corrupt_sectors_give_defaults_and_a_fault(void)
{
    put_free_value(0, 1234.0f, 1u);
    put_free_value(1, 2345.0f, 2u);
    fake_flash_sector(0)[20] ^= 0x01u; /* a bit of each copy's values */
    fake_flash_sector(1)[24] ^= 0x80u;
    app_power_cycle();
    TEST_ASSERT_FALSE(oibar_pstore_have_copy());
    TEST_ASSERT_EQUAL_FLOAT(oibar_param_def(FREE_PARAM)->default_value, free_value());
    TEST_ASSERT_TRUE(event_seen(oibar_v1_EVT_PARAMS_DEFAULTED, 1u));
    TEST_ASSERT_TRUE(fault_latched(oibar_v1_FAULT_PARAMS_INVALID));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_FAULT, oibar_app_state());
}

static void test_garbage_next_to_a_blank_sector_is_invalid_not_blank(void)
{
    memset(fake_flash_sector(1), 0x00, 64); /* e.g. a .bin written with a zero-filled gap */
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_INVALID, boot_params());
}

static void test_newer_valid_copy_wins_from_either_sector(void)
{
    put_free_value(0, 1000.0f, 7u);
    put_free_value(1, 2000.0f, 8u);
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_LOADED, boot_params());
    TEST_ASSERT_EQUAL_FLOAT(2000.0f, free_value());
    TEST_ASSERT_EQUAL_UINT32(8u, oibar_pstore_seq());
    put_free_value(0, 3000.0f, 9u);
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_LOADED, boot_params());
    TEST_ASSERT_EQUAL_FLOAT(3000.0f, free_value());
    TEST_ASSERT_EQUAL_UINT(0u, oibar_pstore_sector());
}

static void test_crc_flip_rejects_that_copy_and_the_older_wins(void)
{
    put_free_value(0, 1000.0f, 1u);
    put_free_value(1, 2000.0f, 2u);
    fake_flash_sector(1)[4u * (OIBAR_PSTORE_WORDS - 1u)] ^= 0x10u; /* the CRC word itself */
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_LOADED, boot_params());
    TEST_ASSERT_EQUAL_FLOAT(1000.0f, free_value());
}

static void test_sequence_number_wraps(void)
{
    put_free_value(0, 1000.0f, 0xFFFFFFFFu);
    put_free_value(1, 2000.0f, 0u); /* one save after 0xFFFFFFFF */
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_LOADED, boot_params());
    TEST_ASSERT_EQUAL_FLOAT(2000.0f, free_value());
    /* A save from 0xFFFFFFFF writes 0 into the other sector, and that wins. */
    put_free_value(1, 2000.0f, 0xFFFFFFFEu);
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_LOADED, boot_params());
    TEST_ASSERT_EQUAL_UINT32(0xFFFFFFFFu, oibar_pstore_seq());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_param_set(FREE_PARAM, 3000.0f, oibar_v1_STATE_IDLE));
    TEST_ASSERT_TRUE(oibar_pstore_save());
    TEST_ASSERT_EQUAL_UINT32(0u, oibar_pstore_seq());
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_LOADED, boot_params());
    TEST_ASSERT_EQUAL_FLOAT(3000.0f, free_value());
    TEST_ASSERT_EQUAL_UINT(1u, oibar_pstore_sector());
}

static void test_version_mismatch_is_rejected(void)
{
    float v[OIBAR_PARAM_COUNT];
    defaults(v);
    v[FREE_PARAM - 1] = 1500.0f;
    uint32_t rec[OIBAR_PSTORE_WORDS];
    oibar_pstore_encode(v, 5u, rec);
    rec[1] = (OIBAR_PSTORE_VERSION + 1u) | ((uint32_t)OIBAR_PARAM_COUNT << 16);
    /* A good CRC over the other version: only the version is wrong. */
    rec[OIBAR_PSTORE_WORDS - 1u] = oibar_crc32c((const uint8_t *)rec, 4u * (OIBAR_PSTORE_WORDS - 1u));
    memcpy(fake_flash_sector(0), rec, sizeof rec);
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_INVALID, boot_params());
    TEST_ASSERT_EQUAL_FLOAT(oibar_param_def(FREE_PARAM)->default_value, free_value());
}

static void test_copy_failing_cross_validation_is_rejected(void)
{
    float v[OIBAR_PARAM_COUNT];
    defaults(v);
    /* Each in its bounds; together every healthy valve stroke is a mismatch (D10). */
    v[PARAM_DEBOUNCE_MS - 1] = 100.0f;
    v[PARAM_VALVE_MISMATCH_MS - 1] = 150.0f;
    put_copy(1, v, 2u);
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_INVALID, boot_params());
    TEST_ASSERT_EQUAL_FLOAT(oibar_param_def(PARAM_DEBOUNCE_MS)->default_value,
                            oibar_param_f(PARAM_DEBOUNCE_MS));
    TEST_ASSERT_TRUE(oibar_params_consistent());
    /* With an older valid copy beside it, the older one is loaded. */
    put_free_value(0, 1200.0f, 1u);
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_LOADED, boot_params());
    TEST_ASSERT_EQUAL_FLOAT(1200.0f, free_value());
    TEST_ASSERT_EQUAL_UINT(0u, oibar_pstore_sector());
}

static void test_copy_out_of_bounds_or_nan_is_rejected(void)
{
    float v[OIBAR_PARAM_COUNT];
    defaults(v);
    v[PARAM_OVERPRESSURE_KPA - 1] = 2900.0f; /* above 90 % of the tank rating */
    put_copy(0, v, 3u);
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_INVALID, boot_params());
    defaults(v);
    v[PARAM_SOFT_DOCK_MAX_FORCE_N - 1] = 0.0f / 0.0f;
    put_copy(0, v, 3u);
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_INVALID, boot_params());
    defaults(v);
    v[PARAM_DEBOUNCE_MS - 1] = 10.5f; /* an integer parameter */
    put_copy(0, v, 3u);
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_INVALID, boot_params());
}

/* --- save ----------------------------------------------------------------- */

static void test_save_goes_to_the_other_sector_with_the_next_sequence_number(void)
{
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_BLANK, boot_params());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_param_set(FREE_PARAM, 1111.0f, oibar_v1_STATE_IDLE));
    TEST_ASSERT_TRUE(oibar_pstore_save());
    TEST_ASSERT_EQUAL_UINT(0u, oibar_pstore_sector());
    TEST_ASSERT_EQUAL_UINT32(1u, oibar_pstore_seq());
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_param_set(FREE_PARAM, 2222.0f, oibar_v1_STATE_IDLE));
    TEST_ASSERT_TRUE(oibar_pstore_save());
    TEST_ASSERT_EQUAL_UINT(1u, oibar_pstore_sector());
    TEST_ASSERT_EQUAL_UINT32(2u, oibar_pstore_seq());
    TEST_ASSERT_EQUAL(OIBAR_PSTORE_LOADED, boot_params());
    TEST_ASSERT_EQUAL_FLOAT(2222.0f, free_value());
}

/* The heart of it: cut the power after every number of flash operations a
 * save does, from both sides (the copy in use in sector 0, then in sector 1);
 * every reboot finds a valid copy, the old one until the save completed. */
static void test_power_cut_at_every_step_of_a_save_leaves_the_old_or_the_new_copy(void)
{
    for (unsigned side = 0; side < 2u; side++) {
        fake_hal_reset();
        (void)boot_params();
        TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_param_set(FREE_PARAM, 1000.0f, oibar_v1_STATE_IDLE));
        TEST_ASSERT_TRUE(oibar_pstore_save());
        if (side == 1u) {
            TEST_ASSERT_TRUE(oibar_pstore_save()); /* the copy in use now in sector 1 */
        }
        static uint8_t before[HAL_FLASH_SECTORS][HAL_FLASH_SECTOR_BYTES];
        memcpy(before[0], fake_flash_sector(0), HAL_FLASH_SECTOR_BYTES);
        memcpy(before[1], fake_flash_sector(1), HAL_FLASH_SECTOR_BYTES);
        const uint32_t ops_before = fake_flash_ops();
        (void)boot_params();
        TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_param_set(FREE_PARAM, 2000.0f, oibar_v1_STATE_IDLE));
        TEST_ASSERT_TRUE(oibar_pstore_save());
        const uint32_t save_ops = fake_flash_ops() - ops_before;
        TEST_ASSERT_EQUAL_UINT32(1u + OIBAR_PSTORE_WORDS, save_ops); /* one erase, one per word */

        for (uint32_t cut = 0; cut <= save_ops; cut++) {
            memcpy(fake_flash_sector(0), before[0], HAL_FLASH_SECTOR_BYTES);
            memcpy(fake_flash_sector(1), before[1], HAL_FLASH_SECTOR_BYTES);
            fake_hal_power_cycle();
            TEST_ASSERT_EQUAL(OIBAR_PSTORE_LOADED, boot_params());
            TEST_ASSERT_EQUAL_FLOAT(1000.0f, free_value());
            TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_param_set(FREE_PARAM, 2000.0f, oibar_v1_STATE_IDLE));
            fake_flash_cut_after((int32_t)cut);
            const bool saved = oibar_pstore_save();
            TEST_ASSERT_EQUAL(cut == save_ops, saved);
            fake_hal_power_cycle(); /* power back */
            TEST_ASSERT_EQUAL_MESSAGE(OIBAR_PSTORE_LOADED, boot_params(), "no valid copy after a cut");
            TEST_ASSERT_EQUAL_FLOAT(saved ? 2000.0f : 1000.0f, free_value());
            /* the next save after the cut works and wins */
            TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_param_set(FREE_PARAM, 3000.0f, oibar_v1_STATE_IDLE));
            TEST_ASSERT_TRUE(oibar_pstore_save());
            TEST_ASSERT_EQUAL(OIBAR_PSTORE_LOADED, boot_params());
            TEST_ASSERT_EQUAL_FLOAT(3000.0f, free_value());
        }
    }
}

static void test_flash_error_fails_the_save_and_keeps_the_copy_in_use(void)
{
    app_power_cycle();
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, set_param(FREE_PARAM, 1000.0f));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_SAVE_PARAMS, 0.0f));
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, set_param(FREE_PARAM, 2000.0f));
    fake_flash_set_fail(true);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_SAVE_FAILED, oibar_app_command(oibar_v1_CMD_SAVE_PARAMS, 0.0f));
    app_power_cycle();
    TEST_ASSERT_EQUAL_FLOAT(1000.0f, free_value());
}

static void test_a_save_that_does_not_read_back_fails(void)
{
    app_power_cycle();
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, set_param(FREE_PARAM, 1000.0f));
    fake_flash_set_silent_drop(true);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_SAVE_FAILED, oibar_app_command(oibar_v1_CMD_SAVE_PARAMS, 0.0f));
    TEST_ASSERT_FALSE(oibar_pstore_have_copy());
}

static void test_save_over_the_link_command_survives_a_power_cycle(void)
{
    app_power_cycle();
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, set_param(FREE_PARAM, 1750.0f));
    (void)event_seen(oibar_v1_EVT_UNSPECIFIED, 0u); /* drain */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, oibar_app_command(oibar_v1_CMD_SAVE_PARAMS, 0.0f));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state()); /* not a transition */
    TEST_ASSERT_TRUE(event_seen(oibar_v1_EVT_PARAMS_SAVED, 1u));
    app_power_cycle();
    TEST_ASSERT_EQUAL_FLOAT(1750.0f, free_value());
    TEST_ASSERT_FALSE(event_seen(oibar_v1_EVT_PARAMS_DEFAULTED, 0u));
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
}

/* SAFETY_RULE_SAVE_ONLY_WHEN_SAFE: the erase blocks the main loop, so it
 * never starts outside BOOT/IDLE or with a valve open or reading open. */
static void test_save_refused_outside_the_safe_states(void)
{
    static const oibar_v1_State k_unsafe[] = {
        oibar_v1_STATE_APPROACH_READY, oibar_v1_STATE_SOFT_DOCKED, oibar_v1_STATE_HARD_DOCKED,
        oibar_v1_STATE_TRANSFER_ARMED, oibar_v1_STATE_TRANSFERRING, oibar_v1_STATE_FAULT,
    };
    for (unsigned i = 0; i < sizeof k_unsafe / sizeof k_unsafe[0]; i++) {
        TEST_ASSERT_TRUE(bench_goto(k_unsafe[i]));
        const uint32_t ops = fake_flash_ops();
        TEST_ASSERT_EQUAL(oibar_v1_NACK_INVALID_IN_STATE,
                          oibar_app_command(oibar_v1_CMD_SAVE_PARAMS, 0.0f));
        TEST_ASSERT_EQUAL_UINT32(ops, fake_flash_ops());
        TEST_ASSERT_EQUAL(k_unsafe[i], oibar_app_state());
    }
}

static void test_save_refused_in_idle_with_a_valve_reading_open(void)
{
    bench_start();
    TEST_ASSERT_EQUAL(oibar_v1_STATE_IDLE, oibar_app_state());
    fake_plant_override_di(HAL_DI_TV_VALVE_OPEN, 1);
    fake_hal_advance_ms(30); /* debounced, shorter than the mismatch window */
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PRECONDITION_FAILED,
                      oibar_app_command(oibar_v1_CMD_SAVE_PARAMS, 0.0f));
    TEST_ASSERT_EQUAL_UINT32(0u, fake_flash_ops());
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_blank_flash_gives_defaults_and_an_event_not_a_fault);
    RUN_TEST(test_corrupt_sectors_give_defaults_and_a_fault);
    RUN_TEST(test_garbage_next_to_a_blank_sector_is_invalid_not_blank);
    RUN_TEST(test_newer_valid_copy_wins_from_either_sector);
    RUN_TEST(test_crc_flip_rejects_that_copy_and_the_older_wins);
    RUN_TEST(test_sequence_number_wraps);
    RUN_TEST(test_version_mismatch_is_rejected);
    RUN_TEST(test_copy_failing_cross_validation_is_rejected);
    RUN_TEST(test_copy_out_of_bounds_or_nan_is_rejected);
    RUN_TEST(test_save_goes_to_the_other_sector_with_the_next_sequence_number);
    RUN_TEST(test_power_cut_at_every_step_of_a_save_leaves_the_old_or_the_new_copy);
    RUN_TEST(test_flash_error_fails_the_save_and_keeps_the_copy_in_use);
    RUN_TEST(test_a_save_that_does_not_read_back_fails);
    RUN_TEST(test_save_over_the_link_command_survives_a_power_cycle);
    RUN_TEST(test_save_refused_outside_the_safe_states);
    RUN_TEST(test_save_refused_in_idle_with_a_valve_reading_open);
    return UNITY_END();
}
