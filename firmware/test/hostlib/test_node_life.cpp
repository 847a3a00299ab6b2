// The node's life with the real Spresense adapters over the real library code
// (Camera.cpp's image buffers and threads, GS2200Hal / GS2200AtCmd /
// TelitWiFi), on the host fakes of the layer beneath them (hostlib/). Each
// case starts from power-on; pytest runs each in its own process.
#include "test/hostlib/node_board.h"

namespace {

using namespace cubecam;
using namespace nodeboard;
using hostlib::module;
using hostlib::video_driver;

}  // namespace

TEST_CASE("boot: the node joins through the real GS2200 library and answers /status") {
    Joined j;
    CHECK(module().associated());
    CHECK(module().joined_ssid() == "lab");
    CHECK_FALSE(module().power_save());  // begin() turned it on; streaming wants it off
    uint8_t cid = http_get("/status");
    REQUIRE(j.board.run_until([cid] { return !module().peer(cid).received.empty() && !module().peer(cid).open; }));
    const std::string& reply = module().peer(cid).received;
    CHECK(reply.find("HTTP/1.1 200") == 0);
    CHECK(reply.find("\"ip\":\"192.168.1.23\"") != std::string::npos);
    check_no_violations();
    check_secret_kept(kPassphrase);
    // Contracts §2: log lines start with '['. The GS2200 library prints its
    // own on the same port (ConsoleLog, GS2200Hal.cpp); this is the one a boot shows.
    for (const std::string& line : lines_of(hostlib::serial_output())) {
        if (line.empty() || line[0] != '[') CHECK(line == "GS2200 is ready to go.\r");  // println ends in CR LF
    }
}

TEST_CASE("stream: four clients get whole frames; a fifth gets 503; a client leaves") {
    Joined j;
    Board& b = j.board;
    REQUIRE(video_driver().streaming());
    CHECK(video_driver().jpeg_quality() == b.node.running().jpeg_quality);
    std::vector<std::vector<uint8_t>> frames;
    for (uint8_t k = 1; k <= 8; ++k) frames.push_back(fake::jpeg(30000 + 1500 * k, k));
    b.capture(frames[0]);

    std::vector<uint8_t> clients;
    for (int i = 0; i < 4; ++i) clients.push_back(http_get("/stream"));
    uint8_t fifth = http_get("/stream");
    auto parts_of = [](uint8_t cid) { return jpeg_parts(module().peer(cid).received); };
    REQUIRE(b.run_until([&] { return !module().peer(fifth).open; }));
    CHECK(module().peer(fifth).received.find("HTTP/1.1 503") == 0);

    for (size_t k = 0; k < 4; ++k) {
        if (k > 0) b.capture(frames[k]);
        REQUIRE(b.run_until([&] {
            for (uint8_t c : clients) {
                if (parts_of(c).size() < k + 1) return false;
            }
            return true;
        }));
    }
    // One client leaves; the others go on, and its frame goes back to the driver.
    module().client_close(clients[1]);
    for (size_t k = 4; k < 8; ++k) {
        b.capture(frames[k]);
        REQUIRE(b.run_until([&] { return parts_of(clients[0]).size() == k + 1 && parts_of(clients[3]).size() == k + 1; }));
    }
    for (uint8_t c : clients) {
        for (const std::string& part : parts_of(c)) {
            bool intact = false;
            for (const auto& f : frames) intact = intact || part == text(f);
            CHECK_MESSAGE(intact, "client ", int(c), " got a frame that is not one the sensor delivered");
        }
    }
    // Nothing is leased once the clients are between frames: the adapter keeps
    // the newest frame and the driver has every other buffer.
    REQUIRE(b.run_until([&] { return video_driver().queued_buffers() == spresense::kCameraBuffers - 1; }, 2000));
    check_no_violations();
}

TEST_CASE("Wi-Fi drops and the module restarts; the node rejoins each time") {
    Joined j;
    Board& b = j.board;
    viewer_of(b, fake::jpeg(20000, 1));

    module().drop_association();
    REQUIRE(b.run_until([] { return !module().listening(); }));
    REQUIRE(b.run_until([] { return module().listening(); }));
    module().reboot();
    REQUIRE(b.run_until([] { return !module().listening(); }));
    REQUIRE(b.run_until([] { return module().listening(); }));

    uint8_t cid = http_get("/capture");
    REQUIRE(b.run_until([cid] { return !module().peer(cid).open; }));
    CHECK(module().peer(cid).received.find("HTTP/1.1 200") == 0);
    CHECK(module().peer(cid).received.find(text(fake::jpeg(20000, 1))) != std::string::npos);
    check_no_violations();
}

TEST_CASE("access point with a 32-byte SSID and a 63-byte passphrase") {
    const std::string ssid(32, 'S');
    const std::string pass = std::string(62, 'p') + "!";
    Settings s = station(ssid.c_str(), pass.c_str());
    s.mode = WifiMode::AccessPoint;
    Joined j(s);
    CHECK(module().access_point());
    CHECK(module().joined_ssid() == ssid);
    const auto& cmds = module().commands;
    CHECK(std::find(cmds.begin(), cmds.end(), "AT+WPAPSK=" + ssid + "," + pass) != cmds.end());
    uint8_t cid = http_get("/status");
    REQUIRE(j.board.run_until([cid] { return !module().peer(cid).open; }));
    CHECK(module().peer(cid).received.find("HTTP/1.1 200") == 0);
    check_no_violations();
    check_secret_kept(pass.c_str());
}

TEST_CASE("passphrases with commas and quotes and spaces and UTF-8 reach the module intact") {
    struct Case {
        std::string passphrase;
        std::string wpapsk;  // the AT+WPAPSK the module gets
        bool key;            // and then AT+WPSK with the key
    };
    const Case cases[] = {
        {"correct horse battery", "AT+WPAPSK=lab,correct horse battery", false},
        {"a,b,c,d,e", "AT+WPAPSK=lab,\"a,b,c,d,e\"", false},
        {" spaced, out ", "AT+WPAPSK=lab,\" spaced, out \"", false},
        {"my \"secret\", ok", "AT+WPAPSK=lab,cubecam-key-follows", true},
        {"ends, in \\", "AT+WPAPSK=lab,cubecam-key-follows", true},
        {"caf\xc3\xa9 cr\xc3\xa8me", "AT+WPAPSK=lab,cubecam-key-follows", true},
    };
    for (const Case& c : cases) {
        CAPTURE(c.passphrase);
        PowerOn power;
        module().networks = {{"lab", c.passphrase, -48, 6}};
        Settings s = station("lab", c.passphrase.c_str());
        Board b(&s);
        b.boot();
        REQUIRE(b.run_until([] { return module().listening(); }));
        CHECK(module().joined_ssid() == "lab");
        const auto& cmds = module().commands;
        auto wpapsk = std::find(cmds.begin(), cmds.end(), c.wpapsk);
        REQUIRE(wpapsk != cmds.end());
        bool key_sent = wpapsk + 1 != cmds.end() && (wpapsk + 1)->compare(0, 8, "AT+WPSK=") == 0;
        CHECK(key_sent == c.key);
        CHECK(std::find(cmds.begin(), cmds.end(), "AT+WA=lab") != cmds.end());
        check_no_violations();
        check_secret_kept(c.passphrase.c_str());
    }
}

TEST_CASE("access point whose SSID has quotes and whose passphrase goes as its key") {
    const std::string ssid = "\"cam\" " + std::string(26, 'S');
    const std::string pass = "say \"hi\", " + std::string(53, 'p');
    REQUIRE(ssid.size() == 32);
    REQUIRE(pass.size() == 63);
    Settings s = station(ssid.c_str(), pass.c_str());
    s.mode = WifiMode::AccessPoint;
    Joined j(s);
    CHECK(module().access_point());
    CHECK(module().joined_ssid() == ssid);
    CHECK(module().key() == hostlib::Gs2200m::derived_key(ssid, pass));  // what a station derives too
    const auto& cmds = module().commands;
    std::string escaped = "\\\"cam\\\" " + std::string(26, 'S');
    CHECK(std::find(cmds.begin(), cmds.end(), "AT+WA=" + escaped + ",,6") != cmds.end());
    check_no_violations();
    check_secret_kept(pass.c_str());
}

TEST_CASE("Improv scan on a fresh board lists the module's networks") {
    PowerOn power;
    Board b(nullptr);
    b.boot();
    b.run_until([] { return false; }, 50);
    hostlib::serial_input(fake::improv_rpc(improv::Command::GetWifiNetworks, {}));
    std::vector<std::vector<std::string>> results;
    auto scan_done = [&] {
        std::vector<fake::DecodedFrame> frames;
        std::vector<std::string> lines;
        fake::split_output(hostlib::serial_output(), frames, lines);
        results.clear();
        for (const fake::DecodedFrame& f : frames) {
            if (f.type != improv::FrameType::RpcResult || f.data[0] != uint8_t(improv::Command::GetWifiNetworks)) continue;
            std::vector<std::string> strings;
            for (size_t at = 2; at < f.data.size(); at += 1 + f.data[at]) {
                strings.push_back(std::string(f.data.begin() + long(at) + 1, f.data.begin() + long(at) + 1 + f.data[at]));
            }
            results.push_back(strings);
        }
        return !results.empty() && results.back().empty();
    };
    REQUIRE(b.run_until(scan_done, 200));
    REQUIRE(results.size() == 3);
    CHECK(results[0] == std::vector<std::string>{"lab", "-48", "YES"});
    CHECK(results[1] == std::vector<std::string>{"guest", "-71", "NO"});
    check_no_violations();
}

TEST_CASE("a write the module does not answer is retried; streaming stays at the fast SPI clock") {
    Joined j;
    Board& b = j.board;
    b.capture(fake::jpeg(40000, 7));
    module().ignore_write_requests = 1;
    uint8_t cid = http_get("/capture");
    REQUIRE(b.run_until([cid] { return !module().peer(cid).open; }));
    CHECK(module().peer(cid).received.find(text(fake::jpeg(40000, 7))) != std::string::npos);
    // The retried write went out at the library's 4 MHz (WiFi_Write restarts
    // the transaction at SPI_FREQ); every other one at ours.
    const std::vector<uint32_t>& clocks = module().bulk_clock_hz;
    REQUIRE(clocks.size() >= 29);
    CHECK(std::count(clocks.begin(), clocks.end(), 4000000u) == 1);
    CHECK(std::count(clocks.begin(), clocks.end(), spresense::kSpiClockHz) == long(clocks.size()) - 1);
    check_no_violations();
}

TEST_CASE("iS110B type C: the data-ready line on pin 20") {
    PowerOn power;
    hostlib::set_data_ready_pin(20);
    hostlib::set_reset_pin(21);
    Settings s = station("lab", kPassphrase);
    Board b(&s, iS110B_TypeC);
    b.boot();
    CHECK(b.run_until([] { return module().listening(); }));
    CHECK(module().resets() == 1);  // its reset input is D21 on that board
    check_no_violations();
}

TEST_CASE("the camera stops delivering frames; the node restarts it and streaming goes on") {
    Joined j;
    Board& b = j.board;
    uint8_t viewer = viewer_of(b, fake::jpeg(25000, 1));
    REQUIRE(video_driver().opens() == 1);
    REQUIRE(b.run_until([] { return video_driver().opens() == 2; }, int(kCameraStallMs) + 1000));
    CHECK(hostlib::serial_output().find("[W][camera] no frame for 5 s; camera restarted") != std::string::npos);
    CHECK(video_driver().streaming());
    b.capture(fake::jpeg(26000, 2));
    REQUIRE(b.run_until([&] { return jpeg_parts(module().peer(viewer).received).size() == 2; }));
    CHECK(jpeg_parts(module().peer(viewer).received)[1] == text(fake::jpeg(26000, 2)));
    REQUIRE(b.run_until([&] { return video_driver().queued_buffers() == spresense::kCameraBuffers - 1; }, 2000));
    check_no_violations();
}

TEST_CASE("frames that overflow the JPEG buffer are counted and a run of them latches an error and restarts the camera") {
    Joined j;
    Board& b = j.board;
    REQUIRE(video_driver().opens() == 1);
    std::vector<uint8_t> too_big = fake::jpeg(700000, 3);  // larger than any buffer the node asks for
    for (uint32_t i = 0; i < kEmptyFrameRun; ++i) {
        REQUIRE(video_driver().capture(too_big));
        // The camera thread takes it (empty: the JPEG did not fit) before the next one.
        for (int t = 0; t < 2000 && b.camera.empty_frames() == i; ++t) {
            std::this_thread::sleep_for(std::chrono::milliseconds(1));
        }
        REQUIRE(b.camera.empty_frames() == i + 1);
        b.run_until([] { return false; }, 20);
    }
    REQUIRE(b.run_until([] { return video_driver().opens() == 2; }, 200));
    CHECK(hostlib::serial_output().find("[E][node] camera:") != std::string::npos);
    uint8_t cid = http_get("/status");
    REQUIRE(b.run_until([cid] { return !module().peer(cid).open; }));
    const std::string& reply = module().peer(cid).received;
    CHECK(reply.find("\"frames_empty\":") != std::string::npos);
    CHECK(reply.find("\"frames_empty\":0") == std::string::npos);
    CHECK(reply.find("\"last_error\":\"\"") == std::string::npos);
    check_no_violations();
}

TEST_CASE("a static address is set without starting the DHCP client first") {
    Settings s = station("lab", kPassphrase);
    const char ip[] = "192.168.1.77/24,192.168.1.1";
    REQUIRE(settings_set(s, "ip", ip, strlen(ip)).ok());
    Joined j(s);
    const auto& cmds = module().commands;
    CHECK(std::find(cmds.begin(), cmds.end(), "AT+NDHCP=1") == cmds.end());
    CHECK(std::find(cmds.begin(), cmds.end(), "AT+NSET=192.168.1.77,255.255.255.0,192.168.1.1") != cmds.end());
    uint8_t cid = http_get("/status");
    REQUIRE(j.board.run_until([cid] { return !module().peer(cid).open; }));
    CHECK(module().peer(cid).received.find("\"ip\":\"192.168.1.77\"") != std::string::npos);
    check_no_violations();
}

TEST_CASE("Improv provisioning of a fresh board touches no SPI before the module is set up") {
    PowerOn power;
    Board b(nullptr);
    b.boot();
    b.run_until([] { return false; }, 50);
    hostlib::serial_input(fake::improv_rpc(improv::Command::WifiSettings, {"lab", kPassphrase}));
    REQUIRE(b.run_until([] { return module().listening(); }));
    // The library's ConsoleLog lines of a bus that was never begun ("SPI WRITE: Timeout ...").
    CHECK(hostlib::serial_output().find("Timeout") == std::string::npos);
    CHECK(module().resets() == 1);
    check_no_violations();
}

TEST_CASE("a set-up command the module refuses fails the join instead of going unnoticed") {
    PowerOn power;
    module().failing_commands = {"AT+WRXPS=0"};  // power save would stay on
    Settings s = station("lab", kPassphrase);
    Board b(&s);
    b.boot();
    b.run_until([] { return false; }, 3000);
    CHECK_FALSE(module().listening());
    CHECK(std::find(module().commands.begin(), module().commands.end(), "AT+WA=lab") == module().commands.end());
    module().failing_commands.clear();
    REQUIRE(b.run_until([] { return module().listening(); }));
    CHECK_FALSE(module().power_save());
    check_no_violations();
}
