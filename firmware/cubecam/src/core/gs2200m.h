// The text the Telit GS2200M speaks over its AT interface, parsed and built
// without any I/O, so the Spresense adapter stays glue and this is tested on
// the host: connection ids, the words of event lines, AT+WS scan lines, the
// header of a bulk-data write, and the Wi-Fi credentials in AT commands.
#ifndef CUBECAM_CORE_GS2200M_H
#define CUBECAM_CORE_GS2200M_H

#include <stddef.h>
#include <stdint.h>

#include "hal.h"
#include "text.h"
#include "wpa.h"

namespace cubecam {
namespace gs2200m {

const uint8_t kEsc = 0x1B;
// <ESC> 'Z' <cid> <4 decimal digits: data length>, then the data.
const size_t kBulkHeaderBytes = 7;
const uint16_t kMaxBulkData = 9999;

// Connection ids are one hex digit, 0-9 a-f.
char cid_char(uint8_t cid);
bool parse_cid(char c, uint8_t& cid);

// The connection id that is word `word` (0 = the first) after `keyword` in an
// event line: "CONNECT <server cid> <new cid> <ip> <port>" (word 1),
// "DISCONNECT <cid>" (word 0).
bool event_cid(const char* line, const char* keyword, int word, uint8_t& cid);

// One line of the AT+WS answer: "<bssid>, <ssid>, <channel>, <type>, <rssi>,
// <security>" (Telit AT command guide). False for the header, the
// "No.Of AP Found" line and anything malformed. Spaces around the SSID are
// taken as padding.
bool parse_scan_line(const char* line, ScanEntry& out);

// Writes the bulk-data header for `len` data bytes (at most kMaxBulkData).
void bulk_header(uint8_t cid, uint16_t len, uint8_t out[kBulkHeaderBytes]);

// Credentials in AT commands. The module's Serial-to-WiFi application splits
// a command's arguments at commas; an argument whose first non-space
// character is '"' is quoted: it ends at the next '"' that does not follow a
// '\', and the backslashes stay in it. The SSID argument then has each \"
// turned into " (AppS2wParse_Ssid); the passphrase is taken as it stands,
// 8 to 63 bytes (AppS2wCmd_WpaPsk). AT+WPSK takes the 32-byte key as 64 hex
// digits. (GainSpan/Telit S2W sources: s2w_general_parse.c, the AT+WPAPSK,
// AT+WPSK and AT+WA handlers.)
enum class PassphraseArg : uint8_t {
    Plain,   // as it stands: printable ASCII, no comma, no space at either end, no leading '"'
    Quoted,  // in quotes: printable ASCII, every '"' after a '\', not ending in '\'
    KeyOnly  // neither: only the derived key (AT+WPSK) carries it
};
PassphraseArg passphrase_arg(const char* passphrase);

// Appends "AT+WPAPSK=<ssid>,<passphrase>\r\n"; false, and nothing appended,
// for a KeyOnly passphrase.
bool add_wpapsk(TextBuf& out, const char* ssid, const char* passphrase);
// Appends "AT+WPSK=<64 hex digits>\r\n".
void add_wpsk(TextBuf& out, const uint8_t psk[wpa::kPskBytes]);
// Appends "AT+WA=<ssid>\r\n", or "AT+WA=<ssid>,,<channel>\r\n" for channel > 0.
void add_wa(TextBuf& out, const char* ssid, uint8_t channel);
// A valid passphrase for AT+WPAPSK when the key follows in AT+WPSK: the
// module then knows which SSID the key belongs to (it drops a stored key
// whose SSID differs from the one it joins).
extern const char kKeyFollows[];
// The longest command the three above write (an SSID of 32 quotes, a
// passphrase of 63 bytes).
const size_t kMaxCredentialCommand = 10 + 2 * 32 + 1 + 2 + 63 + 2 + 1;

}  // namespace gs2200m
}  // namespace cubecam

#endif
