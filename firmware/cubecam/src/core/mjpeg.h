// MJPEG wire text of contracts §1, named once.
//
// Each part is sent as: part headers, the JPEG, then the delimiter of the
// next part. The delimiter goes out right after the JPEG so that a reader
// waiting for the boundary shows the frame at once; the byte stream is the
// same as "delimiter before every part" (the first one follows the response
// head). Every part has Content-Length, because ffmpeg's and OpenCV's reader
// then read exactly that many bytes instead of scanning for the boundary.
// No chunked transfer encoding: the GS2200M cannot do it, and the body simply
// ends when the connection closes.
#ifndef CUBECAM_CORE_MJPEG_H
#define CUBECAM_CORE_MJPEG_H

#include "hal.h"
#include "text.h"

namespace cubecam {

extern const char kBoundary[];
// "\r\n--<boundary>\r\n"
extern const char kPartDelimiter[];
extern const size_t kPartDelimiterLen;

// 200 response head for /stream, followed by the first delimiter.
void write_stream_head(TextBuf& out);
// Content-Type, Content-Length, X-Timestamp, X-Frame and the blank line.
void write_part_header(TextBuf& out, const Frame& f);
// 200 response head for /capture.
void write_capture_head(TextBuf& out, const Frame& f);

}  // namespace cubecam

#endif
