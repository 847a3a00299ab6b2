#include "gs2200m.h"

#include <string.h>

namespace cubecam {
namespace gs2200m {

namespace {

const char* skip_spaces(const char* p) {
    while (*p == ' ') ++p;
    return p;
}

bool printable_ascii(char c) { return c >= 0x20 && c <= 0x7e; }

// The SSID argument: a backslash before every '"', which the module takes
// away again. No quotes around it: an SSID has no comma (settings.h), and its
// first character is then never a '"'.
void add_ssid(TextBuf& out, const char* ssid) {
    for (const char* p = ssid; *p; ++p) {
        if (*p == '"') out.add('\\');
        out.add(*p);
    }
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

const char kKeyFollows[] = "cubecam-key-follows";

PassphraseArg passphrase_arg(const char* passphrase) {
    size_t len = strlen(passphrase);
    bool plain = len > 0 && passphrase[0] != ' ' && passphrase[0] != '"' && passphrase[len - 1] != ' ';
    bool quoted = len > 0 && passphrase[len - 1] != '\\';
    for (size_t i = 0; i < len; ++i) {
        char c = passphrase[i];
        if (!printable_ascii(c)) return PassphraseArg::KeyOnly;
        if (c == ',') plain = false;
        if (c == '"' && (i == 0 || passphrase[i - 1] != '\\')) quoted = false;
    }
    if (plain) return PassphraseArg::Plain;
    return quoted ? PassphraseArg::Quoted : PassphraseArg::KeyOnly;
}

bool add_wpapsk(TextBuf& out, const char* ssid, const char* passphrase) {
    PassphraseArg form = passphrase_arg(passphrase);
    if (form == PassphraseArg::KeyOnly) return false;
    out.add("AT+WPAPSK=");
    add_ssid(out, ssid);
    out.add(',');
    if (form == PassphraseArg::Quoted) {
        out.add('"').add(passphrase).add('"');
    } else {
        out.add(passphrase);
    }
    out.add("\r\n");
    return true;
}

void add_wpsk(TextBuf& out, const uint8_t psk[wpa::kPskBytes]) {
    static const char kHex[] = "0123456789abcdef";
    out.add("AT+WPSK=");
    for (size_t i = 0; i < wpa::kPskBytes; ++i) out.add(kHex[psk[i] >> 4]).add(kHex[psk[i] & 15]);
    out.add("\r\n");
}

void add_wa(TextBuf& out, const char* ssid, uint8_t channel) {
    out.add("AT+WA=");
    add_ssid(out, ssid);
    if (channel > 0) out.add(",,").add_uint(channel);
    out.add("\r\n");
}

}  // namespace gs2200m
}  // namespace cubecam
