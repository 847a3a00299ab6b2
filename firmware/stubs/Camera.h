// Stub: Spresense Camera library (libraries/Camera/Camera.h), as used.
#ifndef CUBECAM_STUB_CAMERA_H
#define CUBECAM_STUB_CAMERA_H

#include <Arduino.h>

enum CamErr {
    CAM_ERR_SUCCESS = 0,
    CAM_ERR_NO_DEVICE = -1,
    CAM_ERR_ILLEGAL_DEVERR = -2,
    CAM_ERR_ALREADY_INITIALIZED = -3,
    CAM_ERR_NOT_INITIALIZED = -4,
    CAM_ERR_NOT_STILL_INITIALIZED = -5,
    CAM_ERR_CANT_CREATE_THREAD = -6,
    CAM_ERR_INVALID_PARAM = -7,
    CAM_ERR_NO_MEMORY = -8,
    CAM_ERR_USR_INUSED = -9,
    CAM_ERR_NOT_PERMITTED = -10,
};

enum CAM_VIDEO_FPS {
    CAM_VIDEO_FPS_NONE,
    CAM_VIDEO_FPS_5,
    CAM_VIDEO_FPS_6,
    CAM_VIDEO_FPS_7_5,
    CAM_VIDEO_FPS_15,
    CAM_VIDEO_FPS_30,
    CAM_VIDEO_FPS_60,
    CAM_VIDEO_FPS_120,
};

enum CAM_IMAGE_PIX_FMT {
    CAM_IMAGE_PIX_FMT_RGB565,
    CAM_IMAGE_PIX_FMT_YUV422,
    CAM_IMAGE_PIX_FMT_JPG,
    CAM_IMAGE_PIX_FMT_GRAY,
    CAM_IMAGE_PIX_FMT_NONE,
};

enum CAM_HDR_MODE {
    CAM_HDR_MODE_OFF = 0,
    CAM_HDR_MODE_AUTO = 1,
    CAM_HDR_MODE_ON = 2,
};

enum CAM_DEVICE_TYPE {
    CAM_DEVICE_TYPE_UNKNOWN,
    CAM_DEVICE_TYPE_ISX012,
    CAM_DEVICE_TYPE_ISX019,
};

#define CAM_IMGSIZE_QVGA_H (320)
#define CAM_IMGSIZE_QVGA_V (240)
#define CAM_IMGSIZE_VGA_H (640)
#define CAM_IMGSIZE_VGA_V (480)

class CamImage {
public:
    CamImage();
    CamImage(const CamImage& obj);
    CamImage& operator=(const CamImage& obj);
    ~CamImage();
    bool isAvailable();
    int getWidth();
    int getHeight();
    uint8_t* getImgBuff();
    size_t getImgSize();
    size_t getImgBuffSize();
    CAM_IMAGE_PIX_FMT getPixFormat();
};

typedef void (*camera_cb_t)(CamImage img);

class CameraClass {
public:
    CamErr begin(int buff_num = 1, CAM_VIDEO_FPS fps = CAM_VIDEO_FPS_30, int video_width = CAM_IMGSIZE_QVGA_H,
                 int video_height = CAM_IMGSIZE_QVGA_V, CAM_IMAGE_PIX_FMT video_fmt = CAM_IMAGE_PIX_FMT_YUV422,
                 int jpgbufsize_divisor = 7);
    CamErr startStreaming(bool enable, camera_cb_t cb = NULL);
    CamErr setJPEGQuality(int quality);
    int getJPEGQuality();
    CamErr setHDR(CAM_HDR_MODE mode);
    CAM_DEVICE_TYPE getDeviceType();
    CamErr setAutoExposure(bool enable);
    CamErr setAutoWhiteBalance(bool enable);
    void end();
};

extern CameraClass theCamera;

#endif
