// The Arduino core's clock and USB serial port as the core's Clock and
// SerialPort. Plain Arduino API, so the host run over the real libraries
// (make hostlib) uses these very classes.
#ifndef CUBECAM_SPRESENSE_ARDUINO_CORE_H
#define CUBECAM_SPRESENSE_ARDUINO_CORE_H

#include "../core/hal.h"

namespace cubecam {
namespace spresense {

// millis() and micros() of the Spresense core are 64-bit (uint64_t: Arduino.h
// of 2.6.0, the set PlatformIO pins, 3.2.0 and 3.4.4), so the device clock
// never wraps. The core's deadlines use the low 32 bits of
// millis(), compared with wrap-around.
class ArduinoClock : public Clock {
public:
    uint32_t millis();
    uint64_t micros();
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
