#include "gs2200.h"

#include <SPI.h>
#include <string.h>

#include "../core/text.h"

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

char cid_char(uint8_t cid) { return "0123456789abcdef"[cid & 15]; }

bool cid_value(char c, uint8_t& cid) {
    if (c >= '0' && c <= '9') {
        cid = static_cast<uint8_t>(c - '0');
    } else if (c >= 'a' && c <= 'f') {
        cid = static_cast<uint8_t>(c - 'a' + 10);
    } else {
        return false;
    }
    return true;
}

// The n-th space-separated word after `keyword` in the newest response line.
bool response_word(const char* keyword, int n, char& first_char) {
    if (RespBuffer_Index <= 0) return false;
    const char* line = reinterpret_cast<const char*>(RespBuffer[RespBuffer_Index - 1]);
    const char* p = strstr(line, keyword);
    if (!p) return false;
    p += strlen(keyword);
    for (int word = 0; *p; ++word) {
        while (*p == ' ') ++p;
        if (word == n) {
            first_char = *p;
            return *p != '\0';
        }
        while (*p && *p != ' ') ++p;
    }
    return false;
}

bool reached(uint32_t now, uint32_t deadline) { return static_cast<int32_t>(now - deadline) >= 0; }

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
    // Our own AT+WPAPSK: the library's (AtCmd_WPAPSK, which activate_ap() and
    // activate_station() use) formats into a 60-byte buffer that SSID 32 +
    // passphrase 63 overflow. Settings validation keeps both printable and
    // comma-free, so they fit this buffer and the module's syntax.
    char cmd[16 + kMaxSsid + kMaxPassphrase];
    TextBuf c(cmd, sizeof cmd);
    c.add("AT+WPAPSK=").add(s.ssid).add(',').add(s.password).add("\r\n");
    if (s.password[0] && AtCmd_SendCommand(cmd) != ATCMD_RESP_OK) return false;
    join_failed_ = AtCmd_WA(s.ssid, "", ap ? kAccessPointChannel : 0) != ATCMD_RESP_OK;
    return true;
}

JoinStatus Gs2200Module::join_status(LinkInfo& info) {
    if (join_failed_) return JoinStatus::Failed;
    uint32_t now = clock_.millis();
    if (!reached(now, next_status_ms_)) return JoinStatus::Pending;
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
    // The library has no scan wrapper. Lines are "<bssid>, <ssid>, <channel>,
    // <type>, <rssi>, <security>" (Telit AT guide; not checked on hardware).
    char cmd[] = "AT+WS\r\n";
    if (AtCmd_SendCommand(cmd) != ATCMD_RESP_OK) return 0;
    size_t n = 0;
    for (int i = 0; i < RespBuffer_Index && n < max; ++i) {
        const char* line = reinterpret_cast<const char*>(RespBuffer[i]);
        const char* field[6];
        int count = 0;
        field[count++] = line;
        for (const char* p = line; *p && count < 6; ++p) {
            if (*p == ',') field[count++] = p + 1;
        }
        if (count < 6) continue;
        const char* ssid = field[1];
        while (*ssid == ' ') ++ssid;
        size_t len = static_cast<size_t>(field[2] - 1 - ssid);
        while (len > 0 && ssid[len - 1] == ' ') --len;
        if (len == 0 || len > kMaxSsid) continue;
        memset(out[n].ssid, 0, sizeof out[n].ssid);
        memcpy(out[n].ssid, ssid, len);
        const char* rssi = field[4];
        while (*rssi == ' ') ++rssi;
        int value = 0;
        bool negative = *rssi == '-';
        for (const char* d = rssi + (negative ? 1 : 0); *d >= '0' && *d <= '9' && value < 200; ++d) {
            value = value * 10 + (*d - '0');
        }
        out[n].rssi = static_cast<int8_t>(negative ? -value : value);
        out[n].secured = strstr(field[5], "NONE") == 0;
        ++n;
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
    char c = 0;
    switch (AtCmd_RecvResponse()) {
    case ATCMD_RESP_BULK_DATA_RX:
        if (ESCBufferCnt < 1 || !cid_value(static_cast<char>(ESCBuffer[0]), ev.cid)) break;
        ev.len = static_cast<uint16_t>(ESCBufferCnt - 1 < cap ? ESCBufferCnt - 1 : cap);
        memcpy(buf, ESCBuffer + 1, ev.len);
        ev.kind = NetEventKind::Data;
        break;
    case ATCMD_RESP_TCP_SERVER_CONNECT:  // "CONNECT <server cid> <new cid> <ip> <port>"
        if (response_word("CONNECT", 1, c) && cid_value(c, ev.cid)) ev.kind = NetEventKind::Accepted;
        break;
    case ATCMD_RESP_DISCONNECT:  // "DISCONNECT <cid>"
        if (response_word("DISCONNECT", 0, c) && cid_value(c, ev.cid)) ev.kind = NetEventKind::Closed;
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
    // <ESC> 'Z' <cid> <4 ASCII digits> <data>, in one SPI write.
    WriteResult r = {WriteStatus::Ok, 0};
    if (len > kNetChunk) len = kNetChunk;
    use_fast_clock();
    tx_[0] = ATCMD_ESC;
    tx_[1] = 'Z';
    tx_[2] = static_cast<uint8_t>(cid_char(cid));
    for (int i = 0, div = 1000; i < 4; ++i, div /= 10) tx_[3 + i] = static_cast<uint8_t>('0' + (len / div) % 10);
    memcpy(tx_ + 7, data, len);
    if (WiFi_Write(tx_, static_cast<uint16_t>(len + 7)) != SPI_RESP_STATUS_OK) {
        r.status = WriteStatus::LinkFailure;
        return r;
    }
    r.accepted = len;
    return r;
}

void Gs2200Module::close(uint8_t cid) { AtCmd_NCLOSE(static_cast<uint8_t>(cid_char(cid))); }

}  // namespace spresense
}  // namespace cubecam
