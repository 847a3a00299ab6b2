#include "settings_store.h"

#include <string.h>

namespace cubecam {

namespace {

void put_u32(uint8_t* p, uint32_t v) {
    for (int i = 0; i < 4; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
}

uint32_t get_u32(const uint8_t* p) {
    return static_cast<uint32_t>(p[0]) | static_cast<uint32_t>(p[1]) << 8 | static_cast<uint32_t>(p[2]) << 16 |
           static_cast<uint32_t>(p[3]) << 24;
}

const size_t kCrcAt = 4 + kSettingsRecordSize;

}  // namespace

SlotStorage::SlotStorage(FlashArea& flash) : flash_(flash) {}

bool SlotStorage::read_slot(int index, uint32_t& seq) {
    if (!flash_.read(static_cast<size_t>(index) * kSettingsSlotBytes, slot_, sizeof slot_)) return false;
    seq = get_u32(slot_);
    return crc32(slot_, kCrcAt) == get_u32(slot_ + kCrcAt);
}

int SlotStorage::newest(uint32_t& seq) {
    uint32_t seq0 = 0, seq1 = 0;
    bool ok0 = read_slot(0, seq0);
    bool ok1 = read_slot(1, seq1);
    // Sequence numbers wrap: the newer is the one ahead by less than half the range.
    if (ok0 && (!ok1 || static_cast<int32_t>(seq0 - seq1) > 0)) {
        seq = seq0;
        return 0;
    }
    seq = seq1;
    return ok1 ? 1 : -1;
}

bool SlotStorage::load(uint8_t* buf, size_t len) {
    if (len != kSettingsRecordSize) return false;
    uint32_t seq;
    int index = newest(seq);
    if (index < 0) return flash_.read(0, buf, len);
    if (!read_slot(index, seq)) return false;
    memcpy(buf, slot_ + 4, len);
    return true;
}

bool SlotStorage::store(const uint8_t* buf, size_t len) {
    if (len != kSettingsRecordSize) return false;
    uint32_t seq = 0;
    int index = newest(seq);
    int target = index == 0 ? 1 : 0;
    put_u32(slot_, index < 0 ? 1 : seq + 1);
    memcpy(slot_ + 4, buf, len);
    put_u32(slot_ + kCrcAt, crc32(slot_, kCrcAt));
    size_t offset = static_cast<size_t>(target) * kSettingsSlotBytes;
    if (!flash_.write(offset, slot_, sizeof slot_)) return false;
    uint8_t back[kSettingsSlotBytes];
    memcpy(back, slot_, sizeof back);
    return flash_.read(offset, slot_, sizeof slot_) && memcmp(back, slot_, sizeof back) == 0;
}

}  // namespace cubecam
