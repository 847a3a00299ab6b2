// A scripted Telit GS2200M on the SPI5 bus, as the GS2200-WiFi library talks
// to it: the module side of the SPI framing (8-byte headers 0xA5, WRITE /
// READ requests, DATA_FROM_MCU / DATA_TO_MCU, the data-ready line), AT
// commands answered in the Telit AT guide's formats, bulk data
// (<ESC>Z<cid><4 digits><data>) to and from TCP clients, and the events a
// real module sends on its own (boot banner, CONNECT, DISCONNECT,
// disassociation). One response or event per READ request, as the library
// reads them.
#ifndef CUBECAM_HOSTLIB_GS2200M_H
#define CUBECAM_HOSTLIB_GS2200M_H

#include <stddef.h>
#include <stdint.h>

#include <deque>
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
    std::string received;  // bytes the node sent to this client
    bool open;
};

class Gs2200m {
public:
    Gs2200m();
    // Power-on: nothing configured, echo on, the boot banner pending.
    void power_on();

    // The SPI side.
    bool data_ready() const;
    uint8_t exchange(uint8_t mosi, uint32_t clock_hz);

    // The world around it.
    std::vector<AccessPoint> networks;
    // A TCP client connects to the listening server; returns its cid.
    uint8_t client_connect();
    void client_send(uint8_t cid, const std::string& bytes);
    void client_close(uint8_t cid);
    const TcpPeer& peer(uint8_t cid) const;
    // The access point drops the node, or the module restarts on its own.
    void drop_association();
    void reboot();
    // The next n WRITE requests get no answer (the data-ready line stays low).
    int ignore_write_requests;

    // What happened.
    std::vector<std::string> commands;     // AT commands, without "\r\n"
    std::vector<uint32_t> bulk_clock_hz;   // SPI clock of each bulk-data write
    std::vector<size_t> bulk_sizes;        // payload bytes of each bulk-data write
    bool associated() const { return associated_; }
    bool access_point() const { return mode_ == 2; }
    std::string joined_ssid() const { return joined_ssid_; }
    bool power_save() const { return power_save_; }
    bool listening() const { return server_cid_ >= 0; }
    // The WPA2 key the module holds (what its access point uses), empty: none.
    const std::vector<uint8_t>& key() const { return key_; }
    static std::vector<uint8_t> derived_key(const std::string& ssid, const std::string& passphrase);

private:
    void on_header(const uint8_t* h);
    void on_payload(const std::string& payload);
    void on_bulk(const std::string& payload, uint32_t clock_hz);
    void on_command(const std::string& cmd);
    std::string answer(const std::string& cmd);
    std::string join(const std::string& args);
    std::string network_status() const;
    std::string scan() const;
    void queue_message(const std::string& text) { pending_.push_back(text); }
    void queue_header(uint8_t type, uint16_t len, uint8_t pending);
    void close_cid(int cid);
    uint8_t free_cid() const;

    // SPI framing state
    uint8_t header_[8];
    size_t header_len_;
    size_t payload_expected_;
    std::string payload_;
    int write_len_;  // length granted by the last WRITE response, -1 if none
    uint32_t payload_clock_hz_;
    std::deque<uint8_t> out_;        // bytes to clock out to the MCU
    std::deque<std::string> pending_;  // messages waiting for a READ request

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
};

Gs2200m& module();

}  // namespace hostlib

#endif
