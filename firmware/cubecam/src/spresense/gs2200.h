// The Telit GS2200M on the iS110B add-on board as the core's Network (sockets
// by connection id) and WifiControl. Written for a module that pushes back: a
// write it refuses (buffer full, or a message waiting) takes 0 bytes and is
// tried again later; every message kind is handled; AT commands keep the
// events that arrive before their reply; the module is reset by its line. Uses the GS2200-WiFi library's SPI and
// AT layer, but routes incoming data by CID itself (the library's read()
// drops data for other CIDs) and sends its own bulk-write, WPAPSK and WA
// commands (the library's WPAPSK buffer is 60 bytes, SSID 32 + passphrase 63
// do not fit, and it neither quotes nor escapes), in station and
// access-point mode alike; a passphrase the AT syntax cannot carry goes as
// the key derived from it (AT+WPSK, core/gs2200m.h).
#ifndef CUBECAM_SPRESENSE_GS2200_H
#define CUBECAM_SPRESENSE_GS2200_H

#include <TelitWiFi.h>

#include "../core/gs2200m.h"
#include "../core/hal.h"
#include "../core/settings.h"

namespace cubecam {
namespace spresense {

const uint32_t kNetStatusPollMs = 500;  // AT+NSTAT while joining, at most this often
// SPI clock to the module. The library fixes 4 MHz; the GS2200M takes up to
// 10 MHz in SPI command mode (Telit guide; the NuttX driver allows 4-10 MHz,
// default 4 MHz). 8 MHz: docs/firmware.md, "Streaming budget", gives the
// reasons and what it buys. Not yet tried on a board: set 4000000 to get the
// library's clock back.
const uint32_t kSpiClockHz = 8000000;
const uint8_t kAccessPointChannel = 6;
// Module messages read in one poll() at most (the loop stays responsive).
const int kMaxDrained = 8;
// Reset of the module (Sony's board code, cxd56_gs2200m.c and gs2200m.c:
// reset held 1 ms, the module talked to 180 ms after release). We wait for
// its boot banner instead, at most kBootWaitMs.
const uint32_t kResetPulseMs = 1;
const uint32_t kBootWaitMs = 1000;
// An AT command's reply: how long we wait for it, and how often a refused
// command write is tried again (Sony's driver: every 10 ms).
const uint32_t kCommandTimeoutMs = 1000;
const uint32_t kScanTimeoutMs = 5000;  // AT+WS dwells on 13 channels
const int kCommandWriteTries = 10;
const uint32_t kCommandRetryMs = 10;
// The link is declared lost only when the module has neither taken a write
// nor sent a message for this long and then does not answer AT.
const uint32_t kLinkSilenceMs = 5000;
// Messages read while an AT command waited for its reply, kept for poll().
const size_t kStashedEvents = 16;
const size_t kStashedBytes = 3072;

class Gs2200Module : public Network, public WifiControl {
public:
    // type: iS110B_TypeA or _TypeB (data-ready on pin 27) or _TypeC (pin 20).
    Gs2200Module(ModuleType type, Clock& clock);
    // Network
    uint16_t open_server(uint16_t port);
    void close_all();
    NetEvent poll(uint8_t* buf, uint16_t cap);
    WriteResult write(uint8_t cid, const uint8_t* data, uint16_t len);
    void close(uint8_t cid);
    // WifiControl
    bool reset_module();
    bool start_join(const Settings& s);
    JoinStatus join_status(LinkInfo& info);
    size_t scan(ScanEntry* out, size_t max);

private:
    enum class Message : uint8_t { Nothing, Event, Reply, Other };
    struct Stashed {
        NetEvent ev;
        uint16_t offset;  // of its data in stash_data_
    };
    void use_fast_clock();
    // AT+WPAPSK, or AT+WPAPSK with a stand-in and AT+WPSK with the key.
    bool send_key(const Settings& s);
    static void addresses(const Settings& s, TWIFI_Adress& out);
    bool configure(bool ap, bool own, TWIFI_Adress& adrs);
    // Reads one message (the data-ready line is high): an event for poll()
    // (data copied to buf), the reply to a command, or something else.
    Message read_message(NetEvent& ev, uint8_t* buf, uint16_t cap, ATCMD_RESP_E& reply);
    // Sends an AT command and returns its reply; events that arrive before the
    // reply are kept for poll().
    ATCMD_RESP_E command(const char* cmd, uint32_t timeout_ms = kCommandTimeoutMs);
    bool drain_into_stash();
    void stash(const NetEvent& ev, const uint8_t* data);
    bool unstash(NetEvent& ev, uint8_t* buf, uint16_t cap);
    ModuleType type_;
    Clock& clock_;
    TelitWiFi telit_;
    bool spi_ready_;
    bool join_failed_;
    uint32_t next_status_ms_;
    uint32_t last_progress_ms_;
    uint8_t last_write_cid_;  // where an <ESC>F belongs
    Stashed stash_[kStashedEvents];
    uint8_t stash_head_;
    uint8_t stash_count_;
    uint16_t stash_used_;
    uint8_t stash_data_[kStashedBytes];
    uint8_t io_[kNetChunk];  // data of a message read while a command waits
    uint8_t tx_[gs2200m::kBulkHeaderBytes + kNetChunk];
};

}  // namespace spresense
}  // namespace cubecam

#endif
