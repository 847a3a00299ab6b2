// The settings record kept power-safe on flash: two slots, each the whole
// record with a sequence number and a CRC-32, written in one go into the
// slot that does not hold the newest record. A power cut at any byte of a
// save leaves the other slot intact, so a boot finds either the old or the
// new settings (docs/firmware.md, "Settings on flash").
#ifndef CUBECAM_CORE_SETTINGS_STORE_H
#define CUBECAM_CORE_SETTINGS_STORE_H

#include <stddef.h>
#include <stdint.h>

#include "hal.h"
#include "settings.h"

namespace cubecam {

// Bytes of a flash area by offset. write() may stop after any byte when the
// power fails; the bytes before stay written.
class FlashArea {
public:
    virtual bool read(size_t offset, uint8_t* buf, size_t len) = 0;
    virtual bool write(size_t offset, const uint8_t* data, size_t len) = 0;
protected:
    ~FlashArea() {}
};

// One slot: sequence number (little-endian), the record, CRC-32 of both.
const size_t kSettingsSlotBytes = 4 + kSettingsRecordSize + 4;
// Slot 0 at offset 0, slot 1 right after it.
const size_t kSettingsAreaBytes = 2 * kSettingsSlotBytes;

class SlotStorage : public SettingsStorage {
public:
    explicit SlotStorage(FlashArea& flash);
    // The record of the newest valid slot; with none, the bytes at offset 0
    // (a record saved by firmware before the slots: its own CRC decides).
    bool load(uint8_t* buf, size_t len);
    // Into the other slot with the next sequence number, then read back.
    bool store(const uint8_t* buf, size_t len);

private:
    // The newest valid slot (0 or 1) and its sequence number; -1: none.
    int newest(uint32_t& seq);
    bool read_slot(int index, uint32_t& seq);
    FlashArea& flash_;
    uint8_t slot_[kSettingsSlotBytes];
};

}  // namespace cubecam

#endif
