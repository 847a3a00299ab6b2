// Host benchmark of the streaming path: CPU time the core spends per streamed
// frame (request routing, part headers, chunking into module-sized writes),
// against a baseline measured in the same run: one memcpy of the frame. The
// network takes every byte at once, so only the core's own work is timed.
// Prints one JSON object.
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include <vector>

#include "core/http_server.h"
#include "core/node.h"

using namespace cubecam;

namespace {

double cpu_seconds() {
    struct timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return static_cast<double>(ts.tv_sec) + static_cast<double>(ts.tv_nsec) * 1e-9;
}

struct StillClock : Clock {
    uint32_t millis() { return 0; }
    uint64_t micros() { return 0; }
};

// Always has a newer frame: every acquire sees the next sequence number.
struct EndlessCamera : Camera {
    std::vector<uint8_t> jpeg;
    uint32_t seq = 0;
    uint32_t latest_seq() { return seq + 1; }
    bool acquire_latest(Frame& f) {
        ++seq;
        f.data = jpeg.data();
        f.size = static_cast<uint32_t>(jpeg.size());
        f.seq = seq;
        f.capture_us = seq * 33333ull;
        f.lease = 0;
        return true;
    }
    void release(int) {}
    CameraRestart restart() { return CameraRestart::Done; }  // never stalls
    uint32_t empty_frames() { return 0; }
};

struct SinkNetwork : Network {
    int pending_accepts = 0;
    uint8_t next_cid = 1;
    bool request_sent[16] = {};
    uint64_t bytes = 0;
    uint64_t writes = 0;
    uint16_t open_server(uint16_t port) { return port; }
    void close_all() {}
    NetEvent poll(uint8_t* buf, uint16_t cap) {
        NetEvent ev = {NetEventKind::None, 0, 0};
        if (pending_accepts > 0) {
            --pending_accepts;
            ev.kind = NetEventKind::Accepted;
            ev.cid = next_cid++;
            return ev;
        }
        for (uint8_t cid = 1; cid < next_cid; ++cid) {
            if (request_sent[cid]) continue;
            static const char kReq[] = "GET /stream HTTP/1.1\r\nHost: cam\r\nUser-Agent: bench\r\n\r\n";
            size_t n = sizeof kReq - 1 < cap ? sizeof kReq - 1 : cap;
            memcpy(buf, kReq, n);
            request_sent[cid] = true;
            ev.kind = NetEventKind::Data;
            ev.cid = cid;
            ev.len = static_cast<uint16_t>(n);
            return ev;
        }
        return ev;
    }
    WriteResult write(uint8_t, const uint8_t*, uint16_t len) {
        bytes += len;
        ++writes;
        WriteResult r = {WriteStatus::Ok, len};
        return r;
    }
    void close(uint8_t) {}
};

double memcpy_seconds_per_frame(size_t size, int frames) {
    std::vector<uint8_t> src(size, 0x5A), dst(size);
    double t0 = cpu_seconds();
    for (int i = 0; i < frames; ++i) {
        src[static_cast<size_t>(i) % size] = static_cast<uint8_t>(i);
        memcpy(dst.data(), src.data(), size);
    }
    double t = cpu_seconds() - t0;
    volatile uint8_t keep = dst[static_cast<size_t>(frames) % size];
    (void)keep;
    return t / frames;
}

double core_seconds_per_frame(size_t size, int clients, int frames, uint64_t& writes) {
    StillClock clock;
    EndlessCamera camera;
    camera.jpeg.assign(size, 0x5A);
    SinkNetwork net;
    net.pending_accepts = clients;
    HttpServer server(net, camera, clock);
    NodeStatus st = {"bench", "0", {127, 0, 0, 1}, -40, 300, 30000, 70, 640, 480, "", 0};
    while (server.streaming_count() < static_cast<size_t>(clients)) server.serve(st);
    uint32_t start = server.frames_sent();
    double t0 = cpu_seconds();
    while (server.frames_sent() - start < static_cast<uint32_t>(frames)) server.serve(st);
    double t = cpu_seconds() - t0;
    writes = net.writes;
    return t / frames;
}

}  // namespace

int main(int argc, char** argv) {
    size_t frame_size = argc > 1 ? static_cast<size_t>(atol(argv[1])) : 45000;
    int frames = argc > 2 ? atoi(argv[2]) : 3000;
    double baseline = memcpy_seconds_per_frame(frame_size, frames * 4);
    uint64_t writes1 = 0, writes4 = 0;
    double one = core_seconds_per_frame(frame_size, 1, frames, writes1);
    double four = core_seconds_per_frame(frame_size, 4, frames, writes4);
    printf("{\"frame_bytes\": %zu, \"frames\": %d, \"memcpy_us_per_frame\": %.3f, "
           "\"core_us_per_frame_1_client\": %.3f, \"core_us_per_frame_4_clients\": %.3f, "
           "\"ratio_1_client\": %.2f, \"ratio_4_clients\": %.2f, \"writes_per_frame\": %.1f, "
           "\"max_write_bytes\": %u, \"ram_per_client_bytes\": %zu, \"ram_http_server_bytes\": %zu, "
           "\"ram_node_bytes\": %zu}\n",
           frame_size, frames, baseline * 1e6, one * 1e6, four * 1e6, one / baseline, four / baseline,
           static_cast<double>(writes1) / frames, kNetChunk, HttpServer::bytes_per_client(), sizeof(HttpServer),
           sizeof(Node));
    return 0;
}
