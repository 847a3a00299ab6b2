// Wi-Fi link supervisor: join with a deadline, reconnect with backoff, and
// the LED patterns that show its state. tick() never blocks by itself; the
// only waits are inside the module calls of WifiControl.
#ifndef CUBECAM_CORE_LINK_H
#define CUBECAM_CORE_LINK_H

#include <stdint.h>

#include "hal.h"
#include "settings.h"

namespace cubecam {

const uint32_t kJoinTimeoutMs = 30000;   // also Improv's provisioning limit
const uint32_t kFirstBackoffMs = 1000;
const uint32_t kMaxBackoffMs = 60000;

enum class LinkState : uint8_t {
    Unconfigured,  // no SSID: waiting for provisioning
    Resetting,     // about to restart the module and start joining
    Joining,       // association / DHCP under way, until the join deadline
    Online,        // joined; the node serves HTTP
    Backoff        // waiting before the next attempt
};

enum class LinkEvent : uint8_t { None, Online, JoinFailed };

class LinkSupervisor {
public:
    explicit LinkSupervisor(WifiControl& wifi);
    // Use these settings; joins at once when they name a network.
    void begin(const Settings& s, uint32_t now);
    // Try other credentials now (Improv). On success they replace the current
    // ones; on failure the supervisor goes back to the previous ones.
    void try_credentials(const Settings& candidate, uint32_t now);
    // The network went away (disassociation, module reboot, write failure).
    void link_lost(uint32_t now);
    LinkEvent tick(uint32_t now);

    LinkState state() const { return state_; }
    bool trying() const { return trying_; }
    const LinkInfo& info() const { return info_; }
    const Settings& settings() const { return trying_ ? candidate_ : settings_; }
    // When the next attempt starts (valid in Backoff).
    uint32_t retry_at_ms() const { return deadline_ms_; }

private:
    void schedule_retry(uint32_t now);

    WifiControl& wifi_;
    Settings settings_;
    Settings candidate_;
    bool trying_;
    LinkState state_;
    LinkInfo info_;
    uint32_t deadline_ms_;
    uint32_t backoff_ms_;
};

const uint8_t kLedLink = 1u << 0;
const uint8_t kLedFrame = 1u << 1;
const uint8_t kLedClient = 1u << 2;
const uint8_t kLedError = 1u << 3;

// LED0: fast blink = waiting for provisioning, slow blink = joining,
//       on = online, short flash every 2 s = waiting to retry.
// LED1: toggles with every frame sent. LED2: a client is streaming.
// LED3: an error is latched (see /status last_error).
uint8_t status_leds(LinkState state, uint32_t now, uint32_t frames_sent, bool streaming, bool error);

}  // namespace cubecam

#endif
