#include <stdlib.h>

#include <string>
#include <vector>

#include <doctest/doctest.h>

#include "core/http_server.h"
#include "core/mjpeg.h"
#include "fakes.h"

using namespace cubecam;

namespace {

struct Part {
    std::string headers;
    std::string body;
};

// Splits a /stream response: head, then parts as contracts §1 lays them out.
bool parse_stream(const std::string& s, std::string& head, std::vector<Part>& parts) {
    size_t end = s.find("\r\n\r\n");
    if (end == std::string::npos) return false;
    head = s.substr(0, end + 4);
    std::string delim = std::string("\r\n--") + kBoundary + "\r\n";
    size_t pos = end + 4;
    if (s.compare(pos, delim.size(), delim) != 0) return false;
    pos += delim.size();
    while (pos < s.size()) {
        size_t hend = s.find("\r\n\r\n", pos);
        if (hend == std::string::npos) break;
        Part p;
        p.headers = s.substr(pos, hend + 4 - pos);
        size_t cl = p.headers.find("Content-Length: ");
        if (cl == std::string::npos) return false;
        size_t n = strtoul(p.headers.c_str() + cl + 16, 0, 10);
        if (hend + 4 + n > s.size()) break;  // partial part at the end
        p.body = s.substr(hend + 4, n);
        parts.push_back(p);
        pos = hend + 4 + n;
        if (s.compare(pos, delim.size(), delim) != 0) break;
        pos += delim.size();
    }
    return true;
}

std::string header_value(const std::string& headers, const std::string& name) {
    size_t p = headers.find(name + ": ");
    if (p == std::string::npos) return "";
    size_t e = headers.find("\r\n", p);
    return headers.substr(p + name.size() + 2, e - p - name.size() - 2);
}

struct Rig {
    fake::Clock clock;
    fake::Camera camera;
    fake::Network net;
    HttpServer server{net, camera, clock};
    NodeStatus status{"cam1", "0.1.0", {10, 0, 0, 5}, -50, 150, 14900, 70, 640, 480, "", 0};

    ServeResult serve(int times = 1) {
        ServeResult r = {false, false};
        for (int i = 0; i < times; ++i) {
            ServeResult one = server.serve(status);
            r.progressed |= one.progressed;
            r.link_lost |= one.link_lost;
        }
        return r;
    }
    void request(uint8_t cid, const std::string& path) {
        net.connect(cid);
        net.send(cid, "GET " + path + " HTTP/1.1\r\nHost: cam\r\n\r\n");
    }
    std::string& sent(uint8_t cid) { return net.conns[cid].sent; }
    ~Rig() { CHECK(camera.bad_releases == 0); }
};

}  // namespace

TEST_CASE("a stream carries each frame intact with X-Timestamp and X-Frame, in writes of at most 1400 B") {
    Rig r;
    r.request(1, "/stream");
    r.serve(3);
    r.camera.capture(fake::jpeg(5000, 0x11), 1234567);
    r.serve(10);
    r.camera.capture(fake::jpeg(3000, 0x22), 2000001);
    r.serve(10);
    std::string head;
    std::vector<Part> parts;
    REQUIRE(parse_stream(r.sent(1), head, parts));
    CHECK(head.find("HTTP/1.1 200 OK\r\n") == 0);
    CHECK(header_value(head, "Content-Type") == std::string("multipart/x-mixed-replace;boundary=") + kBoundary);
    CHECK(header_value(head, "Connection") == "close");
    CHECK(header_value(head, "Cache-Control") == "no-cache");
    CHECK(head.find("Content-Length") == std::string::npos);
    REQUIRE(parts.size() == 2);
    CHECK(parts[0].headers ==
          "Content-Type: image/jpeg\r\nContent-Length: 5000\r\nX-Timestamp: 1.234567\r\nX-Frame: 1\r\n\r\n");
    CHECK(parts[0].body == std::string(reinterpret_cast<const char*>(fake::jpeg(5000, 0x11).data()), 5000));
    CHECK(header_value(parts[1].headers, "X-Timestamp") == "2.000001");
    CHECK(header_value(parts[1].headers, "X-Frame") == "2");
    CHECK(r.net.max_write_seen <= kNetChunk);
    CHECK(r.net.max_write_seen == kNetChunk);  // writes are filled, not one per segment
    CHECK(r.server.frames_sent() == 2);
    CHECK(r.server.frames_dropped() == 0);
    CHECK(r.camera.out == 0);
    CHECK(r.net.conns[1].open);
}

TEST_CASE("a slow client gets only the newest frame and the skipped ones count as drops") {
    Rig r;
    r.request(1, "/stream");
    r.serve(3);
    r.net.accept_limit = 500;  // the client drains slowly
    r.camera.capture(fake::jpeg(4000, 1), 100);
    r.serve(2);  // frame 1 is under way
    for (int i = 0; i < 5; ++i) r.camera.capture(fake::jpeg(4000, static_cast<uint8_t>(2 + i)), 200 + i);
    r.serve(40);
    std::string head;
    std::vector<Part> parts;
    REQUIRE(parse_stream(r.sent(1), head, parts));
    REQUIRE(parts.size() == 2);
    CHECK(header_value(parts[0].headers, "X-Frame") == "1");
    CHECK(header_value(parts[1].headers, "X-Frame") == "6");
    CHECK(static_cast<uint8_t>(parts[1].body[100]) == 6);
    CHECK(r.server.frames_dropped() == 4);
    CHECK(r.camera.out == 0);
}

TEST_CASE("two clients are served independently, routed by connection id") {
    Rig r;
    r.request(3, "/stream");
    r.request(7, "/stream");
    r.serve(3);
    r.camera.capture(fake::jpeg(2000, 9), 10);
    r.serve(10);
    for (uint8_t cid : {3, 7}) {
        std::string head;
        std::vector<Part> parts;
        REQUIRE(parse_stream(r.sent(cid), head, parts));
        CHECK(parts.size() == 1);
    }
    CHECK(r.server.streaming_count() == 2);
    CHECK(r.camera.peak_out <= 2);
    r.net.hang_up(3);
    r.serve();
    CHECK(r.server.streaming_count() == 1);
    CHECK_FALSE(r.net.conns[3].closed_by_server);  // the module already closed that CID
}

TEST_CASE("a client vanishing mid-frame frees its slot and its frame") {
    Rig r;
    r.request(2, "/stream");
    r.serve(3);
    r.net.accept_limit = 100;
    r.camera.capture(fake::jpeg(50000, 4), 10);
    r.serve(3);
    CHECK(r.camera.out == 1);
    r.net.hang_up(2);
    r.serve();
    CHECK(r.camera.out == 0);
    CHECK(r.server.client_count() == 0);
}

TEST_CASE("a write to a client that is gone ends that client only") {
    Rig r;
    r.request(2, "/stream");
    r.request(4, "/stream");
    r.serve(3);
    r.camera.capture(fake::jpeg(8000, 4), 10);
    r.net.conns[2].open = false;  // reset by peer, not yet reported
    ServeResult res = r.serve(10);
    CHECK_FALSE(res.link_lost);
    CHECK(r.server.streaming_count() == 1);
    CHECK(r.camera.out == 0);
}

TEST_CASE("a write failing at link level reports the link lost") {
    Rig r;
    r.request(2, "/stream");
    r.serve(3);
    r.net.write_status = WriteStatus::LinkFailure;
    r.camera.capture(fake::jpeg(800, 1), 1);
    ServeResult res = r.serve(2);
    CHECK(res.link_lost);
}

TEST_CASE("module events about the link are passed up") {
    Rig r;
    r.net.event(NetEventKind::LinkLost);
    CHECK(r.serve().link_lost);
    r.net.event(NetEventKind::ModuleRebooted);
    CHECK(r.serve().link_lost);
}

TEST_CASE("with every slot taken a new client gets 503 and is closed") {
    Rig r;
    for (uint8_t cid = 1; cid <= kMaxClients; ++cid) r.request(cid, "/stream");
    r.serve(4);
    r.net.connect(9);
    r.serve();
    CHECK(r.sent(9).find("HTTP/1.1 503 ") == 0);
    CHECK(r.net.conns[9].closed_by_server);
    CHECK(r.server.streaming_count() == kMaxClients);
}

TEST_CASE("/capture answers one JPEG with the frame headers, or 503 before the first frame") {
    Rig r;
    r.request(1, "/capture");
    r.serve(3);
    CHECK(r.sent(1).find("HTTP/1.1 503 ") == 0);
    CHECK(r.net.conns[1].closed_by_server);
    r.camera.capture(fake::jpeg(3000, 5), 7000042);
    r.request(2, "/capture");
    r.serve(6);
    std::string s = r.sent(2);
    size_t end = s.find("\r\n\r\n");
    std::string head = s.substr(0, end + 4);
    CHECK(header_value(head, "Content-Type") == "image/jpeg");
    CHECK(header_value(head, "Content-Length") == "3000");
    CHECK(header_value(head, "X-Timestamp") == "7.000042");
    CHECK(header_value(head, "X-Frame") == "1");
    CHECK(s.size() == end + 4 + 3000);
    CHECK(r.net.conns[2].closed_by_server);
    CHECK(r.camera.out == 0);
}

TEST_CASE("/time answers the device clock at once") {
    Rig r;
    r.clock.now_us = 12345678901ull;
    r.request(1, "/time");
    r.serve(2);
    std::string s = r.sent(1);
    CHECK(header_value(s, "Content-Type") == "text/plain");
    CHECK(s.substr(s.find("\r\n\r\n") + 4) == "12345.678901");
}

TEST_CASE("/status is JSON with the contract's fields") {
    Rig r;
    r.clock.now_us = 5000000;
    r.request(1, "/status");
    r.serve(2);
    std::string s = r.sent(1);
    std::string body = s.substr(s.find("\r\n\r\n") + 4);
    CHECK(header_value(s, "Content-Type") == "application/json");
    CHECK(header_value(s, "Content-Length") == std::to_string(body.size()));
    for (const char* field : {"\"name\":\"cam1\"", "\"firmware_version\":\"0.1.0\"", "\"uptime_ms\":5000",
                              "\"ip\":\"10.0.0.5\"", "\"rssi\":-50", "\"fps\":{\"configured\":15.0,\"measured\":14.900}",
                              "\"frames_sent\":0", "\"frames_dropped\":0", "\"clients\":0", "\"jpeg_quality\":70",
                              "\"width\":640", "\"height\":480", "\"last_error\":\"\""}) {
        CAPTURE(field);
        CHECK(body.find(field) != std::string::npos);
    }
}

TEST_CASE("/ is a small page with the stream in an img") {
    Rig r;
    r.request(1, "/");
    r.serve(3);
    std::string s = r.sent(1);
    CHECK(header_value(s, "Content-Type") == "text/html; charset=utf-8");
    CHECK(s.find("<img src=\"/stream\"") != std::string::npos);
    CHECK(s.find("<h1>cam1</h1>") != std::string::npos);
}

TEST_CASE("a silent client is dropped after the request timeout") {
    Rig r;
    r.net.connect(1);
    r.serve();
    CHECK(r.server.client_count() == 1);
    r.clock.advance_ms(kRequestTimeoutMs + 1);
    r.serve();
    CHECK(r.server.client_count() == 0);
    CHECK(r.net.conns[1].closed_by_server);
    CHECK(r.sent(1).empty());
}

TEST_CASE("a client that stops reading is dropped after the stall timeout") {
    Rig r;
    r.request(1, "/stream");
    r.serve(3);
    r.camera.capture(fake::jpeg(8000, 1), 1);
    r.net.accept_limit = 0;
    r.serve(3);
    CHECK(r.server.client_count() == 1);
    r.clock.advance_ms(kStallTimeoutMs + 1);
    r.serve();
    CHECK(r.server.client_count() == 0);
    CHECK(r.camera.out == 0);
}

TEST_CASE("a refused write is tried again later and less often while the module keeps refusing") {
    Rig r;
    r.request(1, "/stream");
    r.serve(3);
    r.camera.capture(fake::jpeg(8000, 1), 1);
    r.net.accept_limit = 0;
    size_t before = r.net.writes;
    for (int ms = 0; ms < 1000; ++ms) {
        r.serve();
        r.clock.advance_ms(1);
    }
    // 5, 10, 20, 40, 80, then every 160 ms: 10 tries in a second, not 1000.
    CHECK(r.net.writes - before >= 8);
    CHECK(r.net.writes - before <= 12);
    r.net.accept_limit = 0xFFFF;
    for (int ms = 0; ms < 200; ++ms) {
        r.serve();
        r.clock.advance_ms(1);
    }
    std::string head;
    std::vector<Part> parts;
    REQUIRE(parse_stream(r.sent(1), head, parts));
    REQUIRE(parts.size() == 1);
    std::vector<uint8_t> frame = fake::jpeg(8000, 1);
    CHECK(parts[0].body == std::string(frame.begin(), frame.end()));
    CHECK(r.server.client_count() == 1);
}

TEST_CASE("a connection the module failed is closed and its slot and frame freed") {
    Rig r;
    r.request(1, "/stream");
    r.request(2, "/stream");
    r.serve(3);
    r.camera.capture(fake::jpeg(30000, 1), 1);
    r.serve();
    REQUIRE(r.camera.out > 0);
    r.net.fail(1);
    r.serve(40);
    CHECK(r.net.conns[1].closed_by_server);
    CHECK_FALSE(r.net.conns[2].closed_by_server);
    CHECK(r.server.client_count() == 1);
    CHECK(r.camera.out == 0);
}

TEST_CASE("a busy module gets no write until its messages are read; a 503 waits for it too") {
    Rig r;
    for (uint8_t cid = 1; cid <= kMaxClients; ++cid) r.request(cid, "/status");
    r.net.write_status = WriteStatus::Busy;
    r.serve(4);
    r.net.connect(9);
    r.serve(3);
    CHECK(r.sent(1).empty());
    CHECK_FALSE(r.net.conns[9].closed_by_server);
    r.net.write_status = WriteStatus::Ok;
    r.serve(4);
    CHECK(r.sent(1).find("HTTP/1.1 200 ") == 0);
    CHECK(r.sent(9).find("HTTP/1.1 503 ") == 0);
    CHECK(r.net.conns[9].closed_by_server);
}

TEST_CASE("/stream?fps=N caps one client's rate without counting drops") {
    Rig r;
    r.request(1, "/stream?fps=5");
    r.request(2, "/stream");
    r.serve(4);
    for (int i = 0; i < 30; ++i) {  // one second at 30 fps
        r.camera.capture(fake::jpeg(500, 1), r.clock.now_us);
        r.serve(3);
        r.clock.advance_ms(33);
    }
    std::string head;
    std::vector<Part> capped, full;
    REQUIRE(parse_stream(r.sent(1), head, capped));
    REQUIRE(parse_stream(r.sent(2), head, full));
    CHECK(capped.size() >= 5);
    CHECK(capped.size() <= 6);
    CHECK(full.size() == 30);
    CHECK(r.server.frames_dropped() == 0);
}

TEST_CASE("bytes after a complete request are ignored; errors close the connection") {
    Rig r;
    r.net.connect(1);
    r.net.send(1, "GET /missing HTTP/1.1\r\n\r\nGET / HTTP/1.1\r\n\r\n");
    r.serve(3);
    CHECK(r.sent(1).find("HTTP/1.1 404 Not Found\r\n") == 0);
    CHECK(r.sent(1).find("HTTP/1.1 200") == std::string::npos);
    CHECK(r.net.conns[1].closed_by_server);
}

TEST_CASE("drop_all forgets clients and returns their frames") {
    Rig r;
    r.request(1, "/stream");
    r.serve(3);
    r.net.accept_limit = 10;
    r.camera.capture(fake::jpeg(8000, 1), 1);
    r.serve(2);
    CHECK(r.camera.out == 1);
    r.server.drop_all();
    CHECK(r.camera.out == 0);
    CHECK(r.server.client_count() == 0);
}

TEST_CASE("a connection id reused by the module replaces the stale client") {
    Rig r;
    r.request(5, "/stream");
    r.serve(3);
    r.net.accept_limit = 10;
    r.camera.capture(fake::jpeg(8000, 1), 1);
    r.serve(2);
    CHECK(r.camera.out == 1);
    r.net.accept_limit = 0xFFFF;
    r.net.conns[5].sent.clear();
    r.request(5, "/time");  // DISCONNECT of the old one never arrived
    r.serve(3);
    CHECK(r.camera.out == 0);
    CHECK(r.server.client_count() == 0);
    CHECK(r.sent(5).find("HTTP/1.1 200 OK\r\nContent-Type: text/plain") == 0);
}
