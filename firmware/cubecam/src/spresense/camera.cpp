#include "camera.h"

#include <Arduino.h>

#include <new>

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

// The JPEG buffer is 640*480*2/divisor bytes (ImgBuff::calc_img_size in
// Camera.cpp); a frame that does not fit is delivered empty (counted in
// /status). Sized for the worst frame at each quality: VGA noise, which no
// scene exceeds, encoded 4:2:2 by libjpeg is 190.8 kB at quality 60 and
// 272.5 kB at 80 (the ISX019's encoder is assumed no larger at the same
// number; docs/firmware.md, "Camera buffers"). So 204.8 kB up to 60 and
// 307.2 kB above: 3 x 307.2 = 921.6 kB of the 1536 KB MainCore RAM. Above 80
// a frame of noise-like detail can still overflow: a divisor of 1 (614.4 kB)
// times 3 buffers does not fit.
int jpeg_divisor(uint8_t quality) { return quality <= 60 ? 3 : 2; }

const char* camera_error(CamErr e) {
    switch (e) {
    case CAM_ERR_SUCCESS: return 0;
    case CAM_ERR_NO_DEVICE: return "camera: no camera board found";
    case CAM_ERR_INVALID_PARAM: return "camera: the sensor refused size, rate or quality";
    case CAM_ERR_NO_MEMORY: return "camera: not enough RAM for the frame buffers";
    default: return "camera: the driver reported an error";
    }
}

class Locked {
public:
    explicit Locked(pthread_mutex_t& m) : m_(m) { pthread_mutex_lock(&m_); }
    ~Locked() { pthread_mutex_unlock(&m_); }
private:
    pthread_mutex_t& m_;
};

}  // namespace

void HeldImage::hold(const CamImage& src) {
    drop();
    new (storage_) CamImage(src);
    held_ = true;
}

void HeldImage::drop() {
    if (!held_) return;
    held_ = false;
    image().~CamImage();
}

SpresenseCamera::SpresenseCamera() : seq_(0), empty_(0), latest_us_(0) {
    settings_defaults(settings_);
    pthread_mutex_init(&lock_, 0);
}

const char* SpresenseCamera::begin(const Settings& s) {
    settings_ = s;
    g_camera = this;
    CamErr e = theCamera.begin(kCameraBuffers, video_fps(s.fps), CAM_IMGSIZE_VGA_H, CAM_IMGSIZE_VGA_V,
                               CAM_IMAGE_PIX_FMT_JPG, jpeg_divisor(s.jpeg_quality));
    if (e == CAM_ERR_SUCCESS) e = theCamera.setJPEGQuality(s.jpeg_quality);
    if (e == CAM_ERR_SUCCESS) e = theCamera.setHDR(static_cast<CAM_HDR_MODE>(s.hdr));
    if (e == CAM_ERR_SUCCESS) e = theCamera.startStreaming(true, on_frame);
    return camera_error(e);
}

void SpresenseCamera::on_frame(CamImage img) {
    if (!img.isAvailable()) {
        // The driver flags a JPEG that did not fit its buffer and the library
        // hands it over with size 0 (Camera.cpp); counted, nothing published.
        g_camera->empty_ = g_camera->empty_ + 1;
        return;
    }
    g_camera->publish(img, ::micros());
}

void SpresenseCamera::publish(const CamImage& img, uint64_t captured_us) {
    // The frame it replaces goes back to the driver when `previous` goes out
    // of scope, after the lock (unless a client still holds it).
    HeldImage previous;
    Locked lock(lock_);
    if (latest_.held()) previous.hold(latest_.image());
    latest_.hold(img);
    latest_us_ = captured_us;
    seq_ = seq_ + 1;
}

uint32_t SpresenseCamera::latest_seq() { return seq_; }

uint32_t SpresenseCamera::empty_frames() { return empty_; }

bool SpresenseCamera::acquire_latest(Frame& out) {
    for (size_t i = 0; i < kMaxClients; ++i) {
        HeldImage& lease = leased_[i];
        if (lease.held()) continue;
        {
            Locked lock(lock_);
            if (!latest_.held()) return false;
            lease.hold(latest_.image());
            out.seq = seq_;
            out.capture_us = latest_us_;
        }
        out.data = lease.image().getImgBuff();
        out.size = static_cast<uint32_t>(lease.image().getImgSize());
        out.lease = static_cast<int>(i);
        return true;
    }
    return false;
}

void SpresenseCamera::release(int lease) {
    if (lease >= 0 && static_cast<size_t>(lease) < kMaxClients) leased_[lease].drop();
}

CameraRestart SpresenseCamera::restart() {
    for (size_t i = 0; i < kMaxClients; ++i) {
        if (leased_[i].held()) return CameraRestart::Busy;
    }
    // No callback runs once streaming is off; then nothing of ours refers to
    // the library's buffers, which end() deletes whatever their references.
    theCamera.startStreaming(false, 0);
    {
        Locked lock(lock_);
        latest_.drop();
    }
    theCamera.end();
    return begin(settings_) ? CameraRestart::Failed : CameraRestart::Done;
}

}  // namespace spresense
}  // namespace cubecam
