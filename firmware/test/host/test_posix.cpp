// Host-only tests of the POSIX implementations used by cubecam-native.
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>

#include <string>
#include <vector>

#include <doctest/doctest.h>

#include "../fakes.h"
#include "posix/posix_hw.h"

using namespace cubecam;

TEST_CASE("file storage round-trips and reports a missing file") {
    char dir[] = "/tmp/cubecam-test-XXXXXX";
    REQUIRE(mkdtemp(dir) != nullptr);
    std::string path = std::string(dir) + "/settings.bin";
    posix::FileStorage storage(path);
    uint8_t buf[16] = {};
    CHECK_FALSE(storage.load(buf, sizeof buf));
    uint8_t data[16];
    for (int i = 0; i < 16; ++i) data[i] = static_cast<uint8_t>(i * 7);
    REQUIRE(storage.store(data, sizeof data));
    REQUIRE(storage.load(buf, sizeof buf));
    CHECK(memcmp(buf, data, sizeof buf) == 0);
    CHECK_FALSE(storage.load(buf, 8));  // a record of another size is not ours
    unlink(path.c_str());
    rmdir(dir);
}

TEST_CASE("the folder camera numbers frames by capture time") {
    fake::Clock clock;
    posix::FolderCamera cam(clock);
    cam.add_frame(fake::jpeg(100, 1));
    cam.add_frame(fake::jpeg(200, 2));
    clock.now_us = 500000;
    cam.start(150);  // 15 fps
    CHECK(cam.latest_seq() == 1);
    clock.now_us += 1000000;  // one second later: 15 more frames
    CHECK(cam.latest_seq() == 16);
    Frame f;
    REQUIRE(cam.acquire_latest(f));
    CHECK(f.seq == 16);
    CHECK(f.size == 200);  // frame 16 is the second file
    CHECK(f.capture_us == 500000 + 1000000);
    cam.release(f.lease);
    CHECK(cam.leases_out() == 0);
}

TEST_CASE("the folder camera rejects folders without JPEG files") {
    fake::Clock clock;
    posix::FolderCamera cam(clock);
    std::string error;
    CHECK_FALSE(cam.load("/nonexistent-cubecam", error));
    CHECK(error.find("cannot open") != std::string::npos);
}
