// cubecam sketch for the Sony Spresense: HDR camera board (ISX019) + iS110B
// Wi-Fi add-on (Telit GS2200M). Hardware glue only: it builds the adapters,
// hands them to the portable core (src/core) and runs its loop.
// Everything the node does is in cubecam::Node; see docs/firmware.md.
#include <Arduino.h>

#include "src/core/node.h"
#include "src/spresense/arduino_core.h"
#include "src/spresense/board.h"
#include "src/spresense/camera.h"
#include "src/spresense/gs2200.h"

namespace {

// The iS110B revision sets the GS2200M data-ready pin: types A and B use
// pin 27, type C uses pin 20. Change this to iS110B_TypeC for a type C board.
const ModuleType kWifiBoard = iS110B_TypeA;

// The GS2200 library may block for up to 20 s in one SPI transfer.
const uint32_t kWatchdogMs = 30000;
const unsigned long kSerialBaud = 115200;

struct Board {
    cubecam::spresense::ArduinoClock clock;
    cubecam::spresense::UartSerial serial;
    cubecam::spresense::EepromFlash flash;
    cubecam::SlotStorage storage;
    cubecam::spresense::BoardLeds leds;
    cubecam::spresense::BoardSystem system;
    cubecam::spresense::SpresenseCamera camera;
    cubecam::spresense::Gs2200Module wifi;
    cubecam::Node node;

    Board()
        : storage(flash),
          system(kWatchdogMs),
          wifi(kWifiBoard, clock),
          node(cubecam::Hardware{camera, wifi, wifi, serial, storage, clock, leds, system, "CXD5602"}) {}
};

// Built on first use in setup(), after the Arduino core is up.
Board& board() {
    static Board b;
    return b;
}

}  // namespace

void setup() {
    Serial.begin(kSerialBaud);
    Board& b = board();
    b.system.begin();
    b.node.boot();
    const char* error = b.camera.begin(b.node.running());
    if (error) b.node.set_error(error);
}

void loop() { board().node.loop(); }
