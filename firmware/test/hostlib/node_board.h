// The node as cubecam.ino builds it, over the real Spresense adapters and the
// real library code on the host fakes of the layer beneath (hostlib/), and
// what the tests of test/hostlib/ share: power-on, a joined node, HTTP
// clients on the simulated module, the parts of an MJPEG stream.
#ifndef CUBECAM_TEST_HOSTLIB_NODE_BOARD_H
#define CUBECAM_TEST_HOSTLIB_NODE_BOARD_H

#include <doctest/doctest.h>
#include <string.h>

#include <algorithm>
#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "core/node.h"
#include "hostlib/gs2200m.h"
#include "hostlib/hostlib.h"
#include "hostlib/video_driver.h"
#include "spresense/arduino_core.h"
#include "spresense/camera.h"
#include "spresense/gs2200.h"
#include "test/fakes.h"

namespace nodeboard {

using namespace cubecam;
using hostlib::module;
using hostlib::video_driver;

const char kPassphrase[] = "correct horse battery staple";

inline Settings station(const char* ssid, const char* password) {
    Settings s;
    settings_defaults(s);
    strcpy(s.ssid, ssid);
    strcpy(s.password, password);
    return s;
}

// Ends the real camera (its threads) after everything holding its images is gone.
struct CameraSession {
    ~CameraSession() { theCamera.end(); }
};

// The node as cubecam.ino builds it; the settings record and LEDs are fakes.
struct Board {
    CameraSession session;
    spresense::ArduinoClock clock;
    spresense::UartSerial serial;
    fake::Storage storage;
    fake::Leds leds;
    fake::System system;
    spresense::SpresenseCamera camera;
    spresense::Gs2200Module wifi;
    Node node;

    explicit Board(const Settings* s, ModuleType type = iS110B_TypeA)
        : wifi(type, clock), node(Hardware{camera, wifi, wifi, serial, storage, clock, leds, system, "CXD5602"}) {
        if (s) {
            uint8_t rec[kSettingsRecordSize];
            settings_encode(*s, rec);
            storage.bytes.assign(rec, rec + sizeof rec);
        }
    }

    // What setup() does.
    void boot() {
        node.boot();
        const char* error = camera.begin(node.running());
        if (error) node.set_error(error);
    }

    // Runs loop() (1 ms of device time per pass) until done() or the passes run out.
    template <class Done>
    bool run_until(Done done, int passes = 20000) {
        for (int i = 0; i < passes; ++i) {
            if (done()) return true;
            node.loop();
            hostlib::advance_ms(1);
        }
        return done();
    }

    // The sensor delivers a frame; waits until the camera callback published it.
    void capture(const std::vector<uint8_t>& jpeg) {
        uint32_t before = camera.latest_seq();
        REQUIRE(video_driver().capture(jpeg));
        for (int i = 0; i < 2000 && camera.latest_seq() == before; ++i) {
            std::this_thread::sleep_for(std::chrono::milliseconds(1));
        }
        REQUIRE(camera.latest_seq() == before + 1);
    }
};

inline void check_no_violations() {
    for (const std::string& v : hostlib::violations()) FAIL_CHECK(v);
}

inline void check_secret_kept(const char* secret) {
    CHECK(hostlib::serial_output().find(secret) == std::string::npos);
}

inline uint8_t http_get(const char* path) {
    uint8_t cid = module().client_connect();
    module().client_send(cid, std::string("GET ") + path + " HTTP/1.1\r\nHost: cubecam\r\n\r\n");
    return cid;
}

// The JPEG bodies of a multipart stream, each as Content-Length says.
inline std::vector<std::string> jpeg_parts(const std::string& stream) {
    std::vector<std::string> parts;
    const std::string key = "Content-Length: ";
    for (size_t at = stream.find(key); at != std::string::npos; at = stream.find(key, at + 1)) {
        size_t len = static_cast<size_t>(atol(stream.c_str() + at + key.size()));
        size_t body = stream.find("\r\n\r\n", at);
        if (body == std::string::npos || body + 4 + len > stream.size()) break;
        parts.push_back(stream.substr(body + 4, len));
    }
    return parts;
}

inline std::vector<std::string> lines_of(const std::string& out) {
    std::vector<fake::DecodedFrame> frames;
    std::vector<std::string> lines;
    fake::split_output(out, frames, lines);
    return lines;
}

inline std::string text(const std::vector<uint8_t>& v) { return std::string(v.begin(), v.end()); }

// Everything back to power-on, with two networks around.
struct PowerOn {
    PowerOn() {
        hostlib::power_on();
        module().networks = {{"lab", kPassphrase, -48, 6}, {"guest", "", -71, 11}};
    }
};

// A node that booted with these settings and serves.
struct Joined {
    PowerOn power;
    Board board;
    explicit Joined(const Settings& s = station("lab", kPassphrase)) : board(&s) {
        board.boot();
        REQUIRE(board.run_until([] { return module().listening(); }));
    }
};

// A client on /stream that has received `first`.
inline uint8_t viewer_of(Board& b, const std::vector<uint8_t>& first) {
    b.capture(first);
    uint8_t cid = http_get("/stream");
    REQUIRE(b.run_until([&] { return jpeg_parts(module().peer(cid).received).size() == 1; }));
    return cid;
}

}  // namespace nodeboard

#endif
