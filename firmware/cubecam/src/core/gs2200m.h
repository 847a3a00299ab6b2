// The text the Telit GS2200M speaks over its AT interface, parsed and built
// without any I/O, so the Spresense adapter stays glue and this is tested on
// the host: connection ids, the words of event lines, AT+WS scan lines and
// the header of a bulk-data write.
#ifndef CUBECAM_CORE_GS2200M_H
#define CUBECAM_CORE_GS2200M_H

#include <stddef.h>
#include <stdint.h>

#include "hal.h"

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

}  // namespace gs2200m
}  // namespace cubecam

#endif
