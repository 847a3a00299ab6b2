// Hardware interfaces the portable core depends on. Each has a Spresense
// implementation (../spresense/) and a POSIX one (firmware/posix/).
// All calls are made from the main loop only, except where noted.
#ifndef CUBECAM_CORE_HAL_H
#define CUBECAM_CORE_HAL_H

#include <stddef.h>
#include <stdint.h>

namespace cubecam {

struct Settings;

// Sizes the hardware implementations provide for.
const size_t kMaxClients = 4;     // frames lent out at once: one per HTTP client
const uint16_t kNetChunk = 1400;  // largest Network::write (GS2200M bulk write: 1400 data bytes)

// One camera frame lent to the core. `lease` identifies the loan; the buffer
// stays valid until release(lease).
struct Frame {
    const uint8_t* data;
    uint32_t size;
    uint32_t seq;         // counts every captured frame since boot (X-Frame)
    uint64_t capture_us;  // capture time on the device clock (X-Timestamp)
    int lease;
};

enum class CameraRestart : uint8_t { Done, Busy, Failed };

class Camera {
public:
    // Sequence number of the newest captured frame, 0 before the first one.
    virtual uint32_t latest_seq() = 0;
    // Frames that arrived empty since boot: the JPEG did not fit its buffer.
    virtual uint32_t empty_frames() = 0;
    // Lend the newest frame. False when there is none yet or no free lease.
    virtual bool acquire_latest(Frame& out) = 0;
    virtual void release(int lease) = 0;
    // Stop and start the camera again (it stopped delivering frames). Busy
    // while a frame is lent out: call again once it is released.
    virtual CameraRestart restart() = 0;
protected:
    ~Camera() {}
};

enum class NetEventKind : uint8_t {
    None,
    Accepted,       // a client connected on `cid`
    Data,           // `len` bytes for `cid` were copied into the caller's buffer
    Closed,         // the peer of `cid` closed or reset
    Failed,         // the module failed the connection `cid` (or data sent to it): close it
    LinkLost,       // the access point dropped us (disassociation)
    ModuleRebooted  // the Wi-Fi module restarted on its own
};

struct NetEvent {
    NetEventKind kind;
    uint8_t cid;
    uint16_t len;
};

// Ok with 0 accepted: refused for now (the module's buffer is full); try
// again later, paced. Busy: the module has a message waiting; poll() first,
// then write again at once.
enum class WriteStatus : uint8_t { Ok, Busy, ClientGone, LinkFailure };

struct WriteResult {
    WriteStatus status;
    uint16_t accepted;  // bytes taken; may be 0 (would block) or partial
};

// TCP server sockets addressed by connection id, as the GS2200M numbers them.
class Network {
public:
    // Opens the listening socket; returns the bound port, 0 on failure.
    virtual uint16_t open_server(uint16_t port) = 0;
    // Closes the server and every client connection.
    virtual void close_all() = 0;
    // Returns at most one pending event without blocking. Data is copied into
    // buf (at most cap bytes). None only when nothing waits.
    virtual NetEvent poll(uint8_t* buf, uint16_t cap) = 0;
    virtual WriteResult write(uint8_t cid, const uint8_t* data, uint16_t len) = 0;
    virtual void close(uint8_t cid) = 0;
protected:
    ~Network() {}
};

enum class JoinStatus : uint8_t { Pending, Joined, Failed };

struct LinkInfo {
    uint8_t ip[4];
    int8_t rssi;
};

struct ScanEntry {
    char ssid[33];
    int8_t rssi;
    bool secured;
};

// Association control of the Wi-Fi module.
class WifiControl {
public:
    // Restart and initialise the module. May block for the module's own AT
    // handshake (seconds on the GS2200M); the watchdog allows for it.
    virtual bool reset_module() = 0;
    // Start joining (station) or creating (access point) the network in s.
    virtual bool start_join(const Settings& s) = 0;
    virtual JoinStatus join_status(LinkInfo& info) = 0;
    virtual size_t scan(ScanEntry* out, size_t max) = 0;
protected:
    ~WifiControl() {}
};

class SerialPort {
public:
    // Non-blocking; returns the number of bytes copied (0 when none).
    virtual size_t read(uint8_t* buf, size_t cap) = 0;
    virtual void write(const uint8_t* data, size_t len) = 0;
protected:
    ~SerialPort() {}
};

class SettingsStorage {
public:
    virtual bool load(uint8_t* buf, size_t len) = 0;
    virtual bool store(const uint8_t* buf, size_t len) = 0;
protected:
    ~SettingsStorage() {}
};

class Clock {
public:
    virtual uint32_t millis() = 0;
    virtual uint64_t micros() = 0;  // device clock since boot
protected:
    ~Clock() {}
};

// True once now_ms is at or past deadline_ms on the wrapping 32-bit
// millisecond clock (deadlines less than 24 days ahead).
inline bool deadline_reached(uint32_t now_ms, uint32_t deadline_ms) {
    return static_cast<int32_t>(now_ms - deadline_ms) >= 0;
}

class Leds {
public:
    virtual void show(uint8_t mask) = 0;  // bit n = LEDn on
protected:
    ~Leds() {}
};

class System {
public:
    virtual void kick_watchdog() = 0;
    virtual void reboot() = 0;
protected:
    ~System() {}
};

}  // namespace cubecam

#endif
