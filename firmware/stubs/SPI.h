// Stub: Spresense SPI library (libraries/SPI/SPI.h), as used.
#ifndef CUBECAM_STUB_SPI_H
#define CUBECAM_STUB_SPI_H

#include <Arduino.h>

#define MSBFIRST 1
#define SPI_MODE0 0
#define SPI_MODE1 1

class SPISettings {
public:
    SPISettings(uint32_t clock, uint8_t bitOrder, uint8_t dataMode);
};

class SPIClass {
public:
    void begin();
    void end();
    void beginTransaction(SPISettings settings);
    void endTransaction();
    uint8_t transfer(uint8_t data);
};

extern SPIClass SPI5;

#endif
