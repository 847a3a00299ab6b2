#include <string.h>

#include <string>
#include <vector>

#include <doctest/doctest.h>

#include "core/improv.h"
#include "fakes.h"

using namespace cubecam;
using improv::Framer;

namespace {

Framer::Result feed_all(Framer& f, const std::string& bytes, uint32_t now = 0) {
    Framer::Result r = Framer::Result::NeedMore;
    for (char c : bytes) {
        r = f.feed(static_cast<uint8_t>(c), now);
        if (r != Framer::Result::NeedMore) break;
    }
    return r;
}

}  // namespace

TEST_CASE("frames are laid out as the Improv serial spec says") {
    uint8_t data[] = {0x04};
    uint8_t out[improv::kMaxFrame];
    size_t n = improv::encode_frame(improv::FrameType::CurrentState, data, 1, out);
    const uint8_t expected[] = {'I', 'M', 'P', 'R', 'O', 'V', 0x01, 0x01, 0x01, 0x04, 0};
    REQUIRE(n == sizeof expected);
    CHECK(memcmp(out, expected, n - 1) == 0);
    uint8_t sum = 0;
    for (size_t i = 0; i + 1 < n; ++i) sum = static_cast<uint8_t>(sum + out[i]);
    CHECK(out[n - 1] == sum);
    CHECK(improv::encode_frame(improv::FrameType::RpcResult, out, 256, out) == 0);
}

TEST_CASE("the framer accepts what the encoder writes") {
    std::string frame = fake::improv_rpc(improv::Command::WifiSettings, {"lab", "password1"});
    Framer f;
    CHECK(feed_all(f, frame.substr(0, frame.size() - 1)) == Framer::Result::Frame);
    CHECK(f.type() == improv::FrameType::Rpc);
    improv::Rpc rpc;
    REQUIRE(improv::decode_rpc(f.data(), f.data_len(), rpc));
    CHECK(rpc.command == improv::Command::WifiSettings);
    improv::Text s[2];
    REQUIRE(improv::decode_strings(rpc.payload, rpc.payload_len, s, 2));
    CHECK(std::string(s[0].data, s[0].len) == "lab");
    CHECK(std::string(s[1].data, s[1].len) == "password1");
}

TEST_CASE("a wrong checksum is reported and the framer starts over") {
    std::string frame = fake::improv_rpc(improv::Command::GetCurrentState, {});
    frame[frame.size() - 2] ^= 0x55;
    Framer f;
    CHECK(feed_all(f, frame) == Framer::Result::BadChecksum);
    CHECK(f.held_len() == 0);
}

TEST_CASE("non-Improv bytes and other versions are handed back") {
    Framer f;
    CHECK(feed_all(f, "IMPX") == Framer::Result::NotImprov);
    CHECK(std::string(reinterpret_cast<const char*>(f.held()), f.held_len()) == "IMPX");
    f.reset();
    std::string v2 = "IMPROV";
    v2 += '\x02';
    CHECK(feed_all(f, v2) == Framer::Result::NotImprov);
}

TEST_CASE("a partial frame expires after 100 ms without a byte") {
    Framer f;
    feed_all(f, "IMPROV\x01\x03", 1000);
    CHECK_FALSE(f.expired(1000 + improv::kPartialFrameTimeoutMs));
    CHECK(f.expired(1000 + improv::kPartialFrameTimeoutMs + 1));
    CHECK_FALSE(f.in_magic());
    f.reset();
    feed_all(f, "IMP", 0);
    CHECK(f.in_magic());
}

TEST_CASE("RPC data is length-checked before every read") {
    improv::Rpc rpc;
    const uint8_t too_short[] = {0x01};
    CHECK_FALSE(improv::decode_rpc(too_short, 1, rpc));
    const uint8_t bad_len[] = {0x01, 0x05, 'a'};
    CHECK_FALSE(improv::decode_rpc(bad_len, 3, rpc));
    improv::Text s[2];
    const uint8_t overrun[] = {3, 'a', 'b'};
    CHECK_FALSE(improv::decode_strings(overrun, 3, s, 1));
    const uint8_t missing[] = {1, 'a'};
    CHECK_FALSE(improv::decode_strings(missing, 2, s, 2));
    const uint8_t extra[] = {1, 'a', 'z'};
    CHECK_FALSE(improv::decode_strings(extra, 3, s, 1));
    const uint8_t empty_ok[] = {0, 0};
    CHECK(improv::decode_strings(empty_ok, 2, s, 2));
}

TEST_CASE("RPC results carry the total length and each string's length") {
    improv::Text strings[2] = {{"http://10.0.0.5/", 16}, {"x", 1}};
    uint8_t out[improv::kMaxData];
    size_t n = improv::encode_rpc_result(improv::Command::WifiSettings, strings, 2, out);
    REQUIRE(n == 2 + 1 + 16 + 1 + 1);
    CHECK(out[0] == 0x01);
    CHECK(out[1] == 19);
    CHECK(out[2] == 16);
    CHECK(out[19] == 1);
    std::string big(254, 'x');
    improv::Text one = {big.data(), big.size()};
    CHECK(improv::encode_rpc_result(improv::Command::GetDeviceInfo, &one, 1, out) == 0);
}
