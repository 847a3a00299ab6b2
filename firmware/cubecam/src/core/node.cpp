#include "node.h"

#include <string.h>

namespace cubecam {

const char kFirmwareName[] = "cubecam";
const char kFirmwareVersion[] = "0.1.0";

namespace {

const char* link_state_name(LinkState s) {
    switch (s) {
    case LinkState::Unconfigured: return "unconfigured";
    case LinkState::Resetting: return "resetting";
    case LinkState::Joining: return "joining";
    case LinkState::Online: return "online";
    case LinkState::Backoff: return "backoff";
    }
    return "?";
}

improv::Text text_of(const char* s) {
    improv::Text t = {s, strlen(s)};
    return t;
}

// Sends the line built so far and starts the next one.
void emit(LineSink& out, TextBuf& t) {
    out.line(t.c_str());
    t.clear();
}


}  // namespace

Node::Node(const Hardware& hw)
    : hw_(hw),
      link_(hw.wifi),
      server_(hw.network, hw.camera, hw.clock),
      console_(*this, *this),
      at_line_start_(true),
      provisioning_(false),
      bound_port_(0),
      last_error_(""),
      reboot_pending_(false),
      reboot_at_ms_(0),
      fps_window_start_ms_(0),
      fps_window_seq_(0),
      fps_measured_milli_(0),
      camera_seq_(0),
      camera_seen_ms_(0),
      camera_restarts_(0),
      camera_empty_(0),
      empty_run_(0),
      empty_restart_done_(false),
      leds_(0xFF) {
    settings_defaults(running_);
    edited_ = running_;
}

void Node::log(char level, const char* tag, const char* text) {
    char buf[200];
    TextBuf t(buf, sizeof buf);
    t.add('[').add(level).add("][").add(tag).add("] ").add(text).add('\n');
    hw_.serial.write(reinterpret_cast<const uint8_t*>(t.c_str()), t.size());
}

void Node::line(const char* text) {
    hw_.serial.write(reinterpret_cast<const uint8_t*>(text), strlen(text));
    hw_.serial.write(reinterpret_cast<const uint8_t*>("\n"), 1);
}

void Node::set_error(const char* message) {
    last_error_ = message;
    log('E', "node", message);
}

void Node::boot() {
    uint8_t rec[kSettingsRecordSize];
    char buf[180];
    TextBuf t(buf, sizeof buf);
    t.add(kFirmwareName).add(' ').add(kFirmwareVersion).add(" on ").add(hw_.chip);
    log('I', "boot", t.c_str());
    if (!hw_.storage.load(rec, sizeof rec) || !settings_decode(rec, sizeof rec, running_)) {
        settings_defaults(running_);
        log('W', "config", "no valid settings record; using factory defaults");
    }
    edited_ = running_;
    for (size_t i = 0; i < kSettingCount; ++i) {
        t.clear();
        t.add(kSettingFields[i].key).add('=');
        settings_get(running_, kSettingFields[i].key, t);
        log('I', "config", t.c_str());
    }
    uint32_t now = hw_.clock.millis();
    fps_window_start_ms_ = now;
    camera_seen_ms_ = now;
    link_.begin(running_, now);
    if (link_.state() == LinkState::Unconfigured) {
        log('I', "link", "no network configured; waiting for Improv or the console");
    }
}

bool Node::loop() {
    hw_.system.kick_watchdog();
    uint32_t now = hw_.clock.millis();
    pump_serial(now);
    LinkEvent ev = link_.tick(now);
    if (ev != LinkEvent::None) on_link_event(ev, hw_.clock.millis());
    bool progressed = false;
    if (link_.state() == LinkState::Online) {
        ServeResult r = server_.serve(status());
        progressed = r.progressed;
        if (r.link_lost) {
            log('W', "link", "network lost; reconnecting");
            drop_network();
            link_.link_lost(now);
        }
    }
    measure_fps(now);
    watch_camera(now);
    uint8_t leds = status_leds(link_.state(), now, server_.frames_sent(), server_.streaming_count() > 0,
                               last_error_[0] != '\0');
    if (leds != leds_) {
        leds_ = leds;
        hw_.leds.show(leds);
    }
    if (reboot_pending_ && deadline_reached(now, reboot_at_ms_)) {
        reboot_pending_ = false;
        hw_.system.reboot();
    }
    return progressed;
}

void Node::drop_network() {
    server_.drop_all();
    hw_.network.close_all();
    bound_port_ = 0;
}

void Node::measure_fps(uint32_t now) {
    uint32_t elapsed = now - fps_window_start_ms_;
    if (elapsed < kFpsWindowMs) return;
    uint32_t seq = hw_.camera.latest_seq();
    fps_measured_milli_ = static_cast<uint32_t>(static_cast<uint64_t>(seq - fps_window_seq_) * 1000000u / elapsed);
    fps_window_seq_ = seq;
    fps_window_start_ms_ = now;
}

void Node::watch_camera(uint32_t now) {
    watch_empty_frames();
    uint32_t seq = hw_.camera.latest_seq();
    if (seq != camera_seq_) {
        camera_seq_ = seq;
        camera_seen_ms_ = now;
        camera_restarts_ = 0;
        return;
    }
    if (seq == 0 || camera_restarts_ >= kMaxCameraRestarts || !deadline_reached(now, camera_seen_ms_ + kCameraStallMs)) return;
    CameraRestart r = hw_.camera.restart();
    if (r == CameraRestart::Busy) return;  // a client still sends the last frame
    camera_seen_ms_ = now;
    if (r == CameraRestart::Failed) {
        camera_restarts_ = kMaxCameraRestarts;
        set_error("camera: no frames, and it did not start again");
        return;
    }
    if (++camera_restarts_ == kMaxCameraRestarts) {
        set_error("camera: no frames after 3 restarts");
        return;
    }
    log('W', "camera", "no frame for 5 s; camera restarted");
}

void Node::watch_empty_frames() {
    uint32_t empty = hw_.camera.empty_frames();
    if (hw_.camera.latest_seq() != camera_seq_) empty_run_ = 0;  // a whole frame came since
    empty_run_ += empty - camera_empty_;
    camera_empty_ = empty;
    if (empty_run_ < kEmptyFrameRun || empty_restart_done_) return;
    CameraRestart r = hw_.camera.restart();
    if (r == CameraRestart::Busy) return;  // a client still sends the last whole frame
    empty_restart_done_ = true;
    empty_run_ = 0;
    set_error(r == CameraRestart::Failed ? "camera: frames overflow the JPEG buffer, and it did not start again"
                                         : "camera: frames overflow the JPEG buffer (lower jpeg_quality); restarted");
}

NodeStatus Node::status() const {
    NodeStatus st;
    st.name = running_.name;
    st.firmware_version = kFirmwareVersion;
    memcpy(st.ip, link_.info().ip, 4);
    st.rssi = link_.info().rssi;
    st.fps_tenths = frame_rate_tenths(running_.fps);
    st.fps_measured_milli = fps_measured_milli_;
    st.jpeg_quality = running_.jpeg_quality;
    st.width = kFrameWidth;
    st.height = kFrameHeight;
    st.last_error = last_error_;
    st.frames_empty = hw_.camera.empty_frames();
    return st;
}

void Node::write_url(TextBuf& out) const {
    out.add("http://").add_ipv4(link_.info().ip);
    if (bound_port_ != 80) out.add(':').add_uint(bound_port_);
    out.add('/');
}

void Node::on_link_event(LinkEvent ev, uint32_t now) {
    char buf[96];
    TextBuf t(buf, sizeof buf);
    if (ev == LinkEvent::JoinFailed) {
        t.add("could not join '").add(link_.settings().ssid).add("'; next try in ");
        t.add_uint(link_.state() == LinkState::Backoff ? link_.retry_at_ms() - now : 0).add(" ms");
        log('W', "link", t.c_str());
        if (provisioning_) {
            provisioning_ = false;
            send_error(improv::Error::UnableToConnect);
            send_state();
        }
        return;
    }
    bound_port_ = hw_.network.open_server(running_.port);
    if (bound_port_ == 0) {
        set_error("could not open the HTTP server");
        link_.link_lost(now);
        return;
    }
    t.add("listening on ");
    write_url(t);
    log('I', "http", t.c_str());
    if (!provisioning_) return;
    provisioning_ = false;
    // Keep the new credentials, both for this boot and in flash.
    memcpy(running_.ssid, link_.settings().ssid, sizeof running_.ssid);
    memcpy(running_.password, link_.settings().password, sizeof running_.password);
    running_.mode = WifiMode::Station;
    memcpy(edited_.ssid, running_.ssid, sizeof edited_.ssid);
    memcpy(edited_.password, running_.password, sizeof edited_.password);
    edited_.mode = running_.mode;
    uint8_t rec[kSettingsRecordSize];
    settings_encode(running_, rec);
    if (!hw_.storage.store(rec, sizeof rec)) set_error("could not write the settings to flash");
    send_state();
    t.clear();
    write_url(t);
    improv::Text url = {t.c_str(), t.size()};
    send_result(improv::Command::WifiSettings, &url, 1);
}

// ---- serial: Improv frames at the start of a line, console otherwise ----

void Node::pump_serial(uint32_t now) {
    uint8_t in[64];
    size_t n = hw_.serial.read(in, sizeof in);
    // A frame stalls only if no byte came: bytes that waited in the UART while
    // the loop was blocked (a join step) continue it.
    if (n == 0 && framer_.expired(now)) {
        // A slow human typing "I..." is console input; a stalled frame is dropped.
        if (framer_.in_magic()) feed_console(framer_.held(), framer_.held_len());
        framer_.reset();
    }
    for (int chunk = 1; n > 0; ++chunk) {
        feed_serial(in, n, now);
        n = chunk < kSerialChunksPerPass ? hw_.serial.read(in, sizeof in) : 0;
    }
}

void Node::feed_serial(const uint8_t* in, size_t n, uint32_t now) {
    for (size_t i = 0; i < n; ++i) {
        uint8_t b = in[i];
        if (framer_.held_len() == 0 && !(at_line_start_ && b == 'I')) {
            feed_console(&b, 1);
            continue;
        }
        switch (framer_.feed(b, now)) {
        case improv::Framer::Result::NeedMore:
            break;
        case improv::Framer::Result::Frame:
            on_improv_frame();
            framer_.reset();
            at_line_start_ = true;
            break;
        case improv::Framer::Result::BadChecksum:
            send_error(improv::Error::InvalidRpc);
            at_line_start_ = true;
            break;
        case improv::Framer::Result::NotImprov:
            feed_console(framer_.held(), framer_.held_len());
            framer_.reset();
            break;
        }
    }
}

void Node::feed_console(const uint8_t* bytes, size_t n) {
    for (size_t i = 0; i < n; ++i) {
        console_.feed(bytes[i]);
        at_line_start_ = bytes[i] == '\n' || bytes[i] == '\r';
    }
}

void Node::send_improv(improv::FrameType type, const uint8_t* data, size_t len) {
    uint8_t frame[improv::kMaxFrame + 1];
    size_t n = improv::encode_frame(type, data, len, frame);
    if (n == 0) return;
    frame[n++] = '\n';  // as ESPHome does, so the next frame or log starts a line
    hw_.serial.write(frame, n);
}

void Node::send_state() {
    uint8_t s = static_cast<uint8_t>(improv_state());
    send_improv(improv::FrameType::CurrentState, &s, 1);
}

void Node::send_error(improv::Error e) {
    uint8_t v = static_cast<uint8_t>(e);
    send_improv(improv::FrameType::ErrorState, &v, 1);
}

void Node::send_result(improv::Command cmd, const improv::Text* strings, size_t count) {
    uint8_t data[improv::kMaxData];
    size_t n = improv::encode_rpc_result(cmd, strings, count, data);
    if (n > 0) send_improv(improv::FrameType::RpcResult, data, n);
}

improv::State Node::improv_state() const {
    if (provisioning_) return improv::State::Provisioning;
    if (link_.state() == LinkState::Online) return improv::State::Provisioned;
    return improv::State::Authorized;
}

void Node::on_improv_frame() {
    improv::Rpc rpc;
    if (framer_.type() != improv::FrameType::Rpc) return;  // only a device sends the other types
    if (!improv::decode_rpc(framer_.data(), framer_.data_len(), rpc)) {
        send_error(improv::Error::InvalidRpc);
        return;
    }
    switch (rpc.command) {
    case improv::Command::WifiSettings:
        on_wifi_settings(rpc);
        return;
    case improv::Command::GetCurrentState: {
        send_state();
        if (improv_state() != improv::State::Provisioned) return;
        char buf[40];
        TextBuf t(buf, sizeof buf);
        write_url(t);
        improv::Text url = {t.c_str(), t.size()};
        send_result(improv::Command::GetCurrentState, &url, 1);
        return;
    }
    case improv::Command::GetDeviceInfo: {
        improv::Text info[4] = {text_of(kFirmwareName), text_of(kFirmwareVersion), text_of(hw_.chip),
                                text_of(running_.name)};
        send_result(improv::Command::GetDeviceInfo, info, 4);
        return;
    }
    case improv::Command::GetWifiNetworks: {
        if (server_.client_count() > 0) {
            // AT+WS holds the module for seconds: every stream would stall.
            log('W', "improv", "no Wi-Fi scan while HTTP clients are connected; answering an empty list");
            send_result(improv::Command::GetWifiNetworks, 0, 0);
            return;
        }
        ScanEntry found[12];
        size_t count = hw_.wifi.scan(found, sizeof found / sizeof found[0]);
        for (size_t i = 0; i < count; ++i) {
            char rssi[8];
            TextBuf r(rssi, sizeof rssi);
            r.add_int(found[i].rssi);
            found[i].ssid[kMaxSsid] = '\0';
            improv::Text entry[3] = {text_of(found[i].ssid), text_of(rssi), text_of(found[i].secured ? "YES" : "NO")};
            send_result(improv::Command::GetWifiNetworks, entry, 3);
        }
        send_result(improv::Command::GetWifiNetworks, 0, 0);
        return;
    }
    case improv::Command::Hostname:
        on_name_rpc(rpc, improv::Error::BadHostname);
        return;
    case improv::Command::DeviceName:
        on_name_rpc(rpc, improv::Error::InvalidRpc);
        return;
    }
    send_error(improv::Error::UnknownRpc);
}

void Node::on_wifi_settings(const improv::Rpc& rpc) {
    improv::Text creds[2];
    if (!improv::decode_strings(rpc.payload, rpc.payload_len, creds, 2) || creds[0].len == 0) {
        log('E', "improv", "Wi-Fi settings RPC is malformed");
        send_error(improv::Error::InvalidRpc);
        return;
    }
    SettingResult r = validate_ssid(creds[0].data, creds[0].len);
    if (r.ok() && creds[1].len > 0) r = validate_passphrase(creds[1].data, creds[1].len);
    if (!r.ok()) {
        log('E', "improv", r.message);
        send_error(improv::Error::InvalidRpc);
        return;
    }
    Settings candidate = running_;
    memcpy(candidate.ssid, creds[0].data, creds[0].len);
    candidate.ssid[creds[0].len] = '\0';
    memcpy(candidate.password, creds[1].data, creds[1].len);
    candidate.password[creds[1].len] = '\0';
    candidate.mode = WifiMode::Station;
    uint32_t now = hw_.clock.millis();
    drop_network();
    provisioning_ = true;
    send_state();
    link_.try_credentials(candidate, now);
}

void Node::on_name_rpc(const improv::Rpc& rpc, improv::Error invalid) {
    improv::Text name;
    if (rpc.payload_len > 0) {
        if (!improv::decode_strings(rpc.payload, rpc.payload_len, &name, 1) ||
            !settings_set(edited_, "name", name.data, name.len).ok()) {
            send_error(invalid);
            return;
        }
        memcpy(running_.name, edited_.name, sizeof running_.name);
        if (!save_settings()) set_error("could not write the settings to flash");
    }
    improv::Text current = text_of(running_.name);
    send_result(rpc.command, &current, 1);
}

// ---- console host ----

Settings& Node::edited_settings() { return edited_; }

bool Node::save_settings() {
    uint8_t rec[kSettingsRecordSize];
    settings_encode(edited_, rec);
    return hw_.storage.store(rec, sizeof rec);
}

bool Node::factory_reset() {
    settings_defaults(edited_);
    return save_settings();
}

void Node::request_reboot() {
    reboot_pending_ = true;
    reboot_at_ms_ = hw_.clock.millis() + kRebootDelayMs;
}

void Node::report_status(LineSink& out) {
    char buf[96];
    TextBuf t(buf, sizeof buf);
    NodeStatus st = status();
    emit(out, t.add("name=").add(st.name));
    emit(out, t.add("firmware=").add(kFirmwareName).add(' ').add(kFirmwareVersion));
    emit(out, t.add("link=").add(link_state_name(link_.state())));
    emit(out, t.add("ssid=").add(link_.settings().ssid));
    emit(out, t.add("ip=").add_ipv4(st.ip));
    t.add("url=");
    if (bound_port_ != 0) write_url(t);
    emit(out, t);
    emit(out, t.add("rssi=").add_int(st.rssi));
    emit(out, t.add("uptime_ms=").add_uint(hw_.clock.micros() / 1000));
    emit(out, t.add("fps=").add_fixed(st.fps_tenths, 1).add(" measured=").add_fixed(st.fps_measured_milli, 3));
    emit(out, t.add("clients=").add_uint(server_.streaming_count()).add(" frames_sent=").add_uint(server_.frames_sent())
                  .add(" frames_dropped=").add_uint(server_.frames_dropped()));
    emit(out, t.add("last_error=").add(st.last_error));
}

}  // namespace cubecam
