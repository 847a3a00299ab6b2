#include "wpa.h"

#include <string.h>

namespace cubecam {
namespace wpa {

namespace {

uint32_t rotl(uint32_t v, unsigned n) { return (v << n) | (v >> (32 - n)); }

uint32_t load_be32(const uint8_t* p) {
    return (static_cast<uint32_t>(p[0]) << 24) | (static_cast<uint32_t>(p[1]) << 16) |
           (static_cast<uint32_t>(p[2]) << 8) | p[3];
}

void store_be32(uint32_t v, uint8_t* p) {
    for (int i = 0; i < 4; ++i) p[i] = static_cast<uint8_t>(v >> (24 - 8 * i));
}

const size_t kBlockBytes = 64;

// HMAC-SHA1 with the key's two padded blocks hashed once: each message then
// costs the blocks of the message alone.
class Hmac {
public:
    Hmac(const uint8_t* key, size_t key_len) {
        uint8_t k[kBlockBytes];
        memset(k, 0, sizeof k);
        if (key_len > kBlockBytes) {
            Sha1 h;
            h.update(key, key_len);
            h.finish(k);
        } else {
            memcpy(k, key, key_len);
        }
        uint8_t pad[kBlockBytes];
        for (size_t i = 0; i < kBlockBytes; ++i) pad[i] = static_cast<uint8_t>(k[i] ^ 0x36);
        inner_.update(pad, sizeof pad);
        for (size_t i = 0; i < kBlockBytes; ++i) pad[i] = static_cast<uint8_t>(k[i] ^ 0x5c);
        outer_.update(pad, sizeof pad);
    }
    void mac(const uint8_t* msg, size_t msg_len, const uint8_t* more, size_t more_len, uint8_t out[kSha1Bytes]) const {
        Sha1 in = inner_;
        in.update(msg, msg_len);
        in.update(more, more_len);
        uint8_t digest[kSha1Bytes];
        in.finish(digest);
        Sha1 o = outer_;
        o.update(digest, sizeof digest);
        o.finish(out);
    }

private:
    Sha1 inner_;
    Sha1 outer_;
};

}  // namespace

Sha1::Sha1() : buf_len_(0), total_(0) {
    static const uint32_t kInit[5] = {0x67452301u, 0xEFCDAB89u, 0x98BADCFEu, 0x10325476u, 0xC3D2E1F0u};
    memcpy(h_, kInit, sizeof h_);
}

void Sha1::block(const uint8_t* p) {
    uint32_t w[80];
    for (int i = 0; i < 16; ++i) w[i] = load_be32(p + 4 * i);
    for (int i = 16; i < 80; ++i) w[i] = rotl(w[i - 3] ^ w[i - 8] ^ w[i - 14] ^ w[i - 16], 1);
    uint32_t a = h_[0], b = h_[1], c = h_[2], d = h_[3], e = h_[4];
    for (int i = 0; i < 80; ++i) {
        uint32_t f, k;
        if (i < 20) {
            f = (b & c) | (~b & d);
            k = 0x5A827999u;
        } else if (i < 40) {
            f = b ^ c ^ d;
            k = 0x6ED9EBA1u;
        } else if (i < 60) {
            f = (b & c) | (b & d) | (c & d);
            k = 0x8F1BBCDCu;
        } else {
            f = b ^ c ^ d;
            k = 0xCA62C1D6u;
        }
        uint32_t t = rotl(a, 5) + f + e + k + w[i];
        e = d;
        d = c;
        c = rotl(b, 30);
        b = a;
        a = t;
    }
    h_[0] += a;
    h_[1] += b;
    h_[2] += c;
    h_[3] += d;
    h_[4] += e;
}

void Sha1::update(const uint8_t* data, size_t len) {
    total_ += len;
    while (len > 0) {
        if (buf_len_ == 0 && len >= kBlockBytes) {
            block(data);
            data += kBlockBytes;
            len -= kBlockBytes;
            continue;
        }
        size_t take = kBlockBytes - buf_len_ < len ? kBlockBytes - buf_len_ : len;
        memcpy(buf_ + buf_len_, data, take);
        buf_len_ += take;
        data += take;
        len -= take;
        if (buf_len_ == kBlockBytes) {
            block(buf_);
            buf_len_ = 0;
        }
    }
}

void Sha1::finish(uint8_t out[kSha1Bytes]) {
    uint64_t bits = total_ * 8;
    uint8_t pad[kBlockBytes + 8];
    size_t pad_len = (buf_len_ < 56 ? 56 : 120) - buf_len_;
    memset(pad, 0, sizeof pad);
    pad[0] = 0x80;
    for (int i = 0; i < 8; ++i) pad[pad_len + static_cast<size_t>(i)] = static_cast<uint8_t>(bits >> (56 - 8 * i));
    update(pad, pad_len + 8);
    for (int i = 0; i < 5; ++i) store_be32(h_[i], out + 4 * i);
}

void hmac_sha1(const uint8_t* key, size_t key_len, const uint8_t* msg, size_t msg_len, uint8_t out[kSha1Bytes]) {
    Hmac(key, key_len).mac(msg, msg_len, 0, 0, out);
}

void pbkdf2_sha1(const uint8_t* password, size_t password_len, const uint8_t* salt, size_t salt_len,
                 uint32_t iterations, uint8_t* out, size_t out_len) {
    Hmac prf(password, password_len);
    for (uint32_t index = 1; out_len > 0; ++index) {
        uint8_t count[4];
        store_be32(index, count);
        uint8_t u[kSha1Bytes], t[kSha1Bytes];
        prf.mac(salt, salt_len, count, sizeof count, u);
        memcpy(t, u, sizeof t);
        for (uint32_t i = 1; i < iterations; ++i) {
            prf.mac(u, sizeof u, 0, 0, u);
            for (size_t j = 0; j < kSha1Bytes; ++j) t[j] ^= u[j];
        }
        size_t take = out_len < kSha1Bytes ? out_len : kSha1Bytes;
        memcpy(out, t, take);
        out += take;
        out_len -= take;
    }
}

void psk(const char* ssid, const char* passphrase, uint8_t out[kPskBytes]) {
    pbkdf2_sha1(reinterpret_cast<const uint8_t*>(passphrase), strlen(passphrase),
                reinterpret_cast<const uint8_t*>(ssid), strlen(ssid), kPskIterations, out, kPskBytes);
}

}  // namespace wpa
}  // namespace cubecam
