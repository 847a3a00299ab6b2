// The node's persistent settings: the Settings struct, and one table that
// says, for each of its fields, the console key, how the value is written,
// checked, defaulted and stored in the versioned record (magic, version,
// fields in table order, CRC-32). Codec, key list, get/set, defaults and the
// record size all follow from that table.
#ifndef CUBECAM_CORE_SETTINGS_H
#define CUBECAM_CORE_SETTINGS_H

#include <stddef.h>
#include <stdint.h>

#include "text.h"

namespace cubecam {

enum class WifiMode : uint8_t { Station = 0, AccessPoint = 1 };

// Values are the Spresense CAM_HDR_MODE values.
enum class HdrMode : uint8_t { Off = 0, Auto = 1, On = 2 };

// The frame rates the ISX019 accepts through the Arduino enum, in tenths.
enum class FrameRate : uint16_t { Fps30 = 300, Fps15 = 150, Fps7_5 = 75 };

struct IpConfig {
    bool dhcp;
    uint8_t address[4];
    uint8_t prefix;
    uint8_t gateway[4];
};

const size_t kMaxName = 32;
const size_t kMaxSsid = 32;
const size_t kMinPassphrase = 8;
const size_t kMaxPassphrase = 63;

struct Settings {
    char name[kMaxName + 1];
    char ssid[kMaxSsid + 1];
    char password[kMaxPassphrase + 1];
    WifiMode mode;
    IpConfig ip;
    uint16_t port;
    uint8_t jpeg_quality;
    FrameRate fps;
    HdrMode hdr;
};

// How a field is written on the console and kept in the record.
enum class FieldType : uint8_t {
    Text,    // NUL-padded in `bytes` (the char array, its NUL included)
    Choice,  // one of `words`; stored as the matching entry of `values`
    Number,  // decimal min..max; stored in `bytes` (1 or 2) little-endian
    Ip       // "dhcp" or a.b.c.d/prefix,gateway; stored as IpConfig's 10 bytes
};

// Text that may stand in the field.
enum class Charset : uint8_t {
    Name,        // A-Z a-z 0-9 - _
    Ssid,        // printable ASCII without ',' (the scan list and the AT commands separate fields with it)
    Passphrase   // any byte but control characters: printable ASCII, and UTF-8 beyond it
};

struct SettingField {
    const char* key;
    FieldType type;
    uint16_t offset;  // of the member in Settings
    uint8_t bytes;    // of the member, and of the field in the record
    uint16_t min;     // Text: shortest length (0 allowed when empty_ok), Number: smallest value
    uint16_t max;     // Text: longest length, Number: largest value
    const char* const* words;  // Choice
    const uint16_t* values;    // Choice, one per word
    uint8_t count;             // Choice
    Charset charset;           // Text
    bool empty_ok;             // Text: "" is allowed besides min..max
    bool write_only;           // Text: get shows "(set)" or "(empty)"
    const char* default_text;  // the factory value, as typed on the console
    const char* rule;          // what a valid value is, for the error message
    const char* charset_rule;  // Text: the same for a character outside the charset
};

constexpr SettingField text_field(const char* key, uint16_t offset, uint8_t bytes, uint16_t min, Charset charset,
                                  bool empty_ok, bool write_only, const char* default_text, const char* rule,
                                  const char* charset_rule) {
    return SettingField{key,      FieldType::Text, offset,     bytes,        min,  static_cast<uint16_t>(bytes - 1),
                        nullptr,  nullptr,         0,          charset,      empty_ok, write_only,
                        default_text, rule,        charset_rule};
}

constexpr SettingField choice_field(const char* key, uint16_t offset, uint8_t bytes, const char* const* words,
                                    const uint16_t* values, uint8_t count, const char* default_text,
                                    const char* rule) {
    return SettingField{key,   FieldType::Choice, offset, bytes, 0,            0,    words,  values,
                        count, Charset::Name,     false,  false, default_text, rule, nullptr};
}

constexpr SettingField number_field(const char* key, uint16_t offset, uint8_t bytes, uint16_t min, uint16_t max,
                                    const char* default_text, const char* rule) {
    return SettingField{key, FieldType::Number, offset, bytes, min,          max,  nullptr, nullptr,
                        0,   Charset::Name,     false,  false, default_text, rule, nullptr};
}

constexpr SettingField ip_field(const char* key, uint16_t offset, const char* default_text, const char* rule) {
    return SettingField{key,   FieldType::Ip, offset, 10, 0, 0, nullptr, nullptr, 0, Charset::Name, false, false,
                        default_text, rule, nullptr};
}

constexpr const char* kModeWords[] = {"station", "ap"};
constexpr uint16_t kModeValues[] = {0, 1};
constexpr const char* kFpsWords[] = {"30", "15", "7.5"};
constexpr uint16_t kFpsValues[] = {300, 150, 75};
constexpr const char* kHdrWords[] = {"off", "auto", "on"};
constexpr uint16_t kHdrValues[] = {0, 1, 2};

// Console order, record order.
constexpr SettingField kSettingFields[] = {
    text_field("name", offsetof(Settings, name), sizeof(Settings::name), 1, Charset::Name, false, false, "cubecam",
               "name must be 1 to 32 of A-Z a-z 0-9 - _", "name must be 1 to 32 of A-Z a-z 0-9 - _"),
    text_field("ssid", offsetof(Settings, ssid), sizeof(Settings::ssid), 0, Charset::Ssid, true, false, "",
               "ssid must be at most 32 bytes", "ssid must be printable ASCII without commas"),
    // Empty means an open network. Commas, quotes and spaces are fine: the
    // GS2200M adapter quotes the passphrase, or sends the key it derives.
    text_field("password", offsetof(Settings, password), sizeof(Settings::password), kMinPassphrase,
               Charset::Passphrase, true, true, "", "password must be 8 to 63 bytes (WPA2 passphrase)",
               "password must not contain control characters"),
    choice_field("mode", offsetof(Settings, mode), 1, kModeWords, kModeValues, 2, "station",
                 "mode must be station or ap"),
    ip_field("ip", offsetof(Settings, ip), "dhcp",
             "ip must be dhcp or a.b.c.d/prefix,gateway (e.g. 192.168.1.20/24,192.168.1.1)"),
    number_field("port", offsetof(Settings, port), 2, 1, 65535, "80", "port must be 1 to 65535"),
    number_field("jpeg_quality", offsetof(Settings, jpeg_quality), 1, 1, 100, "70", "jpeg_quality must be 1 to 100"),
    choice_field("fps", offsetof(Settings, fps), 2, kFpsWords, kFpsValues, 3, "15",
                 "fps must be 30, 15 or 7.5 (the rates the ISX019 accepts)"),
    choice_field("hdr", offsetof(Settings, hdr), 1, kHdrWords, kHdrValues, 3, "auto", "hdr must be off, auto or on"),
};
constexpr size_t kSettingCount = sizeof kSettingFields / sizeof kSettingFields[0];

constexpr size_t fields_bytes(size_t i) { return i == kSettingCount ? 0 : kSettingFields[i].bytes + fields_bytes(i + 1); }

// The record: magic, version, the fields in table order, CRC-32 of all before it.
const uint32_t kSettingsMagic = 0x43554243u;  // "CBUC" in memory order
const uint16_t kSettingsVersion = 1;
constexpr size_t kSettingsRecordSize = 4 + 2 + fields_bytes(0) + 4;

// Factory settings: every field's default_text.
void settings_defaults(Settings& s);
void settings_encode(const Settings& s, uint8_t out[kSettingsRecordSize]);
// False (and s untouched) when magic, version, CRC or any field is invalid.
bool settings_decode(const uint8_t* rec, size_t len, Settings& s);

uint32_t crc32(const uint8_t* data, size_t len);

// Result of a key/value operation: code 0 = ok, otherwise a console error
// code (see console.h) and a message that says what valid input looks like.
struct SettingResult {
    uint8_t code;
    const char* message;
    bool ok() const { return code == 0; }
};

const uint8_t kErrUnknownKey = 3;
const uint8_t kErrInvalidValue = 4;

SettingResult settings_set(Settings& s, const char* key, const char* value, size_t value_len);
// What no single field shows: access-point mode needs a password (the
// GS2200 library's begin() sets WPA2 for an access point whatever we ask).
SettingResult settings_check(const Settings& s);
// Appends the value of key; a write-only field yields "(set)" or "(empty)", never itself.
SettingResult settings_get(const Settings& s, const char* key, TextBuf& out);
// Appends the console's hint for a key: "(station|ap)", "(1-100)", "(write-only)"...
void settings_hint(const SettingField& f, TextBuf& out);

// Validations shared with Improv provisioning.
SettingResult validate_ssid(const char* v, size_t n);
SettingResult validate_passphrase(const char* v, size_t n);

uint16_t frame_rate_tenths(FrameRate r);

}  // namespace cubecam

#endif
