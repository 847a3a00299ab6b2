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

// The newest line of the last module message.
const char* last_line() {
    return RespBuffer_Index > 0 ? reinterpret_cast<const char*>(RespBuffer[RespBuffer_Index - 1]) : "";
}

}  // namespace

Gs2200Module::Gs2200Module(ModuleType type, Clock& clock)
    : type_(type), clock_(clock), spi_ready_(false), join_failed_(false), next_status_ms_(0) {}

bool Gs2200Module::reset_module() {
    if (!spi_ready_) {
        // Begins SPI5 and leaves a 4 MHz transaction open (GS2200Hal.cpp,
        // Init_GS2200_SPI_cs): the bus stays ours from here on.
        Init_GS2200_SPI_type(type_);
        spi_ready_ = true;
    }
    use_fast_clock();
    // What the module said while nobody listened (its boot banner, events of
    // a lost link) would otherwise be taken as the answer to AT.
    for (int i = 0; i < kMaxDrained && Get_GPIO37Status(); ++i) AtCmd_RecvResponse();
    return AtCmd_AT() == ATCMD_RESP_OK;
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
    TWIFI_Params params = {ap ? ATCMD_MODE_LIMITED_AP : ATCMD_MODE_STATION, ATCMD_PSAVE_DEFAULT};
    if (telit_.begin(params) != 0) return false;
    // begin() turns 802.11 power save on; streaming wants the radio awake.
    AtCmd_WRXPS(0);
    AtCmd_WRXACTIVE(1);
    join_failed_ = false;
    next_status_ms_ = clock_.millis();
    if (ap || !s.ip.dhcp) {
        // An access point needs an address of its own to serve DHCP from.
        static const uint8_t kDefaultAp[4] = {192, 168, 1, 1};
        bool own = !s.ip.dhcp;
        char addr[16], mask[16], gw[16];
        uint8_t m[4];
        uint8_t prefix = own ? s.ip.prefix : 24;
        uint32_t bits = prefix >= 32 ? 0xFFFFFFFFu : ~(0xFFFFFFFFu >> prefix);
        for (int i = 0; i < 4; ++i) m[i] = static_cast<uint8_t>(bits >> (24 - 8 * i));
        TextBuf a(addr, sizeof addr), k(mask, sizeof mask), g(gw, sizeof gw);
        a.add_ipv4(own ? s.ip.address : kDefaultAp);
        k.add_ipv4(m);
        g.add_ipv4(own ? s.ip.gateway : kDefaultAp);
        if (!ap) AtCmd_NDHCP(0);
        AtCmd_NSET(addr, mask, gw);
    } else {
        AtCmd_NDHCP(1);
    }
    AtCmd_WD();
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
    char cmd[] = "AT+WS\r\n";
    if (AtCmd_SendCommand(cmd) != ATCMD_RESP_OK) return 0;
    size_t n = 0;
    for (int i = 0; i < RespBuffer_Index && n < max; ++i) {
        if (gs2200m::parse_scan_line(reinterpret_cast<const char*>(RespBuffer[i]), out[n])) ++n;
    }
    return n;
}

uint16_t Gs2200Module::open_server(uint16_t port) {
    char port_text[6];
    TextBuf p(port_text, sizeof port_text);
    p.add_uint(port);
    char server_cid = static_cast<char>(ATCMD_INVALID_CID);
    if (AtCmd_NSTCP(port_text, &server_cid) != ATCMD_RESP_OK) return 0;
    return port;
}

void Gs2200Module::close_all() { AtCmd_NCLOSEALL(); }

NetEvent Gs2200Module::poll(uint8_t* buf, uint16_t cap) {
    NetEvent ev = {NetEventKind::None, 0, 0};
    if (!Get_GPIO37Status()) return ev;  // the module has nothing for us
    WiFi_InitESCBuffer();
    switch (AtCmd_RecvResponse()) {
    case ATCMD_RESP_BULK_DATA_RX:
        if (ESCBufferCnt < 1 || !gs2200m::parse_cid(static_cast<char>(ESCBuffer[0]), ev.cid)) break;
        ev.len = static_cast<uint16_t>(ESCBufferCnt - 1 < cap ? ESCBufferCnt - 1 : cap);
        memcpy(buf, ESCBuffer + 1, ev.len);
        ev.kind = NetEventKind::Data;
        break;
    case ATCMD_RESP_TCP_SERVER_CONNECT:
        if (gs2200m::event_cid(last_line(), "CONNECT", 1, ev.cid)) ev.kind = NetEventKind::Accepted;
        break;
    case ATCMD_RESP_DISCONNECT:
        if (gs2200m::event_cid(last_line(), "DISCONNECT", 0, ev.cid)) ev.kind = NetEventKind::Closed;
        break;
    case ATCMD_RESP_DISASSOCIATION_EVENT:
        ev.kind = NetEventKind::LinkLost;
        break;
    case ATCMD_RESP_NORMAL_BOOT_MSG:
    case ATCMD_RESP_RESET_APP_SW:
    case ATCMD_RESP_RESET_APP_WD:
    case ATCMD_RESP_RESET_WLAN_WD:
    case ATCMD_RESP_RESET_WLAN_SW:
    case ATCMD_RESP_RESET_WLAN_EXCEPT:
    case ATCMD_RESP_EXTERNAL_RESET:
        ev.kind = NetEventKind::ModuleRebooted;
        break;
    default:
        break;
    }
    return ev;
}

WriteResult Gs2200Module::write(uint8_t cid, const uint8_t* data, uint16_t len) {
    // Header and data in one SPI write.
    WriteResult r = {WriteStatus::Ok, 0};
    if (len > kNetChunk) len = kNetChunk;
    use_fast_clock();
    gs2200m::bulk_header(cid, len, tx_);
    memcpy(tx_ + gs2200m::kBulkHeaderBytes, data, len);
    if (WiFi_Write(tx_, static_cast<uint16_t>(gs2200m::kBulkHeaderBytes + len)) != SPI_RESP_STATUS_OK) {
        r.status = WriteStatus::LinkFailure;
        return r;
    }
    r.accepted = len;
    return r;
}

void Gs2200Module::close(uint8_t cid) { AtCmd_NCLOSE(static_cast<uint8_t>(gs2200m::cid_char(cid))); }

}  // namespace spresense
}  // namespace cubecam
