"""Benchmark of the camera node's streaming path on the host.

Builds ``firmware/build/bench-stream`` (the portable core, -O2) and prints:

* CPU time the core spends per streamed frame (routing, MJPEG part header,
  chunking into <= 1400-byte module writes), for one and for four clients,
  as a ratio against one memcpy of the same frame measured in the same run;
* RAM per client slot and for the whole node (host sizes; the Cortex-M4
  sizes are in ``make -C firmware size``).

The network of the benchmark takes every byte at once, so the numbers are
the core's own cost, not Wi-Fi throughput (see docs/firmware.md for that
arithmetic). Nothing here ran on a Spresense.

    python benchmarks/firmware_stream.py [--frame-bytes 45000] [--frames 3000]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

FIRMWARE = Path(__file__).resolve().parents[1] / "firmware"


def run(frame_bytes: int, frames: int) -> dict:
    subprocess.run(["make", "-C", str(FIRMWARE), "-s", "bench"], check=True)
    out = subprocess.run(
        [str(FIRMWARE / "build" / "bench-stream"), str(frame_bytes), str(frames)],
        check=True, capture_output=True, text=True,
    ).stdout
    return json.loads(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frame-bytes", type=int, default=45000, help="JPEG size per frame (default 45000)")
    parser.add_argument("--frames", type=int, default=3000, help="frames per measurement (default 3000)")
    args = parser.parse_args(argv)
    r = run(args.frame_bytes, args.frames)
    print(f"frame size                 {r['frame_bytes']} B, {r['frames']} frames per run")
    print(f"baseline memcpy per frame  {r['memcpy_us_per_frame']:.2f} us")
    print(f"core per frame, 1 client   {r['core_us_per_frame_1_client']:.2f} us = {r['ratio_1_client']:.2f} x memcpy")
    print(f"core per frame, 4 clients  {r['core_us_per_frame_4_clients']:.2f} us = {r['ratio_4_clients']:.2f} x memcpy")
    print(f"module writes per frame    {r['writes_per_frame']:.1f} (at most {r['max_write_bytes']} B each)")
    print(f"RAM per client slot        {r['ram_per_client_bytes']} B (host build)")
    print(f"RAM HTTP server / node     {r['ram_http_server_bytes']} B / {r['ram_node_bytes']} B (host build)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
