#include "gs2200m.h"

#include <string.h>

namespace cubecam {
namespace gs2200m {

namespace {

const char* skip_spaces(const char* p) {
    while (*p == ' ') ++p;
    return p;
}

}  // namespace

char cid_char(uint8_t cid) { return "0123456789abcdef"[cid & 15]; }

bool parse_cid(char c, uint8_t& cid) {
    if (c >= '0' && c <= '9') {
        cid = static_cast<uint8_t>(c - '0');
    } else if (c >= 'a' && c <= 'f') {
        cid = static_cast<uint8_t>(c - 'a' + 10);
    } else {
        return false;
    }
    return true;
}

bool event_cid(const char* line, const char* keyword, int word, uint8_t& cid) {
    const char* p = strstr(line, keyword);
    if (!p) return false;
    p += strlen(keyword);
    for (int w = 0; *p; ++w) {
        p = skip_spaces(p);
        const char* end = p;
        while (*end && *end != ' ' && *end != '\r' && *end != '\n') ++end;
        if (w == word) return end - p == 1 && parse_cid(*p, cid);
        p = end;
    }
    return false;
}

bool parse_scan_line(const char* line, ScanEntry& out) {
    const char* field[6];
    int count = 0;
    field[count++] = line;
    for (const char* p = line; *p && count < 6; ++p) {
        if (*p == ',') field[count++] = p + 1;
    }
    if (count < 6) return false;
    const char* ssid = skip_spaces(field[1]);
    size_t len = static_cast<size_t>(field[2] - 1 - ssid);
    while (len > 0 && ssid[len - 1] == ' ') --len;
    if (len == 0 || len >= sizeof out.ssid) return false;
    const char* rssi = skip_spaces(field[4]);
    bool negative = *rssi == '-';
    const char* digit = negative ? rssi + 1 : rssi;
    int value = 0;
    if (*digit < '0' || *digit > '9') return false;
    for (; *digit >= '0' && *digit <= '9'; ++digit) {
        value = value * 10 + (*digit - '0');
        if (value > 128) return false;
    }
    if (!negative && value > 127) return false;
    memset(out.ssid, 0, sizeof out.ssid);
    memcpy(out.ssid, ssid, len);
    out.rssi = static_cast<int8_t>(negative ? -value : value);
    out.secured = strstr(field[5], "NONE") == 0;
    return true;
}

void bulk_header(uint8_t cid, uint16_t len, uint8_t out[kBulkHeaderBytes]) {
    out[0] = kEsc;
    out[1] = 'Z';
    out[2] = static_cast<uint8_t>(cid_char(cid));
    for (int i = 0, div = 1000; i < 4; ++i, div /= 10) out[3 + i] = static_cast<uint8_t>('0' + (len / div) % 10);
}

}  // namespace gs2200m
}  // namespace cubecam
