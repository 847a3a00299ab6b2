#include "console.h"

#include <string.h>

#include "settings.h"
#include "text.h"

namespace cubecam {

namespace {

const char* const kHelp[] = {
    "commands:",
    "  help                 this list",
    "  status               link, address, stream counters",
    "  get [key]            one setting, or all",
    "  set <key> <value>    change a setting (save, then reboot to apply)",
    "  save                 store the settings in flash",
    "  factory-reset        store factory defaults",
    "  reboot               restart the node",
};
const size_t kHelpWidth = 80;

// Splits "word rest" at the first space.
size_t word_len(const char* s, size_t n) {
    size_t i = 0;
    while (i < n && s[i] != ' ') ++i;
    return i;
}

bool is(const char* s, size_t n, const char* word) { return strlen(word) == n && memcmp(s, word, n) == 0; }

}  // namespace

Console::Console(ConsoleHost& host, LineSink& out) : host_(host), out_(out), len_(0), overflow_(false) {}

void Console::feed(uint8_t c) {
    if (c == '\r' || c == '\n') {
        if (overflow_) {
            error(kErrLineTooLong, "line too long (128 bytes at most)");
        } else if (len_ > 0) {
            execute(line_, len_);
        }
        len_ = 0;
        overflow_ = false;
        return;
    }
    if (len_ == kMaxConsoleLine) {
        overflow_ = true;
        return;
    }
    line_[len_++] = static_cast<char>(c);
}

void Console::error(uint8_t code, const char* message) {
    char buf[160];
    TextBuf t(buf, sizeof buf);
    t.add("ERR ").add_uint(code).add(' ').add(message);
    out_.line(t.c_str());
}

void Console::execute(const char* line, size_t len) {
    size_t cmd = word_len(line, len);
    const char* args = cmd < len ? line + cmd + 1 : line + len;
    size_t args_len = cmd < len ? len - cmd - 1 : 0;
    if (is(line, cmd, "help")) {
        for (size_t i = 0; i < sizeof kHelp / sizeof kHelp[0]; ++i) out_.line(kHelp[i]);
        help_keys();
    } else if (is(line, cmd, "status")) {
        host_.report_status(out_);
    } else if (is(line, cmd, "get")) {
        cmd_get(args, args_len);
        return;
    } else if (is(line, cmd, "set")) {
        cmd_set(args, args_len);
        return;
    } else if (is(line, cmd, "save")) {
        SettingResult whole = settings_check(host_.edited_settings());
        if (!whole.ok()) return error(whole.code, whole.message);
        if (!host_.save_settings()) return error(kErrStorage, "could not write the settings to flash");
    } else if (is(line, cmd, "factory-reset")) {
        if (!host_.factory_reset()) return error(kErrStorage, "could not write the settings to flash");
    } else if (is(line, cmd, "reboot")) {
        out_.line("OK");
        host_.request_reboot();
        return;
    } else {
        return error(kErrUnknownCommand, "unknown command; try help");
    }
    out_.line("OK");
}

// "keys: name ssid password(write-only) mode(station|ap) ...", wrapped.
void Console::help_keys() {
    char buf[kHelpWidth + 1];
    TextBuf t(buf, sizeof buf);
    t.add("keys:");
    for (size_t i = 0; i < kSettingCount; ++i) {
        char word[64];
        TextBuf w(word, sizeof word);
        w.add(' ').add(kSettingFields[i].key);
        settings_hint(kSettingFields[i], w);
        if (t.size() + w.size() > kHelpWidth) {
            out_.line(t.c_str());
            t.clear();
            t.add("     ");
        }
        t.add(w.c_str());
    }
    out_.line(t.c_str());
}

void Console::cmd_get(const char* args, size_t len) {
    char buf[96];
    TextBuf t(buf, sizeof buf);
    const Settings& s = host_.edited_settings();
    if (len == 0) {
        for (size_t i = 0; i < kSettingCount; ++i) {
            t.clear();
            t.add(kSettingFields[i].key).add('=');
            settings_get(s, kSettingFields[i].key, t);
            out_.line(t.c_str());
        }
        out_.line("OK");
        return;
    }
    char key[16];
    if (len >= sizeof key) return error(kErrUnknownKey, "unknown key; try help");
    memcpy(key, args, len);
    key[len] = '\0';
    t.add(key).add('=');
    SettingResult r = settings_get(s, key, t);
    if (!r.ok()) return error(r.code, r.message);
    out_.line(t.c_str());
    out_.line("OK");
}

void Console::cmd_set(const char* args, size_t len) {
    size_t key_len = word_len(args, len);
    if (key_len == 0 || key_len == len) return error(kErrUsage, "usage: set <key> <value>");
    char key[16];
    if (key_len >= sizeof key) return error(kErrUnknownKey, "unknown key; try help");
    memcpy(key, args, key_len);
    key[key_len] = '\0';
    // The value is the rest of the line, spaces included (SSIDs may have them).
    SettingResult r = settings_set(host_.edited_settings(), key, args + key_len + 1, len - key_len - 1);
    if (!r.ok()) return error(r.code, r.message);
    out_.line("OK");
}

}  // namespace cubecam
