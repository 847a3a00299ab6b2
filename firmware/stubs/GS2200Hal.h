// Stub: GS2200-WiFi library, src/GS2200Hal.h (1.2.x), as used.
#ifndef CUBECAM_STUB_GS2200HAL_H
#define CUBECAM_STUB_GS2200HAL_H

#include <stdint.h>

#define MAX_RECEIVED_DATA 1500

typedef enum {
    SPI_RESP_STATUS_OK = 0,
    SPI_RESP_STATUS_ERROR,
    SPI_RESP_STATUS_TIMEOUT
} SPI_RESP_STATUS_E;

typedef enum {
    iS110B_TypeA = 0,
    iS110B_TypeB,
    iS110B_TypeC,
} ModuleType;

void Init_GS2200_SPI_type(ModuleType type);
int Get_GPIO37Status(void);
SPI_RESP_STATUS_E WiFi_Write(const void* txData, uint16_t dataLength);
void WiFi_InitESCBuffer(void);

#endif
