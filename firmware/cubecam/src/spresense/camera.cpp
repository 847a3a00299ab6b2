#include "camera.h"

#include <Arduino.h>

namespace cubecam {
namespace spresense {

namespace {

// The camera callback is a plain function pointer without context.
SpresenseCamera* g_camera = 0;

CAM_VIDEO_FPS video_fps(FrameRate r) {
    switch (r) {
    case FrameRate::Fps30: return CAM_VIDEO_FPS_30;
    case FrameRate::Fps15: return CAM_VIDEO_FPS_15;
    case FrameRate::Fps7_5: return CAM_VIDEO_FPS_7_5;
    }
    return CAM_VIDEO_FPS_15;
}

// The JPEG buffer is 640*480*2/divisor bytes; a frame that does not fit is
// delivered empty. Higher quality needs a bigger buffer: 87.7 kB up to 70,
// 122.9 kB up to 85, 153.6 kB above.
int jpeg_divisor(uint8_t quality) { return quality <= 70 ? 7 : quality <= 85 ? 5 : 4; }

const char* camera_error(CamErr e) {
    switch (e) {
    case CAM_ERR_SUCCESS: return 0;
    case CAM_ERR_NO_DEVICE: return "camera: no camera board found";
    case CAM_ERR_INVALID_PARAM: return "camera: the sensor refused size, rate or quality";
    case CAM_ERR_NO_MEMORY: return "camera: not enough RAM for the frame buffers";
    default: return "camera: the driver reported an error";
    }
}

}  // namespace

SpresenseCamera::SpresenseCamera(ArduinoClock& clock) : clock_(clock), seq_(0), latest_raw_us_(0) {}

const char* SpresenseCamera::begin(const Settings& s) {
    g_camera = this;
    CamErr e = theCamera.begin(kCameraBuffers, video_fps(s.fps), CAM_IMGSIZE_VGA_H, CAM_IMGSIZE_VGA_V,
                               CAM_IMAGE_PIX_FMT_JPG, jpeg_divisor(s.jpeg_quality));
    if (e == CAM_ERR_SUCCESS) e = theCamera.setJPEGQuality(s.jpeg_quality);
    if (e == CAM_ERR_SUCCESS) e = theCamera.setHDR(static_cast<CAM_HDR_MODE>(s.hdr));
    if (e == CAM_ERR_SUCCESS) e = theCamera.startStreaming(true, on_frame);
    return camera_error(e);
}

void SpresenseCamera::on_frame(CamImage img) {
    if (!img.isAvailable()) return;  // the JPEG did not fit its buffer
    uint32_t now = ::micros();
    CamImage previous;
    noInterrupts();
    previous = g_camera->latest_;
    g_camera->latest_ = img;
    g_camera->latest_raw_us_ = now;
    g_camera->seq_ = g_camera->seq_ + 1;
    interrupts();
    // `previous` goes out of scope here: its buffer returns to the driver
    // outside the critical section (unless a client still holds it).
}

uint32_t SpresenseCamera::latest_seq() { return seq_; }

bool SpresenseCamera::acquire_latest(Frame& out) {
    for (size_t i = 0; i < kMaxClients; ++i) {
        if (leased_[i].isAvailable()) continue;
        noInterrupts();
        leased_[i] = latest_;
        uint32_t seq = seq_;
        uint32_t raw = latest_raw_us_;
        interrupts();
        if (!leased_[i].isAvailable()) return false;
        out.data = leased_[i].getImgBuff();
        out.size = static_cast<uint32_t>(leased_[i].getImgSize());
        out.seq = seq;
        out.capture_us = clock_.widen(raw);
        out.lease = static_cast<int>(i);
        return true;
    }
    return false;
}

void SpresenseCamera::release(int lease) {
    if (lease >= 0 && static_cast<size_t>(lease) < kMaxClients) leased_[lease] = CamImage();
}

}  // namespace spresense
}  // namespace cubecam
