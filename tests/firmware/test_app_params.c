/* Parameter table: definitions, bounds, locking, and docs/firmware.md. */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "fake_hal.h"
#include "oibar/app.h"
#include "oibar/app_params.h"
#include "unity.h"

void setUp(void) { bench_start(); }
void tearDown(void) {}

static void test_definitions_are_consistent(void)
{
    for (unsigned i = 0; i < OIBAR_PARAM_COUNT; i++) {
        const oibar_param_def_t *d = oibar_param_def_at(i);
        TEST_ASSERT_NOT_NULL(d);
        TEST_ASSERT_EQUAL_UINT(i + 1u, (unsigned)d->id);
        TEST_ASSERT_TRUE(d->min <= d->default_value && d->default_value <= d->max);
        /* ParamValue.name / .unit are char[25] / char[9] (oibar.options). */
        TEST_ASSERT_TRUE_MESSAGE(strlen(d->name) <= 24u, d->name);
        TEST_ASSERT_TRUE_MESSAGE(strlen(d->unit) <= 8u, d->name);
        if (d->integer) {
            TEST_ASSERT_EQUAL_FLOAT(floorf(d->default_value), d->default_value);
        }
        for (unsigned j = 0; j < i; j++) {
            TEST_ASSERT_NOT_EQUAL(0, strcmp(d->name, oibar_param_def_at(j)->name));
        }
    }
    TEST_ASSERT_NULL(oibar_param_def(0));
    TEST_ASSERT_NULL(oibar_param_def(PARAM_ID_END));
}

static void test_paper_facts(void)
{
    TEST_ASSERT_EQUAL_FLOAT(50.0f, oibar_param_f(PARAM_CAPTURE_MAX_CLOSING_SPEED_MM_S));
    TEST_ASSERT_EQUAL_FLOAT(10.0f, oibar_param_f(PARAM_CAPTURE_MAX_MISALIGNMENT_DEG));
    TEST_ASSERT_EQUAL_FLOAT(60.0f, oibar_param_f(PARAM_HARD_DOCK_MAX_FORCE_N));
    TEST_ASSERT_EQUAL_FLOAT(30.0f, oibar_param_f(PARAM_SOFT_DOCK_MAX_FORCE_N));
    /* The paper's limits are also the bounds: a host cannot loosen them. */
    TEST_ASSERT_EQUAL_FLOAT(50.0f, oibar_param_def(PARAM_CAPTURE_MAX_CLOSING_SPEED_MM_S)->max);
    TEST_ASSERT_EQUAL_FLOAT(60.0f, oibar_param_def(PARAM_HARD_DOCK_MAX_FORCE_N)->max);
    /* A target the trip would refuse is not a default. */
    TEST_ASSERT_TRUE(oibar_param_f(PARAM_TARGET_MAX_KPA) < oibar_param_f(PARAM_OVERPRESSURE_KPA));
}

static void test_get_and_set_over_the_link_api(void)
{
    oibar_v1_ParamValue v;
    oibar_app_param_get(PARAM_DEBOUNCE_MS, &v);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, v.reason);
    TEST_ASSERT_EQUAL_STRING("debounce_ms", v.name);
    TEST_ASSERT_EQUAL_STRING("ms", v.unit);
    TEST_ASSERT_EQUAL_FLOAT(10.0f, v.value);
    oibar_app_param_set(PARAM_DEBOUNCE_MS, 20.0f, &v);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_NONE, v.reason);
    TEST_ASSERT_EQUAL_FLOAT(20.0f, v.value);
    oibar_app_param_set(PARAM_DEBOUNCE_MS, 1000.0f, &v);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PARAM_OUT_OF_BOUNDS, v.reason);
    TEST_ASSERT_EQUAL_FLOAT(20.0f, v.value); /* unchanged value reported */
    oibar_app_param_set(PARAM_DEBOUNCE_MS, 12.5f, &v);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PARAM_OUT_OF_BOUNDS, v.reason);
    oibar_app_param_set(PARAM_OVERPRESSURE_KPA, NAN, &v);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_PARAM_OUT_OF_BOUNDS, v.reason);
    oibar_app_param_get(999, &v);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_UNKNOWN_PARAM, v.reason);
    oibar_app_param_set(0, 1.0f, &v);
    TEST_ASSERT_EQUAL(oibar_v1_NACK_UNKNOWN_PARAM, v.reason);
}

static void test_locked_outside_safe_states(void)
{
    for (unsigned st = 1; st <= 15; st++) {
        TEST_ASSERT_TRUE(bench_goto((oibar_v1_State)st));
        oibar_v1_ParamValue v;
        oibar_app_param_set(PARAM_DEBOUNCE_MS, 11.0f, &v);
        bool safe = st == oibar_v1_STATE_BOOT || st == oibar_v1_STATE_IDLE || st == oibar_v1_STATE_FAULT;
        TEST_ASSERT_EQUAL(safe ? oibar_v1_NACK_NONE : oibar_v1_NACK_PARAM_LOCKED, v.reason);
        TEST_ASSERT_EQUAL_FLOAT(safe ? 11.0f : 10.0f, oibar_param_f(PARAM_DEBOUNCE_MS));
    }
}

static void test_doc_table_matches_code(void)
{
    char path[512];
    snprintf(path, sizeof path, "%s/docs/firmware.md", OIBAR_SOURCE_DIR);
    FILE *f = fopen(path, "r");
    TEST_ASSERT_NOT_NULL_MESSAGE(f, "cannot open docs/firmware.md");
    char line[512];
    int inside = 0;
    unsigned n = 0;
    while (fgets(line, sizeof line, f) != NULL) {
        if (strstr(line, "<!-- param-table:begin -->") != NULL) {
            inside = 1;
            continue;
        }
        if (strstr(line, "<!-- param-table:end -->") != NULL) {
            break;
        }
        if (!inside || line[0] != '|' || strncmp(line, "| id", 4) == 0 || strncmp(line, "| ---", 5) == 0) {
            continue;
        }
        const oibar_param_def_t *d = oibar_param_def_at(n);
        TEST_ASSERT_NOT_NULL_MESSAGE(d, "doc has more rows than the code");
        char want[256];
        snprintf(want, sizeof want, "| %u | %s | %s | %.7g | %.7g | %.7g |", (unsigned)d->id, d->name,
                 d->unit, (double)d->default_value, (double)d->min, (double)d->max);
        TEST_ASSERT_EQUAL_INT_MESSAGE(0, strncmp(want, line, strlen(want)), want);
        n++;
    }
    fclose(f);
    TEST_ASSERT_EQUAL_UINT_MESSAGE(OIBAR_PARAM_COUNT, n, "doc and code differ in row count");
}

/* D10 at boot: the default table passes the cross-parameter rules (the
 * application faults at init when the table it runs on does not). */
static void test_defaults_pass_the_cross_parameter_rules(void)
{
    oibar_params_init();
    TEST_ASSERT_TRUE(oibar_params_consistent());
    /* Every default is also accepted when set again on its own. */
    for (unsigned i = 0; i < OIBAR_PARAM_COUNT; i++) {
        const oibar_param_def_t *d = oibar_param_def_at(i);
        TEST_ASSERT_EQUAL_MESSAGE(oibar_v1_NACK_NONE,
                                  oibar_param_set((uint32_t)d->id, d->default_value, oibar_v1_STATE_IDLE),
                                  d->name);
    }
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_definitions_are_consistent);
    RUN_TEST(test_paper_facts);
    RUN_TEST(test_get_and_set_over_the_link_api);
    RUN_TEST(test_locked_outside_safe_states);
    RUN_TEST(test_doc_table_matches_code);
    RUN_TEST(test_defaults_pass_the_cross_parameter_rules);
    return UNITY_END();
}
