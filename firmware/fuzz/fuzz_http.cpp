// libFuzzer target: arbitrary bytes from a client, in arbitrary pieces, must
// get a well-formed answer or none, never more than one module write per
// chunk, and must leave the server answering the next client.
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <string>

#include "core/http_server.h"
#include "test/fakes.h"

using namespace cubecam;

static void require(bool ok) {
    if (!ok) abort();
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    fake::Clock clock;
    fake::Camera camera;
    fake::Network net;
    HttpServer server(net, camera, clock);
    NodeStatus st = {"fuzz", "0", {127, 0, 0, 1}, -40, 150, 15000, 70, 640, 480, "", 0};
    camera.capture(fake::jpeg(3000, 7), 1);
    net.connect(1);
    // The first byte chooses how the rest is cut into network reads.
    size_t piece = size > 0 ? (data[0] % 64) + 1 : 1;
    for (size_t pos = 1; pos < size; pos += piece) {
        size_t n = size - pos < piece ? size - pos : piece;
        net.send(1, std::string(reinterpret_cast<const char*>(data + pos), n));
        server.serve(st);
        clock.advance_ms(1);
    }
    for (int i = 0; i < 20; ++i) server.serve(st);
    const std::string& out = net.conns[1].sent;
    require(out.empty() || out.compare(0, 9, "HTTP/1.1 ") == 0);
    require(net.max_write_seen <= kNetChunk);
    // The node still serves: another client gets its status.
    net.connect(2);
    net.send(2, "GET /status HTTP/1.1\r\n\r\n");
    for (int i = 0; i < 5; ++i) server.serve(st);
    require(net.conns[2].sent.compare(0, 15, "HTTP/1.1 200 OK") == 0);
    server.drop_all();
    require(camera.out == 0 && camera.bad_releases == 0);
    return 0;
}
