/**
 * @file assert.h
 * Contract checks for programming errors (NULL where a pointer is required,
 * a broken invariant). Never used for bad input from the wire: that is
 * counted and dropped, see docs/link.md.
 *
 * A failed check calls oibar_assert_failed(). The library ships a weak
 * default (records the location, then abort()); the firmware overrides it
 * with a strong definition that safes the mechanism and resets. Put the
 * override in an object file that is linked anyway (e.g. the one with
 * main()), so the linker does not keep the weak default instead.
 */
#ifndef OIBAR_ASSERT_H
#define OIBAR_ASSERT_H

#ifdef __cplusplus
extern "C" {
#endif

/** Called on a failed OIBAR_ASSERT. Must not return. */
_Noreturn void oibar_assert_failed(const char *file, int line) __attribute__((noreturn));

#define OIBAR_ASSERT(cond)                          \
    do {                                            \
        if (!(cond)) {                              \
            oibar_assert_failed(__FILE__, __LINE__); \
        }                                           \
    } while (0)

#ifdef __cplusplus
}
#endif

#endif /* OIBAR_ASSERT_H */
