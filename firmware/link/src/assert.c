/* Weak default for the contract-check handler; the firmware overrides it. */
#include "oibar/assert.h"

#include <stdlib.h>

/* Where the last check failed, for a debugger or a post-mortem dump. */
const char *volatile oibar_assert_file;
volatile int oibar_assert_line;

__attribute__((weak)) _Noreturn void oibar_assert_failed(const char *file, int line)
{
    oibar_assert_file = file;
    oibar_assert_line = line;
    abort();
}
