// Included first (-include, after nuttx_host.h) when the real Camera library
// (libraries/Camera/Camera.cpp) is built for the host: its calls into the
// NuttX video driver, message queue and pthread API go to the fakes in
// hostlib/video_driver.cpp. Only Camera.cpp gets these names.
#ifndef CUBECAM_HOSTLIB_CAMERA_PRELUDE_H
#define CUBECAM_HOSTLIB_CAMERA_PRELUDE_H

#include <assert.h>
#include <errno.h>
#include <fcntl.h>
#include <malloc.h>
#include <mqueue.h>
#include <pthread.h>
#include <sched.h>
#include <stddef.h>
#include <unistd.h>

// nuttx/video/video.h numbers ioctls the NuttX way (nuttx/fs/ioctl.h); keep
// the host's <sys/ioctl.h>, whose _IOC and struct winsize collide, out.
#define _SYS_IOCTL_H 1
#define ASSERT(x) assert(x)

// NuttX's pthread_attr_t is a plain struct; Camera.cpp sets .stacksize.
struct hostlib_pthread_attr {
    size_t stacksize;
    struct sched_param param;
};
typedef void* (*pthread_startroutine_t)(void*);

extern "C" {
int hostlib_pthread_attr_init(hostlib_pthread_attr* attr);
int hostlib_pthread_attr_setschedparam(hostlib_pthread_attr* attr, const struct sched_param* param);
int hostlib_pthread_create(pthread_t* thread, const hostlib_pthread_attr* attr, pthread_startroutine_t entry,
                           void* arg);
mqd_t hostlib_mq_open(const char* name, int oflag, int mode, struct mq_attr* attr);
int hostlib_mq_send(mqd_t mq, const char* msg, size_t len, unsigned prio);
ssize_t hostlib_mq_receive(mqd_t mq, char* msg, size_t len, unsigned* prio);
int hostlib_mq_close(mqd_t mq);
int hostlib_video_open(const char* path, int oflag);
int hostlib_video_close(int fd);
int hostlib_video_ioctl(int fd, int req, unsigned long arg);
}

#define pthread_attr_t hostlib_pthread_attr
#define pthread_attr_init hostlib_pthread_attr_init
#define pthread_attr_setschedparam hostlib_pthread_attr_setschedparam
#define pthread_create hostlib_pthread_create
#define mq_open hostlib_mq_open
#define mq_send hostlib_mq_send
#define mq_receive hostlib_mq_receive
#define mq_close hostlib_mq_close
#define open hostlib_video_open
#define close hostlib_video_close
#define ioctl hostlib_video_ioctl

#endif
