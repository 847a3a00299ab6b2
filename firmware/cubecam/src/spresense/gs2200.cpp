#include "gs2200.h"

#include <SPI.h>
#include <string.h>

#include "../core/gs2200m.h"
#include "../core/text.h"
#include "../core/wpa.h"

// Defined by the GS2200-WiFi library (GS2200Hal.cpp, GS2200AtCmd.cpp) but not
// declared in its headers: the bulk-data buffer (first byte = CID) and the
// lines of the last response.
extern uint8_t ESCBuffer[];
extern uint32_t ESCBufferCnt;
extern uint8_t* RespBuffer[];
extern int RespBuffer_Index;

namespace cubecam {
namespace spresense {

namespace {

const uint8_t kNoCid = 0xFF;

// The newest line of the last module message.
const char* last_line() {
    return RespBuffer_Index > 0 ? reinterpret_cast<const char*>(RespBuffer[RespBuffer_Index - 1]) : "";
}

// The module's reset input (EXT_RTC_RESET_IN, active low). Sony's board code
// (cxd56_gs2200m.c): PIN_UART2_RTS (Arduino D28) on the iS110B v1.0a,
// PIN_EMMC_DATA3 (D21) on v1.0b and v1.0c. The library's type A is taken to be
// v1.0a and its types B and C v1.0b and v1.0c (their data-ready pins match
// that: D27 = PIN_UART2_CTS for A and B, D20 = PIN_EMMC_DATA2 for C).
uint8_t reset_pin(ModuleType type) { return type == iS110B_TypeA ? 28 : 21; }

bool is_reboot(ATCMD_RESP_E r) {
    return r == ATCMD_RESP_NORMAL_BOOT_MSG || r == ATCMD_RESP_RESET_APP_SW || r == ATCMD_RESP_RESET_APP_WD ||
           r == ATCMD_RESP_RESET_WLAN_WD || r == ATCMD_RESP_RESET_WLAN_SW || r == ATCMD_RESP_RESET_WLAN_EXCEPT ||
           r == ATCMD_RESP_EXTERNAL_RESET;
}

bool is_reply(ATCMD_RESP_E r) {
    return r == ATCMD_RESP_OK || r == ATCMD_RESP_ERROR || r == ATCMD_RESP_INVALID_INPUT ||
           r == ATCMD_RESP_INVALID_CID || r == ATCMD_RESP_ERROR_IP_CONFIG_FAIL;
}

}  // namespace

Gs2200Module::Gs2200Module(ModuleType type, Clock& clock)
    : type_(type),
      clock_(clock),
      spi_ready_(false),
      join_failed_(false),
      next_status_ms_(0),
      last_progress_ms_(0),
      last_write_cid_(kNoCid),
      stash_head_(0),
      stash_count_(0),
      stash_used_(0) {}

bool Gs2200Module::reset_module() {
    if (!spi_ready_) {
        // Begins SPI5 and leaves a 4 MHz transaction open (GS2200Hal.cpp,
        // Init_GS2200_SPI_cs): the bus stays ours from here on.
        Init_GS2200_SPI_type(type_);
        spi_ready_ = true;
    }
    uint8_t pin = reset_pin(type_);
    pinMode(pin, OUTPUT);
    digitalWrite(pin, LOW);
    delay(kResetPulseMs);
    digitalWrite(pin, HIGH);
    stash_count_ = 0;
    stash_used_ = 0;
    last_write_cid_ = kNoCid;
    // Its boot banner ("Serial2WiFi APP") says it is ready; whatever it said
    // before is gone with the reset.
    uint32_t start = clock_.millis();
    bool booted = false;
    while (!booted && !deadline_reached(clock_.millis(), start + kBootWaitMs)) {
        if (!Get_GPIO37Status()) {
            delay(1);
            continue;
        }
        WiFi_InitESCBuffer();
        booted = is_reboot(AtCmd_RecvResponse());
    }
    use_fast_clock();
    last_progress_ms_ = clock_.millis();
    return command("AT\r\n") == ATCMD_RESP_OK;
}

void Gs2200Module::use_fast_clock() {
    // The bus lock is not recursive (a NuttX nxmutex): end the library's
    // transaction before starting ours, or the task blocks for good. The
    // library's write retry starts a 4 MHz one again (WiFi_Write,
    // reinit_spi), so this runs before every bulk write too.
    SPI5.endTransaction();
    SPI5.beginTransaction(SPISettings(kSpiClockHz, MSBFIRST, SPI_MODE1));
}

bool Gs2200Module::start_join(const Settings& s) {
    bool ap = s.mode == WifiMode::AccessPoint;
    bool own = !s.ip.dhcp;
    TWIFI_Params params = {ap ? ATCMD_MODE_LIMITED_AP : ATCMD_MODE_STATION, ATCMD_PSAVE_DEFAULT};
    // A static station address goes to begin(), which sets it (AT+NSET)
    // instead of starting DHCP (AT+NDHCP=1) that we would have to stop again.
    TWIFI_Adress adrs = TWIFI_Adress();  // empty strings unless an address is set below
    if (ap || own) addresses(s, adrs);
    if (telit_.begin(params, ap || !own, adrs) != 0 || !configure(ap, own, adrs)) return false;
    join_failed_ = false;
    next_status_ms_ = clock_.millis();
    // Our own AT+WPAPSK and AT+WA: the library's (AtCmd_WPAPSK, which
    // activate_ap() and activate_station() use) formats into a 60-byte buffer
    // that SSID 32 + passphrase 63 overflow, and neither quotes nor escapes.
    if (s.password[0] && !send_key(s)) return false;
    char cmd[gs2200m::kMaxCredentialCommand];
    TextBuf c(cmd, sizeof cmd);
    gs2200m::add_wa(c, s.ssid, ap ? kAccessPointChannel : 0);
    join_failed_ = AtCmd_SendCommand(cmd) != ATCMD_RESP_OK;
    return true;
}

// The node's own address, mask and gateway (an access point serves DHCP from
// 192.168.1.1/24 unless the settings give an address).
void Gs2200Module::addresses(const Settings& s, TWIFI_Adress& out) {
    static const uint8_t kDefaultAp[4] = {192, 168, 1, 1};
    bool own = !s.ip.dhcp;
    uint8_t m[4];
    uint8_t prefix = own ? s.ip.prefix : 24;
    uint32_t bits = prefix >= 32 ? 0xFFFFFFFFu : ~(0xFFFFFFFFu >> prefix);
    for (int i = 0; i < 4; ++i) m[i] = static_cast<uint8_t>(bits >> (24 - 8 * i));
    TextBuf a(out.device, sizeof out.device), k(out.subnet, sizeof out.subnet), g(out.gateway, sizeof out.gateway);
    a.add_ipv4(own ? s.ip.address : kDefaultAp);
    k.add_ipv4(m);
    g.add_ipv4(own ? s.ip.gateway : kDefaultAp);
}

// After begin(): radio awake, addresses, no old association. begin() turns
// 802.11 power save on (AT+WRXPS=1); streaming wants the radio awake. It
// also forces the regulatory domain to TELEC (Japan): docs/firmware.md.
bool Gs2200Module::configure(bool ap, bool own, TWIFI_Adress& adrs) {
    if (AtCmd_WRXPS(0) != ATCMD_RESP_OK || AtCmd_WRXACTIVE(1) != ATCMD_RESP_OK) return false;
    // begin() sets no address for an access point, and leaves the DHCP client
    // of a static station as the module had it.
    if (ap && AtCmd_NSET(adrs.device, adrs.subnet, adrs.gateway) != ATCMD_RESP_OK) return false;
    if (!ap && own && AtCmd_NDHCP(0) != ATCMD_RESP_OK) return false;
    return AtCmd_WD() == ATCMD_RESP_OK;
}

bool Gs2200Module::send_key(const Settings& s) {
    char cmd[gs2200m::kMaxCredentialCommand];
    TextBuf c(cmd, sizeof cmd);
    if (gs2200m::add_wpapsk(c, s.ssid, s.password)) return AtCmd_SendCommand(cmd) == ATCMD_RESP_OK;
    // A passphrase AT+WPAPSK cannot carry (a comma together with a lone '"',
    // UTF-8, ...): the module gets the key derived from it, after a stand-in
    // passphrase that tells it which SSID the key is for.
    uint8_t key[wpa::kPskBytes];
    wpa::psk(s.ssid, s.password, key);
    gs2200m::add_wpapsk(c, s.ssid, gs2200m::kKeyFollows);
    bool ok = AtCmd_SendCommand(cmd) == ATCMD_RESP_OK;
    c.clear();
    gs2200m::add_wpsk(c, key);
    return ok && AtCmd_SendCommand(cmd) == ATCMD_RESP_OK;
}

JoinStatus Gs2200Module::join_status(LinkInfo& info) {
    if (join_failed_) return JoinStatus::Failed;
    uint32_t now = clock_.millis();
    if (!deadline_reached(now, next_status_ms_)) return JoinStatus::Pending;
    next_status_ms_ = now + kNetStatusPollMs;
    ATCMD_NetworkStatus st;
    if (AtCmd_NSTAT(&st) != ATCMD_RESP_OK || st.addr.ipv4[0] == 0) return JoinStatus::Pending;
    memcpy(info.ip, st.addr.ipv4, 4);
    info.rssi = static_cast<int8_t>(st.signal);
    return JoinStatus::Joined;
}

size_t Gs2200Module::scan(ScanEntry* out, size_t max) {
    // A fresh board scans before any join: SPI5 is not set up until then, and
    // the SPI library ignores every call on a bus that has not begun.
    if (!spi_ready_ && !reset_module()) return 0;
    // The library has no scan wrapper.
    if (command("AT+WS\r\n", kScanTimeoutMs) != ATCMD_RESP_OK) return 0;
    size_t n = 0;
    for (int i = 0; i < RespBuffer_Index && n < max; ++i) {
        if (gs2200m::parse_scan_line(reinterpret_cast<const char*>(RespBuffer[i]), out[n])) ++n;
    }
    return n;
}

uint16_t Gs2200Module::open_server(uint16_t port) {
    // Connections the module still holds (from before a reset of the MCU
    // alone, or a lost link) would come back as events for clients we do not know.
    close_all();
    char cmd[24];
    TextBuf c(cmd, sizeof cmd);
    c.add("AT+NSTCP=").add_uint(port).add("\r\n");
    return command(cmd) == ATCMD_RESP_OK ? port : 0;
}

void Gs2200Module::close_all() {
    // At first-boot provisioning the bus has not been set up: nothing is open.
    if (!spi_ready_) return;
    command("AT+NCLOSEALL\r\n");
    stash_count_ = 0;
    stash_used_ = 0;
}

Gs2200Module::Message Gs2200Module::read_message(NetEvent& ev, uint8_t* buf, uint16_t cap, ATCMD_RESP_E& reply) {
    ev.kind = NetEventKind::None;
    ev.len = 0;
    WiFi_InitESCBuffer();
    reply = AtCmd_RecvResponse();
    if (reply == ATCMD_RESP_TIMEOUT || reply == ATCMD_RESP_SPI_ERROR) return Message::Nothing;
    last_progress_ms_ = clock_.millis();
    switch (reply) {
    case ATCMD_RESP_BULK_DATA_RX:
        if (ESCBufferCnt < 1 || !gs2200m::parse_cid(static_cast<char>(ESCBuffer[0]), ev.cid)) return Message::Other;
        ev.len = static_cast<uint16_t>(ESCBufferCnt - 1 < cap ? ESCBufferCnt - 1 : cap);
        memcpy(buf, ESCBuffer + 1, ev.len);
        ev.kind = NetEventKind::Data;
        break;
    case ATCMD_RESP_TCP_SERVER_CONNECT:
        if (!gs2200m::event_cid(last_line(), "CONNECT", 1, ev.cid)) return Message::Other;
        ev.kind = NetEventKind::Accepted;
        break;
    case ATCMD_RESP_DISCONNECT:
        if (!gs2200m::event_cid(last_line(), "DISCONNECT", 0, ev.cid)) return Message::Other;
        ev.kind = NetEventKind::Closed;
        break;
    case ATCMD_RESP_ERROR_SOCKET_FAILURE:
        // "ERROR: SOCKET FAILURE <cid>"; without a CID it is a command's reply.
        if (!gs2200m::event_cid(last_line(), "SOCKET FAILURE", 0, ev.cid)) return Message::Reply;
        ev.kind = NetEventKind::Failed;
        break;
    case ATCMD_RESP_ESC_FAIL:
        // The bulk write just made failed (<ESC>F carries no CID): that
        // client's stream now lacks a chunk, so it is closed.
        if (last_write_cid_ == kNoCid) return Message::Other;
        ev.cid = last_write_cid_;
        last_write_cid_ = kNoCid;
        ev.kind = NetEventKind::Failed;
        break;
    case ATCMD_RESP_DISASSOCIATION_EVENT:
        ev.kind = NetEventKind::LinkLost;
        break;
    default:
        if (is_reboot(reply)) {
            ev.kind = NetEventKind::ModuleRebooted;
            break;
        }
        return is_reply(reply) ? Message::Reply : Message::Other;
    }
    return Message::Event;
}

ATCMD_RESP_E Gs2200Module::command(const char* cmd, uint32_t timeout_ms) {
    uint16_t len = static_cast<uint16_t>(strlen(cmd));
    SPI_RESP_STATUS_E sent = SPI_RESP_STATUS_ERROR;
    // A refused write (a message waits, or the module is busy) is tried again
    // after reading what waits; a module that does not answer at all is not.
    for (int i = 0; i < kCommandWriteTries && sent == SPI_RESP_STATUS_ERROR; ++i) {
        if (i > 0) delay(kCommandRetryMs);
        if (!drain_into_stash()) return ATCMD_RESP_SPI_ERROR;
        sent = WiFi_Write(cmd, len);
        use_fast_clock();
    }
    if (sent != SPI_RESP_STATUS_OK) return ATCMD_RESP_SPI_ERROR;
    uint32_t start = clock_.millis();
    while (!deadline_reached(clock_.millis(), start + timeout_ms)) {
        if (!Get_GPIO37Status()) {
            delay(1);
            continue;
        }
        NetEvent ev;
        ATCMD_RESP_E reply;
        Message m = read_message(ev, io_, sizeof io_, reply);
        if (m == Message::Event) stash(ev, io_);
        if (m == Message::Reply) return reply;
    }
    return ATCMD_RESP_TIMEOUT;
}

// Reads every waiting message into the stash (replies that come too late for
// their command are dropped). False if the module would not stop talking.
bool Gs2200Module::drain_into_stash() {
    for (size_t i = 0; i < 2 * kStashedEvents; ++i) {
        if (!Get_GPIO37Status()) return true;
        NetEvent ev;
        ATCMD_RESP_E reply;
        if (read_message(ev, io_, sizeof io_, reply) == Message::Event) stash(ev, io_);
    }
    return false;
}

void Gs2200Module::stash(const NetEvent& ev, const uint8_t* data) {
    if (stash_count_ == kStashedEvents) return;  // 16 events behind: the oldest stay, this one is lost
    Stashed& s = stash_[(stash_head_ + stash_count_) % kStashedEvents];
    s.ev = ev;
    s.offset = stash_used_;
    if (ev.kind == NetEventKind::Data) {
        if (stash_used_ + ev.len > kStashedBytes) {
            // No room for a client's bytes: that client could only hang; close it.
            s.ev.kind = NetEventKind::Failed;
            s.ev.len = 0;
        } else {
            memcpy(stash_data_ + stash_used_, data, ev.len);
            stash_used_ = static_cast<uint16_t>(stash_used_ + ev.len);
        }
    }
    ++stash_count_;
}

bool Gs2200Module::unstash(NetEvent& ev, uint8_t* buf, uint16_t cap) {
    if (stash_count_ == 0) return false;
    const Stashed& s = stash_[stash_head_];
    ev = s.ev;
    if (ev.kind == NetEventKind::Data) {
        if (ev.len > cap) ev.len = cap;
        memcpy(buf, stash_data_ + s.offset, ev.len);
    }
    stash_head_ = static_cast<uint8_t>((stash_head_ + 1) % kStashedEvents);
    if (--stash_count_ == 0) stash_used_ = 0;
    return true;
}

NetEvent Gs2200Module::poll(uint8_t* buf, uint16_t cap) {
    NetEvent ev = {NetEventKind::None, 0, 0};
    if (unstash(ev, buf, cap)) return ev;
    // Messages that are not events (late replies, <ESC>O...) are consumed and
    // the next one read: None means the data-ready line is low.
    for (int i = 0; i < kMaxDrained && Get_GPIO37Status(); ++i) {
        ATCMD_RESP_E reply;
        if (read_message(ev, buf, cap, reply) == Message::Event) return ev;
    }
    ev.kind = NetEventKind::None;
    return ev;
}

WriteResult Gs2200Module::write(uint8_t cid, const uint8_t* data, uint16_t len) {
    WriteResult r = {WriteStatus::Ok, 0};
    // The module refuses a write while it has a message for us (Sony's driver
    // reads first when the data-ready line is high, gs2200m_hal_write).
    if (stash_count_ > 0 || Get_GPIO37Status()) {
        r.status = WriteStatus::Busy;
        return r;
    }
    if (len > kNetChunk) len = kNetChunk;
    use_fast_clock();
    // Header and data in one SPI write.
    gs2200m::bulk_header(cid, len, tx_);
    memcpy(tx_ + gs2200m::kBulkHeaderBytes, data, len);
    SPI_RESP_STATUS_E sent = WiFi_Write(tx_, static_cast<uint16_t>(gs2200m::kBulkHeaderBytes + len));
    uint32_t now = clock_.millis();
    if (sent == SPI_RESP_STATUS_OK) {
        last_write_cid_ = cid;
        last_progress_ms_ = now;
        r.accepted = len;
        return r;
    }
    // Refused (WRITE_RESPONSE_NOK after the library's three tries: a full
    // buffer) or unanswered: 0 bytes taken. The link counts as lost only when
    // the module has been silent for kLinkSilenceMs and does not answer AT.
    if (!deadline_reached(now, last_progress_ms_ + kLinkSilenceMs)) return r;
    if (command("AT\r\n") == ATCMD_RESP_OK) {
        last_progress_ms_ = clock_.millis();
        return r;
    }
    r.status = WriteStatus::LinkFailure;
    return r;
}

void Gs2200Module::close(uint8_t cid) {
    char cmd[16];
    TextBuf c(cmd, sizeof cmd);
    c.add("AT+NCLOSE=").add(gs2200m::cid_char(cid)).add("\r\n");
    command(cmd);
}

}  // namespace spresense
}  // namespace cubecam
