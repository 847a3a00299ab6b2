// libFuzzer target: arbitrary console input. Every command line is answered
// with a last line of "OK" or "ERR <code> ...", and the stored password never
// shows (unless the input typed it into another key, which may be shown).
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <string>
#include <vector>

#include "core/console.h"
#include "core/settings.h"

using namespace cubecam;

namespace {

void require(bool ok) {
    if (!ok) abort();
}

const char kSecret[] = "fuzz-secret-42";

struct Host : ConsoleHost, LineSink {
    Settings edited;
    bool secret_typed = false;  // the input itself holds the secret (e.g. "set ssid <secret>")
    std::vector<std::string> lines;
    Settings& edited_settings() { return edited; }
    bool save_settings() {
        uint8_t rec[kSettingsRecordSize];
        settings_encode(edited, rec);
        Settings back;
        require(settings_decode(rec, sizeof rec, back));  // whatever was accepted is storable
        return true;
    }
    bool factory_reset() {
        settings_defaults(edited);
        return true;
    }
    void request_reboot() {}
    void report_status(LineSink& out) { out.line("link=online"); }
    void line(const char* text) {
        require(secret_typed || strstr(text, kSecret) == 0);
        require(strchr(text, '\n') == 0);
        lines.push_back(text);
    }
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    Host host;
    host.secret_typed = std::string(reinterpret_cast<const char*>(data), size).find(kSecret) != std::string::npos;
    settings_defaults(host.edited);
    settings_set(host.edited, "password", kSecret, strlen(kSecret));
    Console console(host, host);
    for (size_t i = 0; i < size; ++i) {
        size_t before = host.lines.size();
        console.feed(data[i]);
        if (host.lines.size() == before) continue;
        const std::string& last = host.lines.back();
        require(last == "OK" || last.compare(0, 4, "ERR ") == 0);
    }
    return 0;
}
