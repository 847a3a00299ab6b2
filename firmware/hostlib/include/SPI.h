// Stand-in for the Spresense core's SPI library (libraries/SPI/SPI.h) on a
// Linux host (make hostlib). The real SPIClass sits on the NuttX cxd56 SPI
// driver, which cannot be built for a host; hostlib/spi_bus.cpp gives the same
// public behaviour over the simulated GS2200M: begin() counts references and
// every other call returns at once while the count is 0, beginTransaction()
// takes the bus lock, which is NOT recursive (a NuttX nxmutex), and
// endTransaction() gives it back.
#ifndef CUBECAM_HOSTLIB_SPI_H
#define CUBECAM_HOSTLIB_SPI_H

#include <Arduino.h>

// enum spi_mode_e of nuttx/spi/spi.h
#define SPI_MODE0 0
#define SPI_MODE1 1
#define SPI_MODE2 2
#define SPI_MODE3 3

class SPISettings {
public:
    SPISettings(uint32_t clock, uint8_t bitOrder, uint8_t dataMode)
        : clock_(clock), bit_order_(bitOrder), data_mode_(dataMode) {}
    SPISettings() : clock_(4000000), bit_order_(MSBFIRST), data_mode_(SPI_MODE0) {}
    uint32_t clock_;
    uint8_t bit_order_;
    uint8_t data_mode_;
};

class SPIClass {
public:
    explicit SPIClass(int port);
    void begin(void);
    void end(void);
    void beginTransaction(SPISettings settings);
    void endTransaction(void);
    uint8_t transfer(uint8_t data);
    void transfer(void* buf, size_t count);

private:
    int port_;
    int ref_count_;
};

extern SPIClass SPI5;

#endif
