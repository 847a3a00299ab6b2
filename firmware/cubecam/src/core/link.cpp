#include "link.h"

#include <string.h>

namespace cubecam {

LinkSupervisor::LinkSupervisor(WifiControl& wifi)
    : wifi_(wifi), trying_(false), state_(LinkState::Unconfigured), deadline_ms_(0), backoff_ms_(kFirstBackoffMs) {
    settings_defaults(settings_);
    settings_defaults(candidate_);
    memset(&info_, 0, sizeof info_);
}

void LinkSupervisor::begin(const Settings& s, uint32_t now) {
    settings_ = s;
    trying_ = false;
    backoff_ms_ = kFirstBackoffMs;
    state_ = s.ssid[0] ? LinkState::Resetting : LinkState::Unconfigured;
    deadline_ms_ = now;
}

void LinkSupervisor::try_credentials(const Settings& candidate, uint32_t now) {
    candidate_ = candidate;
    trying_ = true;
    state_ = LinkState::Resetting;
    deadline_ms_ = now;
}

void LinkSupervisor::link_lost(uint32_t now) {
    memset(&info_, 0, sizeof info_);
    if (state_ == LinkState::Online) schedule_retry(now);
}

void LinkSupervisor::schedule_retry(uint32_t now) {
    if (!settings_.ssid[0]) {
        state_ = LinkState::Unconfigured;
        return;
    }
    state_ = LinkState::Backoff;
    deadline_ms_ = now + backoff_ms_;
    backoff_ms_ = backoff_ms_ * 2 > kMaxBackoffMs ? kMaxBackoffMs : backoff_ms_ * 2;
}

LinkEvent LinkSupervisor::tick(uint32_t now) {
    switch (state_) {
    case LinkState::Unconfigured:
    case LinkState::Online:
        return LinkEvent::None;
    case LinkState::Backoff:
        if (deadline_reached(now, deadline_ms_)) state_ = LinkState::Resetting;
        return LinkEvent::None;
    case LinkState::Resetting:
        if (wifi_.reset_module() && wifi_.start_join(settings())) {
            state_ = LinkState::Joining;
            deadline_ms_ = now + kJoinTimeoutMs;
            return LinkEvent::None;
        }
        break;
    case LinkState::Joining: {
        JoinStatus st = wifi_.join_status(info_);
        if (st == JoinStatus::Joined) {
            if (trying_) settings_ = candidate_;
            trying_ = false;
            state_ = LinkState::Online;
            backoff_ms_ = kFirstBackoffMs;
            return LinkEvent::Online;
        }
        if (st == JoinStatus::Pending && !deadline_reached(now, deadline_ms_)) return LinkEvent::None;
        break;
    }
    }
    // The attempt failed: a trial falls back to the stored credentials.
    if (trying_) backoff_ms_ = kFirstBackoffMs;
    trying_ = false;
    schedule_retry(now);
    return LinkEvent::JoinFailed;
}

uint8_t status_leds(LinkState state, uint32_t now, uint32_t frames_sent, bool streaming, bool error) {
    bool link = false;
    switch (state) {
    case LinkState::Unconfigured: link = (now / 125) % 2 == 0; break;
    case LinkState::Resetting:
    case LinkState::Joining: link = (now / 500) % 2 == 0; break;
    case LinkState::Online: link = true; break;
    case LinkState::Backoff: link = now % 2000 < 100; break;
    }
    uint8_t mask = 0;
    if (link) mask |= kLedLink;
    if (frames_sent & 1u) mask |= kLedFrame;
    if (streaming) mask |= kLedClient;
    if (error) mask |= kLedError;
    return mask;
}

}  // namespace cubecam
