/* docs/state_table.md and the code's transition table are the same table. */
#include <stdio.h>
#include <string.h>

#include "oibar/app_fsm.h"
#include "unity.h"

#define MAX_ROWS 200
#define CELL 48

typedef struct {
    char cell[5][CELL];
} doc_row_t;

static doc_row_t s_doc[MAX_ROWS];
static unsigned s_doc_n;

void setUp(void) {}
void tearDown(void) {}

static void trim(char *s)
{
    size_t n = strlen(s);
    while (n > 0 && (s[n - 1] == ' ' || s[n - 1] == '\n' || s[n - 1] == '\r')) {
        s[--n] = '\0';
    }
    size_t i = 0;
    while (s[i] == ' ') {
        i++;
    }
    memmove(s, s + i, strlen(s + i) + 1);
}

/* Read the rows between the markers; header and separator lines skipped. */
static void load_doc(void)
{
    char path[512];
    snprintf(path, sizeof path, "%s/docs/state_table.md", OIBAR_SOURCE_DIR);
    FILE *f = fopen(path, "r");
    TEST_ASSERT_NOT_NULL_MESSAGE(f, "cannot open docs/state_table.md");
    char line[512];
    int inside = 0;
    s_doc_n = 0;
    while (fgets(line, sizeof line, f) != NULL) {
        if (strstr(line, "<!-- state-table:begin -->") != NULL) {
            inside = 1;
            continue;
        }
        if (strstr(line, "<!-- state-table:end -->") != NULL) {
            break;
        }
        if (!inside || line[0] != '|' || strstr(line, "| state |") == line ||
            strncmp(line, "| ---", 5) == 0) {
            continue;
        }
        TEST_ASSERT_TRUE_MESSAGE(s_doc_n < MAX_ROWS, "too many rows");
        doc_row_t *r = &s_doc[s_doc_n];
        char *p = line + 1;
        for (int c = 0; c < 5; c++) {
            char *bar = strchr(p, '|');
            TEST_ASSERT_NOT_NULL_MESSAGE(bar, line);
            *bar = '\0';
            TEST_ASSERT_TRUE_MESSAGE(strlen(p) < CELL, line);
            strcpy(r->cell[c], p);
            trim(r->cell[c]);
            p = bar + 1;
        }
        s_doc_n++;
    }
    fclose(f);
    TEST_ASSERT_TRUE_MESSAGE(inside, "markers missing in docs/state_table.md");
}

static void test_doc_and_code_tables_are_identical_row_by_row(void)
{
    load_doc();
    unsigned n = 0;
    const oibar_fsm_row_t *t = oibar_fsm_table(&n);
    char msg[256];
    for (unsigned i = 0; i < n && i < s_doc_n; i++) {
        const char *code[5] = {
            oibar_fsm_state_name(t[i].state), oibar_fsm_event_name(t[i].event),
            oibar_fsm_guard_name(t[i].guard), oibar_fsm_next_name(t[i].next),
            oibar_fsm_action_name(t[i].action),
        };
        for (int c = 0; c < 5; c++) {
            snprintf(msg, sizeof msg, "row %u column %d: doc '%s' code '%s'", i + 1, c + 1,
                     s_doc[i].cell[c], code[c]);
            TEST_ASSERT_EQUAL_STRING_MESSAGE(code[c], s_doc[i].cell[c], msg);
        }
    }
    snprintf(msg, sizeof msg, "doc has %u rows, code has %u", s_doc_n, n);
    TEST_ASSERT_EQUAL_UINT_MESSAGE(n, s_doc_n, msg);
}

static void test_every_state_appears_and_names_are_known(void)
{
    unsigned n = 0;
    const oibar_fsm_row_t *t = oibar_fsm_table(&n);
    for (unsigned s = OIBAR_STATE_FIRST; s <= OIBAR_STATE_LAST; s++) {
        bool found = false;
        for (unsigned i = 0; i < n; i++) {
            found = found || t[i].state == s;
        }
        TEST_ASSERT_TRUE_MESSAGE(found, oibar_fsm_state_name(s));
    }
    for (unsigned i = 0; i < n; i++) {
        TEST_ASSERT_NOT_EQUAL(0, strcmp("?", oibar_fsm_state_name(t[i].state)));
        TEST_ASSERT_NOT_EQUAL(0, strcmp("?", oibar_fsm_event_name(t[i].event)));
        TEST_ASSERT_NOT_EQUAL(0, strcmp("?", oibar_fsm_guard_name(t[i].guard)));
        TEST_ASSERT_NOT_EQUAL(0, strcmp("?", oibar_fsm_action_name(t[i].action)));
        TEST_ASSERT_TRUE(t[i].next <= OIBAR_STATE_LAST);
        TEST_ASSERT_NOT_EQUAL(SIG_NONE, t[i].event);
    }
}

/* A state with a timeout must say what its timeout does. */
static void test_every_timed_state_has_a_timeout_row(void)
{
    unsigned n = 0;
    const oibar_fsm_row_t *t = oibar_fsm_table(&n);
    for (unsigned s = OIBAR_STATE_FIRST; s <= OIBAR_STATE_LAST; s++) {
        if (oibar_fsm_state_timeout_param(s) == 0u) {
            continue;
        }
        bool found = false;
        for (unsigned i = 0; i < n; i++) {
            found = found || (t[i].state == s && t[i].event == SIG_TIMEOUT);
        }
        TEST_ASSERT_TRUE_MESSAGE(found, oibar_fsm_state_name(s));
    }
}

/* Guarded alternatives for one (state, event) must end with a row that can
 * be told apart: no two rows with the same state, event and guard. */
static void test_no_duplicate_rows(void)
{
    unsigned n = 0;
    const oibar_fsm_row_t *t = oibar_fsm_table(&n);
    for (unsigned i = 0; i < n; i++) {
        for (unsigned j = i + 1; j < n; j++) {
            bool same = t[i].state == t[j].state && t[i].event == t[j].event &&
                        t[i].guard == t[j].guard;
            TEST_ASSERT_FALSE_MESSAGE(same, oibar_fsm_event_name(t[i].event));
        }
    }
}

/* The superstates form a tree under ANY: every walk up ends at ANY, a
 * superstate is never a transition's target, and the states with no
 * superstate are exactly the ones outside any activity. */
static void test_superstates_form_a_tree(void)
{
    for (unsigned node = OIBAR_STATE_FIRST; node <= OIBAR_FSM_NODE_LAST; node++) {
        unsigned up = node, steps = 0;
        while (up != OIBAR_FSM_ANY) {
            up = oibar_fsm_parent(up);
            TEST_ASSERT_TRUE(up == OIBAR_FSM_ANY || up > OIBAR_STATE_LAST); /* parents are superstates */
            TEST_ASSERT_TRUE_MESSAGE(++steps <= OIBAR_FSM_NODE_LAST, oibar_fsm_state_name(node));
        }
        TEST_ASSERT_NOT_EQUAL(0, strcmp("?", oibar_fsm_state_name(node)));
    }
    const unsigned top[] = { oibar_v1_STATE_BOOT, oibar_v1_STATE_IDLE, oibar_v1_STATE_ABORTING,
                             oibar_v1_STATE_FAULT };
    for (unsigned i = 0; i < 4; i++) {
        TEST_ASSERT_EQUAL_UINT(OIBAR_FSM_ANY, oibar_fsm_parent(top[i]));
    }
    TEST_ASSERT_EQUAL_UINT(OIBAR_FSM_SUPER_DOCKED, oibar_fsm_parent(OIBAR_FSM_SUPER_MATED));
    TEST_ASSERT_EQUAL_UINT(OIBAR_FSM_SUPER_ACTIVE, oibar_fsm_parent(OIBAR_FSM_SUPER_DOCKED));
    TEST_ASSERT_EQUAL_UINT(OIBAR_FSM_SUPER_MATED, oibar_fsm_parent(oibar_v1_STATE_TRANSFERRING));
    unsigned n = 0;
    const oibar_fsm_row_t *t = oibar_fsm_table(&n);
    for (unsigned i = 0; i < n; i++) {
        TEST_ASSERT_TRUE(t[i].next <= OIBAR_STATE_LAST);
    }
}

int main(void)
{
    UNITY_BEGIN();
    RUN_TEST(test_doc_and_code_tables_are_identical_row_by_row);
    RUN_TEST(test_every_state_appears_and_names_are_known);
    RUN_TEST(test_every_timed_state_has_a_timeout_row);
    RUN_TEST(test_no_duplicate_rows);
    RUN_TEST(test_superstates_form_a_tree);
    return UNITY_END();
}
