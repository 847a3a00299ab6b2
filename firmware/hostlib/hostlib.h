// The layer beneath the real Spresense libraries, on a Linux host: a virtual
// clock, GPIO, the USB serial port, the SPI5 bus, a scripted GS2200M on it and
// the NuttX video driver of the ISX019 camera. Tests drive the world through
// these and read what happened; the library code above them is the real one
// from ../shared/vendor/spresense (see firmware/README.md, "make hostlib").
#ifndef CUBECAM_HOSTLIB_HOSTLIB_H
#define CUBECAM_HOSTLIB_HOSTLIB_H

#include <stddef.h>
#include <stdint.h>

#include <string>
#include <vector>

namespace hostlib {

// Everything back to power-on: clock, pins, serial, SPI bus, module, camera
// driver, recorded violations.
void power_on();

// Virtual time. Every millis()/micros() call moves it on by kTickUs, so the
// libraries' busy-wait loops reach their timeouts; delay() moves it by the
// delay.
const uint64_t kTickUs = 10;
void advance_ms(uint32_t ms);
void advance_us(uint64_t us);
uint64_t now_us();

// The MCU alone restarts (watchdog, the console's reboot): pins, serial port,
// SPI bus and camera driver start over; the Wi-Fi module keeps its state and
// the clock runs on.
void mcu_reset();

// Rules of the layer beneath that the code above broke (each one line). On
// the board each of these hangs or faults.
void violation(const std::string& what);
std::vector<std::string> violations();

// The USB serial port: what the node printed (logs, console, Improv, and the
// libraries' own console lines), and bytes typed into it.
std::string serial_output();
void serial_input(const std::string& bytes);

// Data-ready line of the GS2200M (GPIO37 of the module) and its reset input,
// as the board routes them (iS110B type A/B: 27 and 28, type C: 20 and 21).
void set_data_ready_pin(uint8_t pin);
uint8_t data_ready_pin();
void set_reset_pin(uint8_t pin);

// SPI5 as the SPI library sees it: clock of the current transaction. Each
// byte moved costs virtual time: 8 clock periods plus kSpiByteOverheadNs, the
// software around the one SPI5.transfer() call per byte of GS2200Hal.cpp
// (Write_Data, Read_Data): SPI.cpp's transfer() calls the NuttX driver's
// SPI_SETBITS and a one-byte SPI_EXCHANGE, which waits for the byte. The
// overhead is an assumption (0.5-1 us at 156 MHz, the middle taken; no board
// measurement): 1.7 us a byte at 8 MHz, 2.7 us at 4 MHz. docs/firmware.md,
// "Streaming budget".
const uint64_t kSpiByteOverheadNs = 700;
uint32_t spi_clock_hz();
void spi_power_on();

}  // namespace hostlib

#endif
