// Stub: Spresense LowPower library (libraries/LowPower/src/LowPower.h), as used.
#ifndef CUBECAM_STUB_LOWPOWER_H
#define CUBECAM_STUB_LOWPOWER_H

#include <Arduino.h>

typedef enum {
    POR_SUPPLY = 0,
    WDT_REBOOT = 1,
    WDT_RESET = 2,
    POR_NORMAL = 32,
} bootcause_e;

typedef enum {
    CLOCK_MODE_156MHz = 0,
    CLOCK_MODE_32MHz,
    CLOCK_MODE_8MHz,
} clockmode_e;

class LowPowerClass {
public:
    void begin();
    void end();
    bootcause_e bootCause();
    void reboot();
    void clockMode(clockmode_e mode);
};

extern LowPowerClass LowPower;

#endif
