// libFuzzer target: arbitrary bytes on the serial port (Improv frames, console
// lines, noise) reach the whole node. Afterwards the console must still
// answer, and the stored password must never appear in the output (unless the
// input typed it into another key, which may be shown).
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <string>

#include "core/node.h"
#include "test/fakes.h"

using namespace cubecam;

static void require(bool ok) {
    if (!ok) abort();
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    static const char kSecret[] = "fuzz-secret-77";
    fake::Camera camera;
    fake::Network net;
    fake::Wifi wifi;
    fake::Serial serial;
    fake::Storage storage;
    fake::Clock clock;
    fake::Leds leds;
    fake::System system;
    Hardware hw = {camera, net, wifi, serial, storage, clock, leds, system, "FUZZ"};
    Settings s;
    settings_defaults(s);
    settings_set(s, "ssid", "lab", 3);
    settings_set(s, "password", kSecret, strlen(kSecret));
    uint8_t rec[kSettingsRecordSize];
    settings_encode(s, rec);
    storage.bytes.assign(rec, rec + sizeof rec);
    wifi.next = JoinStatus::Joined;
    Node node(hw);
    node.boot();
    // Bytes arrive in bursts; a 0xFF byte stands for a 150 ms pause, so
    // the partial-frame timeout is exercised too.
    std::string stream;
    for (size_t i = 0; i < size; ++i) {
        if (data[i] == 0xFF) {
            clock.advance_ms(150);
        } else {
            serial.in.push_back(static_cast<char>(data[i]));
            stream.push_back(static_cast<char>(data[i]));
        }
        if (serial.in.size() >= 64 || data[i] == 0xFF) node.loop();
    }
    node.loop();
    clock.advance_ms(150);
    node.loop();
    bool typed = stream.find(kSecret) != std::string::npos;
    require(typed || serial.out.find(kSecret) == std::string::npos);
    serial.out.clear();
    serial.in = "\nget fps\n";
    clock.advance_ms(150);
    node.loop();
    node.loop();
    require(serial.out.find("fps=") != std::string::npos && serial.out.find("OK\n") != std::string::npos);
    return 0;
}
