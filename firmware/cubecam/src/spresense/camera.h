// The Spresense camera (ISX019 HDR board) as the core's Camera: VGA JPEG
// streaming into driver buffers; the callback only swaps the latest-frame
// handle, the main loop borrows frames by lease.
#ifndef CUBECAM_SPRESENSE_CAMERA_H
#define CUBECAM_SPRESENSE_CAMERA_H

#include <Camera.h>
#include <pthread.h>

#include "../core/hal.h"
#include "../core/settings.h"

namespace cubecam {
namespace spresense {

// One buffer being filled, one newest frame, one more so a client can keep
// its frame while the next one is captured. More clients on different
// frames pause capture until one lets go; nothing breaks.
const int kCameraBuffers = 3;

// A CamImage that may hold nothing. The library's CamImage copy constructor
// and assignment take a reference on the source's buffer without a null
// check (Camera.cpp, CamImage::operator= and CamImage(const CamImage&)), so
// an empty CamImage must never be copied: this one is built only from an
// image that has a buffer, and emptied by destroying it.
class HeldImage {
public:
    HeldImage() : held_(false) {}
    ~HeldImage() { drop(); }
    // Holds a reference on src's buffer (src must have one), after letting
    // go of the one held before.
    void hold(const CamImage& src);
    // Lets go; the buffer returns to the driver when nobody else holds it.
    void drop();
    bool held() const { return held_; }
    CamImage& image() { return *reinterpret_cast<CamImage*>(storage_); }

private:
    HeldImage(const HeldImage&);
    HeldImage& operator=(const HeldImage&);
    alignas(CamImage) unsigned char storage_[sizeof(CamImage)];
    bool held_;
};

class SpresenseCamera : public Camera {
public:
    SpresenseCamera();
    // Configures and starts VGA JPEG streaming. Returns an error message
    // (a string constant) or 0.
    const char* begin(const Settings& s);
    uint32_t latest_seq();
    uint32_t empty_frames();
    bool acquire_latest(Frame& out);
    void release(int lease);
    CameraRestart restart();

private:
    static void on_frame(CamImage img);  // camera thread, 2 KB stack
    void publish(const CamImage& img, uint64_t captured_us);

    Settings settings_;
    // Guards latest_, seq_ and latest_us_ between the camera thread and loop().
    // A mutex, not noInterrupts(): copying a CamImage takes the buffer's
    // semaphore, and a task must not block with interrupts off.
    pthread_mutex_t lock_;
    HeldImage latest_;
    volatile uint32_t seq_;
    volatile uint32_t empty_;  // written by the camera thread only
    uint64_t latest_us_;
    HeldImage leased_[kMaxClients];
};

}  // namespace spresense
}  // namespace cubecam

#endif
