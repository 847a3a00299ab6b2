// The Spresense board beneath the Arduino API, on the host: virtual time,
// pins, the USB serial port, interrupts and critical sections, NuttX
// semaphores (checked) and the NuttX libc extras the core's String uses.
#include <Arduino.h>
#include <File.h>
#include <pthread.h>

#include <atomic>
#include <mutex>

#include "gs2200m.h"
#include "hostlib.h"
#include "video_driver.h"

namespace hostlib {

namespace {

std::atomic<uint64_t> g_now_us(0);
std::mutex g_mutex;  // guards the strings below
std::vector<std::string> g_violations;
std::string g_serial_out;
std::string g_serial_in;
uint8_t g_data_ready_pin = 27;
uint8_t g_reset_pin = 28;
uint8_t g_pin_modes[256];
thread_local bool t_interrupts_off = false;

uint64_t tick() { return g_now_us.fetch_add(kTickUs) + kTickUs; }

}  // namespace

void power_on() {
    g_now_us = 0;
    {
        std::lock_guard<std::mutex> lock(g_mutex);
        g_violations.clear();
    }
    g_data_ready_pin = 27;
    g_reset_pin = 28;
    mcu_reset();
    module().power_on();
}

void mcu_reset() {
    {
        std::lock_guard<std::mutex> lock(g_mutex);
        g_serial_out.clear();
        g_serial_in.clear();
    }
    memset(g_pin_modes, 0xFF, sizeof g_pin_modes);
    spi_power_on();
    video_driver().power_on();
}

void advance_ms(uint32_t ms) { g_now_us += static_cast<uint64_t>(ms) * 1000; }
uint64_t now_us() { return g_now_us; }
void advance_us(uint64_t us) { g_now_us += us; }

void violation(const std::string& what) {
    std::lock_guard<std::mutex> lock(g_mutex);
    g_violations.push_back(what);
}

std::vector<std::string> violations() {
    std::lock_guard<std::mutex> lock(g_mutex);
    return g_violations;
}

std::string serial_output() {
    std::lock_guard<std::mutex> lock(g_mutex);
    return g_serial_out;
}

void serial_input(const std::string& bytes) {
    std::lock_guard<std::mutex> lock(g_mutex);
    g_serial_in += bytes;
}

void set_data_ready_pin(uint8_t pin) { g_data_ready_pin = pin; }
void set_reset_pin(uint8_t pin) { g_reset_pin = pin; }
uint8_t data_ready_pin() { return g_data_ready_pin; }

}  // namespace hostlib

using hostlib::g_mutex;

extern "C" {

uint64_t millis(void) { return hostlib::tick() / 1000; }
uint64_t micros(void) { return hostlib::tick(); }
void delay(unsigned long ms) { hostlib::advance_ms(static_cast<uint32_t>(ms)); }
void delayMicroseconds(unsigned int us) { hostlib::g_now_us += us; }

void pinMode(uint8_t pin, uint8_t mode) { hostlib::g_pin_modes[pin] = mode; }

void digitalWrite(uint8_t pin, uint8_t value) {
    if (hostlib::g_pin_modes[pin] != OUTPUT) {
        hostlib::violation("pin " + std::to_string(pin) + " written but not an output");
        return;
    }
    if (pin == hostlib::g_reset_pin) hostlib::module().reset_line(value == LOW);
}

int digitalRead(uint8_t pin) {
    if (pin != hostlib::g_data_ready_pin) return LOW;
    if (hostlib::g_pin_modes[pin] != INPUT) {
        hostlib::violation("the GS2200M data-ready pin " + std::to_string(pin) + " read before it was set up as an input");
    }
    hostlib::tick();
    return hostlib::module().data_ready() ? HIGH : LOW;
}

void noInterrupts(void) { hostlib::t_interrupts_off = true; }
void interrupts(void) { hostlib::t_interrupts_off = false; }

// NuttX allows a task to block inside its own critical section (the section
// is given up while it waits); only noInterrupts() forbids that.
irqstate_t enter_critical_section(void) { return 0; }
void leave_critical_section(irqstate_t) {}

#undef sem_wait
int hostlib_sem_wait(sem_t* sem) {
    if (hostlib::t_interrupts_off) {
        hostlib::violation("a semaphore was taken with interrupts off (noInterrupts()): "
                           "the board faults when another task holds it");
    }
    return sem_wait(sem);
}

char* itoa(int value, char* str, int radix) {
    if (radix == 10) {
        snprintf(str, 12, "%d", value);
    } else {
        unsigned v = static_cast<unsigned>(value);
        char digits[33];
        int n = 0;
        do {
            digits[n++] = "0123456789abcdefghijklmnopqrstuvwxyz"[v % static_cast<unsigned>(radix)];
            v /= static_cast<unsigned>(radix);
        } while (v);
        for (int i = 0; i < n; ++i) str[i] = digits[n - 1 - i];
        str[n] = '\0';
    }
    return str;
}

}  // extern "C"

HardwareSerial Serial;

void HardwareSerial::begin(unsigned long) {}

int HardwareSerial::available(void) {
    std::lock_guard<std::mutex> lock(g_mutex);
    return static_cast<int>(hostlib::g_serial_in.size());
}

int HardwareSerial::read(void) {
    std::lock_guard<std::mutex> lock(g_mutex);
    if (hostlib::g_serial_in.empty()) return -1;
    int c = static_cast<uint8_t>(hostlib::g_serial_in[0]);
    hostlib::g_serial_in.erase(0, 1);
    return c;
}

size_t HardwareSerial::write(uint8_t c) { return write(&c, 1); }

size_t HardwareSerial::write(const uint8_t* buffer, size_t size) {
    std::lock_guard<std::mutex> lock(g_mutex);
    hostlib::g_serial_out.append(reinterpret_cast<const char*>(buffer), size);
    return size;
}

size_t HardwareSerial::print(const char* text) { return write(reinterpret_cast<const uint8_t*>(text), strlen(text)); }

size_t HardwareSerial::println(const char* text) { return print(text) + print("\r\n"); }

int File::available() {
    hostlib::violation("File used: cubecam loads no certificates");
    return 0;
}

uint32_t File::size() { return static_cast<uint32_t>(available()); }

int File::read(void*, size_t) { return available(); }

// Two findings in the real Camera library that are harmless on the board:
// create_videobuff() mallocs the table of buffers and delete_videobuff()
// frees it with delete (Camera.cpp, "delete video_imgs"), and the singleton
// that getInstance() creates is dropped at exit by ~CameraClass.
extern "C" const char* __asan_default_options() { return "alloc_dealloc_mismatch=0"; }
extern "C" const char* __lsan_default_suppressions() { return "leak:CameraClass::getInstance\n"; }
