#include "http.h"

#include <string.h>

namespace cubecam {

namespace {

bool is_tchar(uint8_t c) {
    if ((c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9')) return true;
    return c != 0 && strchr("!#$%&'*+-.^_`|~", c) != 0;
}

const uint32_t kMaxStreamFpsTenths = 300;

}  // namespace

HttpRequestParser::HttpRequestParser() { reset(); }

void HttpRequestParser::reset() {
    state_ = State::Method;
    after_lf_ = State::HeaderStart;
    status_ = ParseStatus::Incomplete;
    head_bytes_ = 0;
    method_len_ = 0;
    target_len_ = 0;
    version_len_ = 0;
    header_name_len_ = 0;
    method_[0] = '\0';
    target_[0] = '\0';
    version_[0] = '\0';
    path_[0] = '\0';
    query_ = "";
    query_len_ = 0;
}

ParseStatus HttpRequestParser::feed(const uint8_t* data, size_t len) {
    for (size_t i = 0; i < len && status_ == ParseStatus::Incomplete; ++i) {
        if (++head_bytes_ > kMaxRequestHead) {
            status_ = ParseStatus::HeadTooLarge;
            break;
        }
        status_ = step(data[i]);
    }
    return status_;
}

ParseStatus HttpRequestParser::end_of_line() {
    if (state_ == State::Version) {
        version_[version_len_] = '\0';
        if (strcmp(version_, "HTTP/1.1") != 0 && strcmp(version_, "HTTP/1.0") != 0) {
            return ParseStatus::Malformed;
        }
        state_ = State::HeaderStart;
        return ParseStatus::Incomplete;
    }
    if (state_ == State::HeaderStart) {
        state_ = State::Done;
        return ParseStatus::Complete;
    }
    if (state_ == State::HeaderValue) {
        state_ = State::HeaderStart;
        return ParseStatus::Incomplete;
    }
    return ParseStatus::Malformed;
}

ParseStatus HttpRequestParser::step(uint8_t c) {
    if (state_ == State::LineFeed) {
        if (c != '\n') return ParseStatus::Malformed;
        state_ = after_lf_;
        return end_of_line();
    }
    if (c == '\r' || c == '\n') {
        // Empty lines before the request line are ignored (RFC 9112 2.2).
        if (state_ == State::Method && method_len_ == 0) return ParseStatus::Incomplete;
        if (state_ != State::Version && state_ != State::HeaderStart && state_ != State::HeaderValue) {
            return ParseStatus::Malformed;
        }
        if (c == '\n') return end_of_line();
        after_lf_ = state_;
        state_ = State::LineFeed;
        return ParseStatus::Incomplete;
    }
    switch (state_) {
    case State::Method:
        if (c == ' ' && method_len_ > 0) {
            method_[method_len_] = '\0';
            state_ = State::Target;
            return ParseStatus::Incomplete;
        }
        if (!is_tchar(c) || method_len_ + 1 >= sizeof method_) return ParseStatus::Malformed;
        method_[method_len_++] = static_cast<char>(c);
        return ParseStatus::Incomplete;
    case State::Target:
        if (c == ' ' && target_len_ > 0) {
            finish_target();
            state_ = State::Version;
            return ParseStatus::Incomplete;
        }
        if (c <= 0x20 || c >= 0x7f) return ParseStatus::Malformed;
        if (target_len_ < kMaxTarget) target_[target_len_] = static_cast<char>(c);
        ++target_len_;
        return ParseStatus::Incomplete;
    case State::Version:
        if (version_len_ + 1 >= sizeof version_) return ParseStatus::Malformed;
        version_[version_len_++] = static_cast<char>(c);
        return ParseStatus::Incomplete;
    case State::HeaderStart:
        header_name_len_ = 0;
        state_ = State::HeaderName;
        return step(c);
    case State::HeaderName:
        if (c == ':' && header_name_len_ > 0) {
            state_ = State::HeaderValue;
            return ParseStatus::Incomplete;
        }
        if (!is_tchar(c)) return ParseStatus::Malformed;
        ++header_name_len_;
        return ParseStatus::Incomplete;
    case State::HeaderValue:
        if (c < 0x20 && c != '\t') return ParseStatus::Malformed;
        return c == 0x7f ? ParseStatus::Malformed : ParseStatus::Incomplete;
    case State::LineFeed:
    case State::Done:
        break;
    }
    return ParseStatus::Malformed;
}

void HttpRequestParser::finish_target() {
    if (target_len_ > kMaxTarget || target_[0] != '/') {
        // Too long or not origin-form: matches no route.
        path_[0] = '\0';
        return;
    }
    target_[target_len_] = '\0';
    const char* q = static_cast<const char*>(memchr(target_, '?', target_len_));
    size_t path_len = q ? static_cast<size_t>(q - target_) : target_len_;
    memcpy(path_, target_, path_len);
    path_[path_len] = '\0';
    if (q) {
        query_ = q + 1;
        query_len_ = target_len_ - path_len - 1;
    }
}

bool HttpRequestParser::is_get() const { return strcmp(method_, "GET") == 0; }

bool HttpRequestParser::query_param(const char* name, const char** value, size_t* len) const {
    size_t name_len = strlen(name);
    size_t pos = 0;
    while (pos < query_len_) {
        size_t end = pos;
        while (end < query_len_ && query_[end] != '&') ++end;
        if (end - pos > name_len && memcmp(query_ + pos, name, name_len) == 0 && query_[pos + name_len] == '=') {
            *value = query_ + pos + name_len + 1;
            *len = end - pos - name_len - 1;
            return true;
        }
        pos = end + 1;
    }
    return false;
}

RouteDecision route_request(const HttpRequestParser& req) {
    RouteDecision d = {Route::Error, 400, 0};
    if (req.status() == ParseStatus::HeadTooLarge) {
        d.status = 431;
        return d;
    }
    if (req.status() != ParseStatus::Complete) return d;
    static const struct {
        const char* path;
        Route route;
    } kRoutes[] = {{"/", Route::Index},
                   {"/stream", Route::Stream},
                   {"/capture", Route::Capture},
                   {"/status", Route::Status},
                   {"/time", Route::Time}};
    for (size_t i = 0; i < sizeof kRoutes / sizeof kRoutes[0]; ++i) {
        if (strcmp(req.path(), kRoutes[i].path) != 0) continue;
        if (!req.is_get()) {
            d.status = 405;
            return d;
        }
        d.route = kRoutes[i].route;
        d.status = 200;
        const char* v = 0;
        size_t n = 0;
        if (d.route == Route::Stream && req.query_param("fps", &v, &n)) {
            uint32_t tenths = 0;
            if (!parse_tenths(v, n, tenths) || tenths == 0 || tenths > kMaxStreamFpsTenths) {
                d.route = Route::Error;
                d.status = 400;
                return d;
            }
            d.fps_cap_tenths = tenths;
        }
        return d;
    }
    d.status = 404;
    return d;
}

const char* status_reason(uint16_t status) {
    switch (status) {
    case 200: return "OK";
    case 400: return "Bad Request";
    case 404: return "Not Found";
    case 405: return "Method Not Allowed";
    case 431: return "Request Header Fields Too Large";
    case 503: return "Service Unavailable";
    default: return "Internal Server Error";
    }
}

void write_response_head(TextBuf& out, uint16_t status, const char* content_type, int64_t content_length,
                         const char* extra) {
    out.add("HTTP/1.1 ").add_uint(status).add(' ').add(status_reason(status)).add("\r\n");
    out.add("Content-Type: ").add(content_type).add("\r\n");
    if (content_length >= 0) out.add("Content-Length: ").add_int(content_length).add("\r\n");
    out.add("Connection: close\r\nCache-Control: no-cache\r\nAccess-Control-Allow-Origin: *\r\n");
    out.add(extra).add("\r\n");
}

void write_error_response(TextBuf& out, uint16_t status) {
    const char* reason = status_reason(status);
    // Body: "<status> <reason>\n"
    int64_t body_len = 3 + 1 + static_cast<int64_t>(strlen(reason)) + 1;
    const char* extra = status == 405 ? "Allow: GET\r\n" : "";
    write_response_head(out, status, "text/plain", body_len, extra);
    out.add_uint(status).add(' ').add(reason).add('\n');
}

}  // namespace cubecam
