// The node's persistent settings: one versioned record with a CRC, and the
// key/value view the console uses. Validation lives here, once.
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

void settings_defaults(Settings& s);

// Fixed little-endian record: magic, version, payload, CRC-32 of all before it.
const uint32_t kSettingsMagic = 0x43554243u;  // "CBUC" in memory order
const uint16_t kSettingsVersion = 1;
const size_t kSettingsRecordSize = 4 + 2 + (kMaxName + 1) + (kMaxSsid + 1) + (kMaxPassphrase + 1) +
                                   1 + 1 + 4 + 1 + 4 + 2 + 1 + 2 + 1 + 4;

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

// Keys in console order; password is write-only.
extern const char* const kSettingKeys[];
extern const size_t kSettingKeyCount;

SettingResult settings_set(Settings& s, const char* key, const char* value, size_t value_len);
// Appends the value of key; password yields "(set)" or "(empty)", never itself.
SettingResult settings_get(const Settings& s, const char* key, TextBuf& out);

// Validations shared with Improv provisioning.
SettingResult validate_ssid(const char* v, size_t n);
SettingResult validate_passphrase(const char* v, size_t n);

uint16_t frame_rate_tenths(FrameRate r);

}  // namespace cubecam

#endif
