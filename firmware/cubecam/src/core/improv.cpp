#include "improv.h"

#include <string.h>

namespace cubecam {
namespace improv {

namespace {

const uint8_t kMagic[6] = {'I', 'M', 'P', 'R', 'O', 'V'};

uint8_t checksum(const uint8_t* p, size_t n) {
    uint8_t sum = 0;
    for (size_t i = 0; i < n; ++i) sum = static_cast<uint8_t>(sum + p[i]);
    return sum;
}

}  // namespace

Framer::Framer() : len_(0), last_ms_(0) {}

void Framer::reset() { len_ = 0; }

bool Framer::expired(uint32_t now_ms) const {
    return len_ > 0 && now_ms - last_ms_ > kPartialFrameTimeoutMs;
}

Framer::Result Framer::feed(uint8_t byte, uint32_t now_ms) {
    last_ms_ = now_ms;
    buf_[len_++] = byte;
    if (len_ <= sizeof kMagic) {
        return byte == kMagic[len_ - 1] ? Result::NeedMore : Result::NotImprov;
    }
    if (len_ == 7 && byte != kVersion) return Result::NotImprov;
    if (len_ <= kHeaderLen) return Result::NeedMore;
    size_t total = kHeaderLen + buf_[8] + 1;
    if (len_ < total) return Result::NeedMore;
    bool good = checksum(buf_, total - 1) == buf_[total - 1];
    if (!good) {
        len_ = 0;
        return Result::BadChecksum;
    }
    return Result::Frame;
}

size_t encode_frame(FrameType type, const uint8_t* data, size_t len, uint8_t* out) {
    if (len > kMaxData) return 0;
    memcpy(out, kMagic, sizeof kMagic);
    out[6] = kVersion;
    out[7] = static_cast<uint8_t>(type);
    out[8] = static_cast<uint8_t>(len);
    if (len > 0) memcpy(out + kHeaderLen, data, len);
    out[kHeaderLen + len] = checksum(out, kHeaderLen + len);
    return kHeaderLen + len + 1;
}

size_t encode_rpc_result(Command cmd, const Text* strings, size_t count, uint8_t* out) {
    size_t total = 0;
    for (size_t i = 0; i < count; ++i) {
        if (strings[i].len > 255) return 0;
        total += 1 + strings[i].len;
    }
    if (2 + total > kMaxData) return 0;
    out[0] = static_cast<uint8_t>(cmd);
    out[1] = static_cast<uint8_t>(total);
    size_t pos = 2;
    for (size_t i = 0; i < count; ++i) {
        out[pos++] = static_cast<uint8_t>(strings[i].len);
        memcpy(out + pos, strings[i].data, strings[i].len);
        pos += strings[i].len;
    }
    return pos;
}

bool decode_rpc(const uint8_t* data, size_t len, Rpc& out) {
    if (len < 2) return false;
    size_t payload_len = data[1];
    if (payload_len != len - 2) return false;
    out.command = static_cast<Command>(data[0]);
    out.payload = data + 2;
    out.payload_len = payload_len;
    return true;
}

bool decode_strings(const uint8_t* payload, size_t len, Text* out, size_t count) {
    size_t pos = 0;
    for (size_t i = 0; i < count; ++i) {
        if (pos >= len) return false;
        size_t n = payload[pos++];
        if (n > len - pos) return false;
        out[i].data = reinterpret_cast<const char*>(payload + pos);
        out[i].len = n;
        pos += n;
    }
    return pos == len;
}

}  // namespace improv
}  // namespace cubecam
