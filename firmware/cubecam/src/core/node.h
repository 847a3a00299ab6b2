// The camera node: wires settings, link supervisor, HTTP server, Improv and
// the console to the hardware interfaces. setup() calls boot() once; loop()
// calls loop() forever. Nothing here blocks except the module calls of
// WifiControl and the Improv network scan.
#ifndef CUBECAM_CORE_NODE_H
#define CUBECAM_CORE_NODE_H

#include <stddef.h>
#include <stdint.h>

#include "console.h"
#include "hal.h"
#include "http_server.h"
#include "improv.h"
#include "link.h"
#include "settings.h"
#include "text.h"

namespace cubecam {

extern const char kFirmwareName[];
extern const char kFirmwareVersion[];

struct Hardware {
    Camera& camera;
    Network& network;
    WifiControl& wifi;
    SerialPort& serial;
    SettingsStorage& storage;
    Clock& clock;
    Leds& leds;
    System& system;
    const char* chip;  // Improv device info, e.g. "CXD5602"
};

const uint16_t kFrameWidth = 640;
const uint16_t kFrameHeight = 480;
const uint32_t kRebootDelayMs = 100;   // lets "OK" leave the UART first
const uint32_t kFpsWindowMs = 2000;
// A camera that delivered frames and then none for this long is restarted
// (37 frame periods at 7.5 fps); after this many restarts in a row without a
// frame the node gives up and latches an error.
const uint32_t kCameraStallMs = 5000;
const uint8_t kMaxCameraRestarts = 3;
// Serial input taken per loop pass, in reads of 64 bytes: 512 bytes, more
// than an Improv frame (a Wi-Fi RPC is at most 106 bytes) or a console line.
const int kSerialChunksPerPass = 8;
// This many frames in a row that arrived empty (the JPEG overflowed its
// buffer) latch an error and restart the camera once.
const uint32_t kEmptyFrameRun = 10;

class Node : private ConsoleHost, private LineSink {
public:
    explicit Node(const Hardware& hw);
    // Loads the settings (defaults when missing or corrupt), prints them with
    // the password masked and starts the link.
    void boot();
    // One pass of the main loop. Returns true when I/O progressed, so a host
    // build may call again at once instead of sleeping.
    bool loop();
    // The settings this boot runs with (the camera is configured from them).
    const Settings& running() const { return running_; }
    // Latch an error for /status and LED3 (a string constant).
    void set_error(const char* message);
    // Log line "[<level>][<tag>] <text>".
    void log(char level, const char* tag, const char* text);

private:
    // ConsoleHost
    Settings& edited_settings();
    bool save_settings();
    bool factory_reset();
    void request_reboot();
    void report_status(LineSink& out);
    // LineSink (console answers)
    void line(const char* text);

    void pump_serial(uint32_t now);
    void feed_serial(const uint8_t* in, size_t n, uint32_t now);
    void feed_console(const uint8_t* bytes, size_t n);
    void on_improv_frame();
    void on_wifi_settings(const improv::Rpc& rpc);
    void on_name_rpc(const improv::Rpc& rpc, improv::Error invalid);
    void send_improv(improv::FrameType type, const uint8_t* data, size_t len);
    void send_state();
    void send_error(improv::Error e);
    void send_result(improv::Command cmd, const improv::Text* strings, size_t count);
    improv::State improv_state() const;
    void write_url(TextBuf& out) const;
    void on_link_event(LinkEvent ev, uint32_t now);
    void drop_network();
    void measure_fps(uint32_t now);
    void watch_camera(uint32_t now);
    void watch_empty_frames();
    NodeStatus status() const;

    Hardware hw_;
    Settings running_;
    Settings edited_;
    LinkSupervisor link_;
    HttpServer server_;
    Console console_;
    improv::Framer framer_;
    bool at_line_start_;
    bool provisioning_;
    uint16_t bound_port_;
    const char* last_error_;
    bool reboot_pending_;
    uint32_t reboot_at_ms_;
    uint32_t fps_window_start_ms_;
    uint32_t fps_window_seq_;
    uint32_t fps_measured_milli_;
    uint32_t camera_seq_;
    uint32_t camera_seen_ms_;
    uint8_t camera_restarts_;
    uint32_t camera_empty_;      // empty frames seen so far
    uint32_t empty_run_;         // of them since the last whole frame
    bool empty_restart_done_;    // the one restart a run of them gets
    uint8_t leds_;
};

}  // namespace cubecam

#endif
