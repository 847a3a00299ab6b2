// Stand-in for the Spresense core's File library header (libraries/File/src/
// File.h), which GS2200AtCmd.h includes for AtCmd_TCERTADD(). The real class
// derives from Stream and Print, whose sources include the real Arduino.h; a
// host cannot build them. cubecam never loads certificates, so these methods
// only report that they were reached (hostlib/board.cpp).
#ifndef CUBECAM_HOSTLIB_FILE_H
#define CUBECAM_HOSTLIB_FILE_H

#include <Arduino.h>

class File {
public:
    int available();
    uint32_t size();
    int read(void* buf, size_t nbyte);
};

#endif
