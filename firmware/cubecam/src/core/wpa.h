// The WPA2-Personal pre-shared key: PBKDF2-HMAC-SHA1(passphrase, SSID, 4096
// iterations, 32 bytes) (IEEE 802.11i-2004, annex H.4; PBKDF2 of RFC 8018).
// The GS2200M adapter sends it with AT+WPSK when a passphrase cannot be
// written into AT+WPAPSK; SHA-1 and HMAC are here only for it.
//
// Cost: 2 x 4096 HMACs, 16384 SHA-1 blocks; on the 156 MHz Cortex-M4 of the
// Spresense an estimated 0.1-0.3 s (not measured on a board), once per join.
#ifndef CUBECAM_CORE_WPA_H
#define CUBECAM_CORE_WPA_H

#include <stddef.h>
#include <stdint.h>

namespace cubecam {
namespace wpa {

const size_t kSha1Bytes = 20;
const size_t kPskBytes = 32;
const uint32_t kPskIterations = 4096;

class Sha1 {
public:
    Sha1();
    void update(const uint8_t* data, size_t len);
    void finish(uint8_t out[kSha1Bytes]);

private:
    void block(const uint8_t* p);
    uint32_t h_[5];
    uint8_t buf_[64];
    size_t buf_len_;
    uint64_t total_;
};

void hmac_sha1(const uint8_t* key, size_t key_len, const uint8_t* msg, size_t msg_len, uint8_t out[kSha1Bytes]);

// PBKDF2 with HMAC-SHA1; out_len bytes of key.
void pbkdf2_sha1(const uint8_t* password, size_t password_len, const uint8_t* salt, size_t salt_len,
                 uint32_t iterations, uint8_t* out, size_t out_len);

// The key an access point derives from its SSID and passphrase.
void psk(const char* ssid, const char* passphrase, uint8_t out[kPskBytes]);

}  // namespace wpa
}  // namespace cubecam

#endif
