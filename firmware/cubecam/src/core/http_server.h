// The HTTP server of contracts §1 over connection ids: one slot per client,
// each a small send state machine that always sends the newest frame.
#ifndef CUBECAM_CORE_HTTP_SERVER_H
#define CUBECAM_CORE_HTTP_SERVER_H

#include <stddef.h>
#include <stdint.h>

#include "hal.h"
#include "http.h"

namespace cubecam {

const size_t kClientTextCap = 1024;   // response head / small body / part header per client
const uint32_t kRequestTimeoutMs = 5000;
const uint32_t kStallTimeoutMs = 10000;  // a client that takes no byte for this long is dropped
// A write the module refused is tried again after 5 ms, then 10, 20... up to
// 160 ms while it keeps refusing: a stalled client costs the others little
// (each refusal holds the loop for the library's ~6 ms of retries).
const uint32_t kFirstWriteRetryMs = 5;
const uint32_t kMaxWriteRetryMs = 160;

// What /status and / report besides the server's own counters.
struct NodeStatus {
    const char* name;
    const char* firmware_version;
    uint8_t ip[4];
    int8_t rssi;
    uint16_t fps_tenths;           // configured
    uint32_t fps_measured_milli;   // captured frames per 1000 s
    uint8_t jpeg_quality;
    uint16_t width;
    uint16_t height;
    const char* last_error;        // "" when none
    uint32_t frames_empty;         // frames that overflowed the JPEG buffer since boot
};

struct ServeResult {
    bool progressed;  // some bytes moved; the caller may loop again at once
    bool link_lost;   // the module reported loss of the network or a write failed at link level
};

class HttpServer {
public:
    HttpServer(Network& net, Camera& camera, Clock& clock);
    // Forget every client (after the link or the server went away).
    void drop_all();
    // Handles pending network events and moves at most one chunk per client.
    ServeResult serve(const NodeStatus& status);

    uint32_t frames_sent() const { return frames_sent_; }
    uint32_t frames_dropped() const { return frames_dropped_; }
    size_t client_count() const;
    size_t streaming_count() const;
    // RAM one client slot takes (request parser, text buffer, send state).
    static constexpr size_t bytes_per_client();

private:
    enum class SlotState : uint8_t { Free, Reading, Sending, StreamWaiting, StreamSending };

    struct Segment {
        const uint8_t* data;
        uint32_t len;
    };

    struct Slot {
        SlotState state;
        uint8_t cid;
        HttpRequestParser parser;
        char text[kClientTextCap];
        Segment segs[3];
        uint8_t seg_count;
        uint8_t seg_index;
        uint32_t seg_offset;
        int lease;
        uint32_t last_seq;
        uint32_t fps_cap_tenths;
        uint32_t next_frame_ms;
        uint32_t deadline_ms;
        uint32_t retry_at_ms;  // a refused write is tried again from then
        uint32_t retry_ms;     // the wait after the next refusal
    };

    void on_accepted(uint8_t cid, uint32_t now);
    // Answers 503 to the clients that found no free slot, once the module takes it.
    void send_rejections();
    void close_first_rejected();
    void on_data(uint8_t cid, uint16_t len, const NodeStatus& status, uint32_t now);
    void on_closed(uint8_t cid, bool close_connection);
    void respond(Slot& s, const NodeStatus& status, uint32_t now);
    void start_next_frame(Slot& s, uint32_t now);
    bool pump(Slot& s, uint32_t now, bool& link_lost);
    void finish_send(Slot& s, uint32_t now);
    void queue(Slot& s, size_t text_len, const uint8_t* body, uint32_t body_len, const char* trailer,
               uint32_t trailer_len);
    void free_slot(Slot& s, bool close_connection);
    Slot* find(uint8_t cid);
    void write_status_json(TextBuf& out, const NodeStatus& st);
    void write_index_html(TextBuf& out, const NodeStatus& st);

    Network& net_;
    Camera& camera_;
    Clock& clock_;
    Slot slots_[kMaxClients];
    uint8_t rejected_[kMaxClients];  // cids waiting for their 503 (a ring)
    uint8_t rejected_head_;
    uint8_t rejected_count_;
    uint8_t io_[kNetChunk];
    uint32_t frames_sent_;
    uint32_t frames_dropped_;
};

constexpr size_t HttpServer::bytes_per_client() { return sizeof(Slot); }

}  // namespace cubecam

#endif
