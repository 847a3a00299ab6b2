// Stub: Spresense EEPROM emulation (libraries/EEPROM/src/EEPROM.h), as used.
#ifndef CUBECAM_STUB_EEPROM_H
#define CUBECAM_STUB_EEPROM_H

#include <Arduino.h>

#define E2END 4000

class EEPROMClass {
public:
    uint8_t read(int idx);
    void write(int idx, uint8_t val);
    void update(int idx, uint8_t val);
    uint16_t length();
    template <typename T>
    T& get(int idx, T& t);
    template <typename T>
    const T& put(int idx, const T& t);
};

extern EEPROMClass EEPROM;

#endif
