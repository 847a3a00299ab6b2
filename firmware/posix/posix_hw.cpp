#include "posix/posix_hw.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>
#include <arpa/inet.h>

#include <algorithm>

#include "core/text.h"

namespace cubecam {
namespace posix {

namespace {

uint64_t monotonic_us() {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return static_cast<uint64_t>(ts.tv_sec) * 1000000u + static_cast<uint64_t>(ts.tv_nsec) / 1000u;
}

bool ends_with(const std::string& s, const char* suffix) {
    size_t n = strlen(suffix);
    if (s.size() < n) return false;
    for (size_t i = 0; i < n; ++i) {
        char c = s[s.size() - n + i];
        if (c >= 'A' && c <= 'Z') c = static_cast<char>(c - 'A' + 'a');
        if (c != suffix[i]) return false;
    }
    return true;
}

bool read_file(const std::string& path, std::vector<uint8_t>& out) {
    FILE* f = fopen(path.c_str(), "rb");
    if (!f) return false;
    uint8_t chunk[4096];
    size_t n;
    while ((n = fread(chunk, 1, sizeof chunk, f)) > 0) out.insert(out.end(), chunk, chunk + n);
    fclose(f);
    return true;
}

void set_nonblocking(int fd) { fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) | O_NONBLOCK); }

const uint64_t kLingerMs = 2000;
const int kClientSendBuffer = 64 * 1024;

}  // namespace

// ---- clock ----

MonotonicClock::MonotonicClock() : boot_us_(monotonic_us()) {}
void MonotonicClock::restart() { boot_us_ = monotonic_us(); }
uint32_t MonotonicClock::millis() { return static_cast<uint32_t>(micros() / 1000u); }
uint64_t MonotonicClock::micros() { return monotonic_us() - boot_us_; }

// ---- camera ----

FolderCamera::FolderCamera(Clock& clock) : clock_(clock), start_us_(0), fps_tenths_(150), leases_out_(0) {}

bool FolderCamera::load(const std::string& dir, std::string& error) {
    DIR* d = opendir(dir.c_str());
    if (!d) {
        error = "cannot open image folder " + dir + ": " + strerror(errno);
        return false;
    }
    std::vector<std::string> names;
    while (struct dirent* e = readdir(d)) {
        std::string name = e->d_name;
        if (ends_with(name, ".jpg") || ends_with(name, ".jpeg")) names.push_back(name);
    }
    closedir(d);
    std::sort(names.begin(), names.end());
    for (size_t i = 0; i < names.size(); ++i) {
        std::vector<uint8_t> data;
        if (!read_file(dir + "/" + names[i], data) || data.size() < 4 || data[0] != 0xFF || data[1] != 0xD8) {
            error = "not a JPEG file: " + dir + "/" + names[i];
            return false;
        }
        frames_.push_back(data);
    }
    if (frames_.empty()) {
        error = "no .jpg files in " + dir;
        return false;
    }
    return true;
}

void FolderCamera::add_frame(const std::vector<uint8_t>& jpeg) { frames_.push_back(jpeg); }

void FolderCamera::start(uint16_t fps_tenths) {
    fps_tenths_ = fps_tenths;
    start_us_ = clock_.micros();
}

uint32_t FolderCamera::latest_seq() {
    uint64_t elapsed = clock_.micros() - start_us_;
    return static_cast<uint32_t>(elapsed * fps_tenths_ / 10000000u) + 1;
}

bool FolderCamera::acquire_latest(Frame& out) {
    if (frames_.empty()) return false;
    uint32_t seq = latest_seq();
    const std::vector<uint8_t>& img = frames_[(seq - 1) % frames_.size()];
    out.data = &img[0];
    out.size = static_cast<uint32_t>(img.size());
    out.seq = seq;
    out.capture_us = start_us_ + static_cast<uint64_t>(seq - 1) * 10000000u / fps_tenths_;
    out.lease = 0;
    ++leases_out_;
    return true;
}

void FolderCamera::release(int lease) {
    (void)lease;
    --leases_out_;
}

// ---- TCP ----

TcpNetwork::TcpNetwork(const std::string& bind_address, int port_override)
    : bind_(bind_address), port_override_(port_override), listen_fd_(-1), next_poll_(1) {
    for (int i = 0; i < kCids; ++i) fds_[i] = -1;
}

TcpNetwork::~TcpNetwork() {
    close_all();
    for (size_t i = 0; i < lingering_.size(); ++i) ::close(lingering_[i].fd);
}

uint16_t TcpNetwork::open_server(uint16_t port) {
    close_all();
    int fd = socket(AF_INET, SOCK_STREAM, 0);
    if (fd < 0) return 0;
    int one = 1;
    setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    struct sockaddr_in addr;
    memset(&addr, 0, sizeof addr);
    addr.sin_family = AF_INET;
    addr.sin_port = htons(port_override_ >= 0 ? static_cast<uint16_t>(port_override_) : port);
    if (inet_pton(AF_INET, bind_.c_str(), &addr.sin_addr) != 1 ||
        bind(fd, reinterpret_cast<struct sockaddr*>(&addr), sizeof addr) != 0 || listen(fd, 16) != 0) {
        ::close(fd);
        return 0;
    }
    socklen_t len = sizeof addr;
    getsockname(fd, reinterpret_cast<struct sockaddr*>(&addr), &len);
    uint16_t bound = ntohs(addr.sin_port);
    if (port_override_ == 0) port_override_ = bound;  // an ephemeral port stays the same across reboots
    set_nonblocking(fd);
    listen_fd_ = fd;
    printf("http: http://%s:%u/\n", bind_.c_str(), bound);
    fflush(stdout);
    return bound;
}

void TcpNetwork::close_all() {
    if (listen_fd_ >= 0) ::close(listen_fd_);
    listen_fd_ = -1;
    for (int i = 0; i < kCids; ++i) {
        if (fds_[i] >= 0) ::close(fds_[i]);
        fds_[i] = -1;
    }
}

void TcpNetwork::drain_lingering() {
    uint64_t now = monotonic_us() / 1000u;
    for (size_t i = 0; i < lingering_.size();) {
        char sink[512];
        ssize_t n = recv(lingering_[i].fd, sink, sizeof sink, MSG_DONTWAIT);
        bool waiting = n > 0 || (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK));
        if (waiting && now < lingering_[i].until_ms) {
            ++i;
            continue;
        }
        ::close(lingering_[i].fd);
        lingering_[i] = lingering_.back();
        lingering_.pop_back();
    }
}

NetEvent TcpNetwork::poll(uint8_t* buf, uint16_t cap) {
    NetEvent ev = {NetEventKind::None, 0, 0};
    drain_lingering();
    if (listen_fd_ < 0) return ev;
    int fd = accept(listen_fd_, 0, 0);
    if (fd >= 0) {
        for (int cid = 1; cid < kCids; ++cid) {
            if (fds_[cid] >= 0) continue;
            set_nonblocking(fd);
            int one = 1;
            setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
            setsockopt(fd, SOL_SOCKET, SO_SNDBUF, &kClientSendBuffer, sizeof kClientSendBuffer);
            fds_[cid] = fd;
            ev.kind = NetEventKind::Accepted;
            ev.cid = static_cast<uint8_t>(cid);
            return ev;
        }
        ::close(fd);  // all 15 connection ids in use, as the module would refuse
    }
    for (int i = 0; i < kCids - 1; ++i) {
        int cid = next_poll_;
        next_poll_ = static_cast<uint8_t>(next_poll_ % (kCids - 1) + 1);
        if (fds_[cid] < 0) continue;
        ssize_t n = recv(fds_[cid], buf, cap, MSG_DONTWAIT);
        if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR)) continue;
        ev.cid = static_cast<uint8_t>(cid);
        if (n > 0) {
            ev.kind = NetEventKind::Data;
            ev.len = static_cast<uint16_t>(n);
        } else {
            ev.kind = NetEventKind::Closed;
            ::close(fds_[cid]);
            fds_[cid] = -1;
        }
        return ev;
    }
    return ev;
}

WriteResult TcpNetwork::write(uint8_t cid, const uint8_t* data, uint16_t len) {
    WriteResult r = {WriteStatus::ClientGone, 0};
    if (cid >= kCids || fds_[cid] < 0) return r;
    ssize_t n = send(fds_[cid], data, len, MSG_DONTWAIT | MSG_NOSIGNAL);
    if (n >= 0) {
        r.status = WriteStatus::Ok;
        r.accepted = static_cast<uint16_t>(n);
    } else if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) {
        r.status = WriteStatus::Ok;
    }
    return r;
}

void TcpNetwork::close(uint8_t cid) {
    if (cid >= kCids || fds_[cid] < 0) return;
    shutdown(fds_[cid], SHUT_WR);
    Lingering l = {fds_[cid], monotonic_us() / 1000u + kLingerMs};
    lingering_.push_back(l);
    fds_[cid] = -1;
}

void TcpNetwork::wait_fds(std::vector<int>& fds) const {
    if (listen_fd_ >= 0) fds.push_back(listen_fd_);
    for (int i = 0; i < kCids; ++i) {
        if (fds_[i] >= 0) fds.push_back(fds_[i]);
    }
}

// ---- simulated Wi-Fi ----

SimulatedWifi::SimulatedWifi(Clock& clock, const std::string& address, uint32_t join_ms,
                             const std::vector<std::string>& fail_ssids)
    : clock_(clock), join_ms_(join_ms), fail_ssids_(fail_ssids), join_started_ms_(0) {
    if (!parse_ipv4(address.c_str(), address.size(), ip_)) memset(ip_, 0, sizeof ip_);
}

bool SimulatedWifi::reset_module() { return true; }

bool SimulatedWifi::start_join(const Settings& s) {
    ssid_ = s.ssid;
    join_started_ms_ = clock_.millis();
    return true;
}

JoinStatus SimulatedWifi::join_status(LinkInfo& info) {
    if (clock_.millis() - join_started_ms_ < join_ms_) return JoinStatus::Pending;
    if (std::find(fail_ssids_.begin(), fail_ssids_.end(), ssid_) != fail_ssids_.end()) return JoinStatus::Failed;
    memcpy(info.ip, ip_, 4);
    info.rssi = -42;
    return JoinStatus::Joined;
}

size_t SimulatedWifi::scan(ScanEntry* out, size_t max) {
    static const struct {
        const char* ssid;
        int8_t rssi;
        bool secured;
    } kAir[] = {{"cubetrack-lab", -41, true}, {"cubetrack-guest", -67, false}, {"neighbour", -83, true}};
    size_t n = 0;
    for (; n < max && n < sizeof kAir / sizeof kAir[0]; ++n) {
        memset(out[n].ssid, 0, sizeof out[n].ssid);
        strncpy(out[n].ssid, kAir[n].ssid, sizeof out[n].ssid - 1);
        out[n].rssi = kAir[n].rssi;
        out[n].secured = kAir[n].secured;
    }
    return n;
}

// ---- serial ----

FdSerial::FdSerial(int read_fd, int write_fd, int tee_fd) : read_fd_(read_fd), write_fd_(write_fd), tee_fd_(tee_fd) {
    if (read_fd_ >= 0) set_nonblocking(read_fd_);
    if (write_fd_ >= 0) set_nonblocking(write_fd_);
}

size_t FdSerial::read(uint8_t* buf, size_t cap) {
    if (read_fd_ < 0) return 0;
    ssize_t n = ::read(read_fd_, buf, cap);
    if (n == 0) read_fd_ = -1;  // end of input (stdin closed): stop polling it
    return n > 0 ? static_cast<size_t>(n) : 0;
}

void FdSerial::write(const uint8_t* data, size_t len) {
    if (tee_fd_ >= 0) {
        ssize_t ignored = ::write(tee_fd_, data, len);
        (void)ignored;
    }
    if (write_fd_ < 0) return;
    const int kWaitMs = 50;
    while (len > 0) {
        ssize_t n = ::write(write_fd_, data, len);
        if (n > 0) {
            data += n;
            len -= static_cast<size_t>(n);
            continue;
        }
        if (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) return;
        struct pollfd p = {write_fd_, POLLOUT, 0};
        if (::poll(&p, 1, kWaitMs) <= 0) return;  // nobody reads: drop the rest
    }
}

std::string open_pty(int& master_fd, int& slave_fd) {
    master_fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (master_fd < 0 || grantpt(master_fd) != 0 || unlockpt(master_fd) != 0) return "";
    const char* name = ptsname(master_fd);
    if (!name) return "";
    std::string path = name;
    slave_fd = open(path.c_str(), O_RDWR | O_NOCTTY);
    if (slave_fd < 0) return "";
    // Raw at once: a cooked slave would echo our boot log back to us.
    struct termios t;
    tcgetattr(slave_fd, &t);
    cfmakeraw(&t);
    cfsetispeed(&t, B115200);
    cfsetospeed(&t, B115200);
    tcsetattr(slave_fd, TCSANOW, &t);
    return path;
}

// ---- settings file ----

FileStorage::FileStorage(const std::string& path) : path_(path) {}

bool FileStorage::load(uint8_t* buf, size_t len) {
    std::vector<uint8_t> data;
    if (!read_file(path_, data) || data.size() != len) return false;
    memcpy(buf, &data[0], len);
    return true;
}

bool FileStorage::store(const uint8_t* buf, size_t len) {
    std::string tmp = path_ + ".tmp";
    FILE* f = fopen(tmp.c_str(), "wb");
    if (!f) return false;
    bool ok = fwrite(buf, 1, len, f) == len;
    ok = fclose(f) == 0 && ok;
    return ok && rename(tmp.c_str(), path_.c_str()) == 0;
}

}  // namespace posix
}  // namespace cubecam
