// Stub: GS2200-WiFi library, src/TelitWiFi.h (1.2.x), as used.
#ifndef CUBECAM_STUB_TELITWIFI_H
#define CUBECAM_STUB_TELITWIFI_H

#include <Arduino.h>
#include <GS2200AtCmd.h>
#include <GS2200Hal.h>

typedef struct {
    ATCMD_MODE_E mode;
    ATCMD_PSAVE_E psave;
} TWIFI_Params;

class TelitWiFi {
public:
    TelitWiFi();
    ~TelitWiFi();
    int begin(TWIFI_Params params);
    int activate_station(const String& ssid, const String& passphrase);
    int activate_ap(const String& ssid, const String& passphrase, uint8_t channel);
    void stop(char cid);
    bool write(char cid, const uint8_t* data, uint16_t length);
    bool available();
    int read(char cid, uint8_t* data, int length);
};

#endif
