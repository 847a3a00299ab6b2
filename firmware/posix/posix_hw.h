// POSIX implementations of the hardware interfaces, used by cubecam-native,
// the benchmark and the tests. Host-only code: heap and std:: are fine here,
// but nothing allocates per frame.
#ifndef CUBECAM_POSIX_HW_H
#define CUBECAM_POSIX_HW_H

#include <stdint.h>

#include <string>
#include <vector>

#include "core/hal.h"
#include "core/settings.h"

namespace cubecam {
namespace posix {

// CLOCK_MONOTONIC since the last restart() ("device clock since boot").
class MonotonicClock : public Clock {
public:
    MonotonicClock();
    void restart();
    uint32_t millis();
    uint64_t micros();
private:
    uint64_t boot_us_;
};

// Cycles through JPEG files at a fixed rate. Frame k is "captured" at
// k / fps after start(); sequence numbers count every captured frame.
class FolderCamera : public Camera {
public:
    FolderCamera(Clock& clock);
    // Loads every *.jpg / *.jpeg in dir, sorted by name. False when none.
    bool load(const std::string& dir, std::string& error);
    // Adds one frame from memory (benchmarks and tests).
    void add_frame(const std::vector<uint8_t>& jpeg);
    void start(uint16_t fps_tenths);
    uint32_t latest_seq();
    bool acquire_latest(Frame& out);
    void release(int lease);
    // The files never stop: there is nothing to restart.
    CameraRestart restart() { return CameraRestart::Done; }
    uint32_t empty_frames() { return 0; }  // files are whole frames
    int leases_out() const { return leases_out_; }
private:
    Clock& clock_;
    std::vector<std::vector<uint8_t> > frames_;
    uint64_t start_us_;
    uint16_t fps_tenths_;
    int leases_out_;
};

// Non-blocking TCP server; connection ids 1..15 as on the GS2200M (0 is the
// server's own). A closed connection is half-closed and drained before the
// socket goes away, so that an answer is not lost to a TCP reset.
class TcpNetwork : public Network {
public:
    // port_override < 0: use the port the core asks for. 0: an ephemeral port,
    // kept across reopen. Prints "http: http://<bind>:<port>/" when listening.
    TcpNetwork(const std::string& bind_address, int port_override);
    ~TcpNetwork();
    uint16_t open_server(uint16_t port);
    void close_all();
    NetEvent poll(uint8_t* buf, uint16_t cap);
    WriteResult write(uint8_t cid, const uint8_t* data, uint16_t len);
    void close(uint8_t cid);
    // File descriptors worth waiting on (listening socket and clients).
    void wait_fds(std::vector<int>& fds) const;
private:
    static const int kCids = 16;
    struct Lingering {
        int fd;
        uint64_t until_ms;
    };
    void drain_lingering();
    std::string bind_;
    int port_override_;
    int listen_fd_;
    int fds_[kCids];
    uint8_t next_poll_;
    std::vector<Lingering> lingering_;
};

// Simulated Wi-Fi module: joining any SSID succeeds after join_ms, except
// the ones listed as failing, which fail after join_ms.
class SimulatedWifi : public WifiControl {
public:
    SimulatedWifi(Clock& clock, const std::string& address, uint32_t join_ms,
                  const std::vector<std::string>& fail_ssids);
    bool reset_module();
    bool start_join(const Settings& s);
    JoinStatus join_status(LinkInfo& info);
    size_t scan(ScanEntry* out, size_t max);
private:
    Clock& clock_;
    uint8_t ip_[4];
    uint32_t join_ms_;
    std::vector<std::string> fail_ssids_;
    std::string ssid_;
    uint32_t join_started_ms_;
};

// Serial over file descriptors: a pty master or stdin/stdout. Writes wait a
// little for room and then drop, like a UART nobody listens to.
class FdSerial : public SerialPort {
public:
    FdSerial(int read_fd, int write_fd, int tee_fd);
    size_t read(uint8_t* buf, size_t cap);
    void write(const uint8_t* data, size_t len);
    int read_fd() const { return read_fd_; }
private:
    int read_fd_;
    int write_fd_;
    int tee_fd_;
};

// Opens a pty pair in raw mode; keeps the slave open so the master never
// sees EIO when a client closes. Returns the slave path, "" on failure.
std::string open_pty(int& master_fd, int& slave_fd);

class FileStorage : public SettingsStorage {
public:
    explicit FileStorage(const std::string& path);
    bool load(uint8_t* buf, size_t len);
    bool store(const uint8_t* buf, size_t len);
private:
    std::string path_;
};

// The host has no LEDs; the patterns are unit-tested in the core.
class NoLeds : public Leds {
public:
    void show(uint8_t) {}
};

// Reboot is simulated in-process by the main loop.
class HostSystem : public System {
public:
    HostSystem() : reboot_requested_(false) {}
    void kick_watchdog() {}  // the host has no watchdog
    void reboot() { reboot_requested_ = true; }
    bool take_reboot_request() {
        bool r = reboot_requested_;
        reboot_requested_ = false;
        return r;
    }
private:
    bool reboot_requested_;
};

}  // namespace posix
}  // namespace cubecam

#endif
