// Spresense implementations of the small hardware interfaces: EEPROM
// settings, LEDs, watchdog and reboot.
#ifndef CUBECAM_SPRESENSE_BOARD_H
#define CUBECAM_SPRESENSE_BOARD_H

#include "../core/hal.h"
#include "../core/settings_store.h"

namespace cubecam {
namespace spresense {

// The EEPROM emulation (a 4000-byte file on the SPI flash, zero-filled when
// new) as the flash area of the settings slots (core/settings_store.h). A
// slot is written with one EEPROM.put(): one fopen/fwrite/fclose of the file
// (EEPROM.h), not one per byte as EEPROM.update() does.
class EepromFlash : public FlashArea {
public:
    bool read(size_t offset, uint8_t* buf, size_t len);
    bool write(size_t offset, const uint8_t* data, size_t len);
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
