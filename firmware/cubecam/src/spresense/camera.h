// The Spresense camera (ISX019 HDR board) as the core's Camera: VGA JPEG
// streaming into driver buffers; the callback only swaps the latest-frame
// handle, the main loop borrows frames by lease.
#ifndef CUBECAM_SPRESENSE_CAMERA_H
#define CUBECAM_SPRESENSE_CAMERA_H

#include <Camera.h>

#include "../core/hal.h"
#include "../core/http_server.h"
#include "../core/settings.h"
#include "board.h"

namespace cubecam {
namespace spresense {

// One buffer being filled, one newest frame, one more so a client can keep
// its frame while the next one is captured. More clients on different
// frames pause capture until one lets go; nothing breaks.
const int kCameraBuffers = 3;

class SpresenseCamera : public Camera {
public:
    explicit SpresenseCamera(ArduinoClock& clock);
    // Configures and starts VGA JPEG streaming. Returns an error message
    // (a string constant) or 0.
    const char* begin(const Settings& s);
    uint32_t latest_seq();
    bool acquire_latest(Frame& out);
    void release(int lease);
private:
    static void on_frame(CamImage img);  // camera thread, 2 KB stack
    ArduinoClock& clock_;
    CamImage latest_;
    volatile uint32_t seq_;
    volatile uint32_t latest_raw_us_;
    CamImage leased_[kMaxClients];
};

}  // namespace spresense
}  // namespace cubecam

#endif
