// Stub: the parts of the Spresense Arduino core the firmware uses.
#ifndef CUBECAM_STUB_ARDUINO_H
#define CUBECAM_STUB_ARDUINO_H

#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#define HIGH 0x1
#define LOW 0x0
#define INPUT 0x0
#define OUTPUT 0x1
#define LED0 64
#define LED1 65
#define LED2 66
#define LED3 67
#define LED_BUILTIN LED0

uint32_t millis(void);
uint32_t micros(void);
void delay(uint32_t ms);
void pinMode(uint8_t pin, uint8_t mode);
void digitalWrite(uint8_t pin, uint8_t value);
int digitalRead(uint8_t pin);
void noInterrupts(void);
void interrupts(void);

class String {
public:
    String(const char* s = "");
    const char* c_str() const;
    unsigned int length() const;
};

class HardwareSerial {
public:
    void begin(unsigned long baud);
    void end();
    int available(void);
    int read(void);
    size_t write(uint8_t c);
    size_t write(const uint8_t* buffer, size_t size);
    void flush(void);
    operator bool();
};

extern HardwareSerial Serial;

#endif
