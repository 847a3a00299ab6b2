#include "board.h"

#include <Arduino.h>
#include <EEPROM.h>
#include <LowPower.h>
#include <Watchdog.h>
#include <string.h>

namespace cubecam {
namespace spresense {

namespace {

const uint8_t kLedPins[4] = {LED0, LED1, LED2, LED3};

// A whole settings slot, so that EEPROM.get/put move it in one file access.
struct Slot {
    uint8_t bytes[kSettingsSlotBytes];
};

}  // namespace

bool EepromFlash::read(size_t offset, uint8_t* buf, size_t len) {
    if (offset + len > EEPROM.length()) return false;
    if (len == kSettingsSlotBytes) {
        Slot slot;
        EEPROM.get(static_cast<int>(offset), slot);
        memcpy(buf, slot.bytes, len);
        return true;
    }
    // Only the record of firmware before the slots is read this way, once.
    for (size_t i = 0; i < len; ++i) buf[i] = EEPROM.read(static_cast<int>(offset + i));
    return true;
}

bool EepromFlash::write(size_t offset, const uint8_t* data, size_t len) {
    if (len != kSettingsSlotBytes || offset + len > EEPROM.length()) return false;
    Slot slot;
    memcpy(slot.bytes, data, len);
    EEPROM.put(static_cast<int>(offset), slot);
    return true;
}

BoardLeds::BoardLeds() {
    for (size_t i = 0; i < sizeof kLedPins; ++i) pinMode(kLedPins[i], OUTPUT);
}

void BoardLeds::show(uint8_t mask) {
    for (size_t i = 0; i < sizeof kLedPins; ++i) digitalWrite(kLedPins[i], (mask >> i) & 1u ? HIGH : LOW);
}

BoardSystem::BoardSystem(uint32_t watchdog_ms) : watchdog_ms_(watchdog_ms) {}

void BoardSystem::begin() {
    LowPower.begin();
    Watchdog.begin();
    Watchdog.start(watchdog_ms_);
}

void BoardSystem::kick_watchdog() { Watchdog.kick(); }

void BoardSystem::reboot() { LowPower.reboot(); }

}  // namespace spresense
}  // namespace cubecam
