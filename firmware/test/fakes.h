// Scriptable fakes of the hardware interfaces for the unit tests and the
// fuzzers. They run on the host and on the Cortex-M4 under QEMU alike (no
// POSIX calls, no test framework).
#ifndef CUBECAM_TEST_FAKES_H
#define CUBECAM_TEST_FAKES_H

#include <stdint.h>
#include <string.h>

#include <deque>
#include <map>
#include <string>
#include <vector>

#include "core/hal.h"
#include "core/improv.h"
#include "core/settings.h"

namespace fake {

using namespace cubecam;

struct Clock : cubecam::Clock {
    uint64_t now_us = 0;
    uint32_t millis() override { return static_cast<uint32_t>(now_us / 1000); }
    uint64_t micros() override { return now_us; }
    void advance_ms(uint32_t ms) { now_us += static_cast<uint64_t>(ms) * 1000; }
};

// Frames are pushed by the test; leases are counted so leaks show.
struct Camera : cubecam::Camera {
    static constexpr int kLeases = 8;
    std::vector<std::vector<uint8_t>> images;
    uint32_t seq = 0;
    uint64_t capture_us = 0;
    int out = 0;
    int peak_out = 0;
    int bad_releases = 0;
    int restarts = 0;
    CameraRestart restart_result = CameraRestart::Done;
    bool held[kLeases] = {};
    std::vector<uint8_t> held_data[kLeases];

    void capture(const std::vector<uint8_t>& jpeg, uint64_t at_us) {
        images.push_back(jpeg);
        ++seq;
        capture_us = at_us;
    }
    uint32_t empty = 0;
    uint32_t latest_seq() override { return seq; }
    uint32_t empty_frames() override { return empty; }
    bool acquire_latest(Frame& f) override {
        if (seq == 0) return false;
        for (int i = 0; i < kLeases; ++i) {
            if (held[i]) continue;
            held[i] = true;
            held_data[i] = images.back();  // a private copy: the "buffer" stays valid while leased
            f.data = held_data[i].data();
            f.size = static_cast<uint32_t>(held_data[i].size());
            f.seq = seq;
            f.capture_us = capture_us;
            f.lease = i;
            ++out;
            if (out > peak_out) peak_out = out;
            return true;
        }
        return false;
    }
    void release(int lease) override {
        if (lease < 0 || lease >= kLeases || !held[lease]) {
            ++bad_releases;
            return;
        }
        held[lease] = false;
        --out;
    }
    CameraRestart restart() override {
        if (out > 0) return CameraRestart::Busy;
        ++restarts;
        return restart_result;
    }
};

struct Network : cubecam::Network {
    struct Conn {
        std::string sent;
        bool open = true;
        bool closed_by_server = false;
    };
    std::deque<NetEvent> events;
    std::deque<std::string> payloads;  // one per Data event
    std::map<uint8_t, Conn> conns;
    uint16_t opened_port = 0;
    bool fail_open = false;
    size_t accept_limit = 0xFFFF;  // bytes taken per write
    WriteStatus write_status = WriteStatus::Ok;  // Busy: a message waits; poll() first
    size_t max_write_seen = 0;
    size_t writes = 0;
    int close_all_calls = 0;

    void connect(uint8_t cid) {
        events.push_back({NetEventKind::Accepted, cid, 0});
        conns[cid] = Conn();
    }
    void send(uint8_t cid, const std::string& data) {
        events.push_back({NetEventKind::Data, cid, static_cast<uint16_t>(data.size())});
        payloads.push_back(data);
    }
    void hang_up(uint8_t cid) {
        events.push_back({NetEventKind::Closed, cid, 0});
        conns[cid].open = false;
    }
    void event(NetEventKind kind) { events.push_back({kind, 0, 0}); }
    void fail(uint8_t cid) { events.push_back({NetEventKind::Failed, cid, 0}); }

    uint16_t open_server(uint16_t port) override {
        opened_port = fail_open ? 0 : port;
        return opened_port;
    }
    void close_all() override { ++close_all_calls; }
    NetEvent poll(uint8_t* buf, uint16_t cap) override {
        if (events.empty()) return {NetEventKind::None, 0, 0};
        NetEvent ev = events.front();
        events.pop_front();
        if (ev.kind == NetEventKind::Data) {
            std::string p = payloads.front();
            payloads.pop_front();
            if (p.size() > cap) p.resize(cap);
            memcpy(buf, p.data(), p.size());
            ev.len = static_cast<uint16_t>(p.size());
        }
        return ev;
    }
    WriteResult write(uint8_t cid, const uint8_t* data, uint16_t len) override {
        ++writes;
        if (len > max_write_seen) max_write_seen = len;
        if (write_status != WriteStatus::Ok) return {write_status, 0};
        Conn& c = conns[cid];
        if (!c.open) return {WriteStatus::ClientGone, 0};
        uint16_t n = static_cast<uint16_t>(len < accept_limit ? len : accept_limit);
        c.sent.append(reinterpret_cast<const char*>(data), n);
        return {WriteStatus::Ok, n};
    }
    void close(uint8_t cid) override {
        conns[cid].open = false;
        conns[cid].closed_by_server = true;
    }
};

struct Wifi : cubecam::WifiControl {
    bool reset_ok = true;
    JoinStatus next = JoinStatus::Pending;
    std::vector<std::string> joined_ssids;
    std::vector<std::string> joined_passwords;
    int resets = 0;
    uint8_t ip[4] = {192, 168, 1, 20};
    bool reset_module() override {
        ++resets;
        return reset_ok;
    }
    bool start_join(const Settings& s) override {
        joined_ssids.push_back(s.ssid);
        joined_passwords.push_back(s.password);
        return true;
    }
    JoinStatus join_status(LinkInfo& info) override {
        if (next == JoinStatus::Joined) {
            memcpy(info.ip, ip, 4);
            info.rssi = -55;
        }
        return next;
    }
    size_t scan(ScanEntry* out, size_t max) override {
        const char* names[] = {"lab", "guest"};
        size_t n = 0;
        for (; n < 2 && n < max; ++n) {
            memset(out[n].ssid, 0, sizeof out[n].ssid);
            strcpy(out[n].ssid, names[n]);
            out[n].rssi = static_cast<int8_t>(-40 - 10 * static_cast<int>(n));
            out[n].secured = n == 0;
        }
        return n;
    }
};

struct Serial : cubecam::SerialPort {
    std::string in;
    std::string out;
    size_t read(uint8_t* buf, size_t cap) override {
        size_t n = in.size() < cap ? in.size() : cap;
        memcpy(buf, in.data(), n);
        in.erase(0, n);
        return n;
    }
    void write(const uint8_t* data, size_t len) override { out.append(reinterpret_cast<const char*>(data), len); }
};

struct Storage : cubecam::SettingsStorage {
    std::vector<uint8_t> bytes;
    bool fail_store = false;
    int stores = 0;
    bool load(uint8_t* buf, size_t len) override {
        if (bytes.size() != len) return false;
        memcpy(buf, bytes.data(), len);
        return true;
    }
    bool store(const uint8_t* buf, size_t len) override {
        if (fail_store) return false;
        ++stores;
        bytes.assign(buf, buf + len);
        return true;
    }
};

struct Leds : cubecam::Leds {
    uint8_t mask = 0;
    int updates = 0;
    void show(uint8_t m) override {
        mask = m;
        ++updates;
    }
};

struct System : cubecam::System {
    int kicks = 0;
    int reboots = 0;
    void kick_watchdog() override { ++kicks; }
    void reboot() override { ++reboots; }
};

// A fake JPEG of n bytes with SOI/EOI markers and a recognisable body.
inline std::vector<uint8_t> jpeg(size_t n, uint8_t fill) {
    std::vector<uint8_t> v(n, fill);
    v[0] = 0xFF;
    v[1] = 0xD8;
    v[n - 2] = 0xFF;
    v[n - 1] = 0xD9;
    return v;
}

// An Improv RPC frame as a client sends it (with the trailing newline).
inline std::string improv_rpc(improv::Command cmd, const std::vector<std::string>& strings) {
    std::vector<uint8_t> payload;
    for (const std::string& s : strings) {
        payload.push_back(static_cast<uint8_t>(s.size()));
        payload.insert(payload.end(), s.begin(), s.end());
    }
    std::vector<uint8_t> data;
    data.push_back(static_cast<uint8_t>(cmd));
    data.push_back(static_cast<uint8_t>(payload.size()));
    data.insert(data.end(), payload.begin(), payload.end());
    uint8_t frame[improv::kMaxFrame];
    size_t n = improv::encode_frame(improv::FrameType::Rpc, data.data(), data.size(), frame);
    return std::string(reinterpret_cast<char*>(frame), n) + "\n";
}

struct DecodedFrame {
    improv::FrameType type;
    std::vector<uint8_t> data;
};

// Splits serial output into Improv frames and text lines.
inline void split_output(const std::string& out, std::vector<DecodedFrame>& frames, std::vector<std::string>& lines) {
    size_t i = 0;
    while (i < out.size()) {
        if (out.compare(i, 6, "IMPROV") == 0 && i + 9 <= out.size()) {
            size_t len = static_cast<uint8_t>(out[i + 8]);
            DecodedFrame f;
            f.type = static_cast<improv::FrameType>(out[i + 7]);
            f.data.assign(out.begin() + static_cast<long>(i) + 9, out.begin() + static_cast<long>(i + 9 + len));
            frames.push_back(f);
            i += 9 + len + 1;
            if (i < out.size() && out[i] == '\n') ++i;
            continue;
        }
        size_t nl = out.find('\n', i);
        if (nl == std::string::npos) nl = out.size();
        lines.push_back(out.substr(i, nl - i));
        i = nl + 1;
    }
}

}  // namespace fake

#endif
