// A Telit GS2200M on the SPI5 bus, as the GS2200-WiFi library talks to it,
// behaving as the real module does at its worst. The module side of the SPI
// framing (8-byte headers 0xA5, WRITE / READ requests, DATA_FROM_MCU /
// DATA_TO_MCU, the data-ready line GPIO37), AT commands answered in the Telit
// AT guide's formats, bulk data (<ESC>Z<cid><4 digits><data>) to and from TCP
// clients, and what a module does on its own: a transmit buffer per
// connection that the radio drains at a set rate (0 for a client that stopped
// reading), WRITE_RESPONSE_NOK when it is full or a message waits, events
// (boot banner, CONNECT, DISCONNECT, ERROR: SOCKET FAILURE, <ESC>F, late OKs,
// disassociation) at any time, including between a command and its reply and
// while the MCU writes; the reset line. Each behaviour names its source in
// gs2200m.cpp. One message per READ request, as the library reads them.
// Time is the host's virtual clock (hostlib.h): the radio drains and
// scheduled events fire as it moves.
#ifndef CUBECAM_HOSTLIB_GS2200M_H
#define CUBECAM_HOSTLIB_GS2200M_H

#include <stddef.h>
#include <stdint.h>

#include <deque>
#include <functional>
#include <map>
#include <string>
#include <vector>

namespace hostlib {

struct AccessPoint {
    std::string ssid;
    std::string passphrase;  // empty: open network (any bytes: the key is derived from them)
    int rssi;
    int channel;
};

struct TcpPeer {
    std::string received;  // bytes this client has read (left the module's transmit buffer)
    bool open;             // the connection is up (a closed one stays up until its buffer has drained)
    // Module side of the connection: bytes waiting for the radio, how fast the
    // radio drains them to this client (0: the client stopped reading).
    std::string tx;
    double drain_bytes_per_s;
    double drain_credit;
    bool closing;  // NCLOSE: the rest of tx still goes out, then the connection ends
    size_t serial;  // 1 for the first client connection since power-on, 2 for the next...
};

class Gs2200m {
public:
    // Per-connection transmit buffer. No public figure: 8 KB is a guess at a
    // socket send buffer of an embedded TCP stack; small is the harsher case.
    static const size_t kConnBufferBytes = 8192;
    // From the reset line's release to the boot banner. Sony's board code
    // waits 180 ms after it before talking to the module (gs2200m.c,
    // gs2200m_initialize: up_mdelay(180)); the module is ready a little earlier.
    static const uint64_t kBootUs = 150000;

    Gs2200m();
    // Power-on: nothing configured, echo on, the boot banner pending.
    void power_on();

    // The SPI side.
    bool data_ready();
    uint8_t exchange(uint8_t mosi, uint32_t clock_hz);
    // The bytes the next WiFi_Write carries (hostlib's link-time wrapper of the
    // library's WiFi_Write calls this; see gs2200m.cpp, "write refused").
    void next_write(const void* data, uint16_t len);
    // EXT_RTC_RESET_IN (active low), driven by the MCU.
    void reset_line(bool asserted);
    bool in_reset() const { return in_reset_; }
    int resets() const { return resets_; }

    // The world around it.
    std::vector<AccessPoint> networks;
    double default_drain_bytes_per_s;  // a new client's drain rate
    // A TCP client connects to the listening server; returns its cid.
    uint8_t client_connect();
    void client_send(uint8_t cid, const std::string& bytes);
    void client_close(uint8_t cid);
    // The client's host resets the connection: the module reports it with
    // ERROR: SOCKET FAILURE <cid> (socket_failure) or DISCONNECT <cid>.
    void client_reset(uint8_t cid, bool socket_failure);
    void set_drain(uint8_t cid, double bytes_per_s);
    TcpPeer& peer(uint8_t cid);  // the newest connection on cid
    // Every client connection, also those whose cid went to a later one.
    const TcpPeer& connection(size_t serial);
    size_t connections() const { return serial_; }
    // The access point drops the node, or the module restarts on its own.
    void drop_association();
    void reboot();
    // A message nobody asked for now: a late "OK" of an earlier command.
    void late_reply() { queue_message("OK\r\n"); }
    // Time from a command to its reply (AT+WS: 13 channels x 150 ms instead).
    uint64_t reply_delay_us;
    // Commands answered ERROR (exactly these texts, without "\r\n").
    std::vector<std::string> failing_commands;
    // The next bulk write fails in the module (it answers <ESC>F, the data is lost).
    int fail_bulk_writes;
    // The next n WRITE requests get no answer (the data-ready line stays low).
    int ignore_write_requests;
    // The module hangs: it answers nothing and its data-ready line stays low
    // until its reset line is pulsed (the 20 s SPI timeouts of issue 24, 4).
    bool wedged;
    // Called with each AT command as it arrives, before the module replies
    // (a scripted scenario puts an event between a command and its reply).
    std::function<void(const std::string&)> on_command_hook;
    // Runs `action` once the virtual clock reaches at_us (between or during
    // the MCU's SPI transfers).
    void at(uint64_t at_us, std::function<void()> action);

    // What happened.
    std::vector<std::string> commands;     // AT commands, without "\r\n"
    std::vector<uint64_t> command_us;      // when each arrived
    std::vector<uint32_t> bulk_clock_hz;   // SPI clock of each bulk-data write
    std::vector<size_t> bulk_sizes;        // payload bytes of each bulk-data write
    size_t refused_writes;                 // WRITE requests answered NOK
    size_t esc_f_sent;                     // bulk writes answered <ESC>F
    bool associated() const { return associated_; }
    bool access_point() const { return mode_ == 2; }
    std::string joined_ssid() const { return joined_ssid_; }
    bool power_save() const { return power_save_; }
    bool listening() const { return server_cid_ >= 0; }
    // The WPA2 key the module holds (what its access point uses), empty: none.
    const std::vector<uint8_t>& key() const { return key_; }
    static std::vector<uint8_t> derived_key(const std::string& ssid, const std::string& passphrase);

private:
    void advance();
    void on_header(const uint8_t* h);
    bool refuse_write(uint16_t len);
    void on_payload(const std::string& payload);
    void on_bulk(const std::string& payload, uint32_t clock_hz);
    void on_command(const std::string& cmd);
    std::string answer(const std::string& cmd);
    std::string join(const std::string& args);
    std::string network_status() const;
    std::string scan() const;
    void queue_message(const std::string& text) { pending_.push_back(text); }
    void queue_header(uint8_t type, uint16_t len, uint8_t pending);
    void report_end(const std::string& msg);
    void end_client(uint8_t cid, const char* message);  // the client's side ended it  // the MCU read msg: a cid it ended is free again
    void close_cid(int cid, bool graceful);
    uint8_t free_cid() const;
    void reset_framing();

    // SPI framing state
    uint8_t header_[8];
    size_t header_len_;
    size_t payload_expected_;
    std::string payload_;
    int write_len_;  // length granted by the last WRITE response, -1 if none
    uint32_t payload_clock_hz_;
    std::string lookahead_;            // what the MCU is about to write
    std::deque<uint8_t> out_;          // bytes to clock out to the MCU
    std::deque<std::string> pending_;  // messages waiting for a READ request

    // time
    uint64_t last_us_;
    bool advancing_;
    std::multimap<uint64_t, std::function<void()>> schedule_;
    bool in_reset_;
    uint64_t boot_at_us_;  // 0: not booting
    int resets_;

    // module state
    bool echo_;
    int mode_;  // 0 station, 2 limited AP
    bool dhcp_;
    bool power_save_;
    std::string static_ip_;
    std::string key_ssid_;      // the SSID of the last AT+WPAPSK
    std::vector<uint8_t> key_;  // the WPA2 key it uses (AT+WPAPSK or AT+WPSK), empty: none
    bool associated_;
    std::string joined_ssid_;
    std::string ip_;
    int server_cid_;
    std::map<uint8_t, TcpPeer> peers_;
    std::vector<TcpPeer> retired_;  // connections whose cid was reused
    std::vector<uint8_t> unreported_;  // cids whose end the MCU has not read yet
    size_t serial_;
};

Gs2200m& module();

}  // namespace hostlib

#endif
