#include "mjpeg.h"

#include <string.h>

#include "http.h"

namespace cubecam {

#define CUBECAM_BOUNDARY "cubecam-mjpeg-boundary"

const char kBoundary[] = CUBECAM_BOUNDARY;
const char kPartDelimiter[] = "\r\n--" CUBECAM_BOUNDARY "\r\n";
const size_t kPartDelimiterLen = sizeof kPartDelimiter - 1;

namespace {

void add_frame_headers(TextBuf& out, const Frame& f) {
    out.add("X-Timestamp: ").add_timestamp(f.capture_us).add("\r\n");
    out.add("X-Frame: ").add_uint(f.seq).add("\r\n");
}

}  // namespace

void write_stream_head(TextBuf& out) {
    write_response_head(out, 200, "multipart/x-mixed-replace;boundary=" CUBECAM_BOUNDARY, -1, "");
    out.add(kPartDelimiter);
}

void write_part_header(TextBuf& out, const Frame& f) {
    out.add("Content-Type: image/jpeg\r\nContent-Length: ").add_uint(f.size).add("\r\n");
    add_frame_headers(out, f);
    out.add("\r\n");
}

void write_capture_head(TextBuf& out, const Frame& f) {
    char extra[96];
    TextBuf e(extra, sizeof extra);
    e.add("Content-Disposition: inline; filename=capture.jpg\r\n");
    add_frame_headers(e, f);
    write_response_head(out, 200, "image/jpeg", f.size, e.c_str());
}

}  // namespace cubecam
