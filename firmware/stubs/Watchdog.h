// Stub: Spresense Watchdog library (libraries/Watchdog/Watchdog.h), as used.
#ifndef CUBECAM_STUB_WATCHDOG_H
#define CUBECAM_STUB_WATCHDOG_H

#include <Arduino.h>

class WatchdogClass {
public:
    void begin();
    void end();
    void start(uint32_t timeout);  // 1..40000 ms
    void stop();
    void kick();
    uint32_t timeleft();
};

extern WatchdogClass Watchdog;

#endif
