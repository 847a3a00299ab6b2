#include <string>
#include <vector>

#include <doctest/doctest.h>

#include "core/node.h"
#include "fakes.h"

using namespace cubecam;

namespace {

struct Board {
    fake::Camera camera;
    fake::Network net;
    fake::Wifi wifi;
    fake::Serial serial;
    fake::Storage storage;
    fake::Clock clock;
    fake::Leds leds;
    fake::System system;
    Hardware hw{camera, net, wifi, serial, storage, clock, leds, system, "TEST"};

    void store(const Settings& s) {
        std::vector<uint8_t> rec(kSettingsRecordSize);
        settings_encode(s, rec.data());
        storage.bytes = rec;
    }
    // Runs the loop for ms milliseconds in 1 ms steps.
    void run(Node& node, uint32_t ms) {
        for (uint32_t i = 0; i < ms; ++i) {
            node.loop();
            clock.advance_ms(1);
        }
    }
    void split(std::vector<fake::DecodedFrame>& frames, std::vector<std::string>& lines) {
        fake::split_output(serial.out, frames, lines);
        serial.out.clear();
    }
};

Settings provisioned(const char* ssid) {
    Settings s;
    settings_defaults(s);
    REQUIRE(settings_set(s, "ssid", ssid, strlen(ssid)).ok());
    return s;
}

std::vector<std::string> strings_of(const fake::DecodedFrame& f) {
    std::vector<std::string> out;
    size_t pos = 2;
    while (pos < f.data.size()) {
        size_t n = f.data[pos];
        out.push_back(std::string(f.data.begin() + static_cast<long>(pos) + 1,
                                  f.data.begin() + static_cast<long>(pos + 1 + n)));
        pos += 1 + n;
    }
    return out;
}

}  // namespace

TEST_CASE("zero-filled storage boots with defaults and waits for provisioning") {
    Board b;
    b.storage.bytes.assign(kSettingsRecordSize, 0);
    Node node(b.hw);
    node.boot();
    b.run(node, 50);
    std::vector<fake::DecodedFrame> frames;
    std::vector<std::string> lines;
    b.split(frames, lines);
    CHECK(frames.empty());
    bool warned = false;
    for (const std::string& l : lines) {
        CHECK(l.compare(0, 1, "[") == 0);  // every log line is a tagged line
        warned |= l.find("factory defaults") != std::string::npos;
    }
    CHECK(warned);
    CHECK(b.wifi.resets == 0);
    CHECK(b.net.opened_port == 0);
    CHECK(b.system.kicks >= 50);
}

TEST_CASE("stored settings are used and printed with the password masked") {
    Board b;
    Settings s = provisioned("lab");
    REQUIRE(settings_set(s, "password", "topsecret99", 11).ok());
    REQUIRE(settings_set(s, "port", "8080", 4).ok());
    b.store(s);
    b.wifi.next = JoinStatus::Joined;
    Node node(b.hw);
    node.boot();
    b.run(node, 5);
    CHECK(b.serial.out.find("topsecret99") == std::string::npos);
    CHECK(b.serial.out.find("[I][config] password=(set)\n") != std::string::npos);
    CHECK(b.net.opened_port == 8080);
    CHECK(b.serial.out.find("listening on http://192.168.1.20:8080/") != std::string::npos);
}

TEST_CASE("Improv: state, device info and scan") {
    Board b;
    Node node(b.hw);
    node.boot();
    b.serial.out.clear();
    b.serial.in = fake::improv_rpc(improv::Command::GetCurrentState, {}) +
                  fake::improv_rpc(improv::Command::GetDeviceInfo, {}) +
                  fake::improv_rpc(improv::Command::GetWifiNetworks, {});
    b.run(node, 3);
    std::vector<fake::DecodedFrame> frames;
    std::vector<std::string> lines;
    b.split(frames, lines);
    REQUIRE(frames.size() == 5);
    CHECK(frames[0].type == improv::FrameType::CurrentState);
    CHECK(frames[0].data == std::vector<uint8_t>{0x02});
    CHECK(frames[1].type == improv::FrameType::RpcResult);
    CHECK(frames[1].data[0] == 0x03);
    CHECK(strings_of(frames[1]) == std::vector<std::string>{"cubecam", "0.1.0", "TEST", "cubecam"});
    CHECK(strings_of(frames[2]) == std::vector<std::string>{"lab", "-40", "YES"});
    CHECK(strings_of(frames[3]) == std::vector<std::string>{"guest", "-50", "NO"});
    CHECK(frames[4].data == std::vector<uint8_t>{0x04, 0x00});
}

TEST_CASE("an Improv frame whose bytes waited in the UART while the loop was blocked is not cut") {
    Board b;
    Node node(b.hw);
    node.boot();
    b.serial.out.clear();
    // 32 + 63 bytes of credentials: one frame of more than 64 bytes.
    std::string frame = fake::improv_rpc(improv::Command::WifiSettings, {std::string(32, 's'), std::string(63, 'p')});
    REQUIRE(frame.size() > 100);
    b.serial.in = frame.substr(0, 40);
    node.loop();
    // A join step (AT commands) holds the loop for 2 s; the rest arrived meanwhile.
    b.clock.advance_ms(2000);
    b.serial.in += frame.substr(40);
    node.loop();
    node.loop();
    std::vector<fake::DecodedFrame> frames;
    std::vector<std::string> lines;
    b.split(frames, lines);
    REQUIRE(frames.size() >= 1);
    CHECK(frames[0].data == std::vector<uint8_t>{0x03});  // PROVISIONING: the frame was taken whole
    CHECK(b.wifi.joined_ssids == std::vector<std::string>{std::string(32, 's')});
}

TEST_CASE("Improv provisioning: joins, saves, answers PROVISIONED with the URL; password never printed") {
    Board b;
    Node node(b.hw);
    node.boot();
    b.serial.out.clear();
    b.serial.in = fake::improv_rpc(improv::Command::WifiSettings, {"lab", "s3cret-pass"});
    b.run(node, 5);
    b.wifi.next = JoinStatus::Joined;
    b.run(node, 5);
    std::vector<fake::DecodedFrame> frames;
    std::vector<std::string> lines;
    b.split(frames, lines);
    REQUIRE(frames.size() == 3);
    CHECK(frames[0].data == std::vector<uint8_t>{0x03});  // PROVISIONING
    CHECK(frames[1].data == std::vector<uint8_t>{0x04});  // PROVISIONED
    CHECK(frames[2].type == improv::FrameType::RpcResult);
    CHECK(frames[2].data[0] == 0x01);
    CHECK(strings_of(frames[2]) == std::vector<std::string>{"http://192.168.1.20/"});
    Settings saved;
    REQUIRE(settings_decode(b.storage.bytes.data(), b.storage.bytes.size(), saved));
    CHECK(std::string(saved.ssid) == "lab");
    CHECK(std::string(saved.password) == "s3cret-pass");
    for (const std::string& l : lines) CHECK(l.find("s3cret") == std::string::npos);
    CHECK(b.net.opened_port == 80);
    // Asking again reports the state and the URL.
    b.serial.in = fake::improv_rpc(improv::Command::GetCurrentState, {});
    b.run(node, 2);
    frames.clear();
    b.split(frames, lines);
    REQUIRE(frames.size() == 2);
    CHECK(frames[0].data == std::vector<uint8_t>{0x04});
    CHECK(strings_of(frames[1]) == std::vector<std::string>{"http://192.168.1.20/"});
}

TEST_CASE("Improv provisioning takes passphrases with commas, quotes, spaces and UTF-8, byte for byte") {
    for (const std::string& pass : {std::string("my \"secret\", ok?"), std::string(" lead,trail "),
                                    std::string("caf\xc3\xa9 cr\xc3\xa8me 123")}) {
        CAPTURE(pass);
        Board b;
        Node node(b.hw);
        node.boot();
        b.serial.out.clear();
        b.serial.in = fake::improv_rpc(improv::Command::WifiSettings, {"lab", pass});
        b.run(node, 5);
        b.wifi.next = JoinStatus::Joined;
        b.run(node, 5);
        CHECK(b.wifi.joined_passwords == std::vector<std::string>{pass});
        Settings saved;
        REQUIRE(settings_decode(b.storage.bytes.data(), b.storage.bytes.size(), saved));
        CHECK(std::string(saved.password) == pass);
        CHECK(b.serial.out.find(pass) == std::string::npos);
    }
}

TEST_CASE("Improv provisioning that cannot join answers error 3 and READY, and keeps the old settings") {
    Board b;
    b.store(provisioned("old"));
    Node node(b.hw);
    node.boot();
    b.run(node, 2);
    b.serial.out.clear();
    b.serial.in = fake::improv_rpc(improv::Command::WifiSettings, {"new", "password1"});
    b.run(node, 2);
    b.wifi.next = JoinStatus::Failed;
    b.run(node, 2);
    std::vector<fake::DecodedFrame> frames;
    std::vector<std::string> lines;
    b.split(frames, lines);
    REQUIRE(frames.size() == 3);
    CHECK(frames[0].data == std::vector<uint8_t>{0x03});
    CHECK(frames[1].type == improv::FrameType::ErrorState);
    CHECK(frames[1].data == std::vector<uint8_t>{0x03});
    CHECK(frames[2].data == std::vector<uint8_t>{0x02});
    Settings saved;
    REQUIRE(settings_decode(b.storage.bytes.data(), b.storage.bytes.size(), saved));
    CHECK(std::string(saved.ssid) == "old");
}

TEST_CASE("Improv credentials that the module cannot take get a clear error, not an overflow") {
    Board b;
    Node node(b.hw);
    node.boot();
    b.serial.out.clear();
    b.serial.in = fake::improv_rpc(improv::Command::WifiSettings, {std::string(32, 's'), std::string(64, 'p')});
    b.run(node, 2);
    std::vector<fake::DecodedFrame> frames;
    std::vector<std::string> lines;
    b.split(frames, lines);
    REQUIRE(frames.size() == 1);
    CHECK(frames[0].type == improv::FrameType::ErrorState);
    CHECK(frames[0].data == std::vector<uint8_t>{0x01});
    REQUIRE_FALSE(lines.empty());
    CHECK(lines.back() == "[E][improv] password must be 8 to 63 bytes (WPA2 passphrase)");
    CHECK(b.wifi.joined_ssids.empty());
}

TEST_CASE("bad checksums and unknown RPCs get Improv errors") {
    Board b;
    Node node(b.hw);
    node.boot();
    b.serial.out.clear();
    std::string bad = fake::improv_rpc(improv::Command::GetCurrentState, {});
    bad[bad.size() - 2] ^= 1;
    b.serial.in = bad + fake::improv_rpc(static_cast<improv::Command>(0x42), {});
    b.run(node, 2);
    std::vector<fake::DecodedFrame> frames;
    std::vector<std::string> lines;
    b.split(frames, lines);
    REQUIRE(frames.size() == 2);
    CHECK(frames[0].data == std::vector<uint8_t>{0x01});
    CHECK(frames[1].data == std::vector<uint8_t>{0x02});
}

TEST_CASE("console and Improv share the port") {
    Board b;
    Node node(b.hw);
    node.boot();
    b.serial.out.clear();
    b.serial.in = "get fps\n" + fake::improv_rpc(improv::Command::GetCurrentState, {}) + "set name cam-7\n";
    b.run(node, 3);
    std::vector<fake::DecodedFrame> frames;
    std::vector<std::string> lines;
    b.split(frames, lines);
    CHECK(frames.size() == 1);
    CHECK(lines == std::vector<std::string>{"fps=15", "OK", "OK"});
}

TEST_CASE("a stalled Improv frame is dropped after 100 ms; a slowly typed I is console input") {
    Board b;
    Node node(b.hw);
    node.boot();
    b.serial.out.clear();
    b.serial.in = std::string("IMPROV\x01\x03\x05", 9);
    b.run(node, 150);
    b.serial.in = "help\n";
    b.run(node, 2);
    std::vector<fake::DecodedFrame> frames;
    std::vector<std::string> lines;
    b.split(frames, lines);
    CHECK(frames.empty());
    REQUIRE_FALSE(lines.empty());
    CHECK(lines.front() == "commands:");
    CHECK(lines.back() == "OK");
    b.serial.in = "I";
    b.run(node, 150);
    b.serial.in = "MPROVE\n";
    b.run(node, 2);
    lines.clear();
    b.split(frames, lines);
    CHECK(lines == std::vector<std::string>{"ERR 1 unknown command; try help"});
}

TEST_CASE("console changes apply after save and reboot") {
    Board b;
    Node node(b.hw);
    node.boot();
    b.serial.in = "set fps 30\nsave\nreboot\n";
    b.run(node, 50);
    CHECK(b.system.reboots == 0);  // "OK" first
    b.run(node, 100);
    CHECK(b.system.reboots == 1);
    CHECK(node.running().fps == FrameRate::Fps15);
    Node after(b.hw);
    after.boot();
    CHECK(after.running().fps == FrameRate::Fps30);
}

TEST_CASE("a lost link drops the clients, rejoins after the backoff and reopens the server") {
    Board b;
    b.store(provisioned("lab"));
    b.wifi.next = JoinStatus::Joined;
    Node node(b.hw);
    node.boot();
    b.run(node, 3);
    CHECK(b.net.opened_port == 80);
    b.net.connect(1);
    b.net.send(1, "GET /stream HTTP/1.1\r\n\r\n");
    b.camera.capture(fake::jpeg(20000, 1), 0);
    b.net.accept_limit = 100;
    b.run(node, 5);
    CHECK(b.camera.out == 1);
    b.net.opened_port = 0;
    b.net.event(NetEventKind::ModuleRebooted);
    b.run(node, 2);
    CHECK(b.camera.out == 0);
    CHECK(b.net.close_all_calls >= 1);
    int resets = b.wifi.resets;
    b.run(node, kFirstBackoffMs + 5);
    CHECK(b.wifi.resets == resets + 1);
    CHECK(b.net.opened_port == 80);
    CHECK(b.serial.out.find("[W][link] network lost; reconnecting\n") != std::string::npos);
}

TEST_CASE("a server that cannot open is an error and a retry") {
    Board b;
    b.store(provisioned("lab"));
    b.wifi.next = JoinStatus::Joined;
    b.net.fail_open = true;
    Node node(b.hw);
    node.boot();
    b.run(node, 3);
    CHECK(b.serial.out.find("[E][node] could not open the HTTP server") != std::string::npos);
    CHECK((b.leds.mask & kLedError) != 0);
    b.net.fail_open = false;
    b.run(node, kFirstBackoffMs + 5);
    CHECK(b.net.opened_port == 80);
}

TEST_CASE("measured fps follows the camera") {
    Board b;
    b.store(provisioned("lab"));
    b.wifi.next = JoinStatus::Joined;
    Node node(b.hw);
    node.boot();
    for (int i = 0; i < 90; ++i) {  // 3 s at 30 fps
        b.camera.capture(fake::jpeg(100, 1), b.clock.now_us);
        b.run(node, 33);
        b.clock.advance_ms(i % 3 == 0 ? 1 : 0);
    }
    b.serial.in = "status\n";
    b.run(node, 2);
    size_t p = b.serial.out.find("fps=15.0 measured=");
    REQUIRE(p != std::string::npos);
    double measured = atof(b.serial.out.c_str() + p + 18);
    CHECK(measured > 28.0);
    CHECK(measured < 32.0);
}

TEST_CASE("a camera that stops delivering frames is restarted, once no frame is lent out") {
    Board b;
    b.store(provisioned("lab"));
    b.wifi.next = JoinStatus::Joined;
    Node node(b.hw);
    node.boot();
    b.run(node, kCameraStallMs * 2);
    CHECK(b.camera.restarts == 0);  // no frame yet: nothing stopped
    b.camera.capture(fake::jpeg(100, 1), b.clock.now_us);
    Frame lent;
    REQUIRE(b.camera.acquire_latest(lent));  // a client still sends it
    b.run(node, kCameraStallMs + 10);
    CHECK(b.camera.restarts == 0);
    b.camera.release(lent.lease);
    b.run(node, 2);
    CHECK(b.camera.restarts == 1);
    CHECK(b.serial.out.find("[W][camera] no frame for 5 s; camera restarted") != std::string::npos);
    b.camera.capture(fake::jpeg(100, 2), b.clock.now_us);  // frames again: the count starts over
    b.run(node, kCameraStallMs - 10);
    CHECK(b.camera.restarts == 1);
    b.run(node, (kMaxCameraRestarts + 1) * kCameraStallMs);
    CHECK(b.camera.restarts == 1 + kMaxCameraRestarts);  // three more, then it gives up
    CHECK(b.serial.out.find("[E][node] camera: no frames after 3 restarts") != std::string::npos);
    CHECK((b.leds.mask & kLedError) != 0);
}

TEST_CASE("a camera that does not come back from a restart latches an error") {
    Board b;
    b.store(provisioned("lab"));
    Node node(b.hw);
    node.boot();
    b.camera.capture(fake::jpeg(100, 1), b.clock.now_us);
    b.camera.restart_result = CameraRestart::Failed;
    b.run(node, 3 * kCameraStallMs);
    CHECK(b.camera.restarts == 1);
    CHECK(b.serial.out.find("camera: no frames, and it did not start again") != std::string::npos);
}
