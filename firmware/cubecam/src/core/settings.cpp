#include "settings.h"

#include <string.h>

namespace cubecam {

namespace {

const SettingResult kOk = {0, ""};
const SettingResult kUnknownKey = {kErrUnknownKey,
                                   "unknown key; keys: name ssid password mode ip port jpeg_quality fps hdr"};

SettingResult invalid(const char* message) {
    SettingResult r = {kErrInvalidValue, message};
    return r;
}

bool is_name_char(char c) {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '-' ||
           c == '_';
}

// Printable ASCII without ',' (the GS2200M AT command separator).
bool is_wifi_text(const char* v, size_t n) {
    for (size_t i = 0; i < n; ++i) {
        if (v[i] < 0x20 || v[i] > 0x7e || v[i] == ',') return false;
    }
    return true;
}

void copy_text(char* dst, size_t cap, const char* src, size_t n) {
    if (n >= cap) n = cap - 1;
    memcpy(dst, src, n);
    dst[n] = '\0';
}

bool equals(const char* v, size_t n, const char* word) {
    return strlen(word) == n && memcmp(v, word, n) == 0;
}

class Writer {
public:
    explicit Writer(uint8_t* p) : p_(p) {}
    void u8(uint8_t v) { *p_++ = v; }
    void u16(uint16_t v) {
        u8(static_cast<uint8_t>(v));
        u8(static_cast<uint8_t>(v >> 8));
    }
    void u32(uint32_t v) {
        u16(static_cast<uint16_t>(v));
        u16(static_cast<uint16_t>(v >> 16));
    }
    void bytes(const void* v, size_t n) {
        memcpy(p_, v, n);
        p_ += n;
    }
    void text(const char* s, size_t field) {
        memset(p_, 0, field);
        memcpy(p_, s, strlen(s));
        p_ += field;
    }
private:
    uint8_t* p_;
};

class Reader {
public:
    explicit Reader(const uint8_t* p) : p_(p) {}
    uint8_t u8() { return *p_++; }
    uint16_t u16() {
        uint16_t lo = u8();
        return static_cast<uint16_t>(lo | (u8() << 8));
    }
    uint32_t u32() {
        uint32_t lo = u16();
        return lo | (static_cast<uint32_t>(u16()) << 16);
    }
    void bytes(void* v, size_t n) {
        memcpy(v, p_, n);
        p_ += n;
    }
    // A text field must hold its terminating NUL inside the field.
    bool text(char* dst, size_t field) {
        const void* nul = memchr(p_, 0, field);
        if (!nul) return false;
        memcpy(dst, p_, field);
        p_ += field;
        return true;
    }
private:
    const uint8_t* p_;
};

bool valid_name(const char* v, size_t n) {
    if (n == 0 || n > kMaxName) return false;
    for (size_t i = 0; i < n; ++i) {
        if (!is_name_char(v[i])) return false;
    }
    return true;
}

bool valid_frame_rate(uint16_t tenths) {
    return tenths == static_cast<uint16_t>(FrameRate::Fps30) ||
           tenths == static_cast<uint16_t>(FrameRate::Fps15) ||
           tenths == static_cast<uint16_t>(FrameRate::Fps7_5);
}

SettingResult parse_ip_config(const char* v, size_t n, IpConfig& ip) {
    static const char kMsg[] = "ip must be dhcp or a.b.c.d/prefix,gateway (e.g. 192.168.1.20/24,192.168.1.1)";
    if (equals(v, n, "dhcp")) {
        memset(&ip, 0, sizeof ip);
        ip.dhcp = true;
        return kOk;
    }
    const char* slash = static_cast<const char*>(memchr(v, '/', n));
    const char* comma = static_cast<const char*>(memchr(v, ',', n));
    if (!slash || !comma || comma < slash) return invalid(kMsg);
    IpConfig parsed;
    memset(&parsed, 0, sizeof parsed);
    uint32_t prefix = 0;
    if (!parse_ipv4(v, static_cast<size_t>(slash - v), parsed.address) ||
        !parse_uint(slash + 1, static_cast<size_t>(comma - slash - 1), 32, prefix) || prefix == 0 ||
        !parse_ipv4(comma + 1, static_cast<size_t>(v + n - comma - 1), parsed.gateway)) {
        return invalid(kMsg);
    }
    parsed.prefix = static_cast<uint8_t>(prefix);
    ip = parsed;
    return kOk;
}

}  // namespace

uint32_t crc32(const uint8_t* data, size_t len) {
    uint32_t crc = 0xFFFFFFFFu;
    for (size_t i = 0; i < len; ++i) {
        crc ^= data[i];
        for (int b = 0; b < 8; ++b) crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
    }
    return ~crc;
}

uint16_t frame_rate_tenths(FrameRate r) { return static_cast<uint16_t>(r); }

void settings_defaults(Settings& s) {
    memset(&s, 0, sizeof s);
    copy_text(s.name, sizeof s.name, "cubecam", 7);
    s.mode = WifiMode::Station;
    s.ip.dhcp = true;
    s.port = 80;
    s.jpeg_quality = 70;
    s.fps = FrameRate::Fps15;
    s.hdr = HdrMode::Auto;
}

void settings_encode(const Settings& s, uint8_t out[kSettingsRecordSize]) {
    Writer w(out);
    w.u32(kSettingsMagic);
    w.u16(kSettingsVersion);
    w.text(s.name, sizeof s.name);
    w.text(s.ssid, sizeof s.ssid);
    w.text(s.password, sizeof s.password);
    w.u8(static_cast<uint8_t>(s.mode));
    w.u8(s.ip.dhcp ? 1 : 0);
    w.bytes(s.ip.address, 4);
    w.u8(s.ip.prefix);
    w.bytes(s.ip.gateway, 4);
    w.u16(s.port);
    w.u8(s.jpeg_quality);
    w.u16(static_cast<uint16_t>(s.fps));
    w.u8(static_cast<uint8_t>(s.hdr));
    w.u32(crc32(out, kSettingsRecordSize - 4));
}

bool settings_decode(const uint8_t* rec, size_t len, Settings& s) {
    if (len < kSettingsRecordSize) return false;
    Reader r(rec);
    if (r.u32() != kSettingsMagic || r.u16() != kSettingsVersion) return false;
    Reader tail(rec + kSettingsRecordSize - 4);
    if (tail.u32() != crc32(rec, kSettingsRecordSize - 4)) return false;
    Settings d;
    memset(&d, 0, sizeof d);
    if (!r.text(d.name, sizeof d.name) || !r.text(d.ssid, sizeof d.ssid) ||
        !r.text(d.password, sizeof d.password)) {
        return false;
    }
    uint8_t mode = r.u8();
    d.ip.dhcp = r.u8() != 0;
    r.bytes(d.ip.address, 4);
    d.ip.prefix = r.u8();
    r.bytes(d.ip.gateway, 4);
    d.port = r.u16();
    d.jpeg_quality = r.u8();
    uint16_t fps = r.u16();
    uint8_t hdr = r.u8();
    size_t pass_len = strlen(d.password);
    if (mode > 1 || hdr > 2 || !valid_frame_rate(fps) || d.port == 0 || d.jpeg_quality == 0 ||
        d.jpeg_quality > 100 || !valid_name(d.name, strlen(d.name)) ||
        !validate_ssid(d.ssid, strlen(d.ssid)).ok() ||
        (pass_len > 0 && !validate_passphrase(d.password, pass_len).ok()) ||
        (!d.ip.dhcp && (d.ip.prefix == 0 || d.ip.prefix > 32))) {
        return false;
    }
    d.mode = static_cast<WifiMode>(mode);
    d.fps = static_cast<FrameRate>(fps);
    d.hdr = static_cast<HdrMode>(hdr);
    s = d;
    return true;
}

const char* const kSettingKeys[] = {"name", "ssid",         "password", "mode", "ip",
                                    "port", "jpeg_quality", "fps",      "hdr"};
const size_t kSettingKeyCount = sizeof kSettingKeys / sizeof kSettingKeys[0];

SettingResult validate_ssid(const char* v, size_t n) {
    if (n > kMaxSsid) return invalid("ssid must be at most 32 bytes");
    if (!is_wifi_text(v, n)) return invalid("ssid must be printable ASCII without commas");
    return kOk;
}

SettingResult validate_passphrase(const char* v, size_t n) {
    if (n < kMinPassphrase || n > kMaxPassphrase) {
        return invalid("password must be 8 to 63 characters (WPA2 passphrase)");
    }
    if (!is_wifi_text(v, n)) return invalid("password must be printable ASCII without commas");
    return kOk;
}

SettingResult settings_set(Settings& s, const char* key, const char* v, size_t n) {
    if (strcmp(key, "name") == 0) {
        if (!valid_name(v, n)) return invalid("name must be 1 to 32 of A-Z a-z 0-9 - _");
        copy_text(s.name, sizeof s.name, v, n);
    } else if (strcmp(key, "ssid") == 0) {
        SettingResult r = validate_ssid(v, n);
        if (!r.ok()) return r;
        copy_text(s.ssid, sizeof s.ssid, v, n);
    } else if (strcmp(key, "password") == 0) {
        // Empty means an open network.
        if (n > 0) {
            SettingResult r = validate_passphrase(v, n);
            if (!r.ok()) return r;
        }
        copy_text(s.password, sizeof s.password, v, n);
    } else if (strcmp(key, "mode") == 0) {
        if (equals(v, n, "station")) {
            s.mode = WifiMode::Station;
        } else if (equals(v, n, "ap")) {
            s.mode = WifiMode::AccessPoint;
        } else {
            return invalid("mode must be station or ap");
        }
    } else if (strcmp(key, "ip") == 0) {
        return parse_ip_config(v, n, s.ip);
    } else if (strcmp(key, "port") == 0) {
        uint32_t port = 0;
        if (!parse_uint(v, n, 65535, port) || port == 0) return invalid("port must be 1 to 65535");
        s.port = static_cast<uint16_t>(port);
    } else if (strcmp(key, "jpeg_quality") == 0) {
        uint32_t q = 0;
        if (!parse_uint(v, n, 100, q) || q == 0) return invalid("jpeg_quality must be 1 to 100");
        s.jpeg_quality = static_cast<uint8_t>(q);
    } else if (strcmp(key, "fps") == 0) {
        uint32_t tenths = 0;
        if (!parse_tenths(v, n, tenths) || tenths > 0xFFFF ||
            !valid_frame_rate(static_cast<uint16_t>(tenths))) {
            return invalid("fps must be 30, 15 or 7.5 (the rates the ISX019 accepts)");
        }
        s.fps = static_cast<FrameRate>(tenths);
    } else if (strcmp(key, "hdr") == 0) {
        if (equals(v, n, "off")) {
            s.hdr = HdrMode::Off;
        } else if (equals(v, n, "auto")) {
            s.hdr = HdrMode::Auto;
        } else if (equals(v, n, "on")) {
            s.hdr = HdrMode::On;
        } else {
            return invalid("hdr must be off, auto or on");
        }
    } else {
        return kUnknownKey;
    }
    return kOk;
}

SettingResult settings_get(const Settings& s, const char* key, TextBuf& out) {
    if (strcmp(key, "name") == 0) {
        out.add(s.name);
    } else if (strcmp(key, "ssid") == 0) {
        out.add(s.ssid);
    } else if (strcmp(key, "password") == 0) {
        out.add(s.password[0] ? "(set)" : "(empty)");
    } else if (strcmp(key, "mode") == 0) {
        out.add(s.mode == WifiMode::Station ? "station" : "ap");
    } else if (strcmp(key, "ip") == 0) {
        if (s.ip.dhcp) {
            out.add("dhcp");
        } else {
            out.add_ipv4(s.ip.address).add('/').add_uint(s.ip.prefix).add(',').add_ipv4(s.ip.gateway);
        }
    } else if (strcmp(key, "port") == 0) {
        out.add_uint(s.port);
    } else if (strcmp(key, "jpeg_quality") == 0) {
        out.add_uint(s.jpeg_quality);
    } else if (strcmp(key, "fps") == 0) {
        uint16_t t = frame_rate_tenths(s.fps);
        if (t % 10 == 0) {
            out.add_uint(t / 10);
        } else {
            out.add_fixed(t, 1);
        }
    } else if (strcmp(key, "hdr") == 0) {
        static const char* const kHdr[] = {"off", "auto", "on"};
        out.add(kHdr[static_cast<uint8_t>(s.hdr)]);
    } else {
        return kUnknownKey;
    }
    return kOk;
}

}  // namespace cubecam
