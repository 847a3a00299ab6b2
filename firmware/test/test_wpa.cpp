#include <string.h>

#include <string>

#include <doctest/doctest.h>

#include "core/wpa.h"

using namespace cubecam::wpa;

namespace {

std::string hex(const uint8_t* p, size_t n) {
    static const char digits[] = "0123456789abcdef";
    std::string out;
    for (size_t i = 0; i < n; ++i) {
        out += digits[p[i] >> 4];
        out += digits[p[i] & 15];
    }
    return out;
}

const uint8_t* bytes(const char* s) { return reinterpret_cast<const uint8_t*>(s); }

std::string pbkdf2(const char* password, const char* salt, uint32_t iterations, size_t len) {
    uint8_t out[64];
    pbkdf2_sha1(bytes(password), strlen(password), bytes(salt), strlen(salt), iterations, out, len);
    return hex(out, len);
}

}  // namespace

TEST_CASE("SHA-1 matches FIPS 180 examples, whatever the pieces it is fed in") {
    uint8_t d[kSha1Bytes];
    Sha1 h;
    h.update(bytes("abc"), 3);
    h.finish(d);
    CHECK(hex(d, sizeof d) == "a9993e364706816aba3e25717850c26c9cd0d89d");
    Sha1 million;
    std::string chunk(997, 'a');  // not a multiple of the 64-byte block
    size_t left = 1000000;
    while (left > 0) {
        size_t n = left < chunk.size() ? left : chunk.size();
        million.update(bytes(chunk.c_str()), n);
        left -= n;
    }
    million.finish(d);
    CHECK(hex(d, sizeof d) == "34aa973cd4c4daa4f61eeb2bdbad27316534016f");
}

TEST_CASE("HMAC-SHA1 matches RFC 2202, short and longer-than-a-block keys") {
    uint8_t d[kSha1Bytes];
    uint8_t key[80];
    memset(key, 0x0b, 20);
    hmac_sha1(key, 20, bytes("Hi There"), 8, d);
    CHECK(hex(d, sizeof d) == "b617318655057264e28bc0b6fb378c8ef146be00");
    memset(key, 0xaa, 80);
    const char* msg = "Test Using Larger Than Block-Size Key - Hash Key First";
    hmac_sha1(key, 80, bytes(msg), strlen(msg), d);
    CHECK(hex(d, sizeof d) == "aa4ae5e15272d00e95705637ce8a3b55ed402112");
}

TEST_CASE("PBKDF2-HMAC-SHA1 matches RFC 6070") {
    CHECK(pbkdf2("password", "salt", 1, 20) == "0c60c80f961f0e71f3a9b524af6012062fe037a6");
    CHECK(pbkdf2("password", "salt", 4096, 20) == "4b007901b765489abead49d926f721d065a429c1");
    CHECK(pbkdf2("passwordPASSWORDpassword", "saltSALTsaltSALTsaltSALTsaltSALTsalt", 4096, 25) ==
          "3d2eec4fe41c849b80c8d83662c0e44a8b291a964cf2f07038");
}

TEST_CASE("the WPA2 key matches IEEE 802.11i annex H.4 and a passphrase with commas and quotes") {
    uint8_t k[kPskBytes];
    psk("IEEE", "password", k);
    CHECK(hex(k, sizeof k) == "f42c6fc52df0ebef9ebb4b90b38a5f902e83fe1b135a70e23aed762e9710a12e");
    psk("ThisIsASSID", "ThisIsAPassword", k);
    CHECK(hex(k, sizeof k) == "0dc0d6eb90555ed6419756b9a15ec3e3209b63df707dd508d14581f8982721af");
    psk("lab", "my \"secret\", ok", k);  // Python: hashlib.pbkdf2_hmac("sha1", pass, ssid, 4096, 32)
    CHECK(hex(k, sizeof k) == "4276db25e1b888ac60e88dffe0485c645578ea368f60b72aa436cd38a22d144d");
}
