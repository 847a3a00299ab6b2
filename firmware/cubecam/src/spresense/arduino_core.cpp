#include "arduino_core.h"

#include <Arduino.h>

namespace cubecam {
namespace spresense {

uint32_t ArduinoClock::millis() { return static_cast<uint32_t>(::millis()); }

uint64_t ArduinoClock::micros() { return ::micros(); }

size_t UartSerial::read(uint8_t* buf, size_t cap) {
    size_t n = 0;
    while (n < cap && Serial.available() > 0) {
        int c = Serial.read();
        if (c < 0) break;
        buf[n++] = static_cast<uint8_t>(c);
    }
    return n;
}

void UartSerial::write(const uint8_t* data, size_t len) { Serial.write(data, len); }

}  // namespace spresense
}  // namespace cubecam
