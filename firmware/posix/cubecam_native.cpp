// cubecam-native: the firmware core on the host. Serves the JPEG files of a
// folder as its camera over real TCP, speaks Improv + console on a pty (or
// stdin/stdout) and keeps its settings in a file. See firmware/README.md.
#include <arpa/inet.h>
#include <errno.h>
#include <getopt.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include <memory>
#include <string>
#include <vector>

#include "core/node.h"
#include "core/settings.h"
#include "posix/posix_hw.h"

using namespace cubecam;

namespace {

volatile sig_atomic_t g_stop = 0;

void on_signal(int) { g_stop = 1; }

struct Options {
    std::string images;
    std::string settings = "cubecam-native.settings";
    std::string bind = "127.0.0.1";
    int port = -1;
    std::string serial = "pty";
    std::vector<std::string> sets;
    std::vector<std::string> fail_ssids;
    uint32_t join_ms = 300;
    bool tee_serial = false;
};

const char kUsage[] =
    "usage: cubecam-native --images DIR [options]\n"
    "  --images DIR        JPEG files served as camera frames, cycled in name order\n"
    "  --settings FILE     settings record (default ./cubecam-native.settings)\n"
    "  --port N            listen on N instead of the configured port (0 = ephemeral)\n"
    "  --bind ADDR         address to listen on and report as the node's IP (127.0.0.1)\n"
    "  --serial MODE       pty (default; prints 'serial: PATH'), stdio, or none\n"
    "  --set KEY=VALUE     change a setting in FILE before boot (repeatable)\n"
    "  --fail-ssid SSID    joining this SSID fails (repeatable)\n"
    "  --join-ms N         simulated time to join a network (default 300)\n"
    "  --tee-serial        copy everything the node writes to its serial port to stderr\n";

// A whole decimal number in [0, max]; false otherwise.
bool parse_number(const char* text, long max, long& out) {
    char* end = 0;
    errno = 0;
    out = strtol(text, &end, 10);
    return errno == 0 && end != text && *end == '\0' && out >= 0 && out <= max;
}

bool parse_options(int argc, char** argv, Options& o) {
    static const struct option kLong[] = {{"images", required_argument, 0, 'i'},
                                          {"settings", required_argument, 0, 's'},
                                          {"port", required_argument, 0, 'p'},
                                          {"bind", required_argument, 0, 'b'},
                                          {"serial", required_argument, 0, 'S'},
                                          {"set", required_argument, 0, 'k'},
                                          {"fail-ssid", required_argument, 0, 'f'},
                                          {"join-ms", required_argument, 0, 'j'},
                                          {"tee-serial", no_argument, 0, 't'},
                                          {"help", no_argument, 0, 'h'},
                                          {0, 0, 0, 0}};
    int c;
    long number = 0;
    while ((c = getopt_long(argc, argv, "", kLong, 0)) != -1) {
        switch (c) {
        case 'i': o.images = optarg; break;
        case 's': o.settings = optarg; break;
        case 'p':
            if (!parse_number(optarg, 65535, number)) return false;
            o.port = static_cast<int>(number);
            break;
        case 'b': o.bind = optarg; break;
        case 'S': o.serial = optarg; break;
        case 'k': o.sets.push_back(optarg); break;
        case 'f': o.fail_ssids.push_back(optarg); break;
        case 'j':
            if (!parse_number(optarg, 600000, number)) return false;
            o.join_ms = static_cast<uint32_t>(number);
            break;
        case 't': o.tee_serial = true; break;
        default: return false;
        }
    }
    bool serial_ok = o.serial == "pty" || o.serial == "stdio" || o.serial == "none";
    return !o.images.empty() && serial_ok && optind == argc;
}

// Applies --set KEY=VALUE to the stored record, as a console session would.
bool apply_sets(const Options& o, SettingsStorage& storage) {
    if (o.sets.empty()) return true;
    uint8_t rec[kSettingsRecordSize];
    Settings s;
    if (!storage.load(rec, sizeof rec) || !settings_decode(rec, sizeof rec, s)) settings_defaults(s);
    for (size_t i = 0; i < o.sets.size(); ++i) {
        const std::string& kv = o.sets[i];
        size_t eq = kv.find('=');
        std::string key = kv.substr(0, eq);
        std::string value = eq == std::string::npos ? "" : kv.substr(eq + 1);
        SettingResult r = settings_set(s, key.c_str(), value.data(), value.size());
        if (eq == std::string::npos || !r.ok()) {
            bool secret = false;  // a write-only value (the password) is not shown
            for (size_t f = 0; f < kSettingCount; ++f) {
                secret = secret || (key == kSettingFields[f].key && kSettingFields[f].write_only);
            }
            std::string shown = secret ? key + "=(not shown)" : kv;
            fprintf(stderr, "cubecam-native: --set %s: %s\n", shown.c_str(),
                    eq == std::string::npos ? "expected KEY=VALUE" : r.message);
            return false;
        }
    }
    settings_encode(s, rec);
    if (!storage.store(rec, sizeof rec)) {
        fprintf(stderr, "cubecam-native: cannot write %s\n", o.settings.c_str());
        return false;
    }
    return true;
}

}  // namespace

int main(int argc, char** argv) {
    Options o;
    if (!parse_options(argc, argv, o)) {
        fputs(kUsage, stderr);
        return 2;
    }
    in_addr_t bind_addr = inet_addr(o.bind.c_str());
    if (bind_addr == INADDR_NONE || (ntohl(bind_addr) >> 24) != 127) {
        fprintf(stderr, "cubecam-native: listening on %s: reachable from the network (the default 127.0.0.1 is not)\n",
                o.bind.c_str());
    }
    signal(SIGPIPE, SIG_IGN);
    signal(SIGINT, on_signal);
    signal(SIGTERM, on_signal);

    posix::FileStorage storage(o.settings);
    if (!apply_sets(o, storage)) return 2;
    posix::MonotonicClock clock;
    posix::FolderCamera camera(clock);
    std::string error;
    if (!camera.load(o.images, error)) {
        fprintf(stderr, "cubecam-native: %s\n", error.c_str());
        return 2;
    }

    int serial_read = -1, serial_write = -1, pty_slave = -1;
    if (o.serial == "pty") {
        std::string path = posix::open_pty(serial_read, pty_slave);
        if (path.empty()) {
            fprintf(stderr, "cubecam-native: cannot open a pty: %s\n", strerror(errno));
            return 1;
        }
        serial_write = serial_read;
        printf("serial: %s\n", path.c_str());
        fflush(stdout);
    } else if (o.serial == "stdio") {
        serial_read = 0;
        serial_write = 1;
    }
    posix::FdSerial serial(serial_read, serial_write, o.tee_serial ? 2 : -1);
    posix::TcpNetwork network(o.bind, o.port);
    posix::SimulatedWifi wifi(clock, o.bind, o.join_ms, o.fail_ssids);
    posix::NoLeds leds;
    posix::HostSystem system;
    Hardware hw = {camera, network, wifi, serial, storage, clock, leds, system, "POSIX"};

    while (!g_stop) {
        // One boot: what setup() does on the board, then loop() until reboot.
        clock.restart();
        std::unique_ptr<Node> node(new Node(hw));
        node->boot();
        camera.start(frame_rate_tenths(node->running().fps));
        std::vector<struct pollfd> fds;
        std::vector<int> wait;
        while (!g_stop && !system.take_reboot_request()) {
            if (node->loop()) continue;
            fds.clear();
            wait.clear();
            network.wait_fds(wait);
            if (serial.read_fd() >= 0) wait.push_back(serial.read_fd());
            for (size_t i = 0; i < wait.size(); ++i) {
                struct pollfd p = {wait[i], POLLIN, 0};
                fds.push_back(p);
            }
            ::poll(fds.empty() ? 0 : &fds[0], fds.size(), 1);
        }
        network.close_all();
    }
    if (pty_slave >= 0) close(pty_slave);
    return 0;
}
