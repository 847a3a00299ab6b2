#include <string.h>

#include <vector>

#include <doctest/doctest.h>

#include "core/settings_store.h"

using namespace cubecam;

namespace {

// Flash that loses power after `power_left` more bytes of writing: the bytes
// of a write go in order, those before the cut stay, the rest and every later
// write are lost (the EEPROM emulation's fwrite is assumed to go in order).
struct CutFlash : FlashArea {
    std::vector<uint8_t> bytes = std::vector<uint8_t>(4000, 0);  // a new EEPROM file is zero-filled
    long power_left = -1;                                         // -1: never cut
    bool read(size_t offset, uint8_t* buf, size_t len) override {
        if (offset + len > bytes.size()) return false;
        memcpy(buf, bytes.data() + offset, len);
        return true;
    }
    bool write(size_t offset, const uint8_t* data, size_t len) override {
        if (offset + len > bytes.size()) return false;
        for (size_t i = 0; i < len; ++i) {
            if (power_left == 0) return false;
            if (power_left > 0) --power_left;
            bytes[offset + i] = data[i];
        }
        return true;
    }
};

std::vector<uint8_t> record(const char* name) {
    Settings s;
    settings_defaults(s);
    REQUIRE(settings_set(s, "name", name, strlen(name)).ok());
    std::vector<uint8_t> rec(kSettingsRecordSize);
    settings_encode(s, rec.data());
    return rec;
}

std::vector<uint8_t> loaded(CutFlash& flash) {
    SlotStorage storage(flash);
    std::vector<uint8_t> rec(kSettingsRecordSize);
    if (!storage.load(rec.data(), rec.size())) return {};
    return rec;
}

}  // namespace

TEST_CASE("settings slots: a power cut after any byte of a save leaves the old or the new settings") {
    const std::vector<uint8_t> names[] = {record("first"), record("second"), record("third")};
    // 1, 2 or 3 saves before the cut one: it goes to an empty slot, over the older slot, and again.
    for (size_t before = 1; before <= 3; ++before) {
        for (long cut = 0; cut <= long(kSettingsSlotBytes); ++cut) {
            CAPTURE(before);
            CAPTURE(cut);
            CutFlash flash;
            SlotStorage storage(flash);
            for (size_t i = 0; i < before; ++i) REQUIRE(storage.store(names[i % 3].data(), kSettingsRecordSize));
            const std::vector<uint8_t>& old_rec = names[(before - 1) % 3];
            std::vector<uint8_t> new_rec = record("new");
            flash.power_left = cut;
            bool saved = storage.store(new_rec.data(), kSettingsRecordSize);
            CHECK(saved == (cut == long(kSettingsSlotBytes)));
            flash.power_left = -1;  // power back: the board boots
            std::vector<uint8_t> got = loaded(flash);
            Settings s;
            REQUIRE(settings_decode(got.data(), got.size(), s));
            CHECK((got == old_rec || got == new_rec));
            CHECK((got == new_rec) == (cut == long(kSettingsSlotBytes)));
        }
    }
}

TEST_CASE("settings slots: the newest slot wins, also when the sequence number wraps") {
    CutFlash flash;
    SlotStorage storage(flash);
    std::vector<uint8_t> a = record("a"), b = record("b");
    REQUIRE(storage.store(a.data(), a.size()));
    REQUIRE(storage.store(b.data(), b.size()));
    CHECK(loaded(flash) == b);
    // Slot 0 holds sequence 1 (a), slot 1 sequence 2 (b). Make them 0xFFFFFFFF and 0 (wrapped):
    // the CRC covers the sequence, so rewrite both slots as the store would.
    auto set_seq = [&](size_t slot, uint32_t seq) {
        uint8_t* p = flash.bytes.data() + slot * kSettingsSlotBytes;
        for (int i = 0; i < 4; ++i) p[i] = uint8_t(seq >> (8 * i));
        uint32_t crc = crc32(p, 4 + kSettingsRecordSize);
        for (int i = 0; i < 4; ++i) p[4 + kSettingsRecordSize + i] = uint8_t(crc >> (8 * i));
    };
    set_seq(0, 0xFFFFFFFFu);
    set_seq(1, 0);
    CHECK(loaded(flash) == b);
    std::vector<uint8_t> c = record("c");
    REQUIRE(storage.store(c.data(), c.size()));  // goes over slot 0, sequence 1
    CHECK(loaded(flash) == c);
    CHECK(flash.bytes[0] == 1);
}

TEST_CASE("settings slots: a record saved before the slots existed is still read; a blank flash has none") {
    CutFlash flash;
    std::vector<uint8_t> rec(kSettingsRecordSize);
    Settings s;
    CHECK(loaded(flash).size() == kSettingsRecordSize);
    CHECK_FALSE(settings_decode(loaded(flash).data(), kSettingsRecordSize, s));  // zeros: factory defaults
    std::vector<uint8_t> legacy = record("legacy");
    memcpy(flash.bytes.data(), legacy.data(), legacy.size());
    CHECK(loaded(flash) == legacy);
    SlotStorage storage(flash);
    CHECK_FALSE(storage.store(rec.data(), rec.size() - 1));
    CHECK(kSettingsAreaBytes <= 4000);  // fits the EEPROM emulation (E2END)
}
