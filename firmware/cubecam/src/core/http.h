// Incremental, bounded HTTP/1.x request parser, the router of contracts §1 and
// the one writer of response heads.
#ifndef CUBECAM_CORE_HTTP_H
#define CUBECAM_CORE_HTTP_H

#include <stddef.h>
#include <stdint.h>

#include "text.h"

namespace cubecam {

const size_t kMaxRequestHead = 2048;  // request line + headers; more -> 431
const size_t kMaxTarget = 128;        // longer targets match no route -> 404

enum class ParseStatus : uint8_t { Incomplete, Complete, Malformed, HeadTooLarge };

class HttpRequestParser {
public:
    HttpRequestParser();
    void reset();
    // Consumes bytes until the head is complete or invalid; later calls return
    // the same final status and consume nothing.
    ParseStatus feed(const uint8_t* data, size_t len);
    ParseStatus status() const { return status_; }
    bool is_get() const;
    // The path without the query; empty when the target was too long.
    const char* path() const { return path_; }
    // Finds `name=` in the query; value is not NUL-terminated.
    bool query_param(const char* name, const char** value, size_t* len) const;

private:
    enum class State : uint8_t { Method, Target, Version, LineFeed, HeaderStart, HeaderName, HeaderValue, Done };
    ParseStatus step(uint8_t c);
    ParseStatus end_of_line();
    void finish_target();

    State state_;
    State after_lf_;
    ParseStatus status_;
    size_t head_bytes_;
    char method_[8];
    size_t method_len_;
    char target_[kMaxTarget + 1];
    size_t target_len_;
    char version_[9];
    size_t version_len_;
    size_t header_name_len_;
    char path_[kMaxTarget + 1];
    const char* query_;
    size_t query_len_;
};

enum class Route : uint8_t { Index, Stream, Capture, Status, Time, Error };

struct RouteDecision {
    Route route;
    uint16_t status;           // 200 unless route == Error
    uint32_t fps_cap_tenths;   // /stream?fps=N; 0 = no cap
};

RouteDecision route_request(const HttpRequestParser& req);

const char* status_reason(uint16_t status);

// "HTTP/1.1 <status>" + Content-Type + optional Content-Length + the headers
// every answer carries + `extra` (complete lines) + the blank line.
void write_response_head(TextBuf& out, uint16_t status, const char* content_type, int64_t content_length,
                         const char* extra);

// A complete short error answer (text/plain body naming the status).
void write_error_response(TextBuf& out, uint16_t status);

}  // namespace cubecam

#endif
