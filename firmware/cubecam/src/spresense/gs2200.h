// The Telit GS2200M on the iS110B add-on board as the core's Network (sockets
// by connection id) and WifiControl. Uses the GS2200-WiFi library's SPI and
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
// 10 MHz in SPI command mode (Telit guide; the NuttX driver allows 4-10 MHz).
// 8 MHz is what the >= 15 fps budget of docs/firmware.md assumes. Not yet
// tried on a board: set 4000000 to get the library's clock back.
const uint32_t kSpiClockHz = 8000000;
const uint8_t kAccessPointChannel = 6;
// Module messages read and dropped before a module reset (at most).
const int kMaxDrained = 8;

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
    void use_fast_clock();
    // AT+WPAPSK, or AT+WPAPSK with a stand-in and AT+WPSK with the key.
    bool send_key(const Settings& s);
    ModuleType type_;
    Clock& clock_;
    TelitWiFi telit_;
    bool spi_ready_;
    bool join_failed_;
    uint32_t next_status_ms_;
    uint8_t tx_[gs2200m::kBulkHeaderBytes + kNetChunk];
};

}  // namespace spresense
}  // namespace cubecam

#endif
