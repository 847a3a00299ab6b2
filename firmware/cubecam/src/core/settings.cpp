#include "settings.h"

#include <string.h>

namespace cubecam {

namespace {

const SettingResult kOk = {0, ""};
const SettingResult kUnknownKey = {kErrUnknownKey, "unknown key; try help"};
const char kIpSyntax[] = "dhcp|a.b.c.d/prefix,gateway";

SettingResult invalid(const char* message) {
    SettingResult r = {kErrInvalidValue, message};
    return r;
}

bool equals(const char* v, size_t n, const char* word) { return strlen(word) == n && memcmp(v, word, n) == 0; }

bool in_charset(char c, Charset set) {
    uint8_t b = static_cast<uint8_t>(c);
    if (set == Charset::Ssid) return b >= 0x20 && b <= 0x7e && c != ',';
    if (set == Charset::Passphrase) return b >= 0x20 && b != 0x7f;
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '-' || c == '_';
}

const SettingField* find(const char* key) {
    for (size_t i = 0; i < kSettingCount; ++i) {
        if (strcmp(kSettingFields[i].key, key) == 0) return &kSettingFields[i];
    }
    return 0;
}

// The member a field describes.
uint8_t* member(Settings& s, const SettingField& f) { return reinterpret_cast<uint8_t*>(&s) + f.offset; }
const uint8_t* member(const Settings& s, const SettingField& f) {
    return reinterpret_cast<const uint8_t*>(&s) + f.offset;
}

// Choice and Number members are 1- or 2-byte unsigned integers (or enums of them).
uint16_t read_int(const Settings& s, const SettingField& f) {
    if (f.bytes == 1) return *member(s, f);
    uint16_t v;
    memcpy(&v, member(s, f), sizeof v);
    return v;
}

void write_int(Settings& s, const SettingField& f, uint16_t v) {
    if (f.bytes == 1) {
        *member(s, f) = static_cast<uint8_t>(v);
    } else {
        memcpy(member(s, f), &v, sizeof v);
    }
}

SettingResult check_text(const SettingField& f, const char* v, size_t n) {
    bool length_ok = (n == 0 && f.empty_ok) || (n >= f.min && n <= f.max);
    if (!length_ok) return invalid(f.rule);
    for (size_t i = 0; i < n; ++i) {
        if (!in_charset(v[i], f.charset)) return invalid(f.charset_rule);
    }
    return kOk;
}

bool choice_value(const SettingField& f, const char* v, size_t n, uint16_t& value) {
    for (uint8_t i = 0; i < f.count; ++i) {
        if (equals(v, n, f.words[i])) {
            value = f.values[i];
            return true;
        }
    }
    return false;
}

const char* choice_word(const SettingField& f, uint16_t value) {
    for (uint8_t i = 0; i < f.count; ++i) {
        if (f.values[i] == value) return f.words[i];
    }
    return 0;
}

bool parse_ip_config(const char* v, size_t n, IpConfig& ip) {
    IpConfig parsed;
    memset(&parsed, 0, sizeof parsed);
    if (equals(v, n, "dhcp")) {
        parsed.dhcp = true;
        ip = parsed;
        return true;
    }
    const char* slash = static_cast<const char*>(memchr(v, '/', n));
    const char* comma = static_cast<const char*>(memchr(v, ',', n));
    if (!slash || !comma || comma < slash) return false;
    uint32_t prefix = 0;
    if (!parse_ipv4(v, static_cast<size_t>(slash - v), parsed.address) ||
        !parse_uint(slash + 1, static_cast<size_t>(comma - slash - 1), 32, prefix) || prefix == 0 ||
        !parse_ipv4(comma + 1, static_cast<size_t>(v + n - comma - 1), parsed.gateway)) {
        return false;
    }
    parsed.prefix = static_cast<uint8_t>(prefix);
    ip = parsed;
    return true;
}

SettingResult set_field(Settings& s, const SettingField& f, const char* v, size_t n) {
    switch (f.type) {
    case FieldType::Text: {
        SettingResult r = check_text(f, v, n);
        if (!r.ok()) return r;
        memset(member(s, f), 0, f.bytes);
        memcpy(member(s, f), v, n);
        return kOk;
    }
    case FieldType::Choice: {
        uint16_t value = 0;
        if (!choice_value(f, v, n, value)) return invalid(f.rule);
        write_int(s, f, value);
        return kOk;
    }
    case FieldType::Number: {
        uint32_t value = 0;
        if (!parse_uint(v, n, f.max, value) || value < f.min) return invalid(f.rule);
        write_int(s, f, static_cast<uint16_t>(value));
        return kOk;
    }
    case FieldType::Ip:
        return parse_ip_config(v, n, s.ip) ? kOk : invalid(f.rule);
    }
    return invalid(f.rule);
}

// A stored field is valid when the console would have accepted it.
bool field_valid(const Settings& s, const SettingField& f) {
    switch (f.type) {
    case FieldType::Text: {
        const char* text = reinterpret_cast<const char*>(member(s, f));
        return check_text(f, text, strlen(text)).ok();
    }
    case FieldType::Choice:
        return choice_word(f, read_int(s, f)) != 0;
    case FieldType::Number: {
        uint16_t v = read_int(s, f);
        return v >= f.min && v <= f.max;
    }
    case FieldType::Ip: {
        // As parse_ip_config leaves it: DHCP with no address at all.
        static const uint8_t kNone[4] = {0, 0, 0, 0};
        if (!s.ip.dhcp) return s.ip.prefix >= 1 && s.ip.prefix <= 32;
        return s.ip.prefix == 0 && memcmp(s.ip.address, kNone, 4) == 0 && memcmp(s.ip.gateway, kNone, 4) == 0;
    }
    }
    return false;
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
    // Text with its NUL padding, so the record holds nothing else.
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
        if (!memchr(p_, 0, field)) return false;
        bytes(dst, field);
        return true;
    }
private:
    const uint8_t* p_;
};

void encode_field(Writer& w, const Settings& s, const SettingField& f) {
    switch (f.type) {
    case FieldType::Text:
        w.text(reinterpret_cast<const char*>(member(s, f)), f.bytes);
        break;
    case FieldType::Choice:
    case FieldType::Number:
        if (f.bytes == 1) {
            w.u8(static_cast<uint8_t>(read_int(s, f)));
        } else {
            w.u16(read_int(s, f));
        }
        break;
    case FieldType::Ip:
        w.u8(s.ip.dhcp ? 1 : 0);
        w.bytes(s.ip.address, 4);
        w.u8(s.ip.prefix);
        w.bytes(s.ip.gateway, 4);
        break;
    }
}

bool decode_field(Reader& r, Settings& s, const SettingField& f) {
    switch (f.type) {
    case FieldType::Text:
        return r.text(reinterpret_cast<char*>(member(s, f)), f.bytes);
    case FieldType::Choice:
    case FieldType::Number:
        write_int(s, f, f.bytes == 1 ? r.u8() : r.u16());
        return true;
    case FieldType::Ip: {
        uint8_t dhcp = r.u8();
        s.ip.dhcp = dhcp != 0;
        r.bytes(s.ip.address, 4);
        s.ip.prefix = r.u8();
        r.bytes(s.ip.gateway, 4);
        return dhcp <= 1;  // the encoder writes 0 or 1
    }
    }
    return false;
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
    for (size_t i = 0; i < kSettingCount; ++i) {
        const SettingField& f = kSettingFields[i];
        set_field(s, f, f.default_text, strlen(f.default_text));
    }
}

void settings_encode(const Settings& s, uint8_t out[kSettingsRecordSize]) {
    Writer w(out);
    w.u32(kSettingsMagic);
    w.u16(kSettingsVersion);
    for (size_t i = 0; i < kSettingCount; ++i) encode_field(w, s, kSettingFields[i]);
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
    for (size_t i = 0; i < kSettingCount; ++i) {
        if (!decode_field(r, d, kSettingFields[i]) || !field_valid(d, kSettingFields[i])) return false;
    }
    s = d;
    return true;
}

SettingResult validate_ssid(const char* v, size_t n) { return check_text(*find("ssid"), v, n); }

SettingResult validate_passphrase(const char* v, size_t n) {
    const SettingField& f = *find("password");
    return n == 0 ? invalid(f.rule) : check_text(f, v, n);
}

SettingResult settings_check(const Settings& s) {
    if (s.mode == WifiMode::AccessPoint && s.password[0] == '\0') {
        return invalid("mode ap needs a password (8-63 characters): the access point is always WPA2");
    }
    return SettingResult{0, ""};
}

SettingResult settings_set(Settings& s, const char* key, const char* v, size_t n) {
    const SettingField* f = find(key);
    return f ? set_field(s, *f, v, n) : kUnknownKey;
}

SettingResult settings_get(const Settings& s, const char* key, TextBuf& out) {
    const SettingField* f = find(key);
    if (!f) return kUnknownKey;
    switch (f->type) {
    case FieldType::Text: {
        const char* text = reinterpret_cast<const char*>(member(s, *f));
        if (f->write_only) {
            out.add(text[0] ? "(set)" : "(empty)");
        } else {
            out.add(text);
        }
        break;
    }
    case FieldType::Choice:
        out.add(choice_word(*f, read_int(s, *f)));
        break;
    case FieldType::Number:
        out.add_uint(read_int(s, *f));
        break;
    case FieldType::Ip:
        if (s.ip.dhcp) {
            out.add("dhcp");
        } else {
            out.add_ipv4(s.ip.address).add('/').add_uint(s.ip.prefix).add(',').add_ipv4(s.ip.gateway);
        }
        break;
    }
    return kOk;
}

void settings_hint(const SettingField& f, TextBuf& out) {
    switch (f.type) {
    case FieldType::Text:
        if (f.write_only) out.add("(write-only)");
        return;
    case FieldType::Choice:
        for (uint8_t i = 0; i < f.count; ++i) out.add(i ? '|' : '(').add(f.words[i]);
        out.add(')');
        return;
    case FieldType::Number:
        out.add('(').add_uint(f.min).add('-').add_uint(f.max).add(')');
        return;
    case FieldType::Ip:
        out.add('(').add(kIpSyntax).add(')');
        return;
    }
}

}  // namespace cubecam
