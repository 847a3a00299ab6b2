#include <string.h>

#include <string>

#include <doctest/doctest.h>

#include "core/gs2200m.h"

using namespace cubecam;
using namespace cubecam::gs2200m;

TEST_CASE("connection ids are one hex digit") {
    uint8_t cid = 99;
    for (uint8_t v = 0; v < 16; ++v) {
        REQUIRE(parse_cid(cid_char(v), cid));
        CHECK(cid == v);
    }
    CHECK_FALSE(parse_cid('g', cid));
    CHECK_FALSE(parse_cid('A', cid));  // the module writes them in lower case
    CHECK_FALSE(parse_cid(' ', cid));
}

TEST_CASE("event lines name their connection by position") {
    uint8_t cid = 0;
    REQUIRE(event_cid("CONNECT 0 3 192.168.1.50 50013", "CONNECT", 1, cid));
    CHECK(cid == 3);
    REQUIRE(event_cid("CONNECT 0 b 10.0.0.2 1234", "CONNECT", 1, cid));
    CHECK(cid == 11);
    REQUIRE(event_cid("DISCONNECT 7", "DISCONNECT", 0, cid));
    CHECK(cid == 7);
    REQUIRE(event_cid("DISCONNECT  e\r", "DISCONNECT", 0, cid));
    CHECK(cid == 14);
    CHECK_FALSE(event_cid("DISCONNECT", "DISCONNECT", 0, cid));
    CHECK_FALSE(event_cid("DISCONNECT 12", "DISCONNECT", 0, cid));  // not one digit
    CHECK_FALSE(event_cid("CONNECT 0", "CONNECT", 1, cid));
    CHECK_FALSE(event_cid("OK", "CONNECT", 1, cid));
}

TEST_CASE("AT+WS lines give SSID, RSSI and whether the network is secured") {
    ScanEntry e;
    REQUIRE(parse_scan_line(" 00:23:69:d3:7e:4d,   Linksys-G            ,   06,  INFRA , -59 , WPA2-PERSONAL", e));
    CHECK(std::string(e.ssid) == "Linksys-G");
    CHECK(e.rssi == -59);
    CHECK(e.secured);
    REQUIRE(parse_scan_line(" 00:1d:73:8b:2c:01, guest net , 11, INFRA , -71 , NONE", e));
    CHECK(std::string(e.ssid) == "guest net");  // inner spaces stay
    CHECK(e.rssi == -71);
    CHECK_FALSE(e.secured);
    std::string longest = " 00:1d:73:8b:2c:02, " + std::string(32, 'x') + " , 01, INFRA , -90 , WPA-PERSONAL";
    REQUIRE(parse_scan_line(longest.c_str(), e));
    CHECK(strlen(e.ssid) == 32);
}

TEST_CASE("scan header, count line and malformed lines are not networks") {
    ScanEntry e;
    CHECK_FALSE(parse_scan_line("    BSSID              SSID                     Channel  Type  RSSI Security", e));
    CHECK_FALSE(parse_scan_line("No.Of AP Found:2", e));
    CHECK_FALSE(parse_scan_line("OK", e));
    CHECK_FALSE(parse_scan_line("", e));
    CHECK_FALSE(parse_scan_line(" 00:1d:73:8b:2c:02,    , 01, INFRA , -90 , NONE", e));  // hidden SSID
    std::string too_long = " 00:1d:73:8b:2c:02, " + std::string(33, 'x') + " , 01, INFRA , -90 , NONE";
    CHECK_FALSE(parse_scan_line(too_long.c_str(), e));
    CHECK_FALSE(parse_scan_line(" 00:1d:73:8b:2c:02, lab , 01, INFRA , strong , NONE", e));
    CHECK_FALSE(parse_scan_line(" 00:1d:73:8b:2c:02, lab , 01, INFRA , -300 , NONE", e));
}

TEST_CASE("bulk writes start with ESC Z, the cid and four digits of length") {
    uint8_t h[kBulkHeaderBytes];
    bulk_header(10, 1400, h);
    CHECK(std::string(reinterpret_cast<char*>(h), sizeof h) == "\x1bZa1400");
    bulk_header(1, 7, h);
    CHECK(std::string(reinterpret_cast<char*>(h), sizeof h) == "\x1bZ10007");
}
