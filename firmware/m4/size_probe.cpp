// Symbols whose sizes (arm-none-eabi-nm -S) are the static RAM of the core's
// objects on the Cortex-M4: what the sketch holds for the node.
#include "core/http_server.h"
#include "core/node.h"

char cubecam_ram_node[sizeof(cubecam::Node)];
char cubecam_ram_http_server[sizeof(cubecam::HttpServer)];
char cubecam_ram_per_client[cubecam::HttpServer::bytes_per_client()];
