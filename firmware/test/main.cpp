// doctest runner shared by the host (ASan/UBSan) and the Cortex-M4 (QEMU) builds.
#define DOCTEST_CONFIG_IMPLEMENT_WITH_MAIN
#include <doctest/doctest.h>
