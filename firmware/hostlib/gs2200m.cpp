#include "gs2200m.h"

#include <stdio.h>
#include <stdlib.h>

#include "core/wpa.h"
#include "hostlib.h"
#include "test/s2w.h"

namespace hostlib {

namespace {

// Header types (GS2200Hal.cpp uses the same numbers).
const uint8_t kWriteRequest = 0x01;
const uint8_t kReadRequest = 0x02;
const uint8_t kDataFromMcu = 0x03;
const uint8_t kWriteResponseOk = 0x11;
const uint8_t kReadResponseOk = 0x12;
const uint8_t kReadResponseNok = 0x14;
const uint8_t kDataToMcu = 0x15;
const uint8_t kIdle = 0xF5;
const char kEsc = 0x1B;
const size_t kMaxRead = 1500;       // the library's READ requests ask for this much
const size_t kClientChunk = 1400;   // bytes of client data per bulk message
const char kMac[] = "00:1d:c9:00:11:22";
const char kAssignedIp[] = "192.168.1.23";

uint8_t checksum(const uint8_t* h) {
    uint32_t sum = 0;
    for (int i = 1; i < 7; ++i) sum += h[i];
    return static_cast<uint8_t>(~sum);
}

std::vector<std::string> split(const std::string& s, char sep) {
    std::vector<std::string> parts;
    size_t start = 0;
    for (;;) {
        size_t end = s.find(sep, start);
        parts.push_back(s.substr(start, end == std::string::npos ? std::string::npos : end - start));
        if (end == std::string::npos) return parts;
        start = end + 1;
    }
}

char hex_digit(int v) { return "0123456789abcdef"[v & 15]; }

const char* const kOk = "OK\r\n";
const char* const kError = "ERROR\r\n";
const char* const kInvalid = "ERROR: INVALID INPUT\r\n";

}  // namespace

Gs2200m::Gs2200m() { power_on(); }

void Gs2200m::power_on() {
    ignore_write_requests = 0;
    commands.clear();
    bulk_clock_hz.clear();
    bulk_sizes.clear();
    networks.clear();
    header_len_ = 0;
    payload_expected_ = 0;
    payload_.clear();
    write_len_ = -1;
    payload_clock_hz_ = 0;
    out_.clear();
    pending_.clear();
    reboot();
}

void Gs2200m::reboot() {
    echo_ = true;
    mode_ = 0;
    dhcp_ = true;
    power_save_ = false;
    static_ip_.clear();
    key_ssid_.clear();
    key_.clear();
    associated_ = false;
    joined_ssid_.clear();
    ip_ = "0.0.0.0";
    server_cid_ = -1;
    for (auto& p : peers_) p.second.open = false;
    queue_message("\r\nSerial2WiFi APP\r\n");
}

bool Gs2200m::data_ready() const {
    if (!out_.empty()) return true;
    bool mid_write = header_len_ > 0 || payload_expected_ > 0 || write_len_ >= 0;
    return !pending_.empty() && !mid_write;
}

uint8_t Gs2200m::exchange(uint8_t mosi, uint32_t clock_hz) {
    if (payload_expected_ > 0) {
        payload_.push_back(static_cast<char>(mosi));
        if (--payload_expected_ == 0) {
            payload_clock_hz_ = clock_hz;
            std::string p;
            p.swap(payload_);
            on_payload(p);
        }
        return kIdle;
    }
    if (header_len_ > 0 || mosi == 0xA5) {
        header_[header_len_++] = mosi;
        if (header_len_ == 8) {
            header_len_ = 0;
            on_header(header_);
        }
        return kIdle;
    }
    if (mosi != kIdle) violation("GS2200M: byte 0x" + std::to_string(mosi) + " outside a frame");
    if (out_.empty()) return kIdle;
    uint8_t b = out_.front();
    out_.pop_front();
    return b;
}

void Gs2200m::queue_header(uint8_t type, uint16_t len, uint8_t pending) {
    uint8_t h[8] = {0xA5, type, 0, 0, pending, static_cast<uint8_t>(len), static_cast<uint8_t>(len >> 8), 0};
    h[7] = checksum(h);
    out_.insert(out_.end(), h, h + 8);
}

void Gs2200m::on_header(const uint8_t* h) {
    if (checksum(h) != h[7]) violation("GS2200M: SPI header with a bad checksum");
    uint16_t len = static_cast<uint16_t>(h[5] | (h[6] << 8));
    switch (h[1]) {
    case kWriteRequest:
        if (ignore_write_requests > 0) {
            --ignore_write_requests;
            write_len_ = -1;
            return;
        }
        write_len_ = len;
        queue_header(kWriteResponseOk, len, 0);
        return;
    case kDataFromMcu:
        if (write_len_ < 0 || len != write_len_) violation("GS2200M: data header without a granted WRITE of its length");
        if (len == 0) violation("GS2200M: zero-length write");
        write_len_ = -1;
        payload_expected_ = len;
        return;
    case kReadRequest: {
        if (pending_.empty()) {
            queue_header(kReadResponseNok, 0, 0);
            return;
        }
        std::string msg = pending_.front();
        pending_.pop_front();
        size_t n = msg.size() < len ? msg.size() : len;
        if (n > kMaxRead) n = kMaxRead;
        if (n < msg.size()) pending_.push_front(msg.substr(n));
        queue_header(kReadResponseOk, static_cast<uint16_t>(n), pending_.empty() ? 0 : 1);
        queue_header(kDataToMcu, static_cast<uint16_t>(n), 0);
        out_.insert(out_.end(), msg.begin(), msg.begin() + static_cast<long>(n));
        return;
    }
    default:
        violation("GS2200M: unknown SPI header type " + std::to_string(h[1]));
    }
}

void Gs2200m::on_payload(const std::string& payload) {
    if (payload.size() >= 2 && payload[0] == kEsc && payload[1] == 'Z') {
        on_bulk(payload, payload_clock_hz_);
        return;
    }
    if (payload.size() < 2 || payload.compare(payload.size() - 2, 2, "\r\n") != 0) {
        violation("GS2200M: AT command without CR LF: " + payload);
        return;
    }
    on_command(payload.substr(0, payload.size() - 2));
}

void Gs2200m::on_bulk(const std::string& payload, uint32_t clock_hz) {
    if (payload.size() < 7) {
        violation("GS2200M: bulk write shorter than its header");
        return;
    }
    int cid = static_cast<int>(strtol(payload.substr(2, 1).c_str(), nullptr, 16));
    size_t declared = static_cast<size_t>(atoi(payload.substr(3, 4).c_str()));
    if (declared != payload.size() - 7) violation("GS2200M: bulk header says " + std::to_string(declared) +
                                                  " bytes, " + std::to_string(payload.size() - 7) + " followed");
    bulk_clock_hz.push_back(clock_hz);
    bulk_sizes.push_back(payload.size() - 7);
    auto it = peers_.find(static_cast<uint8_t>(cid));
    if (it != peers_.end() && it->second.open) it->second.received.append(payload, 7, std::string::npos);
}

void Gs2200m::on_command(const std::string& cmd) {
    commands.push_back(cmd);
    std::string reply = answer(cmd);
    queue_message(echo_ ? cmd + "\r\n" + reply : reply);
}

std::string Gs2200m::answer(const std::string& cmd) {
    size_t eq = cmd.find('=');
    std::string name = cmd.substr(0, eq);
    std::string args = eq == std::string::npos ? "" : cmd.substr(eq + 1);
    int n = atoi(args.c_str());
    if (cmd == "AT") return kOk;
    if (cmd == "ATE0" || cmd == "ATE1") {
        echo_ = cmd == "ATE1";
        return kOk;
    }
    if (cmd == "AT+VER=??") return "S2W APP VERSION=5.3.1\r\nS2W GEPS VERSION=5.3.1\r\nS2W WLAN VERSION=5.3.1\r\nOK\r\n";
    if (cmd == "AT+NMAC=?") return std::string(kMac) + "\r\n" + kOk;
    if (cmd == "AT+WREGDOMAIN=?") return std::string("REG_DOMAIN=TELEC\r\n") + kOk;
    if (name == "AT+WREGDOMAIN" || name == "AT+WSEC" || name == "AT+BDATA" || name == "AT+WRXACTIVE") return kOk;
    if (name == "AT+WRXPS") {
        power_save_ = n == 1;
        return kOk;
    }
    if (name == "AT+WM") {
        mode_ = n;
        return kOk;
    }
    if (name == "AT+NDHCP") {
        dhcp_ = n == 1;
        return kOk;
    }
    if (name == "AT+DHCPSRVR") return n == 1 && mode_ != 2 ? kError : kOk;
    if (name == "AT+NSET") {
        std::vector<std::string> f = split(args, ',');
        if (f.size() != 3) return kInvalid;
        static_ip_ = f[0];
        return kOk;
    }
    if (cmd == "AT+WD") {
        associated_ = false;
        close_cid(-1);
        return kOk;
    }
    if (name == "AT+WPAPSK") {
        std::string ssid, passphrase;
        if (!s2w::wpapsk(args, ssid, passphrase)) return kInvalid;
        key_ssid_ = ssid;
        key_ = derived_key(ssid, passphrase);
        return std::string("Computing PSK from SSID and PassPhrase...\r\n") + kOk;
    }
    if (name == "AT+WPSK") {  // the key itself; the SSID stays the one of the last AT+WPAPSK
        std::vector<uint8_t> key;
        if (!s2w::wpsk(args, key)) return kInvalid;
        key_ = key;
        return kOk;
    }
    if (name == "AT+WA") return join(args);
    if (cmd == "AT+NSTAT=?") return network_status();
    if (name == "AT+NSTCP") {
        if (!associated_) return kError;
        server_cid_ = free_cid();
        peers_[static_cast<uint8_t>(server_cid_)] = TcpPeer{"", true};
        return std::string("CONNECT ") + hex_digit(server_cid_) + "\r\n" + kOk;
    }
    if (name == "AT+NCLOSE") {
        close_cid(static_cast<int>(strtol(args.c_str(), nullptr, 16)));
        return kOk;
    }
    if (cmd == "AT+NCLOSEALL") {
        close_cid(-1);
        return kOk;
    }
    if (cmd == "AT+WS") return scan();
    return kInvalid;
}

std::vector<uint8_t> Gs2200m::derived_key(const std::string& ssid, const std::string& passphrase) {
    uint8_t key[cubecam::wpa::kPskBytes];
    cubecam::wpa::psk(ssid.c_str(), passphrase.c_str(), key);
    return std::vector<uint8_t>(key, key + sizeof key);
}

std::string Gs2200m::join(const std::string& args) {
    std::string ssid;
    if (!s2w::wa(args, ssid)) return kInvalid;
    // The module drops a stored key computed for another SSID.
    if (!key_ssid_.empty() && key_ssid_ != ssid) key_.clear();
    if (mode_ == 2) {  // limited AP: create the network
        if (key_.empty()) return kError;
        associated_ = true;
        joined_ssid_ = ssid;
        ip_ = static_ip_.empty() ? "0.0.0.0" : static_ip_;
        return kOk;
    }
    const AccessPoint* ap = nullptr;
    for (const AccessPoint& a : networks) {
        if (a.ssid == ssid) ap = &a;
    }
    if (!ap) return kError;
    if (!ap->passphrase.empty() && key_ != derived_key(ap->ssid, ap->passphrase)) return kError;
    if (!dhcp_ && static_ip_.empty()) return "ERROR: IP CONFIG FAIL\r\n";
    associated_ = true;
    joined_ssid_ = ssid;
    ip_ = dhcp_ ? kAssignedIp : static_ip_;
    return "\r\n    IP              SubNet         Gateway   \r\n " + ip_ + ":255.255.255.0:192.168.1.1\r\n" + kOk;
}

std::string Gs2200m::network_status() const {
    int rssi = 0;
    for (const AccessPoint& a : networks) {
        if (associated_ && a.ssid == joined_ssid_) rssi = a.rssi;
    }
    std::string s = std::string("MAC=") + kMac + "\r\n";
    s += std::string("WSTATE=") + (associated_ ? "CONNECTED" : "NOT CONNECTED") + " MODE=" + (mode_ == 2 ? "AP" : "STA") + "\r\n";
    s += "BSSID=00:1d:73:8b:2c:6a SSID=\"" + joined_ssid_ + "\" CHANNEL=6 SECURITY=WPA2-PERSONAL\r\n";
    s += "RSSI=" + std::to_string(rssi) + "\r\n";
    s += "IP addr=" + std::string(associated_ ? ip_ : "0.0.0.0") + " SubNet=255.255.255.0 Gateway=192.168.1.1\r\n";
    s += "DNS1=192.168.1.1 DNS2=0.0.0.0\r\nRx Count=0 Tx Count=0\r\n";
    return s + kOk;
}

std::string Gs2200m::scan() const {
    std::string s = "    BSSID              SSID                     Channel  Type  RSSI Security\r\n";
    char line[160];
    int i = 0;
    for (const AccessPoint& a : networks) {
        snprintf(line, sizeof line, " 00:1d:73:8b:2c:%02x, %-20s , %02d, INFRA , %d , %s\r\n", i++, a.ssid.c_str(),
                 a.channel, a.rssi, a.passphrase.empty() ? "NONE" : "WPA2-PERSONAL");
        s += line;
    }
    return s + "No.Of AP Found:" + std::to_string(networks.size()) + "\r\n" + kOk;
}

uint8_t Gs2200m::free_cid() const {
    for (uint8_t cid = 0; cid < 16; ++cid) {
        auto it = peers_.find(cid);
        if (it == peers_.end() || !it->second.open) return cid;
    }
    violation("GS2200M: all 16 connection ids in use");
    return 15;
}

void Gs2200m::close_cid(int cid) {
    for (auto& p : peers_) {
        if (cid < 0 || p.first == cid) p.second.open = false;
    }
    if (cid < 0 || cid == server_cid_) server_cid_ = -1;
}

uint8_t Gs2200m::client_connect() {
    if (server_cid_ < 0) {
        violation("test: a client connected while no server listens");
        return 0xFF;
    }
    uint8_t cid = free_cid();
    peers_[cid] = TcpPeer{"", true};
    queue_message(std::string("CONNECT ") + hex_digit(server_cid_) + " " + hex_digit(cid) + " 192.168.1.50 50" +
                  std::to_string(10 + cid) + "\r\n");
    return cid;
}

void Gs2200m::client_send(uint8_t cid, const std::string& bytes) {
    for (size_t at = 0; at < bytes.size(); at += kClientChunk) {
        std::string chunk = bytes.substr(at, kClientChunk);
        char head[8];
        snprintf(head, sizeof head, "%cZ%c%04u", kEsc, hex_digit(cid), static_cast<unsigned>(chunk.size()));
        queue_message(std::string(head, 7) + chunk);
    }
}

void Gs2200m::client_close(uint8_t cid) {
    peers_[cid].open = false;
    queue_message(std::string("DISCONNECT ") + hex_digit(cid) + "\r\n");
}

const TcpPeer& Gs2200m::peer(uint8_t cid) const { return peers_.at(cid); }

void Gs2200m::drop_association() {
    associated_ = false;
    close_cid(-1);
    queue_message("Disassociation Event\r\n");
}

Gs2200m& module() {
    static Gs2200m m;
    return m;
}

}  // namespace hostlib
