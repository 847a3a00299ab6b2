// How the GS2200M's Serial-to-WiFi application reads the arguments of the
// credential commands (the rules are summed up in core/gs2200m.h): the model
// the scripted module (hostlib/gs2200m.cpp), the encoder's tests and its
// fuzz target decode AT+WPAPSK, AT+WPSK and AT+WA with. Written from the
// behaviour of the S2W sources, not copied from them.
#ifndef CUBECAM_TEST_S2W_H
#define CUBECAM_TEST_S2W_H

#include <ctype.h>
#include <stddef.h>
#include <stdint.h>

#include <string>
#include <vector>

namespace s2w {

// The next argument of `line` from `pos` on; pos moves past it and its comma.
// False when nothing is left, or the argument is misquoted (a second '"').
inline bool next_arg(const std::string& line, size_t& pos, std::string& arg) {
    if (pos >= line.size()) return false;
    size_t p = pos;
    while (p < line.size() && isspace(static_cast<unsigned char>(line[p]))) ++p;
    bool quoted = p < line.size() && line[p] == '"';
    size_t i = quoted ? p + 1 : pos;
    bool closed = false;
    char prev = '\0';
    arg.clear();
    for (; i < line.size(); ++i) {
        char c = line[i];
        if (c == ',' && (!quoted || closed)) break;
        if (c == '"' && quoted && prev != '\\') {
            if (closed) return false;
            closed = true;
            c = '\0';
        } else if (!closed) {
            arg += c;
        }
        prev = c;
    }
    pos = i < line.size() ? i + 1 : i;
    return true;
}

// An SSID argument: \" becomes ", 1 to 32 bytes.
inline bool ssid(const std::string& arg, std::string& out) {
    out.clear();
    size_t i = 0;
    while (i < arg.size() && out.size() < 32) {
        bool escaped = arg[i] == '\\' && i + 1 < arg.size() && arg[i + 1] == '"';
        out += escaped ? '"' : arg[i];
        i += escaped ? 2 : 1;
    }
    return i == arg.size() && !out.empty();
}

// AT+WPAPSK=<ssid>,<passphrase> (the text after '=').
inline bool wpapsk(const std::string& args, std::string& ssid_out, std::string& passphrase) {
    size_t pos = 0;
    std::string arg;
    if (!next_arg(args, pos, arg) || !ssid(arg, ssid_out)) return false;
    if (!next_arg(args, pos, passphrase)) return false;
    return passphrase.size() >= 8 && passphrase.size() <= 63;
}

// AT+WPSK=<64 hex digits>.
inline bool wpsk(const std::string& args, std::vector<uint8_t>& key) {
    size_t i = 0;
    while (i < args.size() && isspace(static_cast<unsigned char>(args[i]))) ++i;
    key.clear();
    for (; i < args.size() && key.size() <= 32; i += 2) {
        if (i + 1 >= args.size() || !isxdigit(static_cast<unsigned char>(args[i])) ||
            !isxdigit(static_cast<unsigned char>(args[i + 1]))) {
            return false;
        }
        key.push_back(static_cast<uint8_t>(std::stoi(args.substr(i, 2), nullptr, 16)));
    }
    return i >= args.size() && key.size() == 32;
}

// AT+WA=<ssid>[,<bssid>[,<channel>]]: the SSID.
inline bool wa(const std::string& args, std::string& ssid_out) {
    size_t pos = 0;
    std::string arg;
    return next_arg(args, pos, arg) && ssid(arg, ssid_out);
}

}  // namespace s2w

#endif
