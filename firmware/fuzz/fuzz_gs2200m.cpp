// libFuzzer target: the GS2200M's AT text (core/gs2200m): the scan-line and
// event-line parsers that read what the module sends, and the credential
// commands the node writes to it.
//
// Input: byte 0 picks the part, the rest is its text:
//   0  an AT+WS answer line: a network is 1-32 bytes of SSID found in the
//      line, without spaces at either end, and an RSSI of -128..127;
//   1  an event line: CONNECT's and DISCONNECT's connection ids are 0-15;
//   2  credentials "<ssid>\n<passphrase>": whatever the settings accept, the
//      commands fit their buffer and the module (test/s2w.h, its argument
//      rules) reads back exactly the SSID and passphrase, or only its key
//      goes: UTF-8, or no form of AT+WPAPSK carries it;
//   3  a bulk-data header: cid and length read back from the 7 bytes.
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <string>
#include <vector>

#include "core/gs2200m.h"
#include "core/settings.h"
#include "test/s2w.h"

using namespace cubecam;
using namespace cubecam::gs2200m;

namespace {

void require(bool ok) {
    if (!ok) abort();
}

std::string args_of(const std::string& cmd, const char* name) {
    size_t n = strlen(name);
    require(cmd.size() >= n + 2 && cmd.compare(0, n, name) == 0 && cmd.compare(cmd.size() - 2, 2, "\r\n") == 0);
    return cmd.substr(n, cmd.size() - n - 2);
}

void scan_line(const std::string& line) {
    ScanEntry e;
    memset(&e, 0x5A, sizeof e);
    if (!parse_scan_line(line.c_str(), e)) return;
    size_t len = strnlen(e.ssid, sizeof e.ssid);
    require(len >= 1 && len <= kMaxSsid && len < sizeof e.ssid);
    require(e.ssid[0] != ' ' && e.ssid[len - 1] != ' ');
    require(line.find(std::string(e.ssid, len)) != std::string::npos);
}

void event_line(const std::string& line) {
    uint8_t cid = 0xFF;
    if (event_cid(line.c_str(), "CONNECT", 1, cid)) require(cid < 16);
    cid = 0xFF;
    if (event_cid(line.c_str(), "DISCONNECT", 0, cid)) require(cid < 16);
}

void credentials(const std::string& text) {
    size_t nl = text.find('\n');
    if (nl == std::string::npos) return;
    std::string ssid = text.substr(0, nl), pass = text.substr(nl + 1);
    if (ssid.empty() || ssid.find('\0') != std::string::npos || pass.find('\0') != std::string::npos) return;
    if (!validate_ssid(ssid.data(), ssid.size()).ok() || !validate_passphrase(pass.data(), pass.size()).ok()) return;
    char buf[kMaxCredentialCommand];
    TextBuf t(buf, sizeof buf);
    std::string read_ssid, read_pass;
    if (add_wpapsk(t, ssid.c_str(), pass.c_str())) {
        require(!t.overflowed());
        require(s2w::wpapsk(args_of(t.c_str(), "AT+WPAPSK="), read_ssid, read_pass));
        require(read_ssid == ssid && read_pass == pass);
    } else {
        require(t.size() == 0 && passphrase_arg(pass.c_str()) == PassphraseArg::KeyOnly);
        // Key-only on purpose: bytes beyond ASCII (how the module's line
        // reader takes them is not known), and a space at either end is
        // never left bare; otherwise no form reaches the module intact.
        bool ascii = true;
        for (char c : pass) ascii = ascii && static_cast<uint8_t>(c) < 0x80;
        bool edge_space = pass[0] == ' ' || pass[pass.size() - 1] == ' ';
        if (ascii) {
            require(!(s2w::wpapsk(ssid + ",\"" + pass + "\"", read_ssid, read_pass) && read_pass == pass));
            if (!edge_space) require(!(s2w::wpapsk(ssid + "," + pass, read_ssid, read_pass) && read_pass == pass));
        }
        t.clear();
        require(add_wpapsk(t, ssid.c_str(), kKeyFollows) && !t.overflowed());
        require(s2w::wpapsk(args_of(t.c_str(), "AT+WPAPSK="), read_ssid, read_pass) && read_ssid == ssid);
    }
    for (uint8_t channel : {0, 6}) {
        t.clear();
        add_wa(t, ssid.c_str(), channel);
        require(!t.overflowed() && s2w::wa(args_of(t.c_str(), "AT+WA="), read_ssid) && read_ssid == ssid);
    }
}

void bulk(const uint8_t* data, size_t size) {
    if (size < 3) return;
    uint8_t cid = data[0] & 15;
    uint16_t len = static_cast<uint16_t>((data[1] | (data[2] << 8)) % (kMaxBulkData + 1));
    uint8_t h[kBulkHeaderBytes];
    bulk_header(cid, len, h);
    uint8_t back = 0xFF;
    require(h[0] == kEsc && h[1] == 'Z' && parse_cid(static_cast<char>(h[2]), back) && back == cid);
    require(atoi(std::string(reinterpret_cast<const char*>(h + 3), 4).c_str()) == len);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    if (size == 0) return 0;
    std::string text(reinterpret_cast<const char*>(data + 1), size - 1);
    switch (data[0] % 4) {
    case 0:
        scan_line(text);
        break;
    case 1:
        event_line(text);
        break;
    case 2:
        credentials(text);
        break;
    default:
        bulk(data + 1, size - 1);
        break;
    }
    return 0;
}
