// Stand-in for the Spresense core's Arduino.h on a Linux host (make hostlib).
// The real one needs the NuttX kernel headers and ARM code; this declares the
// part of it that the GS2200-WiFi library, the Camera library and our
// adapters use, with the real signatures (millis() and micros() return
// uint64_t as in cores/spresense/Arduino.h), and takes the real String
// (cores/spresense/WString.h). Behind it: hostlib/board.cpp.
#ifndef CUBECAM_HOSTLIB_ARDUINO_H
#define CUBECAM_HOSTLIB_ARDUINO_H

#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

typedef uint8_t byte;

#define LOW 0x0
#define HIGH 0x1
#define INPUT 0x0
#define OUTPUT 0x1
#define LSBFIRST 0x0
#define MSBFIRST 0x1

// variants/spresense/pins_arduino.h
#define LED0 (64)
#define LED1 (65)
#define LED2 (66)
#define LED3 (67)

#ifdef __cplusplus
extern "C" {
#endif
void pinMode(uint8_t pin, uint8_t mode);
void digitalWrite(uint8_t pin, uint8_t value);
int digitalRead(uint8_t pin);
uint64_t millis(void);
uint64_t micros(void);
void delay(unsigned long ms);
void delayMicroseconds(unsigned int us);
void interrupts(void);
void noInterrupts(void);

// NuttX critical sections (nuttx/irq.h), which the GS2200 library takes
// around each SPI transfer. Unlike noInterrupts() they may be held across a
// semaphore wait.
typedef uint32_t irqstate_t;
irqstate_t enter_critical_section(void);
void leave_critical_section(irqstate_t flags);
#ifdef __cplusplus
}

#include <WString.h>

// The USB serial port (UART1), shared on the board with printf() and the
// GS2200 library's ConsoleLog(). Only what the code under test calls.
class HardwareSerial {
public:
    void begin(unsigned long baud);
    int available(void);
    int read(void);
    size_t write(uint8_t c);
    size_t write(const uint8_t* buffer, size_t size);
    size_t print(const char* text);
    size_t println(const char* text);
};

extern HardwareSerial Serial;
#endif

#endif
