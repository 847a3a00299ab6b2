// Spresense implementations of the small hardware interfaces: clock, UART,
// EEPROM settings, LEDs, watchdog and reboot.
#ifndef CUBECAM_SPRESENSE_BOARD_H
#define CUBECAM_SPRESENSE_BOARD_H

#include "../core/hal.h"

namespace cubecam {
namespace spresense {

// millis()/micros() of the board, widened to 64 bits. micros() must be called
// at least once per 71 minutes (the main loop does, many times a second).
class ArduinoClock : public Clock {
public:
    ArduinoClock();
    uint32_t millis();
    uint64_t micros();
    // A raw 32-bit micros() value taken recently (e.g. in the camera thread),
    // on the 64-bit clock.
    uint64_t widen(uint32_t raw);
private:
    uint32_t last_raw_;
    uint64_t high_;
};

// USB serial (UART1 through the CP2102N), shared by Improv, console and logs.
class UartSerial : public SerialPort {
public:
    size_t read(uint8_t* buf, size_t cap);
    void write(const uint8_t* data, size_t len);
};

// The settings record at offset 0 of the EEPROM emulation (a zero-filled
// file on the SPI flash when new; the CRC tells it apart).
class EepromStorage : public SettingsStorage {
public:
    bool load(uint8_t* buf, size_t len);
    bool store(const uint8_t* buf, size_t len);
};

// LED0..LED3 of the main board, active high.
class BoardLeds : public Leds {
public:
    BoardLeds();
    void show(uint8_t mask);
};

// Hardware watchdog (reboots the board when not kicked) and reboot.
class BoardSystem : public System {
public:
    explicit BoardSystem(uint32_t watchdog_ms);
    void begin();
    void kick_watchdog();
    void reboot();
private:
    uint32_t watchdog_ms_;
};

}  // namespace spresense
}  // namespace cubecam

#endif
