// Bounded text building without printf (newlib-nano has no float printf).
#ifndef CUBECAM_CORE_TEXT_H
#define CUBECAM_CORE_TEXT_H

#include <stddef.h>
#include <stdint.h>

namespace cubecam {

// Appends into a caller-owned buffer, never past its end. Once something did
// not fit, overflowed() stays true and the content is cut at the limit.
class TextBuf {
public:
    TextBuf(char* buf, size_t cap);
    TextBuf& add(const char* s);
    TextBuf& add(const char* s, size_t n);
    TextBuf& add(char c);
    TextBuf& add_uint(uint64_t v);
    TextBuf& add_int(int64_t v);
    // v / 10^decimals with exactly `decimals` digits after the point.
    TextBuf& add_fixed(int64_t v, unsigned decimals);
    // <seconds>.<6-digit microseconds>, the X-Timestamp and /time format.
    TextBuf& add_timestamp(uint64_t micros);
    TextBuf& add_ipv4(const uint8_t ip[4]);
    // JSON string with quotes and escapes.
    TextBuf& add_json_string(const char* s);
    const char* c_str() const { return buf_; }
    size_t size() const { return len_; }
    bool overflowed() const { return overflow_; }
    void clear();

private:
    char* buf_;
    size_t cap_;
    size_t len_;
    bool overflow_;
};

// Parses an unsigned decimal of at most max_digits digits; s[0..n) only.
bool parse_uint(const char* s, size_t n, uint32_t max_value, uint32_t& out);
// Parses "30", "7.5", "0.5" into tenths (300, 75, 5). One decimal at most.
bool parse_tenths(const char* s, size_t n, uint32_t& out);
// Parses a dotted quad.
bool parse_ipv4(const char* s, size_t n, uint8_t out[4]);

}  // namespace cubecam

#endif
