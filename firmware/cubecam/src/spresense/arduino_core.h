// The Arduino core's clock and USB serial port as the core's Clock and
// SerialPort. Plain Arduino API, so the host run over the real libraries
// (make hostlib) uses these very classes.
#ifndef CUBECAM_SPRESENSE_ARDUINO_CORE_H
#define CUBECAM_SPRESENSE_ARDUINO_CORE_H

#include "../core/hal.h"

namespace cubecam {
namespace spresense {

// millis() and micros() of the Spresense core 3.x are 64-bit (uint64_t), so
// the device clock never wraps. A core whose micros() is unsigned long (32
// bits, wrapping every 71.6 minutes) is extended to 64 bits here; loop()
// reads the clock far more often than that. The core's deadlines use the low
// 32 bits of millis(), compared with wrap-around.
class ArduinoClock : public Clock {
public:
    ArduinoClock();
    uint32_t millis();
    uint64_t micros();
private:
    uint32_t last_low_us_;
    uint64_t high_us_;
};

// USB serial (UART1 through the CP2102N), shared by Improv, console and logs,
// and by the libraries' own console output.
class UartSerial : public SerialPort {
public:
    size_t read(uint8_t* buf, size_t cap);
    void write(const uint8_t* data, size_t len);
};

}  // namespace spresense
}  // namespace cubecam

#endif
