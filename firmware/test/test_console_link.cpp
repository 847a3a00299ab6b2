#include <string>
#include <vector>

#include <doctest/doctest.h>

#include "core/console.h"
#include "core/link.h"
#include "core/settings.h"
#include "fakes.h"

using namespace cubecam;

namespace {

struct Host : ConsoleHost, LineSink {
    Settings edited;
    std::vector<std::string> lines;
    int saves = 0;
    bool save_ok = true;
    int reboots = 0;
    Host() { settings_defaults(edited); }
    Settings& edited_settings() override { return edited; }
    bool save_settings() override {
        ++saves;
        return save_ok;
    }
    bool factory_reset() override {
        settings_defaults(edited);
        return save_settings();
    }
    void request_reboot() override { ++reboots; }
    void report_status(LineSink& out) override { out.line("link=online"); }
    void line(const char* text) override { lines.push_back(text); }
};

std::vector<std::string> run(Host& h, const std::string& input) {
    Console c(h, h);
    h.lines.clear();
    for (char ch : input) c.feed(static_cast<uint8_t>(ch));
    return h.lines;
}

}  // namespace

TEST_CASE("every console answer ends in OK or ERR") {
    Host h;
    for (const char* cmd : {"help", "status", "get", "get fps", "set fps 30", "save", "reboot", "factory-reset",
                            "bogus", "get nokey", "set fps", "set fps 12", "set"}) {
        CAPTURE(cmd);
        std::vector<std::string> out = run(h, std::string(cmd) + "\n");
        REQUIRE_FALSE(out.empty());
        const std::string& last = out.back();
        CHECK((last == "OK" || last.compare(0, 4, "ERR ") == 0));
    }
}

TEST_CASE("help lists every key with what it takes, in lines that fit a terminal") {
    Host h;
    std::vector<std::string> out = run(h, "help\n");
    REQUIRE(out.back() == "OK");
    std::string keys;
    for (const std::string& line : out) {
        CHECK(line.size() <= 80);
        if (line.compare(0, 5, "keys:") == 0 || (!keys.empty() && line.compare(0, 5, "     ") == 0)) keys += line.substr(5);
    }
    for (size_t i = 0; i < kSettingCount; ++i) CHECK(keys.find(std::string(" ") + kSettingFields[i].key) != std::string::npos);
    for (const char* hint : {"password(write-only)", "mode(station|ap)", "ip(dhcp|a.b.c.d/prefix,gateway)", "port(1-65535)",
                             "jpeg_quality(1-100)", "fps(30|15|7.5)", "hdr(off|auto|on)"}) {
        CHECK(keys.find(hint) != std::string::npos);
    }
}

TEST_CASE("get and set round-trip, values keep their spaces") {
    Host h;
    CHECK(run(h, "set ssid My Lab Net\n") == std::vector<std::string>{"OK"});
    CHECK(run(h, "get ssid\n") == std::vector<std::string>{"ssid=My Lab Net", "OK"});
    CHECK(run(h, "set fps 7.5\r\nget fps\r\n") == std::vector<std::string>{"OK", "fps=7.5", "OK"});
    std::vector<std::string> all = run(h, "get\n");
    CHECK(all.size() == kSettingCount + 1);
    CHECK(all.front() == "name=cubecam");
}

TEST_CASE("save refuses access-point mode without a password, which the module would make WPA2 anyway") {
    Host h;
    CHECK(run(h, "set mode ap\n") == std::vector<std::string>{"OK"});
    std::vector<std::string> out = run(h, "save\n");
    REQUIRE(out.size() == 1);
    CHECK(out[0].compare(0, 6, "ERR 4 ") == 0);
    CHECK(h.saves == 0);
    CHECK(run(h, "set password hunter2hunter2\nsave\n").back() == "OK");
    CHECK(h.saves == 1);
    CHECK(run(h, "set mode station\nset password \nsave\n").back() == "OK");  // an open network is fine for a station
}

TEST_CASE("the password is write-only") {
    Host h;
    CHECK(run(h, "set password hunter2hunter2\n") == std::vector<std::string>{"OK"});
    for (const char* cmd : {"get password\n", "get\n", "status\n", "help\n"}) {
        for (const std::string& line : run(h, cmd)) CHECK(line.find("hunter2") == std::string::npos);
    }
    CHECK(run(h, "get password\n").front() == "password=(set)");
}

TEST_CASE("set password takes the rest of the line: commas, quotes and spaces at either end") {
    Host h;
    CHECK(run(h, "set password  my \"secret\", ok \r\n") == std::vector<std::string>{"OK"});
    CHECK(std::string(h.edited.password) == " my \"secret\", ok ");
    for (const std::string& line : run(h, "get\n")) CHECK(line.find("secret") == std::string::npos);
}

TEST_CASE("console errors have codes and say what is valid") {
    Host h;
    CHECK(run(h, "frobnicate\n").back() == "ERR 1 unknown command; try help");
    CHECK(run(h, "set fps\n").back() == "ERR 2 usage: set <key> <value>");
    CHECK(run(h, "get colour\n").back().compare(0, 6, "ERR 3 ") == 0);
    std::string bad = run(h, "set password short\n").back();
    CHECK(bad.compare(0, 6, "ERR 4 ") == 0);
    CHECK(bad.find("8 to 63") != std::string::npos);
    h.save_ok = false;
    CHECK(run(h, "save\n").back().compare(0, 6, "ERR 6 ") == 0);
    std::string longline(300, 'x');
    CHECK(run(h, longline + "\nget fps\n") == std::vector<std::string>{"ERR 7 line too long (128 bytes at most)", "fps=15", "OK"});
}

TEST_CASE("reboot answers OK before asking for the reboot; factory-reset restores defaults") {
    Host h;
    run(h, "set fps 30\n");
    CHECK(run(h, "factory-reset\n") == std::vector<std::string>{"OK"});
    CHECK(h.edited.fps == FrameRate::Fps15);
    CHECK(run(h, "reboot\n") == std::vector<std::string>{"OK"});
    CHECK(h.reboots == 1);
}

TEST_CASE("empty lines are ignored") {
    Host h;
    CHECK(run(h, "\n\r\n\r").empty());
}

// ---- link supervisor ----

namespace {

Settings with_ssid(const char* ssid) {
    Settings s;
    settings_defaults(s);
    REQUIRE(settings_set(s, "ssid", ssid, strlen(ssid)).ok());
    return s;
}

}  // namespace

TEST_CASE("without an SSID the link waits for provisioning") {
    fake::Wifi wifi;
    LinkSupervisor link(wifi);
    Settings s;
    settings_defaults(s);
    link.begin(s, 0);
    CHECK(link.tick(10) == LinkEvent::None);
    CHECK(link.state() == LinkState::Unconfigured);
    CHECK(wifi.resets == 0);
}

TEST_CASE("join succeeds, then a lost link is retried with growing backoff") {
    fake::Wifi wifi;
    LinkSupervisor link(wifi);
    link.begin(with_ssid("lab"), 0);
    CHECK(link.tick(0) == LinkEvent::None);
    CHECK(link.state() == LinkState::Joining);
    CHECK(link.tick(100) == LinkEvent::None);
    wifi.next = JoinStatus::Joined;
    CHECK(link.tick(200) == LinkEvent::Online);
    CHECK(link.info().ip[0] == 192);
    uint32_t t = 1000;
    uint32_t expected = kFirstBackoffMs;
    for (int i = 0; i < 10; ++i) {
        link.link_lost(t);
        CHECK(link.state() == LinkState::Backoff);
        CHECK(link.retry_at_ms() - t == expected);
        link.tick(t + expected - 1);
        CHECK(link.state() == LinkState::Backoff);
        link.tick(t + expected);
        CHECK(link.state() == LinkState::Resetting);
        wifi.next = JoinStatus::Failed;
        CHECK(link.tick(t + expected) == LinkEvent::None);  // reset + start join
        CHECK(link.tick(t + expected + 1) == LinkEvent::JoinFailed);
        t = link.retry_at_ms();
        link.tick(t);
        link.tick(t);
        wifi.next = JoinStatus::Joined;
        CHECK(link.tick(t + 1) == LinkEvent::Online);
        expected = kFirstBackoffMs;  // a success resets the backoff
        t += 10;
    }
}

TEST_CASE("the backoff doubles up to its cap while joins keep failing") {
    fake::Wifi wifi;
    wifi.next = JoinStatus::Failed;
    LinkSupervisor link(wifi);
    link.begin(with_ssid("lab"), 0);
    uint32_t t = 0;
    uint32_t last_wait = 0;
    for (int i = 0; i < 12; ++i) {
        link.tick(t);  // Resetting -> Joining
        CHECK(link.tick(t) == LinkEvent::JoinFailed);
        uint32_t wait = link.retry_at_ms() - t;
        CHECK(wait >= last_wait);
        CHECK(wait <= kMaxBackoffMs);
        last_wait = wait;
        t = link.retry_at_ms();
        link.tick(t);
    }
    CHECK(last_wait == kMaxBackoffMs);
}

TEST_CASE("a join that never completes times out") {
    fake::Wifi wifi;
    LinkSupervisor link(wifi);
    link.begin(with_ssid("lab"), 0);
    link.tick(0);
    CHECK(link.tick(kJoinTimeoutMs - 1) == LinkEvent::None);
    CHECK(link.tick(kJoinTimeoutMs) == LinkEvent::JoinFailed);
}

TEST_CASE("a module that does not come up counts as a failed attempt") {
    fake::Wifi wifi;
    wifi.reset_ok = false;
    LinkSupervisor link(wifi);
    link.begin(with_ssid("lab"), 0);
    CHECK(link.tick(0) == LinkEvent::JoinFailed);
    CHECK(link.state() == LinkState::Backoff);
}

TEST_CASE("trial credentials replace the stored ones only when they work") {
    fake::Wifi wifi;
    LinkSupervisor link(wifi);
    link.begin(with_ssid("old"), 0);
    link.try_credentials(with_ssid("new"), 0);
    CHECK(link.trying());
    wifi.next = JoinStatus::Failed;
    link.tick(0);
    CHECK(link.tick(1) == LinkEvent::JoinFailed);
    CHECK_FALSE(link.trying());
    CHECK(std::string(link.settings().ssid) == "old");
    link.try_credentials(with_ssid("new"), 10);
    wifi.next = JoinStatus::Joined;
    link.tick(10);
    CHECK(link.tick(11) == LinkEvent::Online);
    CHECK(std::string(link.settings().ssid) == "new");
    CHECK(wifi.joined_ssids == std::vector<std::string>{"new", "new"});
}

TEST_CASE("LED patterns tell the link state apart") {
    CHECK((status_leds(LinkState::Online, 0, 0, false, false) & kLedLink) != 0);
    CHECK((status_leds(LinkState::Online, 777, 0, false, false) & kLedLink) != 0);
    CHECK((status_leds(LinkState::Unconfigured, 0, 0, false, false) & kLedLink) != 0);
    CHECK((status_leds(LinkState::Unconfigured, 125, 0, false, false) & kLedLink) == 0);
    CHECK((status_leds(LinkState::Joining, 250, 0, false, false) & kLedLink) != 0);
    CHECK((status_leds(LinkState::Joining, 500, 0, false, false) & kLedLink) == 0);
    CHECK((status_leds(LinkState::Backoff, 50, 0, false, false) & kLedLink) != 0);
    CHECK((status_leds(LinkState::Backoff, 150, 0, false, false) & kLedLink) == 0);
    CHECK((status_leds(LinkState::Online, 0, 1, false, false) & kLedFrame) != 0);
    CHECK((status_leds(LinkState::Online, 0, 2, false, false) & kLedFrame) == 0);
    CHECK((status_leds(LinkState::Online, 0, 0, true, false) & kLedClient) != 0);
    CHECK((status_leds(LinkState::Online, 0, 0, false, true) & kLedError) != 0);
}

TEST_CASE("deadlines hold across the 32-bit millisecond wrap") {
    CHECK(deadline_reached(1000, 1000));
    CHECK_FALSE(deadline_reached(999, 1000));
    uint32_t near_wrap = 0xFFFFFF00u;
    uint32_t deadline = near_wrap + 0x200;  // wrapped past zero
    CHECK_FALSE(deadline_reached(near_wrap, deadline));
    CHECK_FALSE(deadline_reached(0xFFFFFFFFu, deadline));
    CHECK(deadline_reached(deadline, deadline));
    CHECK(deadline_reached(deadline + 5, deadline));
}
