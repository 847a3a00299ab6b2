#include <string.h>

#include <string>

#include <doctest/doctest.h>

#include "core/http.h"

using namespace cubecam;

namespace {

RouteDecision route(const std::string& request, size_t split = 0) {
    HttpRequestParser p;
    const uint8_t* d = reinterpret_cast<const uint8_t*>(request.data());
    if (split) {
        // Fed byte by byte: the parser is incremental.
        for (size_t i = 0; i < request.size(); ++i) p.feed(d + i, 1);
    } else {
        p.feed(d, request.size());
    }
    return route_request(p);
}

}  // namespace

TEST_CASE("routes of contracts §1") {
    CHECK(route("GET / HTTP/1.1\r\nHost: x\r\n\r\n").route == Route::Index);
    CHECK(route("GET /stream HTTP/1.1\r\n\r\n").route == Route::Stream);
    CHECK(route("GET /capture HTTP/1.0\r\n\r\n").route == Route::Capture);
    CHECK(route("GET /status HTTP/1.1\r\n\r\n").route == Route::Status);
    CHECK(route("GET /time HTTP/1.1\r\n\r\n").route == Route::Time);
    CHECK(route("GET /time?x=1 HTTP/1.1\r\n\r\n").route == Route::Time);
    RouteDecision d = route("GET /nope HTTP/1.1\r\n\r\n");
    CHECK(d.route == Route::Error);
    CHECK(d.status == 404);
    CHECK(route("POST /status HTTP/1.1\r\nContent-Length: 0\r\n\r\n").status == 405);
    CHECK(route("HEAD /stream HTTP/1.1\r\n\r\n").status == 405);
    CHECK(route("POST /other HTTP/1.1\r\n\r\n").status == 404);
}

TEST_CASE("incremental parsing gives the same answer as one read") {
    std::string req = "GET /stream?fps=7.5 HTTP/1.1\r\nHost: cam\r\nUser-Agent: t\r\n\r\n";
    RouteDecision a = route(req);
    RouteDecision b = route(req, 1);
    CHECK(a.route == Route::Stream);
    CHECK(b.route == Route::Stream);
    CHECK(a.fps_cap_tenths == 75);
    CHECK(b.fps_cap_tenths == 75);
}

TEST_CASE("bare LF line ends are accepted, empty lines before the request skipped") {
    CHECK(route("\r\nGET /status HTTP/1.1\nHost: x\n\n").route == Route::Status);
}

TEST_CASE("stream rate caps are validated") {
    CHECK(route("GET /stream?fps=5 HTTP/1.1\r\n\r\n").fps_cap_tenths == 50);
    CHECK(route("GET /stream?dummy=param.mjpg HTTP/1.1\r\n\r\n").fps_cap_tenths == 0);
    CHECK(route("GET /stream?a=b&fps=2 HTTP/1.1\r\n\r\n").fps_cap_tenths == 20);
    CHECK(route("GET /stream?fps=0 HTTP/1.1\r\n\r\n").status == 400);
    CHECK(route("GET /stream?fps=abc HTTP/1.1\r\n\r\n").status == 400);
    CHECK(route("GET /stream?fps=31 HTTP/1.1\r\n\r\n").status == 400);
}

TEST_CASE("malformed requests are 400") {
    const char* bad[] = {
        "GET /\r\n\r\n",                            // HTTP/0.9
        "GET / HTTP/2.0\r\n\r\n",                   // unsupported version
        "GET  / HTTP/1.1\r\n\r\n",                  // empty target
        "G(T / HTTP/1.1\r\n\r\n",                   // bad method char
        "GET / HTTP/1.1\r\nNoColon\r\n\r\n",        // header without ':'
        "GET / HTTP/1.1\r\n: empty\r\n\r\n",        // empty header name
        "GET / HTTP/1.1\r\n folded\r\n\r\n",        // obsolete line folding
        "GET / HTTP/1.1\rX\r\n\r\n",                // CR without LF
        "GET /\x01 HTTP/1.1\r\n\r\n",               // control char in target
        "GET / HTTP/1.1\r\nX: a\x01\r\n\r\n",       // control char in value
        "VERYLONGMETHOD / HTTP/1.1\r\n\r\n",        // method too long
    };
    for (const char* r : bad) {
        CAPTURE(r);
        RouteDecision d = route(r);
        CHECK(d.route == Route::Error);
        CHECK(d.status == 400);
    }
}

TEST_CASE("request heads over 2 KiB are 431, up to 2 KiB are served") {
    std::string head = "GET /status HTTP/1.1\r\nX-Pad: ";
    std::string tail = "\r\n\r\n";
    std::string exact = head + std::string(kMaxRequestHead - head.size() - tail.size(), 'a') + tail;
    REQUIRE(exact.size() == kMaxRequestHead);
    CHECK(route(exact).route == Route::Status);
    std::string over = head + std::string(kMaxRequestHead - head.size() - tail.size() + 1, 'a') + tail;
    RouteDecision d = route(over);
    CHECK(d.status == 431);
}

TEST_CASE("an overlong target is a 404, not an overflow") {
    std::string req = "GET /" + std::string(1000, 's') + " HTTP/1.1\r\n\r\n";
    CHECK(route(req).status == 404);
    std::string stream = "GET /stream?fps=5&" + std::string(200, 'q') + " HTTP/1.1\r\n\r\n";
    CHECK(route(stream).status == 404);
}

TEST_CASE("incomplete input is not a request yet") {
    HttpRequestParser p;
    std::string part = "GET /status HTTP/1.1\r\nHost: x\r\n";
    CHECK(p.feed(reinterpret_cast<const uint8_t*>(part.data()), part.size()) == ParseStatus::Incomplete);
    CHECK(route_request(p).status == 400);
    CHECK(p.feed(reinterpret_cast<const uint8_t*>("\r\n"), 2) == ParseStatus::Complete);
    // Later bytes do not change the verdict.
    CHECK(p.feed(reinterpret_cast<const uint8_t*>("garbage"), 7) == ParseStatus::Complete);
    CHECK(route_request(p).route == Route::Status);
}

TEST_CASE("every response head carries the contract's headers") {
    char buf[512];
    TextBuf t(buf, sizeof buf);
    write_error_response(t, 503);
    std::string s = t.c_str();
    CHECK(s.find("HTTP/1.1 503 Service Unavailable\r\n") == 0);
    CHECK(s.find("\r\nConnection: close\r\n") != std::string::npos);
    CHECK(s.find("\r\nCache-Control: no-cache\r\n") != std::string::npos);
    size_t body = s.find("\r\n\r\n") + 4;
    CHECK(s.substr(body) == "503 Service Unavailable\n");
    CHECK(s.find("Content-Length: 24\r\n") != std::string::npos);
    CHECK(s.find("Transfer-Encoding") == std::string::npos);
}
