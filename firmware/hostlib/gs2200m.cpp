#include "gs2200m.h"

#include <algorithm>

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

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
const uint8_t kWriteResponseNok = 0x13;
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
    wedged = false;
    fail_bulk_writes = 0;
    default_drain_bytes_per_s = 1e6;
    commands.clear();
    command_us.clear();
    failing_commands.clear();
    reply_delay_us = 1000;
    bulk_clock_hz.clear();
    bulk_sizes.clear();
    refused_writes = 0;
    esc_f_sent = 0;
    networks.clear();
    reset_framing();
    pending_.clear();
    schedule_.clear();
    on_command_hook = nullptr;
    peers_.clear();
    retired_.clear();
    unreported_.clear();
    serial_ = 0;
    last_us_ = now_us();
    advancing_ = false;
    in_reset_ = false;
    boot_at_us_ = 0;
    resets_ = 0;
    reboot();
}

void Gs2200m::reset_framing() {
    header_len_ = 0;
    payload_expected_ = 0;
    payload_.clear();
    write_len_ = -1;
    payload_clock_hz_ = 0;
    lookahead_.clear();
    out_.clear();
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
    close_cid(-1, false);
    queue_message("\r\nSerial2WiFi APP\r\n");
}

// The reset input of the module (EXT_RTC_RESET_IN, active low): Sony's board
// code drives it from PIN_UART2_RTS on the iS110B v1.0a and from
// PIN_EMMC_DATA3 on v1.0b/c (cxd56_gs2200m.c, gs2200m_reset), holds it 1 ms and
// talks to the module 180 ms after release. Held low, the module is off: its
// connections, association and every message it had for the MCU are gone.
// Without a pulse the module keeps all of it across a reset of the MCU alone.
void Gs2200m::reset_line(bool asserted) {
    advance();
    if (asserted && !in_reset_) {
        in_reset_ = true;
        wedged = false;
        ++resets_;
        associated_ = false;
        close_cid(-1, false);
        pending_.clear();
        reset_framing();
        boot_at_us_ = 0;
    } else if (!asserted && in_reset_) {
        in_reset_ = false;
        boot_at_us_ = now_us() + kBootUs;
    }
}

void Gs2200m::at(uint64_t at_us, std::function<void()> action) { schedule_.emplace(at_us, std::move(action)); }

// The radio drains each connection's transmit buffer at its client's rate;
// scheduled events fire; a released module boots.
void Gs2200m::advance() {
    if (advancing_) return;
    advancing_ = true;
    uint64_t now = now_us();
    if (now < last_us_) last_us_ = now;
    while (!schedule_.empty() && schedule_.begin()->first <= now) {
        std::function<void()> action = schedule_.begin()->second;
        schedule_.erase(schedule_.begin());
        action();
    }
    if (boot_at_us_ != 0 && now >= boot_at_us_) {
        boot_at_us_ = 0;
        reboot();
    }
    double dt_s = static_cast<double>(now - last_us_) / 1e6;
    last_us_ = now;
    for (auto& p : peers_) {
        TcpPeer& c = p.second;
        if (c.tx.empty()) {
            c.drain_credit = 0;
        } else {
            c.drain_credit += c.drain_bytes_per_s * dt_s;
            size_t n = std::min(static_cast<size_t>(c.drain_credit), c.tx.size());
            c.received.append(c.tx, 0, n);
            c.tx.erase(0, n);
            c.drain_credit -= static_cast<double>(n);
        }
        if (c.closing && c.tx.empty()) {
            c.closing = false;
            c.open = false;
        }
    }
    advancing_ = false;
}

// GPIO37 is high whenever the module has a message for the MCU (GS2200Hal.cpp,
// Get_GPIO37Status: "If GS2200 has data to transmit, it will set the GPIO37
// high"), also while the MCU is in the middle of a write (Sony's driver checks
// it between the two halves of a WRITE_REQUEST, gs2200m_hal_write).
bool Gs2200m::data_ready() {
    advance();
    if (in_reset_ || wedged) return false;
    return !out_.empty() || !pending_.empty();
}

void Gs2200m::next_write(const void* data, uint16_t len) {
    lookahead_.assign(static_cast<const char*>(data), len);
}

uint8_t Gs2200m::exchange(uint8_t mosi, uint32_t clock_hz) {
    advance();
    if (in_reset_ || wedged) return 0x00;
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

void Gs2200m::report_end(const std::string& msg) {
    for (const char* word : {"DISCONNECT ", "ERROR: SOCKET FAILURE "}) {
        size_t n = strlen(word);
        if (msg.compare(0, n, word) != 0 || msg.size() <= n) continue;
        uint8_t cid = static_cast<uint8_t>(strtol(msg.substr(n, 1).c_str(), nullptr, 16));
        auto it = std::find(unreported_.begin(), unreported_.end(), cid);
        if (it != unreported_.end()) unreported_.erase(it);
    }
}

void Gs2200m::queue_header(uint8_t type, uint16_t len, uint8_t pending) {
    uint8_t h[8] = {0xA5, type, 0, 0, pending, static_cast<uint8_t>(len), static_cast<uint8_t>(len >> 8), 0};
    h[7] = checksum(h);
    out_.insert(out_.end(), h, h + 8);
}

// Write refused (WRITE_RESPONSE_NOK, 0x13 in GS2200Hal.cpp and gs2200m.c):
// * a message waits for the MCU: Sony's driver treats the data-ready line high
//   during a WRITE_REQUEST as "gs2200m is busy" and reads first
//   (gs2200m_hal_write); the library does not look, so it gets the refusal;
// * the connection's transmit buffer has no room for the data (the brief's
//   "NOK when full"; Sony's driver retries NOK every 10 ms, up to 100 times).
//   The real module decides before it has seen the CID (a WRITE_REQUEST
//   carries only a length); which connection's fullness refuses a write is not
//   public. The fake refuses exactly the writes whose own connection is full,
//   and learns the CID from the bytes the MCU is about to send (next_write).
bool Gs2200m::refuse_write(uint16_t len) {
    if (!pending_.empty()) return true;
    if (lookahead_.size() != len || len < 7 || lookahead_[0] != kEsc || lookahead_[1] != 'Z') return false;
    auto it = peers_.find(static_cast<uint8_t>(strtol(lookahead_.substr(2, 1).c_str(), nullptr, 16)));
    if (it == peers_.end() || !it->second.open || it->second.closing) return false;
    return it->second.tx.size() + (len - 7u) > kConnBufferBytes;
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
        if (refuse_write(len)) {
            ++refused_writes;
            write_len_ = -1;
            queue_header(kWriteResponseNok, 0, 0);
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
        report_end(msg);
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

// A bulk write the module cannot deliver (its connection is gone, or the
// module fails it) is answered <ESC>F, with no CID: the failure reply at
// completion of a data transfer (Telit AT guide, Table 6; Sony's driver,
// _parse_pkt_in_s2). The data is lost.
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
    bool deliverable = it != peers_.end() && it->second.open && !it->second.closing;
    if (!deliverable || fail_bulk_writes > 0) {
        if (deliverable) --fail_bulk_writes;
        ++esc_f_sent;
        queue_message(std::string(1, kEsc) + "F");
        return;
    }
    it->second.tx.append(payload, 7, std::string::npos);
}

// Replies come after the module has worked on the command; messages that
// arrive meanwhile go first (one queue to the MCU). Times are guesses (no
// public figures) except the scan: AT+WS dwells on each of 13 channels
// (Telit AT guide, AT+WST/AT+WS scan time, default 150 ms a channel).
void Gs2200m::on_command(const std::string& cmd) {
    commands.push_back(cmd);
    command_us.push_back(now_us());
    if (on_command_hook) on_command_hook(cmd);
    bool fail = std::find(failing_commands.begin(), failing_commands.end(), cmd) != failing_commands.end();
    std::string reply = fail ? kError : answer(cmd);
    std::string text = echo_ ? cmd + "\r\n" + reply : reply;
    uint64_t delay_us = cmd == "AT+WS" ? 13 * 150000 : reply_delay_us;
    at(now_us() + delay_us, [this, text] { queue_message(text); });
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
        close_cid(-1, false);
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
        peers_[static_cast<uint8_t>(server_cid_)] = TcpPeer{"", true, "", 0, 0, false, 0};
        return std::string("CONNECT ") + hex_digit(server_cid_) + "\r\n" + kOk;
    }
    if (name == "AT+NCLOSE") {
        close_cid(static_cast<int>(strtol(args.c_str(), nullptr, 16)), true);
        return kOk;
    }
    if (cmd == "AT+NCLOSEALL") {
        close_cid(-1, true);
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

// A CID is given to a new connection only once the MCU has read the message
// that ended its last one (assumed: the module could not otherwise tell the
// MCU which connection a later message or write is about).
uint8_t Gs2200m::free_cid() const {
    for (uint8_t cid = 0; cid < 16; ++cid) {
        if (std::find(unreported_.begin(), unreported_.end(), cid) != unreported_.end()) continue;
        auto it = peers_.find(cid);
        if (it == peers_.end() || !it->second.open) return cid;
    }
    violation("GS2200M: all 16 connection ids in use");
    return 15;
}

// NCLOSE / NCLOSEALL end a connection after what it has buffered (graceful);
// a disassociation, AT+WD or a reset ends it at once.
void Gs2200m::close_cid(int cid, bool graceful) {
    for (auto& p : peers_) {
        if (cid >= 0 && p.first != cid) continue;
        if (graceful && p.second.open && !p.second.tx.empty()) {
            p.second.closing = true;
        } else {
            p.second.open = false;
            p.second.closing = false;
            p.second.tx.clear();
        }
    }
    if (cid < 0 || cid == server_cid_) server_cid_ = -1;
}

uint8_t Gs2200m::client_connect() {
    advance();
    if (server_cid_ < 0) {
        violation("test: a client connected while no server listens");
        return 0xFF;
    }
    uint8_t cid = free_cid();
    auto old = peers_.find(cid);
    if (old != peers_.end() && old->second.serial != 0) retired_.push_back(old->second);
    peers_[cid] = TcpPeer{"", true, "", default_drain_bytes_per_s, 0, false, ++serial_};
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

void Gs2200m::client_close(uint8_t cid) { end_client(cid, "DISCONNECT "); }

// The Telit AT guide lists "ERROR: SOCKET FAILURE <CID>" among the
// asynchronous messages; the library matches its prefix only
// (GS2200AtCmd.cpp, AtCmd_checkResponse).
void Gs2200m::client_reset(uint8_t cid, bool socket_failure) {
    end_client(cid, socket_failure ? "ERROR: SOCKET FAILURE " : "DISCONNECT ");
}

void Gs2200m::end_client(uint8_t cid, const char* message) {
    advance();
    TcpPeer& c = peers_[cid];
    c.open = false;
    c.closing = false;
    c.tx.clear();
    unreported_.push_back(cid);
    queue_message(message + std::string(1, hex_digit(cid)) + "\r\n");
}

void Gs2200m::set_drain(uint8_t cid, double bytes_per_s) {
    advance();
    peers_[cid].drain_bytes_per_s = bytes_per_s;
}

TcpPeer& Gs2200m::peer(uint8_t cid) {
    advance();
    return peers_.at(cid);
}

const TcpPeer& Gs2200m::connection(size_t serial) {
    advance();
    for (const auto& p : peers_) {
        if (p.second.serial == serial) return p.second;
    }
    for (const TcpPeer& p : retired_) {
        if (p.serial == serial) return p;
    }
    violation("test: no client connection " + std::to_string(serial));
    return retired_.at(0);
}

void Gs2200m::drop_association() {
    advance();
    associated_ = false;
    close_cid(-1, false);
    queue_message("Disassociation Event\r\n");
}

Gs2200m& module() {
    static Gs2200m m;
    return m;
}

}  // namespace hostlib
