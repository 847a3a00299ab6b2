// Spresense implementations of the small hardware interfaces: EEPROM
// settings, LEDs, watchdog and reboot.
#ifndef CUBECAM_SPRESENSE_BOARD_H
#define CUBECAM_SPRESENSE_BOARD_H

#include "../core/hal.h"

namespace cubecam {
namespace spresense {

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
