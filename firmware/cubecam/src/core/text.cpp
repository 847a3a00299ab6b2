#include "text.h"

#include <string.h>

namespace cubecam {

TextBuf::TextBuf(char* buf, size_t cap) : buf_(buf), cap_(cap), len_(0), overflow_(false) {
    if (cap_ > 0) buf_[0] = '\0';
}

void TextBuf::clear() {
    len_ = 0;
    overflow_ = false;
    if (cap_ > 0) buf_[0] = '\0';
}

TextBuf& TextBuf::add(const char* s, size_t n) {
    if (cap_ == 0) {
        overflow_ = overflow_ || n > 0;
        return *this;
    }
    size_t room = cap_ - 1 - len_;
    if (n > room) {
        n = room;
        overflow_ = true;
    }
    memcpy(buf_ + len_, s, n);
    len_ += n;
    buf_[len_] = '\0';
    return *this;
}

TextBuf& TextBuf::add(const char* s) { return add(s, strlen(s)); }

TextBuf& TextBuf::add(char c) { return add(&c, 1); }

TextBuf& TextBuf::add_uint(uint64_t v) {
    char digits[20];
    size_t n = 0;
    do {
        digits[n++] = static_cast<char>('0' + v % 10);
        v /= 10;
    } while (v != 0);
    char out[20];
    for (size_t i = 0; i < n; ++i) out[i] = digits[n - 1 - i];
    return add(out, n);
}

TextBuf& TextBuf::add_int(int64_t v) {
    if (v < 0) {
        add('-');
        return add_uint(static_cast<uint64_t>(-(v + 1)) + 1);
    }
    return add_uint(static_cast<uint64_t>(v));
}

TextBuf& TextBuf::add_fixed(int64_t v, unsigned decimals) {
    uint64_t scale = 1;
    for (unsigned i = 0; i < decimals; ++i) scale *= 10;
    uint64_t mag = v < 0 ? static_cast<uint64_t>(-(v + 1)) + 1 : static_cast<uint64_t>(v);
    if (v < 0) add('-');
    add_uint(mag / scale);
    if (decimals == 0) return *this;
    add('.');
    uint64_t frac = mag % scale;
    for (uint64_t d = scale / 10; d > 0; d /= 10) {
        add(static_cast<char>('0' + (frac / d) % 10));
    }
    return *this;
}

TextBuf& TextBuf::add_timestamp(uint64_t micros) {
    return add_fixed(static_cast<int64_t>(micros), 6);
}

TextBuf& TextBuf::add_ipv4(const uint8_t ip[4]) {
    for (int i = 0; i < 4; ++i) {
        if (i) add('.');
        add_uint(ip[i]);
    }
    return *this;
}

TextBuf& TextBuf::add_json_string(const char* s) {
    static const char kHex[] = "0123456789abcdef";
    add('"');
    for (; *s; ++s) {
        unsigned char c = static_cast<unsigned char>(*s);
        if (c == '"' || c == '\\') {
            add('\\').add(static_cast<char>(c));
        } else if (c < 0x20) {
            char esc[6] = {'\\', 'u', '0', '0', kHex[c >> 4], kHex[c & 15]};
            add(esc, sizeof esc);
        } else {
            add(static_cast<char>(c));
        }
    }
    return add('"');
}

bool parse_uint(const char* s, size_t n, uint32_t max_value, uint32_t& out) {
    if (n == 0 || n > 10) return false;
    uint64_t v = 0;
    for (size_t i = 0; i < n; ++i) {
        if (s[i] < '0' || s[i] > '9') return false;
        v = v * 10 + static_cast<uint64_t>(s[i] - '0');
    }
    if (v > max_value) return false;
    out = static_cast<uint32_t>(v);
    return true;
}

bool parse_tenths(const char* s, size_t n, uint32_t& out) {
    const char* dot = static_cast<const char*>(memchr(s, '.', n));
    uint32_t whole = 0;
    if (!dot) {
        if (!parse_uint(s, n, 100000, whole)) return false;
        out = whole * 10;
        return true;
    }
    size_t wn = static_cast<size_t>(dot - s);
    size_t fn = n - wn - 1;
    uint32_t frac = 0;
    if (fn != 1 || !parse_uint(dot + 1, 1, 9, frac)) return false;
    if (wn > 0 && !parse_uint(s, wn, 100000, whole)) return false;
    if (wn == 0) return false;
    out = whole * 10 + frac;
    return true;
}

bool parse_ipv4(const char* s, size_t n, uint8_t out[4]) {
    size_t start = 0;
    for (int part = 0; part < 4; ++part) {
        size_t end = start;
        while (end < n && s[end] != '.') ++end;
        if ((part < 3) != (end < n)) return false;
        uint32_t v = 0;
        if (end - start > 3 || !parse_uint(s + start, end - start, 255, v)) return false;
        out[part] = static_cast<uint8_t>(v);
        start = end + 1;
    }
    return true;
}

}  // namespace cubecam
