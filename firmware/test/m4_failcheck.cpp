// One passing and one failing case: proves that a failed CHECK on the M4
// comes back as QEMU's exit status (semihosting SYS_EXIT_EXTENDED).
#include <doctest/doctest.h>

TEST_CASE("passes") { CHECK(1 + 1 == 2); }

TEST_CASE("fails on purpose") { CHECK(1 + 1 == 3); }
