// The node over a GS2200M that pushes back (hostlib/gs2200m.cpp): full
// transmit buffers, refused writes, events in the middle of writes and AT
// commands, <ESC>F, ERROR: SOCKET FAILURE, late replies, the reset line.
// Scripted scenarios, the 60-second run of the "done when", and a
// seeded random schedule (a failing seed replays with --seed).
#include <doctest/doctest.h>

#include <dirent.h>

#include <fstream>
#include <functional>
#include <iterator>
#include <random>

#include "core/http_server.h"
#include "test/hostlib/node_board.h"

namespace {

using namespace cubecam;
using namespace nodeboard;
using hostlib::module;

uint32_t now_ms() { return static_cast<uint32_t>(hostlib::now_us() / 1000); }

// The sensor: a new frame every period_ms of virtual time, cycling through `frames`.
struct Sensor {
    std::vector<std::vector<uint8_t>> frames;
    uint32_t period_ms;
    uint32_t next_ms;
    size_t next;
    size_t missed;  // frames the sensor had no free buffer for (every buffer lent out)

    Sensor(size_t count, size_t first_size, size_t step, uint32_t period)
        : period_ms(period), next_ms(0), next(0), missed(0) {
        for (size_t k = 0; k < count; ++k) frames.push_back(fake::jpeg(first_size + step * k, uint8_t(k + 1)));
    }
    void tick(Board& b) {
        if (now_ms() < next_ms) return;
        next_ms = now_ms() + period_ms;
        if (hostlib::video_driver().queued_buffers() == 0) {
            ++missed;
            return;
        }
        b.capture(frames[next++ % frames.size()]);
    }
    // Real JPEG files instead (the *.jpg of a folder, in name order), when the
    // test is given one: tests/firmware/test_hostlib.py decodes what clients got.
    void load(const char* dir) {
        std::vector<std::string> names;
        if (DIR* d = opendir(dir)) {
            while (dirent* e = readdir(d)) {
                std::string n = e->d_name;
                if (n.size() > 4 && n.compare(n.size() - 4, 4, ".jpg") == 0) names.push_back(n);
            }
            closedir(d);
        }
        REQUIRE_MESSAGE(!names.empty(), "no .jpg in ", dir);
        std::sort(names.begin(), names.end());
        frames.clear();
        for (const std::string& n : names) {
            std::ifstream f(std::string(dir) + "/" + n, std::ios::binary);
            frames.emplace_back(std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>());
        }
    }
    bool delivered(const std::string& part) const {
        for (const auto& f : frames) {
            if (part == text(f)) return true;
        }
        return false;
    }
};

// Runs the node for `ms` of virtual time with the sensor delivering frames.
void run_for(Board& b, Sensor& sensor, uint32_t ms) {
    uint32_t end = now_ms() + ms;
    while (static_cast<int32_t>(now_ms() - end) < 0) {
        sensor.tick(b);
        b.node.loop();
        hostlib::advance_ms(1);
    }
}

// Every part a client received is whole: its bytes are the Content-Length
// the part header announced and they are a frame the sensor delivered; the
// stream has nothing but parts after its head. Returns the number of parts.
size_t whole_parts(const std::string& s, int cid, const Sensor& sensor) {
    std::vector<std::string> parts = jpeg_parts(s);
    for (const std::string& p : parts) CHECK_MESSAGE(sensor.delivered(p), "client ", int(cid), " got a broken part");
    size_t headers = 0;
    for (size_t at = s.find("Content-Type: image/jpeg"); at != std::string::npos;
         at = s.find("Content-Type: image/jpeg", at + 1)) {
        ++headers;
    }
    // A part may still be on its way when the run ends, no more than one.
    CHECK_MESSAGE(headers <= parts.size() + 1, "client ", int(cid), ": a part header without its whole part");
    return parts.size();
}

size_t whole_parts(uint8_t cid, const Sensor& sensor) { return whole_parts(module().peer(cid).received, cid, sensor); }

size_t count_commands(const std::string& prefix) {
    size_t n = 0;
    for (const std::string& c : module().commands) n += c.compare(0, prefix.size(), prefix) == 0;
    return n;
}

// The link was never torn down: one server opened, no re-join, no log of it.
void check_link_kept() {
    CHECK(count_commands("AT+NSTCP") == 1);
    CHECK(count_commands("AT+WA=") == 1);
    CHECK(hostlib::serial_output().find("network lost") == std::string::npos);
}

uint8_t stream_client() { return http_get("/stream"); }

}  // namespace

TEST_CASE("pushback: a client slower than the node is paced by refused writes and the link stays up") {
    Joined j;
    Sensor sensor(4, 40000, 1000, 100);
    uint8_t slow = stream_client();
    module().set_drain(slow, 150e3);
    run_for(j.board, sensor, 3000);
    CHECK(module().refused_writes > 0);
    CHECK(whole_parts(slow, sensor) >= 5);  // 3 s at 150 kB/s is 11 frames of 40 kB, less the buffer
    CHECK(module().peer(slow).open);
    check_link_kept();
    check_no_violations();
}

TEST_CASE("pushback: a favicon request and a late OK arrive in the middle of a stream") {
    Joined j;
    Sensor sensor(4, 30000, 1000, 100);
    uint8_t viewer = stream_client();
    uint8_t favicon = 0xFF;
    module().at(hostlib::now_us() + 700000, [&] {
        module().late_reply();
        favicon = http_get("/favicon.ico");
    });
    run_for(j.board, sensor, 2000);
    REQUIRE(favicon != 0xFF);
    CHECK(module().peer(favicon).received.find("HTTP/1.1 404") == 0);
    CHECK_FALSE(module().peer(favicon).open);
    CHECK(whole_parts(viewer, sensor) >= 10);
    check_link_kept();
    check_no_violations();
}

TEST_CASE("pushback: a bulk write answered ESC F closes that client and no part is short") {
    Joined j;
    Sensor sensor(4, 30000, 1000, 100);
    uint8_t a = stream_client();
    uint8_t b = stream_client();
    run_for(j.board, sensor, 500);
    module().fail_bulk_writes = 1;
    run_for(j.board, sensor, 1500);
    REQUIRE(module().esc_f_sent == 1);
    CHECK(module().peer(a).open != module().peer(b).open);  // the failed one is closed, the other streams on
    size_t before_a = whole_parts(a, sensor), before_b = whole_parts(b, sensor);
    run_for(j.board, sensor, 1000);
    uint8_t alive = module().peer(a).open ? a : b;
    CHECK(whole_parts(alive, sensor) > (alive == a ? before_a : before_b));
    check_link_kept();
    check_no_violations();
}

TEST_CASE("pushback: ERROR SOCKET FAILURE frees that client's slot") {
    Joined j;
    Sensor sensor(2, 20000, 1000, 100);
    std::vector<uint8_t> viewers;
    for (size_t i = 0; i < kMaxClients; ++i) viewers.push_back(stream_client());
    run_for(j.board, sensor, 1000);
    module().client_reset(viewers[1], true);
    run_for(j.board, sensor, 200);
    uint8_t late = stream_client();
    run_for(j.board, sensor, 1000);
    CHECK(module().peer(late).received.find("HTTP/1.1 200") == 0);
    CHECK(whole_parts(late, sensor) >= 1);
    check_link_kept();
    check_no_violations();
}

TEST_CASE("pushback: a client that connects while the node closes another is served") {
    Joined j;
    uint8_t late = 0xFF;
    module().on_command_hook = [&](const std::string& cmd) {
        if (cmd.compare(0, 10, "AT+NCLOSE=") == 0 && late == 0xFF) late = http_get("/status");
    };
    uint8_t first = http_get("/status");
    REQUIRE(j.board.run_until([&] { return late != 0xFF && !module().peer(first).open; }, 2000));
    REQUIRE(j.board.run_until([&] { return !module().peer(late).open; }, 2000));
    CHECK(module().peer(late).received.find("HTTP/1.1 200") == 0);
    check_link_kept();
    check_no_violations();
}

TEST_CASE("pushback: no Wi-Fi scan while a client streams") {
    Joined j;
    Sensor sensor(2, 20000, 1000, 100);
    uint8_t viewer = stream_client();
    run_for(j.board, sensor, 500);
    size_t before = whole_parts(viewer, sensor);
    hostlib::serial_input(fake::improv_rpc(improv::Command::GetWifiNetworks, {}));
    run_for(j.board, sensor, 1000);
    CHECK(count_commands("AT+WS") == 0);
    CHECK(whole_parts(viewer, sensor) >= before + 5);
    check_no_violations();
}

TEST_CASE("reset: the node pulses the module's reset line at boot and after an MCU reset") {
    Settings s = station("lab", kPassphrase);
    uint8_t viewer;
    {
        Joined j(s);
        CHECK(module().resets() == 1);
        Sensor sensor(2, 20000, 1000, 100);
        viewer = stream_client();
        run_for(j.board, sensor, 500);
        REQUIRE(module().peer(viewer).open);
    }
    // The watchdog (or the console's reboot) restarts the MCU; the module
    // keeps its association, the viewer's connection and the listener.
    hostlib::mcu_reset();
    Board b(&s);
    b.boot();
    REQUIRE(b.run_until([] { return module().resets() == 2; }, 2000));
    CHECK_FALSE(module().peer(viewer).open);
    REQUIRE(b.run_until([] { return module().listening(); }));
    // Whatever the module held is closed before the server opens.
    const std::vector<std::string>& cmds = module().commands;
    REQUIRE(cmds.size() >= 2);
    CHECK(cmds[cmds.size() - 2] == "AT+NCLOSEALL");
    CHECK(cmds.back().compare(0, 8, "AT+NSTCP") == 0);
    uint8_t cid = http_get("/status");
    REQUIRE(b.run_until([cid] { return !module().peer(cid).open; }));
    CHECK(module().peer(cid).received.find("HTTP/1.1 200") == 0);
    check_no_violations();
}

// What each stream client received, to files client-<n>.mjpeg in CUBECAM_STREAM_OUT.
void save_streams(const std::vector<uint8_t>& cids) {
    const char* dir = getenv("CUBECAM_STREAM_OUT");
    if (!dir) return;
    for (uint8_t c : cids) {
        std::ofstream f(std::string(dir) + "/client-" + std::to_string(module().peer(c).serial) + ".mjpeg",
                        std::ios::binary);
        f << module().peer(c).received;
    }
}

// CUBECAM_JPEG_DIR: the sensor delivers those files (else synthetic frames).
TEST_CASE("done: 60 s of three clients with a favicon and a stalled and a reset client") {
    Joined j;
    Board& b = j.board;
    Sensor sensor(6, 25000, 2000, 100);
    if (getenv("CUBECAM_JPEG_DIR")) sensor.load(getenv("CUBECAM_JPEG_DIR"));
    uint8_t a = stream_client(), bb = stream_client(), c = stream_client();
    module().set_drain(a, 0.5e6);
    module().set_drain(bb, 1.0e6);
    module().set_drain(c, 1.5e6);
    run_for(b, sensor, 5000);
    uint8_t favicon = http_get("/favicon.ico");
    run_for(b, sensor, 5000);
    CHECK(module().peer(favicon).received.find("HTTP/1.1 404") == 0);
    CHECK_FALSE(module().peer(favicon).open);
    uint8_t stalled = stream_client();
    run_for(b, sensor, 5000);  // t = 15 s
    size_t a0 = whole_parts(a, sensor), b0 = whole_parts(bb, sensor);
    module().set_drain(stalled, 0);
    uint64_t stalled_at_us = hostlib::now_us();
    run_for(b, sensor, 10000);  // t = 25 s
    size_t a1 = whole_parts(a, sensor), b1 = whole_parts(bb, sensor);
    run_for(b, sensor, 10000);  // t = 35 s
    size_t a2 = whole_parts(a, sensor), b2 = whole_parts(bb, sensor);
    MESSAGE("parts of a/b at 15, 25, 35 s: ", a0, "/", b0, " ", a1, "/", b1, " ", a2, "/", b2);
    module().client_reset(c, true);
    run_for(b, sensor, 5000);
    uint8_t again = stream_client();
    run_for(b, sensor, 20000);  // t = 60 s

    // The stalled client is closed once it has taken nothing for the stall
    // timeout (it stopped taking data when its 8 kB buffer filled).
    const std::string close_stalled = std::string("AT+NCLOSE=") + "0123456789abcdef"[stalled];
    auto first = module().commands.begin() + long(module().commands.size());
    for (size_t i = 0; i < module().commands.size(); ++i) {
        if (module().command_us[i] > stalled_at_us) {
            first = module().commands.begin() + long(i);
            break;
        }
    }
    auto at = std::find(first, module().commands.end(), close_stalled);
    REQUIRE(at != module().commands.end());
    uint64_t closed_us = module().command_us[size_t(at - module().commands.begin())];
    CHECK(closed_us >= stalled_at_us + kStallTimeoutMs * 1000);
    CHECK(closed_us <= stalled_at_us + (kStallTimeoutMs + 2000) * 1000);
    // The others' frame rates do not fall while it stalls, nor after.
    CHECK(a1 - a0 >= (a0 * 10 / 15) * 9 / 10);
    CHECK(b1 - b0 >= (b0 * 10 / 15) * 9 / 10);
    CHECK(a2 - a1 >= (a1 - a0) * 9 / 10);
    CHECK(b2 - b1 >= (b1 - b0) * 9 / 10);
    CHECK(whole_parts(c, sensor) > 0);
    MESSAGE("at 60 s: a ", whole_parts(a, sensor), " b ", whole_parts(bb, sensor), " again ", whole_parts(again, sensor),
            "; refused writes ", module().refused_writes, ", frames the sensor had no buffer for ", sensor.missed);
    // Three clients share ~550 kB/s of SPI (hostlib.h): about 5 fps each of 25-44 kB frames.
    CHECK(whole_parts(again, sensor) >= 80);  // 20 s at >= 4 fps
    CHECK(whole_parts(a, sensor) >= 240);     // 60 s at >= 4 fps
    save_streams({a, bb, again});
    check_link_kept();
    check_no_violations();
}

namespace {

// One seeded schedule: clients come and go, read at 0.3-2 MB/s or stop, the
// module fails a write, replies late, clients reset; 1.5 s of streaming.
void random_schedule(unsigned seed) {
    CAPTURE(seed);
    Joined j;
    std::mt19937 rng(seed);
    auto uniform = [&](double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(rng); };
    Sensor sensor(4, 8000, 3000, 50);
    // Slow replies: more events land between a command and its reply.
    module().reply_delay_us = static_cast<uint64_t>(uniform(500, 20000));
    std::vector<uint8_t> streams;                // cids
    std::vector<size_t> stream_serials, others;  // connections
    auto new_stream = [&](double rate) {
        streams.push_back(stream_client());
        stream_serials.push_back(module().connections());
        module().set_drain(streams.back(), rate);
    };
    for (int i = 0; i < 2; ++i) new_stream(uniform(0.3e6, 2e6));
    uint64_t start = hostlib::now_us();
    for (int i = 0; i < 10; ++i) {
        uint64_t when = start + static_cast<uint64_t>(uniform(0, 1.5e6));
        int kind = std::uniform_int_distribution<int>(0, 6)(rng);
        double rate = rng() % 4 == 0 ? 0 : uniform(0.3e6, 2e6);
        bool sf = rng() % 2 == 0;
        size_t pick = rng();
        module().at(when, [&, kind, rate, sf, pick, when] {
            if (getenv("CUBECAM_SEED")) MESSAGE(when, " event ", kind, " pick ", pick);
            std::vector<uint8_t> live;  // cids of the stream clients still connected
            for (size_t i = 0; i < streams.size(); ++i) {
                const hostlib::TcpPeer& p = module().peer(streams[i]);
                if (p.serial == stream_serials[i] && p.open && !p.closing) live.push_back(streams[i]);
            }
            uint8_t victim = live.empty() ? 0xFF : live[pick % live.size()];
            switch (kind) {
            case 0: new_stream(rate); break;
            case 1:
                http_get(pick % 2 ? "/status" : "/favicon.ico");
                others.push_back(module().connections());
                break;
            case 2: module().late_reply(); break;
            case 3: module().fail_bulk_writes = 1; break;
            case 4: if (victim != 0xFF) module().client_reset(victim, sf); break;
            case 5: if (victim != 0xFF) module().client_close(victim); break;
            default: if (victim != 0xFF) module().set_drain(victim, rate); break;
            }
        });
    }
    run_for(j.board, sensor, 2000);
    if (getenv("CUBECAM_SEED")) {
        for (size_t i = 0; i < module().commands.size(); ++i) MESSAGE(module().command_us[i], " ", module().commands[i]);
    }
    for (size_t c : stream_serials) {
        const std::string& got = module().connection(c).received;
        if (got.compare(0, 12, "HTTP/1.1 503") != 0) whole_parts(got, int(c), sensor);  // 503: every slot was taken
    }
    // A request is answered, or its connection ended (the module failed the answer, or all slots were taken).
    for (size_t c : others) {
        const hostlib::TcpPeer& p = module().connection(c);
        CAPTURE(c);
        CAPTURE(p.open);
        CAPTURE(p.received.substr(0, 40));
        CHECK((p.received.compare(0, 9, "HTTP/1.1 ") == 0 || (p.received.empty() && !p.open)));
    }
    check_link_kept();
    check_no_violations();
}

}  // namespace

// CUBECAM_SEED=n replays seed n alone.
TEST_CASE("random: 200 seeded schedules of events keep the link and every part whole") {
    const char* one = getenv("CUBECAM_SEED");
    if (one) {
        random_schedule(static_cast<unsigned>(atoi(one)));
        return;
    }
    for (unsigned seed = 1; seed <= 200; ++seed) random_schedule(seed);
}

TEST_CASE("a module that stops answering is given up after 5 s of silence and a failed AT and then reset") {
    Joined j;
    Sensor sensor(2, 20000, 1000, 100);
    uint8_t viewer = stream_client();
    run_for(j.board, sensor, 1000);
    REQUIRE(whole_parts(viewer, sensor) > 0);
    REQUIRE(module().resets() == 1);
    module().wedged = true;
    run_for(j.board, sensor, 4000);  // refusals and silence below kLinkSilenceMs: not yet lost
    CHECK(hostlib::serial_output().find("network lost") == std::string::npos);
    run_for(j.board, sensor, 3000);
    CHECK(hostlib::serial_output().find("[W][link] network lost; reconnecting") != std::string::npos);
    REQUIRE(j.board.run_until([] { return module().resets() == 2 && module().listening(); }, 20000));
    uint8_t cid = http_get("/status");
    REQUIRE(j.board.run_until([cid] { return !module().peer(cid).open; }));
    CHECK(module().peer(cid).received.find("HTTP/1.1 200") == 0);
    check_no_violations();
}
