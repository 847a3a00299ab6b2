#include "video_driver.h"

#include <chrono>
#include <map>
#include <memory>
#include <string>

// The names Camera.cpp calls (open, ioctl, mq_send, pthread_create...) are
// the ones defined here.
#include "camera_prelude.h"

#include <arch/board/cxd56_imageproc.h>
#include <arch/chip/cisif.h>
#include <nuttx/video/isx012.h>
#include <nuttx/video/isx019.h>
#include <nuttx/video/video.h>
#include <string.h>

#include "hostlib.h"

#undef pthread_create
#undef pthread_attr_t

namespace hostlib {

namespace {

const int kVideoFd = 42;
const uint8_t kOverwritten = 0xEE;

int fail(int err) {
    errno = err;
    return -1;
}

// Named message queues of NuttX, within the process.
struct MessageQueue {
    std::mutex mutex;
    std::condition_variable changed;
    std::deque<std::string> messages;
    size_t max_messages = 1;
};

std::map<std::string, std::unique_ptr<MessageQueue>>& queues() {
    static std::map<std::string, std::unique_ptr<MessageQueue>> q;
    return q;
}

std::vector<MessageQueue*>& descriptors() {
    static std::vector<MessageQueue*> d;
    return d;
}

}  // namespace

void VideoDriver::power_on() {
    std::lock_guard<std::mutex> lock(mutex_);
    sensor_present = true;
    queued_.clear();
    filled_.clear();
    open_ = false;
    streaming_ = false;
    cancel_ = false;
    opens_ = 0;
    jpeg_quality_ = -1;
    hdr_ = -1;
}

bool VideoDriver::capture(const std::vector<uint8_t>& jpeg) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!streaming_ || queued_.empty()) return false;
    Buffer b = queued_.front();
    queued_.pop_front();
    if (jpeg.size() <= b.length) {
        memcpy(b.data, jpeg.data(), jpeg.size());
        b.bytesused = static_cast<uint32_t>(jpeg.size());
        b.flags = 0;
    } else {
        b.bytesused = 0;  // the JPEG did not fit the buffer
        b.flags = V4L2_BUF_FLAG_ERROR;
    }
    filled_.push_back(b);
    changed_.notify_all();
    return true;
}

size_t VideoDriver::queued_buffers() {
    std::lock_guard<std::mutex> lock(mutex_);
    return queued_.size();
}

bool VideoDriver::wait_delivered(int timeout_ms) {
    std::unique_lock<std::mutex> lock(mutex_);
    return changed_.wait_for(lock, std::chrono::milliseconds(timeout_ms), [this] { return filled_.empty(); });
}

bool VideoDriver::streaming() {
    std::lock_guard<std::mutex> lock(mutex_);
    return streaming_;
}

int VideoDriver::jpeg_quality() {
    std::lock_guard<std::mutex> lock(mutex_);
    return jpeg_quality_;
}

int VideoDriver::hdr_mode() {
    std::lock_guard<std::mutex> lock(mutex_);
    return hdr_;
}

int VideoDriver::opens() {
    std::lock_guard<std::mutex> lock(mutex_);
    return opens_;
}

int VideoDriver::open_device(const char* path) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (strcmp(path, "/dev/video") != 0) return fail(ENOENT);
    if (!sensor_present) return fail(ENODEV);
    if (open_) return fail(EBUSY);
    open_ = true;
    ++opens_;
    return kVideoFd;
}

int VideoDriver::close_device(int fd) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (fd != kVideoFd || !open_) return fail(EBADF);
    open_ = false;
    streaming_ = false;
    queued_.clear();
    filled_.clear();
    return 0;
}

int VideoDriver::control(int fd, int req, unsigned long arg) {
    std::unique_lock<std::mutex> lock(mutex_);
    if (fd != kVideoFd || !open_) return fail(EBADF);
    switch (req) {
    case VIDIOC_REQBUFS:
    case VIDIOC_S_FMT:
        return 0;
    case VIDIOC_S_PARM: {
        // The ISX019 runs at 30, 15 and 7.5 fps (and 60 / 120 at smaller sizes).
        const v4l2_streamparm* p = reinterpret_cast<const v4l2_streamparm*>(arg);
        uint32_t tenths = p->parm.capture.timeperframe.denominator * 10 / p->parm.capture.timeperframe.numerator;
        return tenths == 300 || tenths == 150 || tenths == 75 ? 0 : fail(EINVAL);
    }
    case VIDIOC_QBUF: {
        const v4l2_buffer* b = reinterpret_cast<const v4l2_buffer*>(arg);
        for (const Buffer& q : queued_) {
            if (q.index == b->index) violation("camera: buffer " + std::to_string(b->index) + " queued twice");
        }
        uint8_t* data = reinterpret_cast<uint8_t*>(b->m.userptr);
        memset(data, kOverwritten, b->length);
        queued_.push_back(Buffer{b->index, data, b->length, 0, 0});
        return 0;
    }
    case VIDIOC_DQBUF: {
        v4l2_buffer* b = reinterpret_cast<v4l2_buffer*>(arg);
        changed_.wait(lock, [this] { return !filled_.empty() || cancel_ || !open_; });
        if (cancel_ || filled_.empty()) {
            cancel_ = false;
            return fail(ECANCELED);
        }
        Buffer f = filled_.front();
        filled_.pop_front();
        b->index = static_cast<uint16_t>(f.index);
        b->bytesused = f.bytesused;
        b->flags = f.flags;
        b->m.userptr = reinterpret_cast<unsigned long>(f.data);
        b->length = f.length;
        changed_.notify_all();
        return 0;
    }
    case VIDIOC_CANCEL_DQBUF:
        cancel_ = true;
        changed_.notify_all();
        return 0;
    case VIDIOC_STREAMON:
        streaming_ = true;
        return 0;
    case VIDIOC_STREAMOFF:
        streaming_ = false;
        return 0;
    case VIDIOC_S_EXT_CTRLS: {
        const v4l2_ext_controls* c = reinterpret_cast<const v4l2_ext_controls*>(arg);
        for (int i = 0; i < c->count; ++i) {
            if (c->controls[i].id == V4L2_CID_JPEG_COMPRESSION_QUALITY) jpeg_quality_ = c->controls[i].value;
            if (c->controls[i].id == V4L2_CID_WIDE_DYNAMIC_RANGE) hdr_ = c->controls[i].value;
        }
        return 0;
    }
    default:
        return fail(EINVAL);
    }
}

VideoDriver& video_driver() {
    static VideoDriver d;
    return d;
}

}  // namespace hostlib

extern "C" {

int isx019_initialize(void) { return 0; }
int isx012_initialize(void) { return 0; }
int cxd56_cisif_initialize(void) { return 0; }
int video_initialize(const char*) { return 0; }
int video_uninitialize(const char*) { return 0; }
void imageproc_initialize(void) {}
void imageproc_finalize(void) {}

// The 2D accelerator (colour conversion, resizing): cubecam streams the
// sensor's JPEG as it is.
static int imageproc_unused() {
    hostlib::violation("imageproc: cubecam converts no images");
    return -1;
}
int imageproc_convert_yuv2rgb(uint8_t*, uint32_t, uint32_t) { return imageproc_unused(); }
int imageproc_convert_rgb2yuv(uint8_t*, uint32_t, uint32_t) { return imageproc_unused(); }
void imageproc_convert_yuv2gray(uint8_t*, uint8_t*, size_t, size_t) { imageproc_unused(); }
int imageproc_resize(uint8_t*, uint16_t, uint16_t, uint8_t*, uint16_t, uint16_t, int) { return imageproc_unused(); }
int imageproc_clip_and_resize(uint8_t*, uint16_t, uint16_t, uint8_t*, uint16_t, uint16_t, int, imageproc_rect_t*) {
    return imageproc_unused();
}

int hostlib_video_open(const char* path, int) { return hostlib::video_driver().open_device(path); }
int hostlib_video_close(int fd) { return hostlib::video_driver().close_device(fd); }
int hostlib_video_ioctl(int fd, int req, unsigned long arg) { return hostlib::video_driver().control(fd, req, arg); }

int hostlib_pthread_attr_init(hostlib_pthread_attr* attr) {
    memset(attr, 0, sizeof *attr);
    return 0;
}

int hostlib_pthread_attr_setschedparam(hostlib_pthread_attr* attr, const struct sched_param* param) {
    attr->param = *param;
    return 0;
}

int hostlib_pthread_create(pthread_t* thread, const hostlib_pthread_attr*, pthread_startroutine_t entry, void* arg) {
    return pthread_create(thread, nullptr, entry, arg);
}

mqd_t hostlib_mq_open(const char* name, int, int, struct mq_attr* attr) {
    std::unique_ptr<hostlib::MessageQueue>& q = hostlib::queues()[name];
    if (!q) q.reset(new hostlib::MessageQueue);
    if (attr) q->max_messages = static_cast<size_t>(attr->mq_maxmsg);
    hostlib::descriptors().push_back(q.get());
    return static_cast<mqd_t>(hostlib::descriptors().size() - 1);
}

int hostlib_mq_send(mqd_t mq, const char* msg, size_t len, unsigned) {
    hostlib::MessageQueue* q = hostlib::descriptors().at(static_cast<size_t>(mq));
    std::unique_lock<std::mutex> lock(q->mutex);
    q->changed.wait(lock, [q] { return q->messages.size() < q->max_messages; });
    q->messages.push_back(std::string(msg, len));
    q->changed.notify_all();
    return 0;
}

ssize_t hostlib_mq_receive(mqd_t mq, char* msg, size_t len, unsigned*) {
    hostlib::MessageQueue* q = hostlib::descriptors().at(static_cast<size_t>(mq));
    std::unique_lock<std::mutex> lock(q->mutex);
    q->changed.wait(lock, [q] { return !q->messages.empty(); });
    std::string m = q->messages.front();
    q->messages.pop_front();
    q->changed.notify_all();
    size_t n = m.size() < len ? m.size() : len;
    memcpy(msg, m.data(), n);
    return static_cast<ssize_t>(n);
}

int hostlib_mq_close(mqd_t) { return 0; }

}  // extern "C"
