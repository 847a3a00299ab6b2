#include "http_server.h"

#include <string.h>

#include "mjpeg.h"

namespace cubecam {

namespace {

const int kNoLease = -1;
const int kEventsPerServe = 8;


}  // namespace

HttpServer::HttpServer(Network& net, Camera& camera, Clock& clock)
    : net_(net), camera_(camera), clock_(clock), rejected_head_(0), rejected_count_(0), frames_sent_(0), frames_dropped_(0) {
    for (size_t i = 0; i < kMaxClients; ++i) {
        slots_[i].state = SlotState::Free;
        slots_[i].lease = kNoLease;
    }
}

size_t HttpServer::client_count() const {
    size_t n = 0;
    for (size_t i = 0; i < kMaxClients; ++i) n += slots_[i].state != SlotState::Free;
    return n;
}

size_t HttpServer::streaming_count() const {
    size_t n = 0;
    for (size_t i = 0; i < kMaxClients; ++i) {
        n += slots_[i].state == SlotState::StreamWaiting || slots_[i].state == SlotState::StreamSending;
    }
    return n;
}

HttpServer::Slot* HttpServer::find(uint8_t cid) {
    for (size_t i = 0; i < kMaxClients; ++i) {
        if (slots_[i].state != SlotState::Free && slots_[i].cid == cid) return &slots_[i];
    }
    return 0;
}

void HttpServer::free_slot(Slot& s, bool close_connection) {
    if (s.lease != kNoLease) camera_.release(s.lease);
    s.lease = kNoLease;
    if (close_connection) net_.close(s.cid);
    s.state = SlotState::Free;
}

void HttpServer::drop_all() {
    for (size_t i = 0; i < kMaxClients; ++i) {
        if (slots_[i].state != SlotState::Free) free_slot(slots_[i], false);
    }
    rejected_count_ = 0;
}

ServeResult HttpServer::serve(const NodeStatus& status) {
    ServeResult r = {false, false};
    uint32_t now = clock_.millis();
    for (int i = 0; i < kEventsPerServe; ++i) {
        NetEvent ev = net_.poll(io_, sizeof io_);
        if (ev.kind == NetEventKind::None) break;
        r.progressed = true;
        switch (ev.kind) {
        case NetEventKind::Accepted: on_accepted(ev.cid, now); break;
        case NetEventKind::Data: on_data(ev.cid, ev.len, status, now); break;
        case NetEventKind::Closed: on_closed(ev.cid, false); break;
        case NetEventKind::Failed: on_closed(ev.cid, true); break;
        case NetEventKind::LinkLost:
        case NetEventKind::ModuleRebooted: r.link_lost = true; return r;
        case NetEventKind::None: break;
        }
    }
    send_rejections();
    for (size_t i = 0; i < kMaxClients; ++i) {
        Slot& s = slots_[i];
        if (s.state == SlotState::StreamWaiting) start_next_frame(s, now);
        bool sending = s.state == SlotState::Sending || s.state == SlotState::StreamSending;
        if (sending && deadline_reached(now, s.retry_at_ms)) {
            r.progressed |= pump(s, now, r.link_lost);
            if (r.link_lost) return r;
        } else if (s.state == SlotState::Reading && deadline_reached(now, s.deadline_ms)) {
            free_slot(s, true);
        }
    }
    return r;
}

void HttpServer::on_accepted(uint8_t cid, uint32_t now) {
    // The module reuses a CID only after the old connection ended, even if we
    // missed its DISCONNECT line: whatever was left on that CID is gone.
    Slot* stale = find(cid);
    if (stale) free_slot(*stale, false);
    for (size_t i = 0; i < kMaxClients; ++i) {
        Slot& s = slots_[i];
        if (s.state != SlotState::Free) continue;
        s.state = SlotState::Reading;
        s.cid = cid;
        s.parser.reset();
        s.lease = kNoLease;
        s.seg_count = 0;
        s.deadline_ms = now + kRequestTimeoutMs;
        s.retry_at_ms = now;
        s.retry_ms = kFirstWriteRetryMs;
        return;
    }
    // No free slot: a 503 once the module takes it (the oldest waiting one
    // is dropped unanswered when more than kMaxClients wait).
    if (rejected_count_ == kMaxClients) close_first_rejected();
    rejected_[(rejected_head_ + rejected_count_++) % kMaxClients] = cid;
}

void HttpServer::close_first_rejected() {
    net_.close(rejected_[rejected_head_]);
    rejected_head_ = static_cast<uint8_t>((rejected_head_ + 1) % kMaxClients);
    --rejected_count_;
}

void HttpServer::send_rejections() {
    while (rejected_count_ > 0) {
        TextBuf out(reinterpret_cast<char*>(io_), sizeof io_);
        write_error_response(out, 503);
        WriteResult w = net_.write(rejected_[rejected_head_], io_, static_cast<uint16_t>(out.size()));
        if (w.status == WriteStatus::Busy) return;  // read what waits first
        close_first_rejected();  // taken, refused or gone: the 503 was a best effort
    }
}

void HttpServer::on_data(uint8_t cid, uint16_t len, const NodeStatus& status, uint32_t now) {
    Slot* s = find(cid);
    if (!s || s->state != SlotState::Reading) return;  // bytes after the request are ignored
    if (s->parser.feed(io_, len) != ParseStatus::Incomplete) respond(*s, status, now);
}

// A peer that closed needs nothing more; a connection the module failed (a
// lost chunk, a socket failure) is closed on our side too.
void HttpServer::on_closed(uint8_t cid, bool close_connection) {
    Slot* s = find(cid);
    if (s) free_slot(*s, close_connection);
}

void HttpServer::queue(Slot& s, size_t text_len, const uint8_t* body, uint32_t body_len, const char* trailer,
                       uint32_t trailer_len) {
    s.seg_count = 0;
    s.segs[s.seg_count].data = reinterpret_cast<const uint8_t*>(s.text);
    s.segs[s.seg_count++].len = static_cast<uint32_t>(text_len);
    if (body_len > 0) {
        s.segs[s.seg_count].data = body;
        s.segs[s.seg_count++].len = body_len;
    }
    if (trailer_len > 0) {
        s.segs[s.seg_count].data = reinterpret_cast<const uint8_t*>(trailer);
        s.segs[s.seg_count++].len = trailer_len;
    }
    s.seg_index = 0;
    s.seg_offset = 0;
}

void HttpServer::respond(Slot& s, const NodeStatus& status, uint32_t now) {
    RouteDecision d = route_request(s.parser);
    TextBuf out(s.text, sizeof s.text);
    s.state = SlotState::Sending;
    s.deadline_ms = now + kStallTimeoutMs;
    Frame f;
    switch (d.route) {
    case Route::Stream:
        write_stream_head(out);
        s.state = SlotState::StreamSending;
        s.last_seq = 0;
        s.fps_cap_tenths = d.fps_cap_tenths;
        s.next_frame_ms = now;
        break;
    case Route::Capture:
        if (!camera_.acquire_latest(f)) {
            write_error_response(out, 503);
            break;
        }
        s.lease = f.lease;
        write_capture_head(out, f);
        queue(s, out.size(), f.data, f.size, "", 0);
        return;
    case Route::Time: {
        char body[24];
        TextBuf t(body, sizeof body);
        t.add_timestamp(clock_.micros());
        write_response_head(out, 200, "text/plain", static_cast<int64_t>(t.size()), "");
        out.add(t.c_str());
        break;
    }
    case Route::Status:
    case Route::Index: {
        // The body is built in the shared I/O buffer, which is idle now.
        TextBuf body(reinterpret_cast<char*>(io_), sizeof io_);
        if (d.route == Route::Status) {
            write_status_json(body, status);
        } else {
            write_index_html(body, status);
        }
        write_response_head(out, 200, d.route == Route::Status ? "application/json" : "text/html; charset=utf-8",
                            static_cast<int64_t>(body.size()), "");
        out.add(body.c_str(), body.size());
        break;
    }
    case Route::Error:
        write_error_response(out, d.status);
        break;
    }
    queue(s, out.size(), 0, 0, "", 0);
}

void HttpServer::start_next_frame(Slot& s, uint32_t now) {
    if (camera_.latest_seq() == s.last_seq || !deadline_reached(now, s.next_frame_ms)) return;
    Frame f;
    if (!camera_.acquire_latest(f)) return;
    if (f.seq <= s.last_seq) {
        camera_.release(f.lease);
        return;
    }
    // Frames captured while this client was still busy with an older one are
    // skipped: it only ever gets the newest. A rate-capped client skips on
    // purpose; those are not counted as drops.
    if (s.last_seq != 0 && s.fps_cap_tenths == 0) frames_dropped_ += f.seq - s.last_seq - 1;
    s.last_seq = f.seq;
    s.lease = f.lease;
    if (s.fps_cap_tenths != 0) s.next_frame_ms = now + 10000u / s.fps_cap_tenths;
    TextBuf out(s.text, sizeof s.text);
    write_part_header(out, f);
    queue(s, out.size(), f.data, f.size, kPartDelimiter, static_cast<uint32_t>(kPartDelimiterLen));
    s.state = SlotState::StreamSending;
    s.deadline_ms = now + kStallTimeoutMs;
}

bool HttpServer::pump(Slot& s, uint32_t now, bool& link_lost) {
    // Gather up to one module write from the queued segments.
    uint16_t n = 0;
    uint8_t idx = s.seg_index;
    uint32_t off = s.seg_offset;
    while (n < sizeof io_ && idx < s.seg_count) {
        uint32_t take = s.segs[idx].len - off;
        if (take > sizeof io_ - n) take = sizeof io_ - n;
        memcpy(io_ + n, s.segs[idx].data + off, take);
        n = static_cast<uint16_t>(n + take);
        off += take;
        if (off == s.segs[idx].len) {
            ++idx;
            off = 0;
        }
    }
    if (n == 0) {
        finish_send(s, now);
        return false;
    }
    WriteResult w = net_.write(s.cid, io_, n);
    if (w.status == WriteStatus::Busy) return false;  // the next serve() reads what waits first
    if (w.status != WriteStatus::Ok) {
        link_lost = w.status == WriteStatus::LinkFailure;
        free_slot(s, w.status == WriteStatus::ClientGone);
        return true;
    }
    if (w.accepted == 0) {
        if (deadline_reached(now, s.deadline_ms)) {
            free_slot(s, true);
            return true;
        }
        s.retry_at_ms = now + s.retry_ms;
        s.retry_ms = s.retry_ms * 2 > kMaxWriteRetryMs ? kMaxWriteRetryMs : s.retry_ms * 2;
        return false;
    }
    s.deadline_ms = now + kStallTimeoutMs;
    s.retry_ms = kFirstWriteRetryMs;
    uint32_t left = w.accepted;
    while (left > 0) {
        uint32_t in_seg = s.segs[s.seg_index].len - s.seg_offset;
        uint32_t step = left < in_seg ? left : in_seg;
        s.seg_offset += step;
        left -= step;
        if (s.seg_offset == s.segs[s.seg_index].len) {
            ++s.seg_index;
            s.seg_offset = 0;
        }
    }
    if (s.seg_index == s.seg_count) finish_send(s, now);
    return true;
}

void HttpServer::finish_send(Slot& s, uint32_t now) {
    if (s.state == SlotState::StreamSending) {
        if (s.lease != kNoLease) {
            camera_.release(s.lease);
            s.lease = kNoLease;
            ++frames_sent_;
        }
        s.state = SlotState::StreamWaiting;
        s.deadline_ms = now + kStallTimeoutMs;
        return;
    }
    free_slot(s, true);
}

void HttpServer::write_status_json(TextBuf& out, const NodeStatus& st) {
    out.add("{\"name\":").add_json_string(st.name);
    out.add(",\"firmware_version\":").add_json_string(st.firmware_version);
    out.add(",\"uptime_ms\":").add_uint(clock_.micros() / 1000);
    out.add(",\"ip\":\"").add_ipv4(st.ip).add('"');
    out.add(",\"rssi\":").add_int(st.rssi);
    out.add(",\"fps\":{\"configured\":").add_fixed(st.fps_tenths, 1);
    out.add(",\"measured\":").add_fixed(st.fps_measured_milli, 3).add('}');
    out.add(",\"frames_sent\":").add_uint(frames_sent_);
    out.add(",\"frames_dropped\":").add_uint(frames_dropped_);
    out.add(",\"frames_empty\":").add_uint(st.frames_empty);
    out.add(",\"clients\":").add_uint(streaming_count());
    out.add(",\"jpeg_quality\":").add_uint(st.jpeg_quality);
    out.add(",\"width\":").add_uint(st.width);
    out.add(",\"height\":").add_uint(st.height);
    out.add(",\"last_error\":").add_json_string(st.last_error).add("}\n");
}

void HttpServer::write_index_html(TextBuf& out, const NodeStatus& st) {
    // The name is restricted to [A-Za-z0-9_-] by settings validation.
    out.add("<!doctype html>\n<html><head><meta charset=\"utf-8\"><title>").add(st.name);
    out.add("</title></head>\n<body style=\"font-family:sans-serif\"><h1>").add(st.name).add("</h1>\n");
    out.add("<img src=\"/stream\" alt=\"live stream\" width=\"").add_uint(st.width);
    out.add("\" height=\"").add_uint(st.height).add("\">\n<p>");
    out.add_fixed(st.fps_tenths, 1).add(" fps configured, ").add_fixed(st.fps_measured_milli, 3);
    out.add(" measured &middot; ").add_uint(streaming_count()).add(" streaming &middot; ");
    out.add_uint(frames_sent_).add(" frames sent &middot; <a href=\"/status\">status</a> &middot; ");
    out.add("<a href=\"/capture\">capture</a></p>\n");
    if (st.last_error[0]) out.add("<p>last error: ").add(st.last_error).add("</p>\n");
    out.add("</body></html>\n");
}

}  // namespace cubecam
