#include "board.h"

#include <Arduino.h>
#include <EEPROM.h>
#include <LowPower.h>
#include <Watchdog.h>

namespace cubecam {
namespace spresense {

namespace {

const uint8_t kLedPins[4] = {LED0, LED1, LED2, LED3};

}  // namespace

bool EepromStorage::load(uint8_t* buf, size_t len) {
    if (len > EEPROM.length()) return false;
    for (size_t i = 0; i < len; ++i) buf[i] = EEPROM.read(static_cast<int>(i));
    return true;
}

bool EepromStorage::store(const uint8_t* buf, size_t len) {
    if (len > EEPROM.length()) return false;
    // update() skips unchanged bytes; each call is a file write on the flash.
    for (size_t i = 0; i < len; ++i) EEPROM.update(static_cast<int>(i), buf[i]);
    for (size_t i = 0; i < len; ++i) {
        if (EEPROM.read(static_cast<int>(i)) != buf[i]) return false;
    }
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
