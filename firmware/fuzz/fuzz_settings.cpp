// libFuzzer target: the settings record decoder (flash contents are
// untrusted: a half-written or foreign EEPROM file) and the key/value setters
// behind the console and Improv.
//
// Input: byte 0 = flags (bit 0: give the record a valid magic and version,
// bit 1: a valid CRC, so the fuzzer gets past those checks), then the record
// (kSettingsRecordSize bytes), then up to 32 "key\tvalue" lines for settings_set.
// Properties: a rejected record leaves the settings untouched; an accepted
// one holds only values the console would accept (each readable key's value
// sets back to the same record) and re-encodes to a record that decodes to
// the same settings; whatever the setters accept is storable.
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <string>

#include "core/settings.h"

using namespace cubecam;

namespace {

void require(bool ok) {
    if (!ok) abort();
}

const size_t kMaxLines = 32;

void put_u32(uint8_t* p, uint32_t v) {
    for (int i = 0; i < 4; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
}

std::string encoded(const Settings& s) {
    uint8_t rec[kSettingsRecordSize];
    settings_encode(s, rec);
    return std::string(reinterpret_cast<const char*>(rec), sizeof rec);
}

void check_valid(const Settings& s) {
    std::string rec = encoded(s);
    Settings back;
    require(settings_decode(reinterpret_cast<const uint8_t*>(rec.data()), rec.size(), back));
    require(encoded(back) == rec);
    for (size_t i = 0; i < kSettingCount; ++i) {
        const SettingField& f = kSettingFields[i];
        char buf[96];
        TextBuf value(buf, sizeof buf);
        require(settings_get(s, f.key, value).ok() && !value.overflowed());
        if (f.write_only) continue;
        Settings again = s;
        require(settings_set(again, f.key, value.c_str(), value.size()).ok());
        require(encoded(again) == rec);
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    if (size == 0) return 0;
    uint8_t flags = data[0];
    size_t rec_len = size - 1 < kSettingsRecordSize ? size - 1 : kSettingsRecordSize;
    uint8_t rec[kSettingsRecordSize];
    memcpy(rec, data + 1, rec_len);
    if (rec_len == kSettingsRecordSize) {
        if (flags & 1) {
            put_u32(rec, kSettingsMagic);
            rec[4] = static_cast<uint8_t>(kSettingsVersion);
            rec[5] = static_cast<uint8_t>(kSettingsVersion >> 8);
        }
        if (flags & 2) put_u32(rec + kSettingsRecordSize - 4, crc32(rec, kSettingsRecordSize - 4));
    }
    Settings s;
    memset(&s, 0xA5, sizeof s);
    Settings before = s;
    if (settings_decode(rec, rec_len, s)) {
        check_valid(s);
    } else {
        require(memcmp(&s, &before, sizeof s) == 0);
        settings_defaults(s);
    }
    // The rest: one "key\tvalue" per line (the first kMaxLines).
    std::string rest(reinterpret_cast<const char*>(data + 1 + rec_len), size - 1 - rec_len);
    size_t lines = 0;
    for (size_t pos = 0; pos < rest.size() && lines < kMaxLines; ++lines) {
        size_t end = rest.find('\n', pos);
        if (end == std::string::npos) end = rest.size();
        std::string line = rest.substr(pos, end - pos);
        pos = end + 1;
        size_t tab = line.find('\t');
        if (tab == std::string::npos) continue;
        std::string key = line.substr(0, tab);
        Settings edited = s;
        SettingResult r = settings_set(edited, key.c_str(), line.data() + tab + 1, line.size() - tab - 1);
        require(r.ok() || (r.message != 0 && r.message[0] != '\0'));
        if (r.ok()) {
            s = edited;
        } else {
            require(encoded(edited) == encoded(s));  // a refused value changes nothing
        }
    }
    check_valid(s);  // whatever the setters accepted is storable and reads back
    return 0;
}
