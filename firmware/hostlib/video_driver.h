// The NuttX video driver of the ISX019 camera (/dev/video) as the real Camera
// library (libraries/Camera/Camera.cpp) uses it: user-pointer buffers queued
// with VIDIOC_QBUF and handed back filled by a blocking VIDIOC_DQBUF, in ring
// mode; the test plays the sensor with capture(). A buffer the library gives
// back to the driver is overwritten at once (the sensor may fill it any time),
// so a frame still sent after its buffer went back shows up as garbage.
#ifndef CUBECAM_HOSTLIB_VIDEO_DRIVER_H
#define CUBECAM_HOSTLIB_VIDEO_DRIVER_H

#include <stddef.h>
#include <stdint.h>

#include <condition_variable>
#include <deque>
#include <mutex>
#include <vector>

namespace hostlib {

class VideoDriver {
public:
    void power_on();
    bool sensor_present;

    // The sensor delivers a frame: copied into the oldest queued buffer.
    // False when no buffer was queued (the frame is lost, as on the board).
    bool capture(const std::vector<uint8_t>& jpeg);
    // Buffers the driver holds, ready to be filled.
    size_t queued_buffers();
    // Waits (real time, at most timeout_ms) until DQBUF took every filled buffer.
    bool wait_delivered(int timeout_ms);

    bool streaming();
    int jpeg_quality();
    int hdr_mode();
    int opens();

    // The driver side: open(), ioctl() and close() of Camera.cpp.
    int open_device(const char* path);
    int close_device(int fd);
    int control(int fd, int req, unsigned long arg);

private:
    struct Buffer {
        uint32_t index;
        uint8_t* data;
        uint32_t length;
        uint32_t bytesused;
        uint16_t flags;
    };

    std::mutex mutex_;
    std::condition_variable changed_;
    std::deque<Buffer> queued_;
    std::deque<Buffer> filled_;
    bool open_;
    bool streaming_;
    bool cancel_;
    int opens_;
    int jpeg_quality_;
    int hdr_;
};

VideoDriver& video_driver();

}  // namespace hostlib

#endif
