// Improv Wi-Fi serial protocol, version 1: frame parser, the one frame
// encoder, and RPC decoding. No I/O; enum values are wire bytes.
#ifndef CUBECAM_CORE_IMPROV_H
#define CUBECAM_CORE_IMPROV_H

#include <stddef.h>
#include <stdint.h>

namespace cubecam {
namespace improv {

const uint8_t kVersion = 1;
const size_t kHeaderLen = 9;  // "IMPROV", version, type, length
const size_t kMaxData = 255;
const size_t kMaxFrame = kHeaderLen + kMaxData + 1;
const uint32_t kPartialFrameTimeoutMs = 100;

enum class FrameType : uint8_t { CurrentState = 0x01, ErrorState = 0x02, Rpc = 0x03, RpcResult = 0x04 };

enum class State : uint8_t { Stopped = 0x00, Authorized = 0x02, Provisioning = 0x03, Provisioned = 0x04 };

enum class Error : uint8_t {
    None = 0x00,
    InvalidRpc = 0x01,
    UnknownRpc = 0x02,
    UnableToConnect = 0x03,
    NotAuthorized = 0x04,
    BadHostname = 0x05,
    Unknown = 0xFF
};

enum class Command : uint8_t {
    WifiSettings = 0x01,
    GetCurrentState = 0x02,
    GetDeviceInfo = 0x03,
    GetWifiNetworks = 0x04,
    Hostname = 0x05,
    DeviceName = 0x06
};

struct Text {
    const char* data;
    size_t len;
};

// Byte-at-a-time framer over its own buffer. A frame in progress is dropped
// after 100 ms without a byte.
class Framer {
public:
    enum class Result : uint8_t {
        NeedMore,     // byte taken
        Frame,        // a complete frame with a good checksum is available
        BadChecksum,  // a complete frame failed its checksum (dropped)
        NotImprov     // the bytes so far are not an Improv frame; see held()
    };

    Framer();
    Result feed(uint8_t byte, uint32_t now_ms);
    // True when a partial frame has waited too long; call reset() then.
    bool expired(uint32_t now_ms) const;
    void reset();
    // Bytes held before a NotImprov verdict or an expiry, for the console.
    const uint8_t* held() const { return buf_; }
    size_t held_len() const { return len_; }
    // Only meaningful while the 6-byte magic is incomplete.
    bool in_magic() const { return len_ > 0 && len_ < 6; }

    FrameType type() const { return static_cast<FrameType>(buf_[7]); }
    const uint8_t* data() const { return buf_ + kHeaderLen; }
    size_t data_len() const { return buf_[8]; }

private:
    uint8_t buf_[kMaxFrame];
    size_t len_;
    uint32_t last_ms_;
};

// Encodes one frame into out (at least kMaxFrame bytes); returns its length,
// 0 when data is too long.
size_t encode_frame(FrameType type, const uint8_t* data, size_t len, uint8_t* out);

// Builds RPC result data: command, total length, then (length, bytes) per
// string. Returns the data length or 0 when it would not fit in 255 bytes.
size_t encode_rpc_result(Command cmd, const Text* strings, size_t count, uint8_t* out);

struct Rpc {
    Command command;
    const uint8_t* payload;
    size_t payload_len;
};

// Decodes RPC frame data (command, length, payload). False when malformed.
bool decode_rpc(const uint8_t* data, size_t len, Rpc& out);

// Reads `count` length-prefixed strings from an RPC payload, which must be
// used up exactly. False when malformed.
bool decode_strings(const uint8_t* payload, size_t len, Text* out, size_t count);

}  // namespace improv
}  // namespace cubecam

#endif
