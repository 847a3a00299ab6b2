// The line console of contracts §2: one command per line, answered by lines
// that end in "OK" or "ERR <code> <message>".
#ifndef CUBECAM_CORE_CONSOLE_H
#define CUBECAM_CORE_CONSOLE_H

#include <stddef.h>
#include <stdint.h>

namespace cubecam {

struct Settings;

// Console error codes (ERR <code>). 3 and 4 come from settings.h.
const uint8_t kErrUnknownCommand = 1;
const uint8_t kErrUsage = 2;
const uint8_t kErrStorage = 6;
const uint8_t kErrLineTooLong = 7;

const size_t kMaxConsoleLine = 128;

class LineSink {
public:
    // One line of text without its terminator.
    virtual void line(const char* text) = 0;
protected:
    ~LineSink() {}
};

// What the console acts on; implemented by the node.
class ConsoleHost {
public:
    // Settings being edited; applied at the next boot once saved.
    virtual Settings& edited_settings() = 0;
    virtual bool save_settings() = 0;
    virtual bool factory_reset() = 0;
    virtual void request_reboot() = 0;
    virtual void report_status(LineSink& out) = 0;
protected:
    ~ConsoleHost() {}
};

class Console {
public:
    Console(ConsoleHost& host, LineSink& out);
    // Feeds one byte; "\r", "\n" and "\r\n" end a line, empty lines are ignored.
    void feed(uint8_t c);
    // Runs one command line (without terminator).
    void execute(const char* line, size_t len);

private:
    void help_keys();
    void cmd_get(const char* args, size_t len);
    void cmd_set(const char* args, size_t len);
    void error(uint8_t code, const char* message);

    ConsoleHost& host_;
    LineSink& out_;
    char line_[kMaxConsoleLine + 1];
    size_t len_;
    bool overflow_;
};

}  // namespace cubecam

#endif
