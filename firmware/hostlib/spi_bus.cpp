// SPI5 of the Spresense main board with the public behaviour of the core's
// SPIClass (libraries/SPI/SPI.cpp): begin() counts references and every other
// call returns at once while the count is 0 (the bus is not set up), and
// beginTransaction() takes the bus lock, which on NuttX 3.x is an nxmutex:
// not recursive, so the task that already holds it blocks for good. Here that
// is recorded as a violation instead of hanging the test. Bytes go to the
// simulated GS2200M.
#include <SPI.h>
#include <stdint.h>
#include <GS2200Hal.h>
#include <pthread.h>

#include <new>

#include "gs2200m.h"
#include "hostlib.h"

namespace {

pthread_t g_owner;
bool g_locked = false;
uint32_t g_clock_hz = 0;

uint64_t g_spi_ns = 0;  // SPI time not yet added to the clock (below a microsecond)

bool held_by_me() { return g_locked && pthread_equal(g_owner, pthread_self()); }

uint8_t exchange(uint8_t mosi) {
    g_spi_ns += 8000000000ull / (g_clock_hz ? g_clock_hz : 4000000u) + hostlib::kSpiByteOverheadNs;
    hostlib::advance_us(g_spi_ns / 1000);
    g_spi_ns %= 1000;
    return hostlib::module().exchange(mosi, g_clock_hz);
}

}  // namespace

SPIClass SPI5(5);

SPIClass::SPIClass(int port) : port_(port), ref_count_(0) {}

void SPIClass::begin(void) { ++ref_count_; }

void SPIClass::end(void) {
    if (ref_count_ > 0) --ref_count_;
    if (ref_count_ == 0) g_locked = false;
}

void SPIClass::beginTransaction(SPISettings settings) {
    if (ref_count_ == 0) return;
    if (held_by_me()) {
        hostlib::violation("SPI" + std::to_string(port_) + ": beginTransaction() by the task that holds the bus: "
                           "the NuttX bus lock is not recursive, the board hangs here until the watchdog resets it");
    }
    g_owner = pthread_self();
    g_locked = true;
    g_clock_hz = settings.clock_;
}

void SPIClass::endTransaction(void) {
    if (ref_count_ == 0) return;
    g_locked = false;
}

uint8_t SPIClass::transfer(uint8_t data) {
    if (ref_count_ == 0) return 0;
    return exchange(data);
}

void SPIClass::transfer(void* buf, size_t count) {
    if (ref_count_ == 0 || !buf || count == 0) return;
    uint8_t* p = static_cast<uint8_t*>(buf);
    for (size_t i = 0; i < count; ++i) p[i] = exchange(p[i]);
}

namespace hostlib {

uint32_t spi_clock_hz() { return g_clock_hz; }

void spi_power_on() {
    SPI5.~SPIClass();
    new (&SPI5) SPIClass(5);
    g_locked = false;
    g_clock_hz = 0;
}

}  // namespace hostlib

// The library's WiFi_Write, wrapped at link time (-Wl,--wrap): the module
// learns what the write will carry before it answers the WRITE_REQUEST (see
// Gs2200m::refuse_write). The library code itself is unchanged.
extern "C" SPI_RESP_STATUS_E __real__Z10WiFi_WritePKvt(const void* data, uint16_t len);
extern "C" SPI_RESP_STATUS_E __wrap__Z10WiFi_WritePKvt(const void* data, uint16_t len) {
    hostlib::module().next_write(data, len);
    return __real__Z10WiFi_WritePKvt(data, len);
}
